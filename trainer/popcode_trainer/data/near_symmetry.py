"""Symmetries a mesh almost has: look-alike poses the declaration does not list.

Real parts are often symmetric but for one small hole, notch or flat. Declared, correctly, without
that symmetry, they show look-alike poses whose crops differ only where the feature shows; a
trainer that is not told learns them slowly, and a user should decide whether the feature is ever
visible (then expect look-alike poses, which ``--top-k`` lists) or not (then declare the symmetry).
Candidates are n-fold rotations about the surface's principal axes and the model axes through its
centroid; one is reported when it carries :data:`LOOK_ALIKE_PERCENTILE` of the surface samples within
:data:`LOOK_ALIKE_TOLERANCE` of the diameter onto the surface (:func:`.surface_sample.surface_distance`)
and no declared symmetry does the same.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_runtime.geometry.symmetries import discrete_transforms

from .closure import closure
from .surface_sample import SurfaceSample, surface_distance

LOOK_ALIKE_TOLERANCE = 0.02  # of the diameter: most of the surface lands this close to itself in a look-alike pose
LOOK_ALIKE_PERCENTILE = 90.0  # of the moved samples: the feature that breaks the symmetry may be a tenth of the surface
ORDERS = (2, 3, 4, 5, 6, 8, 12)
SAME_AXIS_COS = 0.995  # candidate axes closer than about 6 deg are one
SAME_TRANSFORM = 0.02  # of the diameter: a candidate that moves no anchor further from a declared symmetry is it
SAME_ROTATION = 1e-6  # largest element difference of two rotation matrices that are one
MAX_LOOK_ALIKE_POSES = 1000  # look-alike axes a little off the declared ones would generate ever more poses


class LookAlikeWarning(UserWarning):
    """A part nearly has a symmetry it does not declare (a pretraining on look-alike parts made so silences it)."""


@dataclass(frozen=True)
class LookAlike:
    """An n-fold rotation that nearly maps the mesh onto itself."""

    order: int
    axis: np.ndarray  # (3,) unit, model frame
    distance_mm: float  # 99th-percentile distance of moved surface samples to the surface
    diameter_mm: float

    def describe(self, name: str) -> str:
        axis = _axis_name(self.axis)
        share = 100 * self.distance_mm / self.diameter_mm
        return (f"{name} looks {self.order}-fold symmetric about {axis}: {LOOK_ALIKE_PERCENTILE:g} % of its surface "
                f"lands within {self.distance_mm:.1f} mm ({share:.1f} % of its diameter), yet it declares no such "
                "symmetry: declare it in models_info.json if "
                "the feature that breaks it is never visible, else expect look-alike poses (`popcode predict "
                "--top-k 2` lists them) and a slower start of training")


def _axis_name(axis: np.ndarray) -> str:
    for index, label in enumerate("xyz"):
        if abs(abs(axis[index]) - 1.0) < 1e-3:
            return label
    return "(" + ", ".join(f"{v + 0.0:.2f}" for v in axis) + ")"


def _candidate_axes(points_mm: np.ndarray) -> list[np.ndarray]:
    centred = points_mm - points_mm.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    axes: list[np.ndarray] = []
    for axis in [*np.eye(3), *vectors.T]:
        axis = axis / np.linalg.norm(axis)
        if all(abs(float(axis @ kept)) < SAME_AXIS_COS for kept in axes):
            axes.append(axis)
    return axes


def _declared(R: np.ndarray, t_mm: np.ndarray, info: Mapping[str, Any], anchors_mm: np.ndarray,
              tolerance_mm: float) -> bool:
    """Whether a declared symmetry is this transform: equal on the anchors, which lie on the continuous axis when
    there is one (a rotation about it then counts as the identity)."""
    moved = anchors_mm @ R.T + t_mm
    transforms = discrete_transforms(info)
    return any(np.abs(anchors_mm @ R_k.T + t_k - moved).max() <= tolerance_mm
               for R_k, t_k in zip(transforms.R, transforms.t_mm, strict=True))


def look_alike_symmetries(sample: SurfaceSample, info: Mapping[str, Any], anchors_mm: np.ndarray
                          ) -> list[LookAlike]:
    """Undeclared n-fold rotations that carry most of a mesh's surface (``sample``) onto itself
    (:data:`LOOK_ALIKE_PERCENTILE` of the samples within :data:`LOOK_ALIKE_TOLERANCE`), the highest such order per
    axis. ``anchors_mm``: points that tell two transforms apart up to the declared continuous symmetry."""
    diameter = sample.diameter_mm
    centre = sample.centroid_mm
    found = []
    for axis in _candidate_axes(sample.points_mm):
        for order in sorted(ORDERS, reverse=True):
            R = axis_angle_to_matrix(axis, 2 * np.pi / order)
            t = centre - R @ centre
            share = surface_distance(sample, R, t, LOOK_ALIKE_PERCENTILE, within=LOOK_ALIKE_TOLERANCE)
            if share <= LOOK_ALIKE_TOLERANCE:
                if not _declared(R, t, info, anchors_mm, SAME_TRANSFORM * diameter):
                    found.append(LookAlike(order, axis, share * diameter, diameter))
                break  # the highest order that fits: its powers (the lower orders) look alike too
    return found


def look_alike_rotations(look_alikes: Sequence[LookAlike], symmetries: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)``: the declared ``symmetries`` (rotations, identity first) closed under composition with the
    look-alike turns, each once, at most :data:`MAX_LOOK_ALIKE_POSES` (the rotation part only, which is all a
    rotation error sees). They are the poses an estimate cannot be told from where the feature that breaks the
    symmetry is hidden."""
    turns = [axis_angle_to_matrix(look_alike.axis, 2 * np.pi / look_alike.order) for look_alike in look_alikes]
    declared = [np.asarray(R, dtype=np.float64) for R in symmetries]
    poses, _, _ = closure(declared, [*turns, *declared], np.matmul,
                          lambda R, poses: bool(np.abs(np.asarray(poses) - R).max(axis=(1, 2)).min() <= SAME_ROTATION),
                          MAX_LOOK_ALIKE_POSES)
    return np.stack(poses[:MAX_LOOK_ALIKE_POSES])
