"""For a part that looks symmetric but for a small feature: how often the estimate is the right pose rather than one
of the look-alike poses the feature tells apart (issue 53).

An estimate within :data:`FOUND_DEG` of the truth up to the part's look-alike poses has found the shape; the share
of those also within :data:`FOUND_DEG` up to the declared symmetries alone has seen the feature. A network blind to
the feature scores about one over the number of look-alike poses; one that sees it, 1.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .confidence import rotation_errors_deg

FOUND_DEG = 15.0


@dataclass(frozen=True)
class LookAlikeShare:
    """One look-alike part's estimates: how many found the shape, and the share of those that found the pose."""

    obj_id: int
    poses: int  # look-alike poses, the declared symmetries' included
    found_shape: int
    right_share: float  # NaN when no estimate found the shape


def look_alike_shares(R_est: np.ndarray, R_true: np.ndarray, obj_ids: np.ndarray,
                      models_info: Mapping[int, Mapping[str, Any]],
                      look_alikes: Mapping[int, np.ndarray]) -> list[LookAlikeShare]:
    """:class:`LookAlikeShare` of each object of ``look_alikes`` (object -> its look-alike rotations ``(K, 3, 3)``,
    :func:`~popcode_trainer.data.near_symmetry.look_alike_rotations`) that the instances show."""
    shares = []
    for obj_id, rotations in sorted(look_alikes.items()):
        mine = obj_ids == obj_id
        if not mine.any():
            continue
        ids = obj_ids[mine]
        up_to_look_alikes = rotation_errors_deg(R_est[mine], R_true[mine], ids, models_info, {obj_id: rotations})
        exact = rotation_errors_deg(R_est[mine], R_true[mine], ids, models_info)
        shape = up_to_look_alikes < FOUND_DEG
        share = float(np.mean(exact[shape] < FOUND_DEG)) if shape.any() else float("nan")
        shares.append(LookAlikeShare(int(obj_id), len(rotations), int(shape.sum()), share))
    return shares
