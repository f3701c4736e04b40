"""Where things lie in a cluttered scene: parts dropped into a bin (or onto a table), and a camera above it.

World frame: z up, the ground is the plane z = 0, the bin is centred on the origin. Parts fall
straight down onto a height field of what already lies there (the ground, earlier parts), so a
part comes to rest touching the pile without passing through it: only the surface points of
both meshes are tested, so interpenetration is limited to the gaps between those points (a few
per cent of a part's size, and rare). No physics: parts may rest in poses a real drop would tip
over from, which the pose estimator has to handle anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, random_rotations

SURFACE_POINTS = 3000  # per mesh: with its vertices, what the drop tests against the pile
HEIGHT_FIELD_CELLS = 160  # per bin side
DROP_CANDIDATES = 4  # positions tried per part; the lowest resting one wins (parts fill gaps, some pile up)
FULL_BIN_CANDIDATES = 64  # tried when those all rest too high


def surface_points_mm(mesh: trimesh.Trimesh, seed: int = 0) -> np.ndarray:
    """Vertices and evenly spread surface samples ``(N, 3)`` of a mesh, in its own frame [mm]."""
    samples = trimesh.sample.sample_surface(mesh, SURFACE_POINTS, seed=seed)[0]
    return np.concatenate([np.asarray(mesh.vertices, dtype=np.float64), np.asarray(samples, dtype=np.float64)])


@dataclass(frozen=True)
class PlacedObject:
    """One object at rest: ``key`` names its mesh, the pose maps model to world [mm]."""

    key: int
    R_m2w: np.ndarray  # (3, 3)
    t_m2w_mm: np.ndarray  # (3,)


class HeightField:
    """The top of the pile over the bin's floor: ``top_mm[i, j]`` is the highest surface above cell (i, j)."""

    def __init__(self, side_mm: float, cells: int = HEIGHT_FIELD_CELLS) -> None:
        self.side_mm, self.cells = side_mm, cells
        self.top_mm = np.zeros((cells, cells))

    def _cells(self, xy_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        index = np.floor((xy_mm / self.side_mm + 0.5) * self.cells).astype(int)
        index = np.clip(index, 0, self.cells - 1)
        return index[:, 0], index[:, 1]

    def resting_height_mm(self, points_mm: np.ndarray, centre_xy_mm: np.ndarray) -> float:
        """Height of the centre at which the rotated points ``(N, 3)`` (relative to the centre) touch the pile."""
        i, j = self._cells(points_mm[:, :2] + centre_xy_mm)
        return float(np.max(self.top_mm[i, j] - points_mm[:, 2]))

    def add(self, points_world_mm: np.ndarray) -> None:
        i, j = self._cells(points_world_mm[:, :2])
        np.maximum.at(self.top_mm, (i, j), points_world_mm[:, 2])


def drop_objects(rng: np.random.Generator, keys: list[int], points_mm: dict[int, np.ndarray], side_mm: float,
                 max_height_mm: float) -> list[PlacedObject]:
    """Drop the objects ``keys`` one by one at uniform random rotations into a square of ``side_mm``.

    Each tries :data:`DROP_CANDIDATES` positions that keep it inside the square and rests at the
    lowest (:data:`FULL_BIN_CANDIDATES` when those pile too high). A part whose top would rise above
    ``max_height_mm`` does not fit: a clear error, not a pile that grows without bound.
    """
    field = HeightField(side_mm)
    placed = []
    for number, key in enumerate(keys):
        R_m2w = random_rotations(1, rng)[0]
        rotated = points_mm[key] @ R_m2w.T
        reach_xy = np.abs(rotated[:, :2]).max(axis=0)
        free_xy = side_mm / 2.0 - reach_xy
        if (free_xy < 0).any():
            raise PopcodeError(f"a part of {2 * reach_xy.max():.0f} mm does not fit into a bin of {side_mm:.0f} mm; "
                               "use a larger bin")
        for candidates in (DROP_CANDIDATES, FULL_BIN_CANDIDATES):  # a crowded bin: look harder for a gap
            centres = rng.uniform(-free_xy, free_xy, size=(candidates, 2))
            heights = [field.resting_height_mm(rotated, centre) for centre in centres]
            best = int(np.argmin(heights))
            top_mm = heights[best] + rotated[:, 2].max()
            if top_mm <= max_height_mm:
                break
        t_m2w_mm = np.array([*centres[best], heights[best]])
        if top_mm > max_height_mm:
            raise PopcodeError(f"{len(keys)} objects do not fit into a bin of {side_mm:.0f} mm: object {number + 1} "
                               f"would rest {top_mm:.0f} mm high (limit {max_height_mm:.0f} mm); use fewer parts "
                               "or a larger bin")
        field.add(rotated + t_m2w_mm)
        placed.append(PlacedObject(key, R_m2w, t_m2w_mm))
    return placed


def look_at_camera(rng: np.random.Generator, target_w_mm: np.ndarray, distance_mm: float,
                   max_tilt_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """A camera ``(R_w2c, t_w2c_mm)`` (OpenCV axes) looking at ``target_w_mm`` from above.

    Tilt from the vertical uniform in [0, max_tilt], azimuth and roll about the viewing axis uniform.
    """
    tilt, azimuth, roll = rng.uniform(0.0, max_tilt_rad), rng.uniform(0.0, 2 * np.pi), rng.uniform(0.0, 2 * np.pi)
    eye_w_mm = target_w_mm + distance_mm * np.array([np.sin(tilt) * np.cos(azimuth),
                                                     np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
    z_axis = (target_w_mm - eye_w_mm) / distance_mm
    helper = np.array([1.0, 0.0, 0.0]) if abs(z_axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x_axis = np.cross(z_axis, helper)
    x_axis = axis_angle_to_matrix(z_axis, np.asarray(roll)) @ (x_axis / np.linalg.norm(x_axis))
    R_w2c = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis])
    return R_w2c, -R_w2c @ eye_w_mm


def model_to_camera(placed: PlacedObject, R_w2c: np.ndarray, t_w2c_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """BOP's ``cam_R_m2c``, ``cam_t_m2c`` [mm] of a placed object."""
    return R_w2c @ placed.R_m2w, R_w2c @ placed.t_m2w_mm + t_w2c_mm
