"""Declared symmetries checked against the mesh (issue 19, build 3).

A ``models_info.json`` entry that declares a symmetry the part does not have
(a flange called 4-fold) or only part of a group (a hex nut with its 60°
rotation alone) trains a code with the wrong peaks, without a word. So every
declared discrete transform, and each continuous one at a few angles, must
carry surface samples back onto the surface, and the discrete set plus the
identity must be closed under composition. A generator alone is refused, not
completed: the file is what the metrics and the model metadata read, so it
must list the whole group itself.

Distances are measured as :mod:`.surface_sample` describes. A mesh that nearly has a symmetry it does
not declare gets a warning (:mod:`.near_symmetry`).
"""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from popcode_runtime.geometry.symmetries import continuous_symmetries, discrete_transforms

from .bop import model_path
from .closure import closure
from .meshes import load_mesh
from .near_symmetry import LookAlike, look_alike_symmetries
from .surface_sample import PERCENTILE, SurfaceSample, diameter_mm, surface_distance, surface_sample

TOLERANCE = 0.02  # of the diameter: the percentile distance a true symmetry stays under
GROUP_TOLERANCE = 0.01  # of the diameter: two transforms that move no anchor further are the same
CONTINUOUS_ANGLES_DEG = (37.0, 90.0, 180.0, 251.0)  # incommensurate with small n-folds
MAX_GROUP = 1000  # elements; a declared set whose closure grows past this is no finite group

_checked: dict[tuple[Any, ...], tuple[LookAlike, ...]] = {}  # (mesh file, its size and mtime, declaration) passed
# (digest of the mesh file's bytes, its models_info entry) that passed -> the look-alikes found: the same part copied
# into another folder (each split holds its models) is not sampled again, and warns as a new file does.
_passed: dict[tuple[str, str], tuple[LookAlike, ...]] = {}


@dataclass(frozen=True)
class Transform:
    """``x -> R x + t_mm`` with the name it was declared under."""

    R: np.ndarray  # (3, 3)
    t_mm: np.ndarray  # (3,)
    name: str

    def then(self, other: Transform) -> Transform:
        """``other`` applied after ``self``."""
        return Transform(other.R @ self.R, other.R @ self.t_mm + other.t_mm,
                         f"{other.name} after {self.name}")


def describe(R: np.ndarray, t_mm: np.ndarray) -> str:
    """A transform as a person reads it: axis, angle [deg] and translation [mm]."""
    axis, angle = matrix_to_axis_angle(np.asarray(R, dtype=np.float64))
    text = f"rotation {np.rad2deg(float(angle)):.1f} deg about ({_numbers(axis)})"
    if np.abs(t_mm).max() > 1e-6:
        text += f" + translation ({_numbers(t_mm)}) mm"
    return text


def _numbers(values: np.ndarray) -> str:
    return ", ".join(f"{v + 0.0:.3g}" for v in values)  # + 0.0: no "-0"


def _refuse(name: str, what: str, share: float) -> None:
    if share > TOLERANCE:
        raise PopcodeError(
            f"{name}: {what} does not map the mesh onto itself: surface samples land {100 * share:.1f} % of the "
            f"diameter away from the surface ({PERCENTILE:g}th percentile, tolerance {100 * TOLERANCE:g} %); "
            "fix or remove it in models_info.json")


def _anchors_mm(info: Mapping[str, Any], diameter_mm: float) -> np.ndarray:
    """Points whose images tell transforms apart: on the continuous axis when there is one (rotations about it
    are then the same pose), else four points that span space."""
    continuous = continuous_symmetries(info)
    if continuous:
        axis, offset = continuous[0]
        return np.stack([offset, offset + 0.5 * diameter_mm * axis])
    return np.vstack([np.zeros(3), 0.5 * diameter_mm * np.eye(3)])


def _same(a: Transform, b: Transform, anchors_mm: np.ndarray, tolerance_mm: float) -> bool:
    moved_a = anchors_mm @ a.R.T + a.t_mm
    moved_b = anchors_mm @ b.R.T + b.t_mm
    return float(np.abs(moved_a - moved_b).max()) <= tolerance_mm


