"""BOP19 recall scores from per-instance pose errors.

A pose counts as correct only if its error is *strictly* below the threshold, as
in the BOP toolkit. Errors are normalised before thresholding the way the
toolkit does it: MSSD and ADI by the object diameter, MSPD by ``640 / image
width``; VSD errors are already in [0, 1]. A metric's score is the recall averaged
over its thresholds (and, for VSD, over the misalignment tolerances tau);
:func:`tightest_recalls` gives the recall at the first, tightest, threshold alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.symmetries import SymmetryClass, symmetry_class


def _bop19_steps(first: float, last: float) -> tuple[float, ...]:
    # np.arange as in the toolkit's eval_bop19_pose.py, so values such as
    # 0.15000000000000002 are the same floats and ties at a threshold agree.
    step = first
    return tuple(np.arange(first, last + step / 5, step).tolist())


@dataclass(frozen=True)
class Thresholds:
    """Every threshold of the evaluation; the defaults are the BOP19 ones and the paper's.

    ``mssd_fractions`` and ``adi_fraction`` are fractions of the object diameter;
    ``mspd_px_at_640`` are pixels for a 640 px wide image (scaled with the width);
    ``vsd_taus`` are fractions of the diameter, ``vsd_thetas`` thresholds on the
    VSD error; ``vsd_delta_mm`` is the visibility tolerance (15 mm for T-LESS);
    ``vsd_single_tau_mm`` / ``vsd_single_theta`` define e_VSD < 0.3 (tau = 20 mm).
    VSS (tau = inf) is scored over ``vss_thetas``: the paper does not say which
    thresholds it used, so the VSD thetas are the default.
    """

    mssd_fractions: tuple[float, ...] = field(default_factory=lambda: _bop19_steps(0.05, 0.5))
    mspd_px_at_640: tuple[float, ...] = field(default_factory=lambda: _bop19_steps(5.0, 50.0))
    vsd_taus: tuple[float, ...] = field(default_factory=lambda: _bop19_steps(0.05, 0.5))
    vsd_thetas: tuple[float, ...] = field(default_factory=lambda: _bop19_steps(0.05, 0.5))
    vsd_delta_mm: float = 15.0
    vsd_single_tau_mm: float = 20.0
    vsd_single_theta: float = 0.3
    vss_thetas: tuple[float, ...] = field(default_factory=lambda: _bop19_steps(0.05, 0.5))
    adi_fraction: float = 0.05


METRICS = ("VSD", "MSSD", "MSPD", "e_VSD<0.3", "VSS", "ADI")
"""Score names, in the column order of the paper's tables."""


@dataclass(frozen=True)
class InstanceErrors:
    """Errors of one method for ``N`` ground-truth instances (one estimate each).

    ``vsd`` holds one error per ``Thresholds.vsd_taus`` ``(N, T)``; ``vsd_single_tau``
    the VSD error at ``vsd_single_tau_mm`` and ``vss`` the VSD error at tau = inf
    ``(N,)``. The depth-based errors are ``None`` when the split has no depth.
    """

    obj_id: np.ndarray  # (N,) int
    image_width_px: np.ndarray  # (N,)
    mssd_mm: np.ndarray  # (N,)
    mspd_px: np.ndarray  # (N,)
    adi_mm: np.ndarray  # (N,)
    vsd: np.ndarray | None = None  # (N, T)
    vsd_single_tau: np.ndarray | None = None  # (N,)
    vss: np.ndarray | None = None  # (N,)

    def __post_init__(self) -> None:
        count = len(self.obj_id)
        for name in ("image_width_px", "mssd_mm", "mspd_px", "adi_mm", "vsd", "vsd_single_tau", "vss"):
            value = getattr(self, name)
            if value is not None and len(value) != count:
                raise PopcodeError(f"{name} has {len(value)} entries but there are {count} instances")

    def select(self, mask: np.ndarray) -> InstanceErrors:
        """The instances where the boolean ``mask`` is true."""
        return InstanceErrors(**{
            name: None if value is None else np.asarray(value)[mask]
            for name, value in self.__dict__.items()
        })


