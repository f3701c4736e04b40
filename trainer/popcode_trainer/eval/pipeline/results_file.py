"""A BOP19 results file as a method: its estimates matched to the split's instances and scored like a model's.

What ``popcode run`` writes (or any method's results: ground-truth boxes or a
detector's, with missed instances, false positives and several estimates of
one object in an image) is scored with the same tables as a model run
directly, as the BOP toolkit scores it (:mod:`.results_matching`): per image
and object the best scored estimates, at most one per instance, matched per
metric and threshold; an instance without an estimate is wrong, the estimates
beyond the instance count and those of an image and object without an
instance are ignored. Each instance's row in the tables shows one estimate:
the kept estimates, by descending score, each take the still unmatched
instance nearest in rotation (up to the object's symmetries).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.bop19_csv import PoseEstimate, read_bop19_results

from ...data.bop import Instance
from ...metrics.confidence import rotation_errors_deg
from .estimates import UNKNOWN_TIME_S, Estimates
from .results_matching import group_results

RESULTS_SUFFIX = ".csv"


@dataclass(frozen=True)
class ResultsMethod:
    """One table row from a BOP19 results file (rotation only: its translations are not rescored)."""

    name: str
    path: Path
    estimates: tuple[PoseEstimate, ...]

    @property
    def paths(self) -> tuple[str, ...]:
        return (str(self.path),)

    @property
    def confidence_thresholds_deg(self) -> set[float | None]:
        return {None}  # a results file's score is whatever its maker wrote: judged as a raw score

    def object_points(self) -> None:
        return None  # no model metadata: the 6-D scores of --translation are for model files

    def estimate(self, instances: Sequence[Instance], models_info: Mapping[int, Mapping[str, Any]],
                 progress: bool = True, top_k: int = 1) -> Estimates:
        """Each instance's estimate (see the module docstring) with the file's score and time; NaN rotation and
        score where the instance has none.

        A results file lists no hypotheses: ``top_k`` is accepted and ignored.
        """
        R_est, score = np.full((len(instances), 3, 3), np.nan), np.full(len(instances), np.nan)
        image_s = np.full(len(instances), UNKNOWN_TIME_S)
        for group in group_results(self.estimates, instances).groups:
            rows = list(group.rows)
            for est in group.estimates:
                errors = rotation_errors_deg(np.repeat(est.R_m2c[None], len(rows), axis=0),
                                             np.stack([instances[row].R_m2c for row in rows]),
                                             np.full(len(rows), est.obj_id), models_info)
                row = rows.pop(int(np.argmin(errors)))
                R_est[row], score[row], image_s[row] = est.R_m2c, est.score, est.time_s
        return Estimates(R_est, np.full(len(instances), np.nan), score, float("nan"), image_s)


def read_results_method(path: Path, name: str) -> ResultsMethod:
    estimates = read_bop19_results(path)
    if not estimates:
        raise PopcodeError(f"{path} holds no estimates")
    for est in estimates:
        R = est.R_m2c
        if not np.isfinite(R).all() or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) <= 0:
            raise PopcodeError(f"{path}: the estimate of scene {est.scene_id} image {est.im_id} object "
                               f"{est.obj_id} is not a rotation matrix")
    return ResultsMethod(name, path, tuple(estimates))
