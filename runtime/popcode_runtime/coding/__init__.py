"""The population code: its layout, encoding and argmax decoding, sub-neuron refinement, the hypotheses of a
code's peaks and the confidence features. Imports the base and geometry."""
