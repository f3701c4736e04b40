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
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.limits import MAX_DISCRETE_SYMMETRIES
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from popcode_runtime.geometry.symmetries import continuous_symmetries, discrete_transforms

from .bop import model_path
from .meshes import load_mesh
from .near_symmetry import LookAlike, LookAlikeWarning, look_alike_symmetries
from .surface_sample import PERCENTILE, SurfaceSample, diameter_mm, surface_distance, surface_sample

TOLERANCE = 0.02  # of the diameter: the percentile distance a true symmetry stays under
GROUP_TOLERANCE = 0.01  # of the diameter: two transforms that move no anchor further are the same
REPEAT_TOLERANCE = 1e-6  # of the diameter: a declared transform this close to an earlier one is listed twice
CONTINUOUS_ANGLES_DEG = (37.0, 90.0, 180.0, 251.0)  # incommensurate with small n-folds
MAX_GROUP = MAX_DISCRETE_SYMMETRIES + 1  # elements, the identity too: a larger closure cannot be declared
_PRODUCT_BLOCK = 1 << 16  # compositions composed and looked up at once (about 20 MB)

_checked: dict[tuple[Any, ...], tuple[LookAlike, ...]] = {}  # (mesh file, its size and mtime, declaration) passed
# (digest of the mesh file's bytes, its models_info entry) that passed -> the look-alikes found: the same part copied
# into another folder (each split holds its models) is not sampled again, and warns as a new file does.
_passed: dict[tuple[str, str], tuple[LookAlike, ...]] = {}


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


def _images(R: np.ndarray, t_mm: np.ndarray, anchors_mm: np.ndarray) -> np.ndarray:
    """Where transforms ``(K, 3, 3)``, ``(K, 3)`` move the anchors, one row ``(K, 3 A)`` per transform: two rows
    within the group tolerance (largest coordinate difference) are the same transform."""
    return (np.einsum("kij,aj->kai", R, anchors_mm) + t_mm[:, None]).reshape(len(R), anchors_mm.size)


def _distinct(images: np.ndarray, tolerance_mm: float, budget: int) -> list[int]:
    """Indices of the rows that differ from every earlier kept row, in order; stops once more than ``budget`` are
    kept. Rows in one cell of a ``tolerance_mm`` grid (repeats) are looked at once, so a million repeats cost one
    sort, not a million comparisons."""
    _, first = np.unique(np.floor(images / tolerance_mm), axis=0, return_index=True)
    kept: list[int] = []
    for index in np.sort(first):
        if not kept or np.abs(images[kept] - images[index]).max(axis=1).min() > tolerance_mm:
            kept.append(int(index))
            if len(kept) > budget:
                break
    return kept


