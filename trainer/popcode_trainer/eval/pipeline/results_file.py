"""A BOP19 results file as a method: its estimates matched to the split's instances and scored like a model's.

What ``popcode run`` writes (or any method's results) can so be scored with the
same tables as a model run directly. Within one image and object the estimates
are taken by descending score, at most as many as there are instances, and each
is matched to the still unmatched instance it is closest to in rotation (up to
the object's symmetries), as the BOP toolkit matches estimates to ground truth.
Every instance must get an estimate: the paper's protocol scores ground-truth
boxes (``popcode run --gt-boxes``); score detection-based results, which miss
some instances, with the BOP toolkit.
"""

from __future__ import annotations

from collections import defaultdict
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

    def known_objects(self) -> set[int]:
        return {est.obj_id for est in self.estimates}

    def object_points(self) -> None:
        return None  # no model metadata: the 6-D scores of --translation are for model files

    def estimate(self, instances: Sequence[Instance], models_info: Mapping[int, Mapping[str, Any]],
                 progress: bool = True, top_k: int = 1) -> Estimates:
        """Each instance's matched estimate (see the module docstring), with the file's score and time; an
        instance without an estimate is an error.

        A results file lists no hypotheses: ``top_k`` is accepted and ignored.
        """
        rows_of: dict[tuple[int, int, int], list[int]] = defaultdict(list)
        for row, inst in enumerate(instances):
            rows_of[(inst.scene_id, inst.im_id, inst.obj_id)].append(row)
        estimates_of: dict[tuple[int, int, int], list[PoseEstimate]] = defaultdict(list)
        for est in self.estimates:
            estimates_of[(est.scene_id, est.im_id, est.obj_id)].append(est)
        R_est, score = np.full((len(instances), 3, 3), np.nan), np.full(len(instances), np.nan)
        image_s = np.full(len(instances), UNKNOWN_TIME_S)
        for key, rows in rows_of.items():
            candidates = sorted(estimates_of.get(key, []), key=lambda est: -est.score)[: len(rows)]
            for est in candidates:
                errors = rotation_errors_deg(np.repeat(est.R_m2c[None], len(rows), axis=0),
                                             np.stack([instances[row].R_m2c for row in rows]),
                                             np.full(len(rows), key[2]), models_info)
                row = rows.pop(int(np.argmin(errors)))
                R_est[row], score[row], image_s[row] = est.R_m2c, est.score, est.time_s
        missing = [i for i, inst in enumerate(instances) if np.isnan(score[i])]
        if missing:
            first = instances[missing[0]]
            raise PopcodeError(f"{self.path} has no estimate for {len(missing)} of {len(instances)} instances "
                               f"(first: scene {first.scene_id} image {first.im_id} object {first.obj_id}); "
                               "evaluate scores ground-truth-box results (popcode run --gt-boxes)")
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
