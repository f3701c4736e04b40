"""Counts a model's metadata or a BOP ``models_info.json`` may carry, in one place: the trainer imports these, so a
file the trainer accepts is one the runtime loads, and each is refused before any work it would size.
"""

from __future__ import annotations

MAX_OBJECTS = 10_000  # per model or models folder; a BOP dataset has at most a few dozen
# A rigid part's finite symmetry group: a 1000-tooth gear's rotations. The count is checked before any matrix is
# read; every later step (closure, the code's peaks, the metrics' transforms) is then bounded by it.
MAX_DISCRETE_SYMMETRIES = 1_000
# One axis is a part's continuous symmetry; a sphere is declared by three. Each one multiplies the transforms the
# metrics expand it into (the BOP toolkit's 315 steps times every discrete symmetry).
MAX_CONTINUOUS_SYMMETRIES = 3
MAX_HULL_POINTS = 1_024  # per object: every box fit projects them all; the trainer writes 64
# All of a model's metadata values together, counted in characters before any is parsed. An exported object takes
# about 24 kB (its hull and depth's surface points: models/*.onnx), so some 700 fit; a crafted model at the limit
# (objects of 1000 symmetries, or of hull and surface points at their limits) loads in a few seconds.
MAX_METADATA_CHARS = 1 << 24
