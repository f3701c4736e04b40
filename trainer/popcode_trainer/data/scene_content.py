"""What image ``k`` of a scene split holds: the split's settings, then the parts (with repeats), distractors, bin
walls and camera drawn from the image's own generator, so that any shard split draws the same world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError

from .render import check_count_and_seed
from .scene_annotation import BOP_VISIB_DELTA_MM
from .scene_layout import PlacedObject, drop_objects, look_at_camera, surface_points_mm
from .sensor import sensor_preset

DISTRACTOR_KEY_BASE = -1  # distractors get keys -1, -2, ...: never an obj_id
MAX_BIN_MM = 100_000.0  # a 100 m bin: beyond it a part is a speck in the image
MAX_SIDE_PX = 4096  # the border-cut silhouettes are rendered 3x larger: within OpenGL's usual 16384 limit


@dataclass(frozen=True)
class SceneSettings:
    """What a scene split is rendered with; stored in the split so a rerun cannot mix settings."""

    scenes: int
    width: int = 720
    height: int = 540
    seed: int = 0
    gray: bool = True
    parts: tuple[int, int] = (4, 10)  # targets per image, drawn uniformly, repeats allowed
    distractors: tuple[int, int] = (0, 3)  # primitives that are not targets
    bin: bool = True  # walls around the pile; False: parts lie on an open table
    bin_size_mm: float = 0.0  # side of the bin; 0: from the largest part and the most parts per image
    fill_range: tuple[float, float] = (0.7, 1.2)  # bin side / min(width, height) in px; above 1 the border cuts
    max_tilt_deg: float = 35.0  # camera axis from the vertical
    visib_delta_mm: float = BOP_VISIB_DELTA_MM
    sensor: str = "none"  # a name in sensor.SENSOR_PRESETS
    empty_share: float = 0.0  # images without parts (half of them without distractors too): a detector's negatives

    def __post_init__(self) -> None:
        check_count_and_seed(self.scenes, "scenes", self.seed)
        if not 8 <= self.width <= MAX_SIDE_PX or not 8 <= self.height <= MAX_SIDE_PX:
            raise PopcodeError(f"need 8 to {MAX_SIDE_PX} pixels a side, got {self.width}x{self.height}")
        if not 1 <= self.parts[0] <= self.parts[1] or not 0 <= self.distractors[0] <= self.distractors[1]:
            raise PopcodeError(f"parts need 1 <= min <= max and distractors 0 <= min <= max, got parts "
                               f"{self.parts}, distractors {self.distractors}")
        if self.parts[1] + self.distractors[1] > 200:
            raise PopcodeError(f"at most 200 objects per image, got up to {self.parts[1] + self.distractors[1]}")
        if not 0.1 <= self.fill_range[0] <= self.fill_range[1] <= 3.0:
            raise PopcodeError(f"fill_range must satisfy 0.1 <= low <= high <= 3, got {self.fill_range}")
        if not 0.0 <= self.max_tilt_deg <= 70.0 or not 0 <= self.bin_size_mm <= MAX_BIN_MM or \
                not 0 < self.visib_delta_mm <= MAX_BIN_MM:  # NaN fails these tests too
            raise PopcodeError(f"need 0 <= max_tilt_deg <= 70, 0 <= bin_size_mm <= {MAX_BIN_MM:g} and "
                               f"0 < visib_delta_mm <= {MAX_BIN_MM:g}, got {self.max_tilt_deg}, {self.bin_size_mm} "
                               f"and {self.visib_delta_mm}")
        if not 0.0 <= self.empty_share <= 1.0:  # NaN fails this test too
            raise PopcodeError(f"empty_share (--empty-share: the share of images without parts) must lie in [0, 1], "
                               f"got {self.empty_share}")
        sensor_preset(self.sensor)


def _distractor_mesh(rng: np.random.Generator, size_mm: float) -> trimesh.Trimesh:
    """A random box, cylinder, capsule or sphere of about ``size_mm``: clutter that is no target."""
    kind = int(rng.integers(4))
    scale = size_mm * rng.uniform(0.25, 0.7, size=3)
    if kind == 0:
        return trimesh.creation.box(extents=scale)
    if kind == 1:
        return trimesh.creation.cylinder(radius=scale[0] / 2, height=scale[2], sections=24)
    if kind == 2:
        return trimesh.creation.capsule(radius=scale[0] / 3, height=scale[2], count=[12, 12])
    return trimesh.creation.icosphere(subdivisions=2, radius=scale[0] / 2)


def _bin_walls(side_mm: float, height_mm: float) -> list[trimesh.Trimesh]:
    thickness = 0.03 * side_mm
    offset = (side_mm + thickness) / 2.0
    walls = []
    for axis in (0, 1):
        for sign in (-1.0, 1.0):
            extents = [side_mm + 2 * thickness, side_mm + 2 * thickness, height_mm]
            extents[axis] = thickness
            centre = [0.0, 0.0, height_mm / 2.0]
            centre[axis] = sign * offset
            walls.append(trimesh.creation.box(extents=extents,
                                              transform=trimesh.transformations.translation_matrix(centre)))
    return walls


@dataclass
class SceneContent:
    """One image's world: targets and distractors at rest, bin walls and ground, camera and appearance."""

    targets: list[PlacedObject]
    distractors: list[PlacedObject]
    distractor_meshes: dict[int, trimesh.Trimesh]
    walls: list[trimesh.Trimesh]
    ground_side_mm: float
    R_w2c: np.ndarray
    t_w2c_mm: np.ndarray


