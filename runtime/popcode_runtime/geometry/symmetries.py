"""Object symmetries from BOP ``models_info.json`` entries.

A BOP entry lists ``symmetries_discrete`` (row-major 4x4 matrices, translation
in mm) and ``symmetries_continuous`` (``{"axis": [...], "offset": [...]}``).
The transformations map the model onto itself: ``x -> R x + t``.
"""

from __future__ import annotations

import contextlib
import itertools
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..base.checks import shown
from ..base.errors import PopcodeError
from ..base.limits import MAX_CONTINUOUS_SYMMETRIES, MAX_DISCRETE_SYMMETRIES
from ..base.text_enum import TextEnum
from .rotations import axis_angle_to_matrix, geodesic_angle


class SymmetryClass(TextEnum):
    """How a pose of the object is ambiguous; decides which code it can use."""

    NONE = "none"
    DISCRETE = "discrete"
    CONTINUOUS = "continuous"


@dataclass(frozen=True)
class SymmetryTransforms:
    """Symmetry transformations ``x -> R[k] x + t[k]``; index 0 is the identity."""

    R: np.ndarray  # (K, 3, 3)
    t_mm: np.ndarray  # (K, 3)

    def __len__(self) -> int:
        return len(self.R)


def _declared(info: Mapping[str, Any], key: str, limit: int) -> Sequence[Any]:
    """The list under ``key`` (absent or null: empty), its length checked before any entry is read."""
    value = info.get(key)
    if value is None:
        return []
    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, (Sequence, np.ndarray)):
        raise PopcodeError(f"{key} must be a list, got {shown(value)} ({type(value).__name__})")
    if len(value) > limit:
        raise PopcodeError(f"{key} lists {len(value)} symmetries; at most {limit} are allowed (the part's group, "
                           "each symmetry once)")
    return value


_JSON_NUMBERS = {int, float}  # exactly these types (a bool is an int subclass, not one of them)


def _numbers(value: Any, name: str, count: int) -> np.ndarray:
    """``count`` numbers as float64; text and true/false are refused, not coerced (``"1"`` and ``true`` are no 1)."""
    items = np.asarray(value, dtype=object).ravel() if isinstance(value, (Sequence, np.ndarray)) else None
    if items is None or isinstance(value, (str, bytes)) or not all(
            isinstance(item, numbers.Real) and not isinstance(item, (bool, np.bool_)) for item in items):
        raise PopcodeError(f"{name} is not a list of numbers: got {shown(value)}")
    if items.size != count:
        raise PopcodeError(f"{name} has {items.size} numbers; {count} are needed")
    try:
        array = items.astype(np.float64)
    except OverflowError as error:  # an integer beyond a float's range
        raise PopcodeError(f"{name} contains NaN or inf") from error
    if not np.isfinite(array).all():
        raise PopcodeError(f"{name} contains NaN or inf")
    return array


