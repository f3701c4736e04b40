"""Surface samples of a mesh and how far a rigid motion carries them off the surface: what the symmetry checks
measure with.

The distance of a moved sample to the surface is measured to a denser sample of the same surface (a k-d
tree), an upper bound of the true distance that exceeds it by about half the sample spacing (its target:
``_SPACING`` of the diameter).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from popcode_runtime.errors import PopcodeError

PERCENTILE = 99.0  # of the moved samples; tolerates a stray sliver, not a misplaced feature
_QUERY_POINTS = 1000
_SPACING = 0.004  # of the diameter: target spacing of the reference sample
_REFERENCE_POINTS = (20_000, 200_000)
_SEED = 0


@dataclass(frozen=True)
class SurfaceSample:
    """Sparse query points and a dense reference sample of one mesh's surface [mm]."""

    points_mm: np.ndarray  # (P, 3)
    reference: cKDTree
    diameter_mm: float


def diameter_mm(mesh: trimesh.Trimesh, info: Mapping[str, Any]) -> float:
    """The declared diameter when it is a positive number, else the bounding-box diagonal."""
    declared = info.get("diameter")
    if isinstance(declared, (int, float)) and np.isfinite(declared) and declared > 0:
        return float(declared)
    return float(np.linalg.norm(mesh.extents))


def surface_sample(mesh: trimesh.Trimesh, diameter_mm: float, name: str) -> SurfaceSample:
    """Seeded surface samples of ``mesh``: the reference dense enough to resolve 2 % of the diameter."""
    area = float(mesh.area)
    if not np.isfinite(area) or area <= 0:
        raise PopcodeError(f"{name}: the mesh has no surface area; its symmetries cannot be checked")
    low, high = _REFERENCE_POINTS
    count = int(np.clip(area / (_SPACING * diameter_mm) ** 2, low, high))
    reference, _ = trimesh.sample.sample_surface(mesh, count, seed=_SEED)
    points, _ = trimesh.sample.sample_surface(mesh, _QUERY_POINTS, seed=_SEED + 1)
    return SurfaceSample(np.asarray(points), cKDTree(np.concatenate([reference, mesh.vertices])), diameter_mm)


def surface_distance(sample: SurfaceSample, R: np.ndarray, t_mm: np.ndarray, percentile: float = PERCENTILE) -> float:
    """How far the moved samples lie from the surface: the ``percentile`` distance, as a share of the diameter."""
    distance, _ = sample.reference.query(sample.points_mm @ np.asarray(R).T + t_mm)
    return float(np.percentile(distance, percentile)) / sample.diameter_mm
