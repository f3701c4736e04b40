"""Built-in, T-LESS-like industrial parts, made procedurally so tests and demos need no download.

Each part is built in millimetres, centred on its bounding box, and covers one symmetry class
(docs/design.md#models-info). The declared symmetries are written in BOP ``models_info.json`` form; the
tests check that each one really maps the mesh onto itself.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial.distance import cdist

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import check_writable_file, json_bytes, write_bytes_atomic
from popcode_runtime.coding.population_code import fibonacci_lattice
from popcode_runtime.geometry.rotations import axis_angle_to_matrix

_SECTIONS = 96  # facets of revolved surfaces: deviates from a true circle by < 0.06 % of the radius
# A diameter over at most this many vertices measures every pair (8 M distances); more are first thinned to the
# extremes along _DIAMETER_DIRECTIONS directions, which with their opposites lie within 3.1 degrees of any direction:
# the farthest pair among them is then at most 0.15 % short of the diameter (1 - cos 3.1 deg).
EXACT_DIAMETER_POINTS = 4096
_DIAMETER_DIRECTIONS = 2000
_DISTANCE_BLOCK = 1 << 22  # distances or projections held at once (16-32 MB)


def revolve(profile_rz: list[tuple[float, float]]) -> trimesh.Trimesh:
    """Closed solid of revolution about +z from an (r, z) profile that starts and ends on the axis."""
    return trimesh.creation.revolve(np.asarray(profile_rz, dtype=np.float64), sections=_SECTIONS)


def _box(extents_mm: tuple[float, float, float], centre_mm: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents_mm, transform=trimesh.transformations.translation_matrix(centre_mm))


def _cylinder(radius_mm: float, height_mm: float, centre_mm: tuple[float, float, float],
              axis: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> trimesh.Trimesh:
    transform = np.eye(4)
    transform[:3, :3] = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], axis)[:3, :3]
    transform[:3, 3] = centre_mm
    return trimesh.creation.cylinder(radius=radius_mm, height=height_mm, sections=48, transform=transform)


def _flanged_sleeve() -> trimesh.Trimesh:
    """Tube with a collar at one end: continuous symmetry about z, ends differ (no flip)."""
    return revolve([(0, -30), (24, -30), (24, -22), (14, -22), (14, 30), (0, 30)])


def _spool() -> trimesh.Trimesh:
    """Waisted spool with equal ends: continuous symmetry about z plus the end-for-end flip."""
    return revolve([(0, -25), (22, -25), (22, -17), (12, -12), (12, 12), (22, 17), (22, 25), (0, 25)])


def _block_with_bosses() -> trimesh.Trimesh:
    """Rectangular block, two round bosses on top: 2-fold about z."""
    parts = [_box((64, 36, 18), (0, 0, 0))]
    parts += [_cylinder(7, 12, (x, 0, 15)) for x in (-18, 18)]
    return trimesh.util.concatenate(parts)


def _square_plate_with_pins() -> trimesh.Trimesh:
    """Square plate with a pin near each corner and a square hub: 4-fold about z."""
    parts = [_box((60, 60, 10), (0, 0, 0)), _box((20, 20, 14), (0, 0, 12))]
    parts += [_cylinder(4, 16, (x, y, 13)) for x in (-20, 20) for y in (-20, 20)]
    return trimesh.util.concatenate(parts)


def _cross_connector() -> trimesh.Trimesh:
    """Bar with a boss on top and bottom and a stub on each end: 2-fold about x, y and z."""
    parts = [_box((70, 24, 16), (0, 0, 0))]
    parts += [_cylinder(9, 10, (0, 0, z)) for z in (-12, 12)]
    parts += [_cylinder(5, 12, (x, 0, 0), axis=(1, 0, 0)) for x in (-40, 40)]
    return trimesh.util.concatenate(parts)


def _angle_bracket() -> trimesh.Trimesh:
    """L-bracket with a gusset and one off-centre pin: no symmetry."""
    parts = [
        _box((60, 40, 8), (0, 0, 0)),
        _box((8, 40, 40), (-26, 0, 24)),
        _box((20, 6, 20), (-12, 12, 12)),
        _cylinder(5, 14, (18, -10, 11)),
    ]
    return trimesh.util.concatenate(parts)


def rotation_4x4(axis: tuple[float, float, float], angle_rad: float) -> list[float]:
    """Row-major 4x4 of a rotation about an axis through the origin (BOP ``symmetries_discrete``)."""
    matrix = np.eye(4)
    matrix[:3, :3] = axis_angle_to_matrix(np.asarray(axis, dtype=np.float64), angle_rad)
    return [float(v) for v in np.round(matrix, 12).ravel()]


Z_AXIS = {"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}


@dataclass(frozen=True)
class BuiltinPart:
    """One built-in part: how to build it and the symmetries it has (BOP ``models_info`` keys)."""

    obj_id: int
    name: str
    build: Callable[[], trimesh.Trimesh]
    symmetries: dict[str, Any]


BUILTIN_PARTS: tuple[BuiltinPart, ...] = (
    BuiltinPart(1, "flanged_sleeve", _flanged_sleeve, {"symmetries_continuous": [Z_AXIS]}),
    BuiltinPart(2, "spool", _spool, {"symmetries_continuous": [Z_AXIS],
                                     "symmetries_discrete": [rotation_4x4((1, 0, 0), np.pi)]}),
    BuiltinPart(3, "block_with_bosses", _block_with_bosses,
                {"symmetries_discrete": [rotation_4x4((0, 0, 1), np.pi)]}),
    BuiltinPart(4, "square_plate_with_pins", _square_plate_with_pins,
                {"symmetries_discrete": [rotation_4x4((0, 0, 1), k * np.pi / 2) for k in (1, 2, 3)]}),
    BuiltinPart(5, "cross_connector", _cross_connector,
                {"symmetries_discrete": [rotation_4x4(axis, np.pi) for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1))]}),
    BuiltinPart(6, "angle_bracket", _angle_bracket, {}),
)


def build_part(obj_id: int) -> trimesh.Trimesh:
    """The mesh (mm) of a built-in part, centred on its bounding box."""
    parts = {part.obj_id: part for part in BUILTIN_PARTS}
    if obj_id not in parts:
        raise PopcodeError(f"no built-in object with id {obj_id}; built-in ids are {sorted(parts)}")
    mesh = parts[obj_id].build()
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def model_info(mesh: trimesh.Trimesh, symmetries: dict[str, Any]) -> dict[str, Any]:
    """BOP ``models_info`` entry of a mesh (mm): diameter, bounding box and the given symmetries."""
    lower, upper = mesh.bounds
    info: dict[str, Any] = {"diameter": mesh_diameter_mm(mesh)}
    for axis_index, name in enumerate("xyz"):
        info[f"min_{name}"] = float(lower[axis_index])
        info[f"size_{name}"] = float(upper[axis_index] - lower[axis_index])
    info.update(symmetries)
    return info


def mesh_diameter_mm(mesh: trimesh.Trimesh) -> float:
    """The largest distance between two of the mesh's vertices [mm], as the BOP toolkit defines the diameter.

    Every pair is measured for up to :data:`EXACT_DIAMETER_POINTS` vertices; a larger mesh is first thinned to its
    extremes along many directions (the two ends of the farthest pair are extremes along its own), so time and
    memory grow with the vertex count, not its square (about 20 s for 4 M vertices on two cores).
    """
    points = np.asarray(mesh.vertices, dtype=np.float64)
    if len(points) > EXACT_DIAMETER_POINTS:
        points = points[_extremes(points, fibonacci_lattice(_DIAMETER_DIRECTIONS))]
    rows = max(1, _DISTANCE_BLOCK // len(points))
    return float(max(cdist(points[i:i + rows], points).max() for i in range(0, len(points), rows)))


def _extremes(points: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Indices of the points farthest along each direction and against it (in float32: only which point matters)."""
    transposed = points.astype(np.float32).T.copy()  # (3, P): each direction's projections are contiguous
    step = max(1, _DISTANCE_BLOCK // len(points))
    found = []
    for start in range(0, len(directions), step):
        support = directions[start:start + step].astype(np.float32) @ transposed  # (step, P)
        found += [support.argmax(axis=1), support.argmin(axis=1)]
    return np.unique(np.concatenate(found))


def write_models_folder(parts: Mapping[int, tuple[trimesh.Trimesh, dict[str, Any]]], out_dir: str | Path) -> Path:
    """A BOP models folder of parts made in code (id -> mesh in mm and its symmetries): each ``obj_XXXXXX.ply``, then
    ``models_info.json`` (last: a folder that has it is complete); returns the folder."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for obj_id, (mesh, _) in parts.items():
        write_bytes_atomic(out_dir / f"obj_{obj_id:06d}.ply", mesh.export(file_type="ply", encoding="binary"))
    write_bytes_atomic(out_dir / "models_info.json", json_bytes({str(obj_id): model_info(mesh, symmetries)
                                                                 for obj_id, (mesh, symmetries) in parts.items()}))
    return out_dir


def write_builtin_models(out_dir: str | Path) -> Path:
    """Write every built-in part as ``obj_XXXXXX.ply`` plus ``models_info.json``; returns the folder.

    Files are written to a temporary name and renamed, so concurrent writers (render shards)
    never see half a file. A folder that holds other models is refused, not overwritten.
    """
    out_dir = Path(out_dir)
    meshes = {part.obj_id: build_part(part.obj_id) for part in BUILTIN_PARTS}
    files = {f"obj_{obj_id:06d}.ply": mesh.export(file_type="ply", encoding="binary")
             for obj_id, mesh in meshes.items()}
    files["models_info.json"] = json_bytes({str(part.obj_id): model_info(meshes[part.obj_id], part.symmetries)
                                            for part in BUILTIN_PARTS})
    for name in files if out_dir.is_dir() else ():
        check_writable_file(out_dir / name, "built-in model file")  # a folder, link or FIFO there is refused
    other = [name for name, data in files.items() if (out_dir / name).is_file()
             and (out_dir / name).read_bytes() != data]
    if other:
        raise PopcodeError(f"{out_dir} holds other models than the built-in parts ({other[0]} differs); write the "
                           "built-in parts into a folder of their own")
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        write_bytes_atomic(out_dir / name, data)
    return out_dir

