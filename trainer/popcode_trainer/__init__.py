"""popcode trainer: data, network, training, evaluation and ONNX export.

The code layout, rotation maths, crop and decoding come from ``popcode_runtime``.
"""

__version__ = "0.1.0"
