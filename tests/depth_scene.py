"""A synthetic depth camera for the depth tests: an L-shaped bracket of two cuboids, ray-cast in numpy.

Runtime-only on purpose (numpy and popcode_runtime), so the runtime-only venv can use it: the bracket's
exact depth image (optionally with a floor behind it and a cuboid occluding it), its BOP box, and its
``models_info`` entry with the hull and surface points a model's metadata carries.
"""

from __future__ import annotations

import numpy as np

from popcode_runtime.geometry.rotations import axis_angle_to_matrix

K = np.array([[600.0, 0.0, 159.5], [0.0, 600.0, 119.5], [0.0, 0.0, 1.0]])
SHAPE = (240, 320)  # (H, W)
# The bracket: (centre, half extents) [mm] of a base plate and an upright; no symmetry.
CUBOIDS = (((0.0, 0.0, 0.0), (30.0, 20.0, 4.0)), ((-26.0, 0.0, 16.0), (4.0, 20.0, 20.0)))
SPACING_MM = 5.0  # of the surface points: 280 points on the bracket


def _inside(points: np.ndarray, centre: np.ndarray, half: np.ndarray, margin: float = 1e-6) -> np.ndarray:
    return np.all(np.abs(points - centre) < half - margin, axis=1)


def surface_points(spacing_mm: float = SPACING_MM) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(P, 3)`` on the bracket's outer surface (a grid on every face, none inside the other cuboid) and
    their outward normals."""
    points, normals = [], []
    for index, (centre, half) in enumerate(CUBOIDS):
        centre, half = np.asarray(centre), np.asarray(half)
        for axis in range(3):
            u, v = [k for k in range(3) if k != axis]
            gu = np.arange(-half[u] + spacing_mm / 2, half[u], spacing_mm)
            gv = np.arange(-half[v] + spacing_mm / 2, half[v], spacing_mm)
            for sign in (-1.0, 1.0):
                face = np.zeros((len(gu) * len(gv), 3))
                face[:, u], face[:, v] = np.repeat(gu, len(gv)), np.tile(gv, len(gu))
                face[:, axis] = sign * half[axis]
                face += centre
                others = [c for k, c in enumerate(CUBOIDS) if k != index]
                keep = ~np.any([_inside(face, np.asarray(c), np.asarray(h)) for c, h in others], axis=0)
                normal = np.zeros(3)
                normal[axis] = sign
                points.append(face[keep])
                normals.append(np.tile(normal, (int(keep.sum()), 1)))
    return np.concatenate(points), np.concatenate(normals)


def corners() -> np.ndarray:
    """The 16 corners of the two cuboids (hull points)."""
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
    return np.concatenate([np.asarray(c) + signs * np.asarray(h) for c, h in CUBOIDS])


def bracket_info(**changes: object) -> dict:
    """The bracket's ``models_info`` entry with hull and surface points, as an export writes them."""
    points, normals = surface_points()
    every = corners()
    info = {"diameter": float(np.linalg.norm(every[:, None] - every[None], axis=-1).max()),
            "hull_points_mm": corners().tolist(), "surface_points_mm": points.tolist(),
            "surface_normals": normals.tolist()}
    return {**info, **changes}


def _rays() -> np.ndarray:
    v, u = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], axis=-1).reshape(-1, 3)


def _cuboid_depth(rays: np.ndarray, R: np.ndarray, t: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Depth [mm] (z of the hit; inf where missed) of a cuboid in the pose ``x_c = R x + t`` (slab method)."""
    origin = R.T @ (-np.asarray(t, dtype=np.float64)) - centre
    direction = rays @ R  # R^T d for each ray
    with np.errstate(divide="ignore", invalid="ignore"):
        low, high = (-half - origin) / direction, (half - origin) / direction
    near = np.nanmax(np.minimum(low, high), axis=1)
    far = np.nanmin(np.maximum(low, high), axis=1)
    return np.where((near <= far) & (near > 0), near, np.inf)  # the rays' z is 1: the ray parameter is the depth


def render_depth(R: np.ndarray, t_mm: np.ndarray, floor_mm: float | None = None,
                 occluder: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The exact depth ``(H, W)`` float [mm, 0: nothing] of the bracket in pose ``(R, t_mm)``, with a fronto-parallel
    floor at ``floor_mm`` and a camera-aligned cuboid ``occluder`` (centre, half extents in the camera frame), and
    the mask ``(H, W)`` of the pixels where the bracket is seen."""
    rays = _rays()
    bracket = np.min([_cuboid_depth(rays, R, t_mm, np.asarray(c), np.asarray(h)) for c, h in CUBOIDS], axis=0)
    scene = bracket.copy()
    if occluder is not None:
        scene = np.minimum(scene, _cuboid_depth(rays, np.eye(3), occluder[0], np.zeros(3), np.asarray(occluder[1])))
    if floor_mm is not None:
        scene = np.minimum(scene, floor_mm)
    visible = np.isfinite(bracket) & (bracket <= scene)
    return np.where(np.isfinite(scene), scene, 0.0).reshape(SHAPE), visible.reshape(SHAPE)


def bracket_box(R: np.ndarray, t_mm: np.ndarray) -> tuple[float, float, float, float]:
    """The BOP box ``(x, y, w, h)`` of the whole bracket (its ``bbox_obj``): first pixel centre to last."""
    rays_hit = render_depth(R, t_mm)[1]
    v, u = np.nonzero(rays_hit)
    return float(u.min()), float(v.min()), float(u.max() - u.min()), float(v.max() - v.min())


def pose(seed: int, distance_mm: float = 500.0) -> tuple[np.ndarray, np.ndarray]:
    """A seeded random rotation and a translation near the optical axis at about ``distance_mm``."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    R = axis_angle_to_matrix(axis / np.linalg.norm(axis), rng.uniform(0.0, np.pi))
    t = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), distance_mm + rng.uniform(-50, 50)])
    return R, t


def perturbed(R: np.ndarray, angle_deg: float, seed: int) -> np.ndarray:
    """``R`` turned by ``angle_deg`` about a random axis."""
    axis = np.random.default_rng(seed).normal(size=3)
    return axis_angle_to_matrix(axis / np.linalg.norm(axis), np.radians(angle_deg)) @ R

