"""Geometry: rotations, symmetries, the camera, the crop and the translation from a box."""
