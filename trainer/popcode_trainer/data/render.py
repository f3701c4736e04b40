"""Headless pyrender renderer that writes BOP-format splits (docs/design.md#bop-files).

Each object gets one scene folder (``scene_id = obj_id``, as T-LESS ``train_primesense``); image
``im_id`` of object ``obj_ids[o]`` has global index ``k = o * images_per_object + im_id`` and belongs
to shard ``k % n``. Its pose, lights and shade come from a generator seeded by ``(seed, obj_id,
im_id)``, so any shard split renders the same images and shard outputs merge into one split.

Every file is written under a temporary name and renamed; an image counts as done once its
record (``<scene>/.popcode_records/<im_id>.json``) exists, written only once its files are on disk
(:class:`ImageRecords`), and the scene JSON files are rebuilt from the records at the end of every
run. An interrupted run, rerun with the same arguments, renders only what is missing; shard
folders copied together and rerun become one split.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
import trimesh
from tqdm import tqdm

from popcode_runtime.base.checks import shown
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import SyncBatch, read_json, write_json_atomic, write_png_atomic
from popcode_runtime.geometry.camera import project_points
from popcode_runtime.geometry.rotations import random_rotations

from .bop import RENDER_MARKER, load_models_info, model_path
from .gl import CentreSampledDepth, delete_offscreen, gl_pose, import_pyrender, offscreen, pyrender_camera
from .meshes import load_mesh
from .objects import write_builtin_models
from .scene_look import LightDraw, draw_lights
from .symmetry_check import check_object_symmetries

RECORDS_FOLDER = ".popcode_records"
BUILTIN_MODELS_FOLDER = "models"
DEPTH_SCALE_MM = 0.1  # depth png value * 0.1 = mm: 0.1 mm steps up to 6.5 m


RECORD_BATCH = 64  # images whose files are synced together before their records are written


class ImageRecords:
    """The records that mark rendered images done, each written only once its image's files are on disk: the files
    go through :attr:`files` (renamed unsynced); every :data:`RECORD_BATCH` images, and when the block ends however
    it ends, one commit makes them durable, then their records are written and committed. A power cut costs at
    most the images since the last commit, which a rerun renders again: their files are overwritten, and a record
    of theirs that reads back empty counts as missing (:func:`image_done`). Syncing each record on its own instead
    cost a two-process render a fifth of its time (bench/results/synced-writes-cost.md)."""

    def __init__(self) -> None:
        self.files = SyncBatch()
        self._pending: list[tuple[Path, dict[str, Any]]] = []

    def done(self, path: Path, record: dict[str, Any]) -> None:
        """Mark an image done with ``record`` at ``path`` once its files (written through :attr:`files`) are
        committed."""
        self._pending.append((path, record))
        if len(self._pending) >= RECORD_BATCH:
            self.flush()

    def flush(self) -> None:
        pending, self._pending = self._pending, []
        self.files.commit()
        for path, record in pending:
            write_json_atomic(path, record, self.files)
        self.files.commit()

    def __enter__(self) -> ImageRecords:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.flush()  # also on an error or Ctrl-C: the images finished before it are kept


def image_done(record: Path) -> bool:
    """Whether the image a record marks is done: the record exists and reads whole (a power cut between a batch's
    record writes and their commit can leave one empty; its image is then rendered again)."""
    try:
        return isinstance(json.loads(record.read_bytes()), dict)
    except (OSError, ValueError):
        return False


MAX_RENDER_SIDE = 8192  # px; Mesa's framebuffers stop at 16384, and BOP images are at most 2560 px wide
MAX_RENDERED_IMAGES = 1_000_000  # per object or scene split: checked before any work (a split's list of images)
MAX_SEED = 2**62  # seeds are stored in the split's JSON, whose reader takes integers of up to 18 digits


def check_count_and_seed(count: int, what: str, seed: int) -> None:
    """Refuse a count or seed that would make a render allocate without bound or fail deep in numpy."""
    if not 1 <= count <= MAX_RENDERED_IMAGES:
        raise PopcodeError(f"{what} must lie in [1, {MAX_RENDERED_IMAGES}], got {count}")
    if not 0 <= seed < MAX_SEED:
        raise PopcodeError(f"seed must lie in [0, 2**62), got {seed}")


def camera_matrix(width: int, height: int) -> np.ndarray:
    """The renderer's pinhole camera: focal length 1.2 x width (about 45 degrees across), centred."""
    focal_px = 1.2 * width
    return np.array([[focal_px, 0.0, (width - 1) / 2.0], [0.0, focal_px, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RenderSettings:
    """What a split is rendered with; stored in the split so a rerun cannot mix settings."""

    images_per_object: int
    width: int = 128
    height: int = 128
    seed: int = 0
    gray: bool = True
    random_position: bool = False
    random_distance: bool = True
    fill_range: tuple[float, float] = (0.45, 0.75)  # object diameter / min(width, height)

    def __post_init__(self) -> None:
        check_count_and_seed(self.images_per_object, "images per object", self.seed)
        if self.width < 8 or self.height < 8:
            raise PopcodeError(f"need at least 8x8 pixels, got {self}")
        if max(self.width, self.height) > MAX_RENDER_SIDE:
            raise PopcodeError(f"images of {self.width}x{self.height} px: at most {MAX_RENDER_SIDE} px a side "
                               f"(OpenGL's framebuffers and each image held in memory)")
        low, high = self.fill_range
        if not 0.05 <= low <= high <= 0.9:
            raise PopcodeError(f"fill_range must satisfy 0.05 <= low <= high <= 0.9, got {self.fill_range}")


def sample_pose(rng: np.random.Generator, vertices_mm: np.ndarray, diameter_mm: float, K: np.ndarray,
                settings: RenderSettings) -> tuple[np.ndarray, np.ndarray]:
    """Uniform rotation and a translation that keeps the whole object inside the image."""
    R_m2c = random_rotations(1, rng)[0]
    low, high = settings.fill_range
    fill = rng.uniform(low, high) if settings.random_distance else (low + high) / 2.0
    distance_mm = K[0, 0] * diameter_mm / (fill * min(settings.width, settings.height))
    centres_px = list(rng.uniform([0.0, 0.0], [settings.width - 1.0, settings.height - 1.0], size=(20, 2))
                      if settings.random_position else [])
    for centre_px in [*centres_px, K[:2, 2]]:  # random positions first, the image centre as the last resort
        t_m2c_mm = distance_mm * np.linalg.solve(K, np.append(centre_px, 1.0))
        projected = project_points(vertices_mm, K, R_m2c, t_m2c_mm)
        if projected.min() >= 0 and (projected < [settings.width - 1, settings.height - 1]).all():
            return R_m2c, t_m2c_mm
    raise PopcodeError(f"the object does not fit into {settings.width}x{settings.height} pixels "
                       f"at fill {fill:.2f}; lower fill_range")


def mask_box(mask: np.ndarray) -> list[int]:
    """The BOP box of a mask: first pixel and the distance to the last (the BOP toolkit's ``calc_2d_bbox``)."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


class _SceneRenderer:
    """One pyrender scene reused for every image: the object, a camera and random lights; a second scene of
    the object and camera alone gives depth at pixel centres."""

    def __init__(self, width: int, height: int) -> None:
        self._pyrender = import_pyrender()
        self._renderer = offscreen(width, height)
        self._depth = CentreSampledDepth(self._renderer, width, height)
        self._scene = self._pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 1.0])
        self._material = self._pyrender.MetallicRoughnessMaterial()
        self._meshes: dict[int, tuple[Any, Any]] = {}  # obj_id -> (shaded mesh, depth mesh)
        self._transient: list[tuple[Any, Any]] = []  # (scene, node) of the current view

    def add_object(self, obj_id: int, mesh: trimesh.Trimesh) -> None:
        Mesh = self._pyrender.Mesh  # noqa: N806 (a class)
        self._meshes[obj_id] = (Mesh.from_trimesh(mesh, material=self._material, smooth=False),
                                Mesh.from_trimesh(mesh, smooth=False))

    def render(self, obj_id: int, rng: np.random.Generator, K: np.ndarray, R_m2c: np.ndarray,
               t_m2c_mm: np.ndarray, radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Colour ``(H, W, 3)`` uint8 and depth ``(H, W)`` float mm of one view with random light and shade."""
        pyrender = self._pyrender
        for scene, node in self._transient:
            scene.remove_node(node)
        shade = rng.uniform(0.35, 0.9)
        self._material.baseColorFactor = np.array([shade, shade, shade, 1.0])
        self._material.metallicFactor = rng.uniform(0.0, 0.4)
        self._material.roughnessFactor = rng.uniform(0.35, 0.9)
        self._scene.ambient_light = np.full(3, rng.uniform(0.05, 0.3))
        camera = pyrender_camera(pyrender, K, radius_mm, float(t_m2c_mm[2]))
        self._transient = [(scene, scene.add(item, pose=pose))
                           for scene, mesh in zip((self._scene, self._depth.scene), self._meshes[obj_id], strict=True)
                           for item, pose in ((mesh, gl_pose(R_m2c, t_m2c_mm)), (camera, np.eye(4)))]
        lights = add_lights(pyrender, self._scene, draw_lights(rng, (1.0, 4.0)))
        self._transient += [(self._scene, node) for node in lights]
        color, _ = self._renderer.render(self._scene)  # its depth is one multisample's, off the pixel centre
        return color, self._depth.render()

    def close(self) -> None:
        self._depth.delete()
        delete_offscreen(self._renderer)


def add_lights(pyrender: Any, scene: Any, lights: list[LightDraw]) -> list[Any]:
    """White directional lights added to ``scene``; returns their nodes."""
    return [scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=light.intensity), pose=light.pose)
            for light in lights]


def _scene_dir(out_dir: Path, obj_id: int) -> Path:
    return out_dir / f"{obj_id:06d}"


def _render_one(renderer: _SceneRenderer, scene_dir: Path, obj_id: int, im_id: int, vertices_mm: np.ndarray,
                diameter_mm: float, settings: RenderSettings, records: ImageRecords) -> None:
    rng = np.random.default_rng([settings.seed, obj_id, im_id])
    K = camera_matrix(settings.width, settings.height)
    R_m2c, t_m2c_mm = sample_pose(rng, vertices_mm, diameter_mm, K, settings)
    radius_mm = float(np.linalg.norm(vertices_mm, axis=1).max())
    color, depth_mm = renderer.render(obj_id, rng, K, R_m2c, t_m2c_mm, radius_mm)
    mask = depth_mm > 0
    stem = f"{im_id:06d}"
    if settings.gray:
        write_png_atomic(scene_dir / "gray" / f"{stem}.png", cv2.cvtColor(color, cv2.COLOR_RGB2GRAY), records.files)
    else:
        write_png_atomic(scene_dir / "rgb" / f"{stem}.png", color, records.files)
    write_png_atomic(scene_dir / "depth" / f"{stem}.png",
                     np.clip(np.round(depth_mm / DEPTH_SCALE_MM), 0, 65535).astype(np.uint16), records.files)
    write_png_atomic(scene_dir / "mask_visib" / f"{stem}_000000.png", mask.astype(np.uint8) * 255, records.files)
    pixels = int(mask.sum())
    box = mask_box(mask)  # the whole object is in view, so the visible and full boxes agree
    record = {
        "scene_gt": [{"cam_R_m2c": R_m2c.ravel().tolist(), "cam_t_m2c": t_m2c_mm.tolist(), "obj_id": obj_id}],
        "scene_gt_info": [{"bbox_obj": box, "bbox_visib": box, "px_count_all": pixels, "px_count_valid": pixels,
                           "px_count_visib": pixels, "visib_fract": 1.0 if pixels else 0.0}],
        "scene_camera": {"cam_K": K.ravel().tolist(), "depth_scale": DEPTH_SCALE_MM},
    }
    records.done(scene_dir / RECORDS_FOLDER / f"{stem}.json", record)


def finalize_scene(scene_dir: Path) -> None:
    """Rebuild the scene's BOP JSON files from every image record present."""
    tables: dict[str, dict[str, Any]] = {"scene_gt": {}, "scene_gt_info": {}, "scene_camera": {}}
    for record_path in sorted((scene_dir / RECORDS_FOLDER).glob("*.json")):
        record = read_json(record_path)
        for name, table in tables.items():
            table[str(int(record_path.stem))] = record[name]
    for name, table in tables.items():
        write_json_atomic(scene_dir / f"{name}.json", table)


def models_digest(models_dir: Path, models_info: dict[int, dict[str, Any]], obj_ids: Sequence[int]) -> str:
    """What the rendered objects are: their meshes' bytes and their ``models_info`` entries."""
    digest = hashlib.sha256(json.dumps({str(i): models_info[i] for i in obj_ids}, sort_keys=True).encode())
    for obj_id in obj_ids:
        digest.update(model_path(models_dir, obj_id).read_bytes())
    return digest.hexdigest()[:32]


def check_settings(out_dir: Path, settings: dict[str, Any]) -> None:
    """Record the split's settings (and its objects' digest) in a new split; refuse to add to one made otherwise,
    naming what differs (shards of one split must render the same objects the same way)."""
    marker = out_dir / RENDER_MARKER
    if marker.is_file():
        previous = read_json(marker)
        if previous != settings:
            differing = sorted(key for key in {*previous, *settings} if previous.get(key) != settings.get(key))
            differences = "; ".join(f"{key}: {shown(previous.get(key))} there, {shown(settings.get(key))} here"
                                    for key in differing[:4])
            raise PopcodeError(f"{out_dir} was rendered with other settings ({differences}); use the same settings "
                               "and objects to complete it, or another folder")
    else:
        write_json_atomic(marker, settings)


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/n"`` -> ``(i, n)`` with ``0 <= i < n``."""
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError as error:
        raise PopcodeError(f"shard must look like i/n (e.g. 0/4), got {text!r}") from error
    if not 0 <= index < count:
        raise PopcodeError(f"shard {text!r}: need 0 <= i < n")
    return index, count


def render_split(models_dir: str | Path, out_dir: str | Path, settings: RenderSettings,
                 obj_ids: Sequence[int] | None = None, shard: tuple[int, int] = (0, 1),
                 progress: bool = True) -> Path:
    """Render this shard's images of ``obj_ids`` (default: every model) into a BOP split; returns it."""
    models_dir, out_dir = Path(models_dir), Path(out_dir)
    models_info = load_models_info(models_dir)
    obj_ids = sorted(models_info) if obj_ids is None else [int(obj_id) for obj_id in obj_ids]
    unknown = [obj_id for obj_id in obj_ids if obj_id not in models_info]
    if unknown or not obj_ids:
        raise PopcodeError(f"object ids {unknown or '[]'} are not in {models_dir / 'models_info.json'} "
                           f"(it lists {sorted(models_info)})")
    shard_index, shard_count = shard
    out_dir.mkdir(parents=True, exist_ok=True)
    check_settings(out_dir, {**asdict(settings), "fill_range": list(settings.fill_range),
                              "obj_ids": obj_ids, "objects": models_digest(models_dir, models_info, obj_ids)})
    todo = []
    for obj_index, obj_id in enumerate(obj_ids):
        records = _scene_dir(out_dir, obj_id) / RECORDS_FOLDER
        for im_id in range(settings.images_per_object):
            k = obj_index * settings.images_per_object + im_id
            if k % shard_count == shard_index and not image_done(records / f"{im_id:06d}.json"):
                todo.append((obj_id, im_id))
    if todo:
        _render_todo(models_dir, out_dir, models_info, todo, settings, progress)
    for obj_id in obj_ids:
        if (_scene_dir(out_dir, obj_id) / RECORDS_FOLDER).is_dir():
            finalize_scene(_scene_dir(out_dir, obj_id))
    return out_dir


def _check_placeable(path: Path, obj_id: int, mesh: trimesh.Trimesh, diameter_mm: float) -> None:
    """The camera distance comes from the declared diameter and aims at the model origin: a mesh reaching further
    from its origin than its diameter (origin outside the part, or a wrong diameter) cannot be framed."""
    reach_mm = float(np.linalg.norm(mesh.vertices, axis=1).max())
    if reach_mm > diameter_mm * (1.0 + 1e-6):
        raise PopcodeError(f"object {obj_id} ({path}): the mesh reaches {reach_mm:.4g} mm from its origin, more than "
                           f"its diameter {diameter_mm:.4g} mm in models_info.json: the diameter is wrong or the "
                           f"mesh is not centred on its origin")


def _render_todo(models_dir: Path, out_dir: Path, models_info: dict[int, dict[str, Any]],
                 todo: list[tuple[int, int]], settings: RenderSettings, progress: bool) -> None:
    meshes: dict[int, trimesh.Trimesh] = {}
    for obj_id in dict.fromkeys(obj_id for obj_id, _ in todo):  # every mesh read and checked before GL starts
        path = model_path(models_dir, obj_id)
        meshes[obj_id] = load_mesh(path)
        _check_placeable(path, obj_id, meshes[obj_id], float(models_info[obj_id]["diameter"]))
        check_object_symmetries(path, models_info[obj_id], obj_id, meshes[obj_id])
    renderer = _SceneRenderer(settings.width, settings.height)
    vertices: dict[int, np.ndarray] = {}
    try:
        for obj_id, mesh in meshes.items():
            renderer.add_object(obj_id, mesh)
            vertices[obj_id] = np.asarray(mesh.vertices, dtype=np.float64)
            scene_dir = _scene_dir(out_dir, obj_id)
            for folder in ("gray" if settings.gray else "rgb", "depth", "mask_visib", RECORDS_FOLDER):
                (scene_dir / folder).mkdir(parents=True, exist_ok=True)
        with ImageRecords() as records:
            for obj_id, im_id in tqdm(todo, desc="render", unit="img", disable=not progress):
                _render_one(renderer, _scene_dir(out_dir, obj_id), obj_id, im_id, vertices[obj_id],
                            float(models_info[obj_id]["diameter"]), settings, records)
    finally:
        renderer.close()


def render_builtin_split(out_dir: str | Path, images_per_object: int, size: tuple[int, int] = (128, 128),
                         seed: int = 0, shard: tuple[int, int] = (0, 1), obj_ids: Sequence[int] | None = None,
                         progress: bool = False, **settings: Any) -> Path:
    """Render the built-in parts into the split ``out_dir`` (models in ``out_dir/models``); returns ``out_dir``."""
    out_dir = Path(out_dir)
    models_dir = write_builtin_models(out_dir / BUILTIN_MODELS_FOLDER)
    render_settings = RenderSettings(images_per_object, width=size[0], height=size[1], seed=seed, **settings)
    return render_split(models_dir, out_dir, render_settings, obj_ids=obj_ids, shard=shard, progress=progress)

