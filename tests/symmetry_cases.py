"""BOP ``models_info.json`` entries for one object of each symmetry class."""

from __future__ import annotations

import numpy as np

from popcode_runtime.geometry.rotations import axis_angle_to_matrix


def _flat(axis, angle_rad, t_mm=(0.0, 0.0, 0.0)) -> list[float]:
    matrix = np.eye(4)
    matrix[:3, :3] = axis_angle_to_matrix(np.asarray(axis, float), angle_rad)
    matrix[:3, 3] = t_mm
    return matrix.reshape(-1).tolist()


BASE = {"diameter": 100.0, "min_x": -40.0, "min_y": -40.0, "min_z": -30.0,
        "size_x": 80.0, "size_y": 80.0, "size_z": 60.0}

CASES = {
    "none": dict(BASE),
    "two_fold": {**BASE, "symmetries_discrete": [_flat([0, 0, 1], np.pi)]},
    "four_fold": {**BASE, "symmetries_discrete": [_flat([0, 0, 1], k * np.pi / 2) for k in (1, 2, 3)]},
    "continuous": {**BASE, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},
    "continuous_flip": {**BASE, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
                        "symmetries_discrete": [_flat([1, 0, 0], np.pi)]},
}

# Equivalent poses of one rotation: 1 for none, 2 for 2-fold, 4 for 4-fold.
DISCRETE_ORDER = {"none": 1, "two_fold": 2, "four_fold": 4}
# Distinct symmetry-axis directions: 1 for a plain continuous symmetry, 2 with a flip.
AXIS_DIRECTIONS = {"continuous": 1, "continuous_flip": 2}
