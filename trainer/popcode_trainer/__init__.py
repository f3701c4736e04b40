"""popcode trainer: data, network, training, evaluation and ONNX export.

The code layout, rotation maths, crop and decoding come from ``popcode_runtime``.
"""

from popcode_runtime import __version__  # one version for both halves, kept in popcode_runtime/VERSION

__all__ = ["__version__"]
