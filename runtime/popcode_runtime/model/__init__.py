"""The model: its ONNX metadata contract, the onnxruntime engine and decoding an output into rotations."""