def recall(errors: np.ndarray, thresholds: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """Fraction of ``errors (N, ...)`` strictly below each threshold, ``(T, ...)``.

    With no instances the recall is NaN (nothing to score, not zero).
    """
    errors = np.asarray(errors, dtype=np.float64)
    thresholds = np.asarray(thresholds, dtype=np.float64)
    if len(errors) == 0:
        return np.full((len(thresholds),) + errors.shape[1:], np.nan)
    below = errors[None] < thresholds.reshape((-1,) + (1,) * errors.ndim)
    return below.mean(axis=1)


def _diameters(obj_id: np.ndarray, diameters_mm: Mapping[int, float]) -> np.ndarray:
    missing = sorted({int(i) for i in obj_id} - set(diameters_mm))
    if missing:
        raise PopcodeError(f"no diameter (models_info.json) for object ids {missing}")
    return np.array([diameters_mm[int(i)] for i in obj_id], dtype=np.float64)


def _normalised(
    errors: InstanceErrors, diameters_mm: Mapping[int, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MSSD and ADI as fractions of each object's diameter, and MSPD in pixels of a 640 px wide image ``(N,)``."""
    diameter = _diameters(errors.obj_id, diameters_mm)
    return errors.mssd_mm / diameter, errors.mspd_px * (640.0 / errors.image_width_px), errors.adi_mm / diameter


def _checked_vsd(errors: InstanceErrors, th: Thresholds) -> np.ndarray | None:
    """The VSD errors ``(N, T)``, one per tau of ``th``; ``None`` without depth."""
    if errors.vsd is not None and np.shape(errors.vsd)[1:] != (len(th.vsd_taus),):
        raise PopcodeError(
            f"VSD errors have shape {np.shape(errors.vsd)}; expected one per tau ({len(th.vsd_taus)})"
        )
    return errors.vsd


def metric_scores(
    errors: InstanceErrors, diameters_mm: Mapping[int, float], thresholds: Thresholds | None = None
) -> dict[str, float]:
    """Every metric's score in [0, 1] over all the given instances, pooled as BOP does.

    Depth-based metrics are absent from the result when their errors are ``None``.
    """
    th = thresholds or Thresholds()
    mssd_fraction, mspd_px_at_640, adi_fraction = _normalised(errors, diameters_mm)
    scores = {
        "MSSD": float(recall(mssd_fraction, th.mssd_fractions).mean()),
        "MSPD": float(recall(mspd_px_at_640, th.mspd_px_at_640).mean()),
        "ADI": float(recall(adi_fraction, [th.adi_fraction])[0]),
    }
    vsd = _checked_vsd(errors, th)
    if vsd is not None:
        scores["VSD"] = float(recall(vsd, th.vsd_thetas).mean())
    if errors.vsd_single_tau is not None:
        scores["e_VSD<0.3"] = float(recall(errors.vsd_single_tau, [th.vsd_single_theta])[0])
    if errors.vss is not None:
        scores["VSS"] = float(recall(errors.vss, th.vss_thetas).mean())
    return {name: scores[name] for name in METRICS if name in scores}


def tightest_thresholds(thresholds: Thresholds | None = None) -> dict[str, float]:
    """The smallest (tightest; the first in BOP19) value of each threshold list, by its :class:`Thresholds` field."""
    th = thresholds or Thresholds()
    names = ("mssd_fractions", "mspd_px_at_640", "vsd_taus", "vsd_thetas")
    return {name: float(min(getattr(th, name))) for name in names}


def tightest_recalls(
    errors: InstanceErrors, diameters_mm: Mapping[int, float], thresholds: Thresholds | None = None
) -> dict[str, float]:
    """Recall in [0, 1] at each metric's tightest BOP19 threshold alone, keyed by metric name.

    MSSD below the smallest of ``mssd_fractions`` (5 % of the diameter), MSPD below
    the smallest of ``mspd_px_at_640`` (5 px at 640 px width) and, with depth, VSD
    at the smallest tau below the smallest theta (0.05 at tau = 5 % of the
    diameter). The normalisation and the strictly-below rule are :func:`metric_scores`'s.
    """
    th = thresholds or Thresholds()
    first = tightest_thresholds(th)
    mssd_fraction, mspd_px_at_640, _ = _normalised(errors, diameters_mm)
    recalls = {
        "MSSD": float(recall(mssd_fraction, [first["mssd_fractions"]])[0]),
        "MSPD": float(recall(mspd_px_at_640, [first["mspd_px_at_640"]])[0]),
    }
    vsd = _checked_vsd(errors, th)
    if vsd is not None:
        tau_index = th.vsd_taus.index(first["vsd_taus"])
        recalls["VSD"] = float(recall(vsd[:, tau_index], [first["vsd_thetas"]])[0])
    return {name: recalls[name] for name in METRICS if name in recalls}


ScoreFunction = Callable[[InstanceErrors, Mapping[int, float], Thresholds | None], dict[str, float]]
"""``score(errors, diameters_mm, thresholds) -> {metric: value}``: :func:`metric_scores` or :func:`tightest_recalls`."""


def scores_per_object(
    errors: InstanceErrors, diameters_mm: Mapping[int, float], thresholds: Thresholds | None = None,
    score: ScoreFunction = metric_scores,
) -> dict[int, dict[str, float]]:
    """``score`` (by default :func:`metric_scores`) for each object id, in increasing id order."""
    obj_ids = np.asarray(errors.obj_id)
    return {
        int(obj): score(errors.select(obj_ids == obj), diameters_mm, thresholds)
        for obj in np.unique(obj_ids)
    }


GROUPS = ("Without ambiguity", "With ambiguity", "All objects")

def ambiguous_objects(models_info: Mapping[int, Mapping[str, Any]]) -> dict[int, bool]:
    """Object id -> whether its pose is ambiguous (any declared symmetry), from ``models_info.json``."""
    return {int(obj): symmetry_class(info) is not SymmetryClass.NONE for obj, info in models_info.items()}


def group_scores(
    errors: InstanceErrors,
    diameters_mm: Mapping[int, float],
    ambiguous: Mapping[int, bool],
    thresholds: Thresholds | None = None,
    average: Literal["instances", "objects"] = "instances",
    score: ScoreFunction = metric_scores,
) -> dict[str, dict[str, float]]:
    """Scores for the groups of :data:`GROUPS` (the paper's Table IV).

    ``average="instances"`` pools the instances of a group, as the BOP toolkit's
    recall does; ``"objects"`` averages the per-object scores. A group without
    instances has NaN scores. ``score`` computes them (e.g. :func:`tightest_recalls`).
    """
    obj_ids = np.asarray(errors.obj_id)
    unknown = sorted({int(i) for i in obj_ids} - set(ambiguous))
    if unknown:
        raise PopcodeError(f"no symmetry information for object ids {unknown}")
    is_ambiguous = np.array([ambiguous[int(i)] for i in obj_ids], dtype=bool)
    masks = dict(zip(GROUPS, (~is_ambiguous, is_ambiguous, np.ones_like(is_ambiguous)), strict=True))
    result = {}
    for group, mask in masks.items():
        chosen = errors.select(mask)
        if average == "instances":
            result[group] = score(chosen, diameters_mm, thresholds)
        elif average == "objects":
            per_object = scores_per_object(chosen, diameters_mm, thresholds, score).values()
            names = score(chosen, diameters_mm, thresholds).keys()
            result[group] = {name: float(np.mean([s[name] for s in per_object])) if per_object else math.nan
                             for name in names}
        else:
            raise PopcodeError(f"average must be 'instances' or 'objects', not {average!r}")
    return result


VISIBILITY_BINS: tuple[tuple[str, float, float], ...] = (
    (">= 0.9", 0.9, math.inf), ("0.6-0.9", 0.6, 0.9), ("0.3-0.6", 0.3, 0.6), ("0.1-0.3", 0.1, 0.3))
"""``(label, low, high)``: an instance with ``low <= visib_fract < high`` falls into the bin (BOP19 tests >= 0.1)."""


def binned_scores(
    errors: InstanceErrors, values: np.ndarray, bins: Sequence[tuple[str, float, float]],
    diameters_mm: Mapping[int, float], thresholds: Thresholds | None = None, what: str = "values",
) -> dict[str, dict[str, float]]:
    """Scores (:func:`metric_scores`, pooled over instances) per bin ``(label, low, high)`` of one value per
    instance (``low <= value < high``), each with its instance count under ``"instances"``; a bin without
    instances has NaN scores. ``what`` names the values in errors."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape != np.shape(errors.obj_id):
        raise PopcodeError(f"{len(values)} {what} for {len(errors.obj_id)} instances")
    result = {}
    for label, low, high in bins:
        chosen = (values >= low) & (values < high)
        result[label] = {**metric_scores(errors.select(chosen), diameters_mm, thresholds),
                         "instances": float(chosen.sum())}
    return result


def visibility_scores(
    errors: InstanceErrors, visib_fract: np.ndarray, diameters_mm: Mapping[int, float],
    thresholds: Thresholds | None = None,
) -> dict[str, dict[str, float]]:
    """:func:`binned_scores` per bin of :data:`VISIBILITY_BINS`."""
    return binned_scores(errors, visib_fract, VISIBILITY_BINS, diameters_mm, thresholds, "visibilities")