def _closure(R: np.ndarray, t_mm: np.ndarray, anchors_mm: np.ndarray, tolerance_mm: float
             ) -> tuple[np.ndarray, np.ndarray, bool, tuple[int, int]]:
    """The transforms that ``(R, t_mm)`` (the identity and the declared ones) generate, breadth first: each new
    element composed with every declared one, a product kept unless it is an element already. Returns the
    elements (declared first, then in the order found), whether they closed within :data:`MAX_GROUP`, and the
    indices ``(a, b)`` of the first product found (declared ``b`` after declared ``a``; ``(0, 0)`` if none).

    Vectorised: products are composed in blocks and looked up in a k-d tree of the elements, so a declared list at
    the limit costs seconds, not the hours of comparing a million products one by one."""
    group_R, group_t, group_images = [R], [t_mm], [_images(R, t_mm, anchors_mm)]
    frontier_R, frontier_t, first = R, t_mm, None
    bound = np.nextafter(tolerance_mm, np.inf)  # the tree finds neighbours strictly nearer than its bound
    rows = max(1, _PRODUCT_BLOCK // len(R))
    while len(frontier_R):
        tree = cKDTree(np.concatenate(group_images))
        room = MAX_GROUP - sum(len(elements) for elements in group_R)
        new_R, new_t, new_images = R[:0], t_mm[:0], group_images[0][:0]  # this round's elements, each once
        for start in range(0, len(frontier_R), rows):
            a_R, a_t = frontier_R[start:start + rows], frontier_t[start:start + rows]
            product_R = np.einsum("bij,fjk->fbik", R, a_R).reshape(-1, 3, 3)  # declared b after element a
            product_t = (np.einsum("bij,fj->fbi", R, a_t) + t_mm).reshape(-1, 3)
            images = _images(product_R, product_t, anchors_mm)
            unknown = np.flatnonzero(np.isinf(tree.query(images, p=np.inf, distance_upper_bound=bound)[0]))
            if first is None and len(unknown):  # the first round's frontier is the declared list itself
                first = divmod(start * len(R) + int(unknown[0]), len(R))
            new_R, new_t = np.concatenate([new_R, product_R[unknown]]), np.concatenate([new_t, product_t[unknown]])
            new_images = np.concatenate([new_images, images[unknown]])
            kept = _distinct(new_images, tolerance_mm, room)  # the round's earlier elements stay first
            new_R, new_t, new_images = new_R[kept], new_t[kept], new_images[kept]
            if len(kept) > room:
                return np.concatenate([*group_R, new_R]), np.concatenate([*group_t, new_t]), False, first or (0, 0)
        group_R.append(new_R)
        group_t.append(new_t)
        group_images.append(new_images)
        frontier_R, frontier_t = new_R, new_t
    return np.concatenate(group_R), np.concatenate(group_t), True, first or (0, 0)


def check_closed(info: Mapping[str, Any], name: str, diameter_mm: float) -> None:
    """Refuse a declared discrete set that repeats a transform or, with the identity, is not closed under
    composition.

    Closure is judged up to the continuous symmetry when there is one; the message names the first composition
    the group lacks and how many it lacks in all, which the user must declare.
    """
    transforms = discrete_transforms(info)  # at most MAX_DISCRETE_SYMMETRIES: counted before any is read
    R, t = transforms.R, transforms.t_mm
    anchors, tolerance = _anchors_mm(info, diameter_mm), GROUP_TOLERANCE * diameter_mm
    # a repeat is the same transform twice, told apart on points that span space: two flips that differ by a turn
    # about a continuous axis are one pose up to that symmetry, yet both may be listed (BOP's models do)
    images = _images(R, t, _anchors_mm({}, diameter_mm))
    distinct = _distinct(images, REPEAT_TOLERANCE * diameter_mm, len(R))
    if len(distinct) < len(R):
        repeat = next(k for k, kept in enumerate([*distinct, len(R)]) if k != kept)
        earlier = int(np.abs(images[:repeat] - images[repeat]).max(axis=1).argmin())
        raise PopcodeError(f"{name}: {_name(repeat)} ({describe(R[repeat], t[repeat])}) repeats {_name(earlier)}; "
                           "list each symmetry once, and not the identity")
    group_R, group_t, closed, (a, b) = _closure(R, t, anchors, tolerance)
    if not closed:
        raise PopcodeError(f"{name}: the declared discrete symmetries generate more than {MAX_DISCRETE_SYMMETRIES} "
                           "transforms besides the identity, more than models_info.json may list; they are not the "
                           "symmetries of a rigid part")
    missing = len(group_R) - len(R)
    if missing:
        raise PopcodeError(
            f"{name}: the declared discrete symmetries are not closed under composition: {_name(b)} after "
            f"{_name(a)} ({describe(group_R[len(R)], group_t[len(R)])}) is not declared, and the group lacks "
            f"{missing} in all; declare all {len(group_R) - 1} non-identity symmetries in symmetries_discrete, "
            "not only a generator")


def _name(index: int) -> str:
    """A transform by its place in the identity-first list."""
    return "the identity" if index == 0 else f"symmetries_discrete[{index - 1}]"


def check_symmetries(mesh: trimesh.Trimesh, info: Mapping[str, Any], name: str,
                     sample: SurfaceSample | None = None) -> None:
    """Refuse declared symmetries that do not map ``mesh`` onto itself or do not form a group (PopcodeError)."""
    transforms, continuous = discrete_transforms(info), continuous_symmetries(info)
    if len(transforms) == 1 and not continuous:
        return
    diameter = diameter_mm(mesh, info)
    check_closed(info, name, diameter)  # first: it costs no surface query per declared transform
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
        warnings.warn(look_alike.describe(f"object {obj_id}"), LookAlikeWarning, stacklevel=2)
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
