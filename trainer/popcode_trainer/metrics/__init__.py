"""BOP pose errors, visibility and recall scores, confidence scores: pure numpy, units in every name or docstring.

A leaf: it needs nothing else of the trainer, so the renderer (visibility masks) and the evaluation can both
use it."""
