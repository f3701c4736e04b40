"""Where a model's rotation errors come from, counted: a neighbour's pose, a flip, or plain error.

``python -m experiments.bin_errors`` reads each instance's error and its overlapping same-part neighbours' from a
split; this counts them, per group of instances: the median rotation error up to the part's symmetries; the share of
gross errors (over :data:`GROSS_DEG`); of those, how many are near-flips (over :data:`FLIP_DEG`: a look-alike pose of a
part without a declared symmetry), and how many equal the pose of another instance of the same part whose box overlaps
this one's (within :data:`NEIGHBOUR_DEG`: the network read the neighbour instead of the target); and the boxes' sizes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from popcode_trainer.data.box_noise import box_intersection
from popcode_trainer.metrics.recall import VISIBILITY_BINS

GROSS_DEG = 30.0  # an error past this is a wrong pose, not an imprecise one
FLIP_DEG = 150.0  # a wrong pose this far off is the part turned round: a look-alike
NEIGHBOUR_DEG = 20.0  # a wrong pose this close to an overlapping same-part instance's is that instance's
NEIGHBOUR_OVERLAP = 0.05  # share of the target's box another instance's box must cover to count as a neighbour


def box_overlap(target: Sequence[float], other: Sequence[float]) -> float:
    """The share of ``target``'s box (x, y, w, h) that ``other`` covers."""
    return box_intersection(target, other) / (target[2] * target[3])


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts of one group of instances (rows of obj_id, visib_fract, box_px, error_deg and neighbour_deg: the
    error of the nearest overlapping same-part instance's pose, None without one)."""
    errors = np.array([r["error_deg"] for r in rows])
    gross = [r for r in rows if r["error_deg"] > GROSS_DEG]
    return {"instances": len(rows), "median_error_deg": float(np.median(errors)) if rows else None,
            "gross": len(gross), "flips": sum(r["error_deg"] > FLIP_DEG for r in gross),
            "gross_with_neighbour": sum(r["neighbour_deg"] is not None for r in gross),
            "neighbour_reads": sum(r["neighbour_deg"] is not None and r["neighbour_deg"] < NEIGHBOUR_DEG
                                   for r in gross),
            "median_box_px": float(np.median([r["box_px"] for r in rows])) if rows else None}


def groups(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """:func:`summary` of all instances, of each visible-fraction bin and of each part."""
    result = {"all": summary(rows)}
    for label, low, high in VISIBILITY_BINS:
        chosen = [r for r in rows if low <= r["visib_fract"] < high]
        if chosen:
            result[f"visible {label}"] = summary(chosen)
    for obj_id in sorted({r["obj_id"] for r in rows}):
        result[f"part {obj_id}"] = summary([r for r in rows if r["obj_id"] == obj_id])
    return result
