"""BOP pose errors, visibility and recall scores: pure numpy, units in every name or docstring."""
