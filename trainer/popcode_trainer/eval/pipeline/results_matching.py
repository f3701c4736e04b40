"""A results file's estimates matched to a split's instances as the BOP toolkit matches them, as one error each.

The toolkit (``scripts/eval_calc_errors.py``, ``bop_toolkit_lib/pose_matching.py``)
works per image and object: of the estimates it keeps the best scored, as many
as there are target instances, and scores each against every instance of the
object in the image. Then, for every metric and threshold on its own, it takes
the kept estimates by descending score and matches each to the not yet matched
instance of lowest error below the threshold; recall is the share of instances
matched. Estimates of an object without an instance in the image count nowhere.

Raising a threshold never unmatches an instance (an estimate that loses its
instance to a better scored one takes the next free one below the threshold).
So each instance has one error, the smallest pair error from which on it is
matched, and ``error < threshold`` tells for every threshold at once whether
the toolkit matches it: the split's usual per-instance scoring then gives the
toolkit's recall. An instance never matched (no estimate left for it, or none
near it) gets an infinite error: wrong at every threshold.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from popcode_runtime.bop.bop19_csv import PoseEstimate

from ...data.bop import Instance
from ...metrics.recall import InstanceErrors
from .split_metrics import SplitMetrics


@dataclass(frozen=True)
class ImageObject:
    """The split instances of one object in one image and the estimates kept for them."""

    rows: tuple[int, ...]  # split indices of the instances, in split (ground-truth) order
    estimates: tuple[PoseEstimate, ...]  # at most len(rows), by descending score (file order among equals)


@dataclass(frozen=True)
class ResultsMatching:
    """A results file grouped by image and object, with what the grouping left over."""

    groups: tuple[ImageObject, ...]
    extra: int  # estimates beyond their image and object's instance count (the lowest scored): ignored
    without_instance: int  # estimates of an image and object with no instance in the split: ignored

    @property
    def without_estimate(self) -> int:
        """Instances left without an estimate: fewer estimates than instances in their image and object."""
        return sum(len(group.rows) - len(group.estimates) for group in self.groups)


def group_results(estimates: Sequence[PoseEstimate], instances: Sequence[Instance]) -> ResultsMatching:
    """The estimates kept for each image and object of ``instances``: its best scored, one per instance."""
    rows_of: dict[tuple[int, int, int], list[int]] = defaultdict(list)
    for row, inst in enumerate(instances):
        rows_of[(inst.scene_id, inst.im_id, inst.obj_id)].append(row)
    estimates_of: dict[tuple[int, int, int], list[PoseEstimate]] = defaultdict(list)
    for est in estimates:
        estimates_of[(est.scene_id, est.im_id, est.obj_id)].append(est)
    groups, kept = [], 0
    for key, rows in rows_of.items():
        best = sorted(estimates_of.get(key, []), key=lambda est: -est.score)[: len(rows)]
        groups.append(ImageObject(tuple(rows), tuple(best)))
        kept += len(best)
    with_instance = sum(len(found) for key, found in estimates_of.items() if key in rows_of)
    return ResultsMatching(tuple(groups), with_instance - kept, len(estimates) - with_instance)


def credited_errors(errors: np.ndarray) -> np.ndarray:
    """``(G,)``: each instance's error under the toolkit's greedy matching (see the module docstring).

    ``errors (E, G)`` are those of estimate ``e`` (by descending score) against
    instance ``g``; an instance is matched at a threshold ``th`` exactly when its
    result is below ``th``. Ties go, as in the toolkit, to the first instance.
    """
    errors = np.asarray(errors, np.float64)
    credited = np.full(errors.shape[1], np.inf)
    for level in np.unique(errors[np.isfinite(errors)]):  # every threshold just above a pair error
        matched = _greedy_match(errors, level)
        credited[matched & np.isinf(credited)] = level
        if matched.sum() == min(errors.shape):
            break
    return credited


def _greedy_match(errors: np.ndarray, level: float) -> np.ndarray:
    """``(G,)``: the instances matched when errors up to ``level`` count as correct, estimates in row order."""
    matched = np.zeros(errors.shape[1], dtype=bool)
    for row in errors:
        open_errors = np.where(matched | (row > level), np.inf, row)
        best = int(np.argmin(open_errors))
        matched[best] |= bool(np.isfinite(open_errors[best]))
    return matched


def matched_errors(matching: ResultsMatching, metrics: SplitMetrics) -> InstanceErrors:
    """Every metric's error of each split instance, in split order, credited by the toolkit's matching (VSD per
    tau), each estimate placed at the instance it is scored against (rotation only: the ground-truth translation)."""
    split = metrics.split
    pairs = [(est.R_m2c, row) for group in matching.groups for est in group.estimates for row in group.rows]
    obj_id = np.array([inst.obj_id for inst in split.instances])
    count, taus = len(obj_id), len(metrics.thresholds.vsd_taus)
    vsd_shapes = {"vsd": (count, taus), "vsd_single_tau": (count,), "vss": (count,)} if metrics.use_depth else {}
    credited = {name: np.full(shape, np.inf) for name, shape in
                {"mssd_mm": (count,), "mspd_px": (count,), "adi_mm": (count,), **vsd_shapes}.items()}
    if pairs:
        scored = metrics.errors(np.stack([R for R, _ in pairs]), rows=np.array([row for _, row in pairs]))
        start = 0
        for group in matching.groups:
            rows, size = list(group.rows), len(group.estimates) * len(group.rows)
            for name, values in credited.items():
                pair_errors = np.asarray(getattr(scored, name))[start:start + size]
                block = pair_errors.reshape(len(group.estimates), len(rows), *pair_errors.shape[1:])
                if block.ndim == 3:  # VSD: one error per tau, each matched on its own
                    values[rows] = np.stack([credited_errors(block[..., t]) for t in range(block.shape[2])], axis=1)
                else:
                    values[rows] = credited_errors(block)
            start += size
    return InstanceErrors(obj_id, metrics.image_size_px[:, 0].copy(), **credited)