class Layouts:
    """Draws the world of image ``k`` from its generator: which parts, where they rest, where the camera is."""

    def __init__(self, meshes: dict[int, trimesh.Trimesh], settings: SceneSettings) -> None:
        self.settings = settings
        self.obj_ids = sorted(meshes)
        self.points_mm = {obj_id: surface_points_mm(mesh) for obj_id, mesh in meshes.items()}
        self.diameters_mm = {obj_id: float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
                             for obj_id, mesh in meshes.items()}
        largest_mm = max(self.diameters_mm.values())
        crowd = settings.parts[1] + settings.distractors[1]
        self.side_mm = settings.bin_size_mm or largest_mm * max(2.0, 0.7 * np.sqrt(crowd))
        self.wall_mm = 0.5 * largest_mm
        self.max_height_mm = self.wall_mm + 2.0 * largest_mm

    def draw(self, rng: np.random.Generator, K: np.ndarray) -> SceneContent:
        settings = self.settings
        targets = [int(obj_id) for obj_id in rng.choice(self.obj_ids, size=int(rng.integers(*settings.parts,
                                                                                            endpoint=True)))]
        distractor_meshes = {DISTRACTOR_KEY_BASE - i: _distractor_mesh(rng, np.median(list(self.diameters_mm.values())))
                             for i in range(int(rng.integers(*settings.distractors, endpoint=True)))}
        points = {**self.points_mm, **{key: surface_points_mm(mesh, seed=int(rng.integers(2**31)))
                                       for key, mesh in distractor_meshes.items()}}
        keys = [*targets, *distractor_meshes]
        order = rng.permutation(len(keys))  # distractors may lie under or over the parts
        placed = drop_objects(rng, [keys[i] for i in order], points, self.side_mm, self.max_height_mm)
        fill = rng.uniform(*settings.fill_range)
        distance_mm = K[0, 0] * self.side_mm / (fill * min(settings.width, settings.height))
        target_w_mm = np.array([*rng.uniform(-0.15, 0.15, size=2) * self.side_mm, 0.0])
        R_w2c, t_w2c_mm = look_at_camera(rng, target_w_mm, distance_mm, np.deg2rad(settings.max_tilt_deg))
        return SceneContent(
            targets=[p for p in placed if p.key >= 0], distractors=[p for p in placed if p.key < 0],
            distractor_meshes=distractor_meshes, walls=_bin_walls(self.side_mm, self.wall_mm) if settings.bin else [],
            ground_side_mm=6.0 * self.side_mm, R_w2c=R_w2c, t_w2c_mm=t_w2c_mm)
