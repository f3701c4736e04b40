"""Data: BOP reader, renderer, built-in objects and the training-sample augmentation."""