def _discrete(info: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The declared rotations and translations, identity first; a model's list at the limit is read in a
    millisecond or two, as every object is read several times when a model loads."""
    declared = _declared(info, "symmetries_discrete", MAX_DISCRETE_SYMMETRIES)
    flats = None
    if all(type(flat) is list and len(flat) == 16 for flat in declared) and \
            set(map(type, itertools.chain.from_iterable(declared))) <= _JSON_NUMBERS:
        with contextlib.suppress(OverflowError):  # an integer beyond a float's range: named below
            flats = np.array(declared, dtype=np.float64).reshape(-1, 16)  # as JSON gives them: read at once
    if flats is None or not np.isfinite(flats).all():  # anything else one by one: the first that is not 16 numbers
        flats = np.array([_numbers(flat, f"symmetries_discrete[{index}]", 16) for index, flat in enumerate(declared)]
                         ).reshape(-1, 16)
    matrices = np.concatenate([np.eye(4)[None], flats.reshape(-1, 4, 4)])
    R = matrices[:, :3, :3]
    proper = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2)) <= 1e-3
    proper &= np.linalg.det(R) >= 0
    if not proper.all():
        raise PopcodeError(f"symmetries_discrete[{int(np.argmin(proper)) - 1}] is not a proper rotation")
    return R.copy(), matrices[:, :3, 3].copy()


def _continuous(info: Mapping[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    result = []
    for index, sym in enumerate(_declared(info, "symmetries_continuous", MAX_CONTINUOUS_SYMMETRIES)):
        name = f"symmetries_continuous[{index}]"
        if not isinstance(sym, Mapping) or "axis" not in sym:
            raise PopcodeError(f"{name} needs 'axis' and 'offset' as 3 numbers each")
        axis = _numbers(sym["axis"], f"{name} axis", 3)
        offset = _numbers(sym.get("offset", [0, 0, 0]), f"{name} offset", 3)
        norm = np.linalg.norm(axis)
        if not np.isfinite(norm) or norm < 1e-9:
            raise PopcodeError(f"{name} has a zero or invalid axis")
        result.append((axis / norm, offset))
    return result


def symmetry_transforms(info: Mapping[str, Any], max_sym_disc_step: float = 0.01) -> SymmetryTransforms:
    """All symmetry transformations of an object, identity first.

    Continuous symmetries are discretised as the BOP toolkit does: ``ceil(pi /
    max_sym_disc_step)`` rotations about the axis (so the vertex furthest from
    the axis moves at most ``max_sym_disc_step`` of the diameter between two),
    each combined with every discrete symmetry as ``continuous o discrete``.
    """
    R_disc, t_disc = _discrete(info)
    continuous = _continuous(info)
    if not continuous:
        return SymmetryTransforms(R_disc, t_disc)
    steps = int(np.ceil(np.pi / max_sym_disc_step))
    angles = np.arange(steps) * (2.0 * np.pi / steps)
    R_list, t_list = [], []
    for axis, offset in continuous:
        R_cont = axis_angle_to_matrix(np.broadcast_to(axis, (steps, 3)), angles)
        t_cont = offset - R_cont @ offset
        # Order as the toolkit: for each discrete symmetry, every continuous step.
        R_list.append(np.einsum("cij,djk->dcik", R_cont, R_disc).reshape(-1, 3, 3))
        t_list.append((np.einsum("cij,dj->dci", R_cont, t_disc) + t_cont[None]).reshape(-1, 3))
    return SymmetryTransforms(np.concatenate(R_list), np.concatenate(t_list))


def discrete_transforms(info: Mapping[str, Any]) -> SymmetryTransforms:
    """The declared ``symmetries_discrete`` as given (translations kept), identity first; no continuous steps."""
    return SymmetryTransforms(*_discrete(info))


def continuous_symmetries(info: Mapping[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The declared ``symmetries_continuous`` as (unit axis ``(3,)``, offset ``(3,)`` [mm]) pairs."""
    return _continuous(info)


def symmetry_rotations(info: Mapping[str, Any]) -> np.ndarray:
    """The discrete symmetry rotations ``(K, 3, 3)``, identity first (what the code encodes).

    Continuous symmetries are not listed: the axis-only code absorbs them.
    """
    return _discrete(info)[0]


def symmetry_class(info: Mapping[str, Any]) -> SymmetryClass:
    """Classify an object: continuous beats discrete beats none."""
    if _continuous(info):
        return SymmetryClass.CONTINUOUS
    if len(_discrete(info)[0]) > 1:
        return SymmetryClass.DISCRETE
    return SymmetryClass.NONE


def continuous_axis(info: Mapping[str, Any]) -> np.ndarray:
    """Unit axis of the object's continuous symmetry (model frame)."""
    continuous = _continuous(info)
    if not continuous:
        raise PopcodeError("the object has no continuous symmetry")
    if len(continuous) > 1:
        first = continuous[0][0]
        if any(abs(abs(float(first @ axis)) - 1.0) > 1e-6 for axis, _ in continuous[1:]):
            raise PopcodeError(
                "the object has continuous symmetries about several axes (e.g. a sphere); "
                "its rotation cannot be encoded"
            )
    return continuous[0][0]


def rotation_error_up_to_symmetry(R_pred: np.ndarray, R_true: np.ndarray, symmetries: np.ndarray,
                                  symmetry_axis: np.ndarray | None = None) -> np.ndarray:
    """Rotation error ``(N,)`` [rad] of ``R_pred`` against every equivalent ``R_true S_k``.

    ``symmetries`` ``(K, 3, 3)`` are the discrete ones (identity included). With
    a continuous symmetry about ``symmetry_axis`` only that axis is defined, so
    the error is the angle between the predicted and the true axis.
    """
    equivalent = np.asarray(R_true)[:, None] @ np.asarray(symmetries)[None]  # (N, K, 3, 3)
    if symmetry_axis is None:
        return geodesic_angle(np.asarray(R_pred)[:, None], equivalent).min(axis=1)
    a = np.asarray(symmetry_axis, dtype=np.float64)
    cos = np.einsum("ni,nki->nk", np.asarray(R_pred) @ a, equivalent @ a)
    return np.arccos(np.clip(cos, -1.0, 1.0)).min(axis=1)
