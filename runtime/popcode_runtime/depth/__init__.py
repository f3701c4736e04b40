"""Depth: translation from a depth image, refinement against it (ICP), one instance's placement."""
