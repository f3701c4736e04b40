"""Export: a training checkpoint -> ONNX file with the runtime's metadata, checked against torch through the two
engines; quantised variants and their agreement; the confidence calibrator fitted on held-out crops."""
