"""The detector: a torchvision FCOS trained from the project's renders, exported for the runtime's ``Detector``."""
