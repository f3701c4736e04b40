"""Evaluation with the BOP benchmark's metrics (``popcode_trainer.metrics``), in two parts that depend one way
(pipeline <- reporting).

- ``pipeline``: models and a BOP split -> per-instance errors: reading the split,
  running every model through the runtime's one inference pipeline, rendering
  depth for VSD, full 6-D poses with the translation from the box.
- ``reporting``: results -> files: the paper's tables (markdown, JSON), the
  BOP19 results CSV, figures, and the one markdown-table writer.
"""
