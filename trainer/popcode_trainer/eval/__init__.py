"""Evaluation with the BOP benchmark's metrics, in three parts that depend one way (metrics <- pipeline <- reporting).

- ``metrics``: pure numpy, shaped and named like the BOP toolkit's: pose errors
  (MSSD, MSPD, ADD, ADI, PROJ, VSD, VSS, re, te), visibility masks, and the
  recall / average-recall scores over the BOP19 thresholds. No files, no models.
- ``pipeline``: models and a BOP split -> per-instance errors: reading the split,
  running every model through the runtime's one inference pipeline, rendering
  depth for VSD, full 6-D poses with the translation from the box.
- ``reporting``: results -> files: the paper's tables (markdown, JSON), the
  BOP19 results CSV, figures, and the one markdown-table writer.
"""
