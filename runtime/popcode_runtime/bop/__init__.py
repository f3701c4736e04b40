"""BOP files: a split's layout, the BOP19 results CSV and the detections a run reads."""
