"""Solids for parts made in code: plates with holes extruded from their outline, solids placed by a rotation and an
offset, and the rotation sets of n-fold parts -- what the project's own parts (``tools.own_parts``) and the generated
pretraining parts (:mod:`.generated_parts`) are built from.

Plates with holes are extruded from a Delaunay triangulation of their outline (no boolean engine needed); parts of
several solids overlap, as the built-in parts do. A circle's vertex count must be a multiple of every rotation order
that should map it onto itself, so each declared symmetry holds to rounding.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh
from scipy.spatial import Delaunay

from .objects import rotation_4x4

_STEP_MM = 1.5  # longest outline edge: Delaunay then keeps the outline where features are >= 3 mm apart
CIRCLE_SECTIONS = 48  # vertices of a hole or boss circle; divisible by 2, 3, 4, 6, 8 and 12, so those rotations keep it


class TriangulationError(RuntimeError):
    """A plate's outline and holes lie too close for its triangulation (features under 3 mm apart)."""


def circle(radius_mm: float, centre_mm: tuple[float, float] = (0.0, 0.0),
            sections: int = CIRCLE_SECTIONS) -> np.ndarray:
    """``(sections, 2)`` points of a circle, the first at angle 0 (so a mirror about x keeps it)."""
    angle = 2 * np.pi * np.arange(sections) / sections
    return np.asarray(centre_mm) + radius_mm * np.column_stack([np.cos(angle), np.sin(angle)])


def _densify(ring_mm: np.ndarray, step_mm: float = _STEP_MM) -> np.ndarray:
    """A closed polygon ``(N, 2)`` with every edge split into pieces no longer than ``step_mm``."""
    following = np.roll(ring_mm, -1, axis=0)
    pieces = []
    for start, end in zip(ring_mm, following, strict=True):
        count = max(1, int(np.ceil(np.linalg.norm(end - start) / step_mm)))
        pieces.append(start + np.outer(np.arange(count) / count, end - start))
    return np.concatenate(pieces)


def _inside(points: np.ndarray, rings: Sequence[np.ndarray]) -> np.ndarray:
    """Even-odd rule: which ``points (P, 2)`` lie inside the region bounded by ``rings`` (outline and holes)."""
    crossings = np.zeros(len(points), dtype=int)
    for ring in rings:
        (ax, ay), (bx, by) = ring.T[:, None, :], np.roll(ring, -1, axis=0).T[:, None, :]
        px, py = points[:, 0, None], points[:, 1, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = ax + (py - ay) * (bx - ax) / (by - ay)  # where the edge meets the line y = py
        crossings += np.sum(((ay > py) != (by > py)) & (px < x_cross), axis=1)
    return crossings % 2 == 1


def _areas(triangles: np.ndarray) -> np.ndarray:
    """Areas ``(T,)`` of 2-D triangles ``(T, 3, 2)``."""
    u, v = triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    return 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])


def _signed_area(ring: np.ndarray) -> float:
    """Shoelace area of a closed polygon ``(N, 2)``, positive counter-clockwise."""
    following = np.roll(ring, -1, axis=0)
    return 0.5 * float(np.sum(ring[:, 0] * following[:, 1] - following[:, 0] * ring[:, 1]))


def slab(outline_mm: np.ndarray, holes_mm: Sequence[np.ndarray], thickness_mm: float,
          z0_mm: float = 0.0) -> trimesh.Trimesh:
    """A closed plate: the outline less the holes (2-D, mm), from ``z0_mm`` up by ``thickness_mm``."""
    rings = [_densify(ring) for ring in (outline_mm, *holes_mm)]
    points = np.concatenate(rings)
    faces = Delaunay(points).simplices  # may leave out a point in the middle of a straight edge: harmless
    areas = _areas(points[faces])
    faces, areas = faces[areas > 1e-9], areas[areas > 1e-9]  # slivers along a straight edge
    inside = _inside(points[faces].mean(axis=1), rings)
    faces, area = faces[inside], areas[inside].sum()
    # Delaunay need not keep an outline edge; a lost one shows as a triangle across it, which changes the area
    expected = abs(_signed_area(rings[0])) - sum(abs(_signed_area(ring)) for ring in rings[1:])
    if abs(area - expected) > 1e-6 * expected:
        raise TriangulationError(f"the outline's triangulation covers {area:.6g} mm^2, not {expected:.6g}: "
                           "make _STEP_MM smaller than the narrowest gap")
    transform = trimesh.transformations.translation_matrix((0.0, 0.0, z0_mm))
    mesh = trimesh.creation.extrude_triangulation(points, faces, thickness_mm, transform=transform)
    mesh.remove_unreferenced_vertices()
    return mesh


def placed(mesh: trimesh.Trimesh, rotation: np.ndarray, offset_mm: Sequence[float]) -> trimesh.Trimesh:
    """``mesh`` turned by ``rotation (3, 3)`` about the origin, then moved by ``offset_mm`` (in place)."""
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation, offset_mm
    return mesh.apply_transform(transform)


def polar(angle_deg: float, radius_mm: float) -> tuple[float, float]:
    """The 2-D point ``radius_mm`` from the origin at ``angle_deg`` from x."""
    return radius_mm * np.cos(np.deg2rad(angle_deg)), radius_mm * np.sin(np.deg2rad(angle_deg))


def about_z(order: int) -> list[list[float]]:
    """The ``order - 1`` turns about z by multiples of ``360 / order`` deg (BOP ``symmetries_discrete``)."""
    return [rotation_4x4((0, 0, 1), 2 * np.pi * k / order) for k in range(1, order)]


def flips(count: int) -> list[list[float]]:
    """Half turns about ``count`` in-plane axes, the first along x, spread over 180 deg."""
    return [rotation_4x4((np.cos(np.pi * k / count), np.sin(np.pi * k / count), 0.0), np.pi) for k in range(count)]
