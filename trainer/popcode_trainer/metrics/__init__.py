"""BOP pose errors, visibility and recall scores, confidence scores, 2-D detection scores: numpy (and pycocotools
for detection AP, as the BOP toolkit computes it), units in every name or docstring.

A leaf: it needs nothing else of the trainer, so the renderer (visibility masks) and the evaluation can both
use it."""