def check_closed(info: Mapping[str, Any], name: str, diameter_mm: float) -> None:
    """Refuse a declared discrete set that, with the identity, is not closed under composition.

    Composition is compared up to the continuous symmetry when there is one;
    the message lists what the closure adds, which the user must declare.
    """
    transforms = discrete_transforms(info)
    declared = [Transform(R, t, "identity" if k == 0 else f"symmetries_discrete[{k - 1}]")
                for k, (R, t) in enumerate(zip(transforms.R, transforms.t_mm, strict=True))]
    anchors, tolerance = _anchors_mm(info, diameter_mm), GROUP_TOLERANCE * diameter_mm
    group, missing, closed = closure(declared, declared, Transform.then,
                                     lambda t, group: any(_same(t, g, anchors, tolerance) for g in group), MAX_GROUP)
    if not closed:
        raise PopcodeError(f"{name}: the declared discrete symmetries generate more than "
                           f"{MAX_GROUP} transforms; they are not the symmetries of a rigid part")
    if missing:
        first = missing[0]
        raise PopcodeError(
            f"{name}: the declared discrete symmetries are not closed under composition: {first.name} "
            f"({describe(first.R, first.t_mm)}) is not declared, and the group lacks {len(missing)} in all; "
            f"declare all {len(group) - 1} non-identity symmetries in symmetries_discrete, not only a generator")


def check_symmetries(mesh: trimesh.Trimesh, info: Mapping[str, Any], name: str,
                     sample: SurfaceSample | None = None) -> None:
    """Refuse declared symmetries that do not map ``mesh`` onto itself or do not form a group (PopcodeError)."""
    transforms, continuous = discrete_transforms(info), continuous_symmetries(info)
    if len(transforms) == 1 and not continuous:
        return
    diameter = diameter_mm(mesh, info)
    sample = sample or surface_sample(mesh, diameter, name)
    for k in range(1, len(transforms)):
        R, t = transforms.R[k], transforms.t_mm[k]
        _refuse(name, f"symmetries_discrete[{k - 1}] ({describe(R, t)})", surface_distance(sample, R, t))
    for k, (axis, offset) in enumerate(continuous):
        R_all = axis_angle_to_matrix(np.broadcast_to(axis, (len(CONTINUOUS_ANGLES_DEG), 3)),
                                     np.deg2rad(CONTINUOUS_ANGLES_DEG))
        shares = [surface_distance(sample, R, offset - R @ offset) for R in R_all]
        worst = int(np.argmax(shares))
        _refuse(name, f"symmetries_continuous[{k}] (axis ({_numbers(axis)}) through ({_numbers(offset)}) mm, "
                      f"turned {CONTINUOUS_ANGLES_DEG[worst]:g} deg)", shares[worst])
    check_closed(info, name, diameter)


def _declaration(info: Mapping[str, Any]) -> str:
    keys = ("diameter", "symmetries_discrete", "symmetries_continuous")
    return json.dumps({key: info.get(key) for key in keys}, sort_keys=True, default=str)


def check_object_symmetries(mesh_path: str | Path, info: Mapping[str, Any], obj_id: int,
                            mesh: trimesh.Trimesh | None = None) -> tuple[LookAlike, ...]:
    """:func:`check_symmetries` of one object's mesh file, and a warning for each symmetry it nearly has
    without declaring it (:func:`.near_symmetry.look_alike_symmetries`), once per file and declaration in a
    process; a file with the bytes and entry of one that passed is not checked again, only warned about.
    Returns those look-alike symmetries."""
    path = Path(mesh_path)
    stat = path.stat()
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns, _declaration(info))
    if key in _checked:
        return _checked[key]
    content = (hashlib.sha256(path.read_bytes()).hexdigest(), json.dumps(info, sort_keys=True, default=str))
    look_alikes = _passed.get(content)
    if look_alikes is None:
        mesh = load_mesh(path) if mesh is None else mesh
        name = f"object {obj_id} ({path})"
        diameter = diameter_mm(mesh, info)
        sample = surface_sample(mesh, diameter, name)
        check_symmetries(mesh, info, name, sample)
        look_alikes = _passed[content] = tuple(look_alike_symmetries(sample, info, _anchors_mm(info, diameter)))
    for look_alike in look_alikes:
        warnings.warn(look_alike.describe(f"object {obj_id}"), stacklevel=2)
    _checked[key] = look_alikes
    return look_alikes


def check_models_symmetries(models_dir: str | Path, models_info: Mapping[int, Mapping[str, Any]],
                            obj_ids: Iterable[int]) -> None:
    """Check the objects ``obj_ids`` of a models folder; objects without a mesh file get a warning."""
    unchecked = []
    for obj_id in obj_ids:
        try:
            path = model_path(models_dir, obj_id)
        except PopcodeError:
            path = None
        if path is not None:
            check_object_symmetries(path, models_info[obj_id], obj_id)
        elif continuous_symmetries(models_info[obj_id]) or len(discrete_transforms(models_info[obj_id])) > 1:
            unchecked.append(obj_id)
    if unchecked:
        warnings.warn(f"no mesh in {models_dir} for objects {unchecked}: their declared symmetries are not checked",
                      stacklevel=2)
