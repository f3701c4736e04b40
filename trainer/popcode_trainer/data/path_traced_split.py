"""A split the project rendered, rendered again by a path tracer: the same scenes, another look.

Single-part splits (:mod:`.render`) keep each record's pose, camera and black background. Scene splits
(:mod:`.scene_render`) store only the targets' poses, so their world (distractors, bin walls, ground
texture, camera) is drawn again from the split's settings and image ``k``'s generator, in the
rasteriser's order (:class:`.scene_content.Layouts`, :func:`.scene_look.draw_scene_look`), and checked
against the recorded poses; the generator then stands where the rasteriser drew its sensor effects, so
the path-traced frame gets the same noise, blur and exposure draw. Only the parts' materials and the
lights are new (:mod:`.path_trace`, seeded by :attr:`.PathTraceSettings.seed`).

The ground truth is geometry and stays: depth, masks, records and scene tables are copied, so scores on
the two splits are paired instance by instance (a sensor preset's depth keeps the holes it has where the
rasterised image was dark). An image counts as done once its record is copied (last,
atomically); a rerun renders what is missing. An image that cannot be rendered stops the run, named.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import copy_file_atomic, read_json, write_bytes_atomic, write_png_atomic

from .bop import RENDER_MARKER, load_models_info
from .path_trace import (
    PathTraceSettings,
    Surface,
    draw_lights,
    draw_part_bsdf,
    expose,
    import_mitsuba,
    path_trace,
    plastic_bsdf,
    textured_bsdf,
)
from .render import BUILTIN_MODELS_FOLDER, RECORDS_FOLDER, check_settings, finalize_scene, image_done, models_digest
from .scene_content import Layouts, SceneContent, SceneSettings
from .scene_layout import model_to_camera
from .scene_look import SceneLook, draw_scene_look
from .scene_render import IMAGES_PER_SCENE_FOLDER, MAX_CAMERA_TRIES, emptied_world, empty_image, load_scene_meshes
from .sensor import apply_sensor_effects, sensor_preset

PATH_TRACED_KEY = "path_traced"  # in the written split's settings: how it was path traced
POSE_TOLERANCE = 1e-6  # mm and rotation entries: the recorded poses are the drawn ones written as JSON


@dataclass(frozen=True)
class PathTraceStats:
    """What one call path traced, for the speed report."""

    images: int
    seconds: float


def _pose(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, t_mm
    return pose


def _record_pose(gt: dict[str, Any]) -> np.ndarray:
    return _pose(np.asarray(gt["cam_R_m2c"], np.float64).reshape(3, 3), np.asarray(gt["cam_t_m2c"], np.float64))


def _scene_settings(settings: dict[str, Any]) -> SceneSettings:
    names = {field.name for field in fields(SceneSettings)}
    return SceneSettings(**{key: tuple(value) if isinstance(value, list) else value
                            for key, value in settings.items() if key in names})


class _SceneReplay:
    """The world of a scene split's image ``k``, drawn again as :mod:`.scene_render` drew it."""

    def __init__(self, settings: dict[str, Any], meshes: dict[int, trimesh.Trimesh]) -> None:
        self.settings = _scene_settings(settings)
        self.meshes = meshes
        self.layouts = Layouts(meshes, self.settings)

    def draw(self, k: int, K: np.ndarray, record: dict[str, Any]
             ) -> tuple[SceneContent, SceneLook, np.random.Generator]:
        """The content and look whose targets lie where the image's record says (an image without parts: whose
        camera does), and the generator after them."""
        rng = np.random.default_rng([self.settings.seed, k])
        keep_distractors = empty_image(k, self.settings.empty_share)
        if keep_distractors is not None:  # the first draw with its parts taken out, as the rasteriser drew it
            content, look = emptied_world(self.layouts, rng, K, keep_distractors)
            if not record["scene_gt"] and self._camera_matches(content, record["scene_camera"]):
                return content, look, rng
        else:
            for _ in range(MAX_CAMERA_TRIES):
                content = self.layouts.draw(rng, K)
                look = draw_scene_look(rng, len(content.targets) + len(content.distractors))
                if self._matches(content, record["scene_gt"]):
                    return content, look, rng
        raise PopcodeError("its recorded poses are not what the split's settings draw (was it rendered by another "
                           "version of popcode, or edited?)")

    @staticmethod
    def _camera_matches(content: SceneContent, camera: dict[str, Any]) -> bool:
        try:  # an edited record without the camera's pose matches nothing, as one with other poses
            recorded = _pose(np.asarray(camera["cam_R_w2c"], np.float64).reshape(3, 3),
                             np.asarray(camera["cam_t_w2c"], np.float64))
        except (KeyError, TypeError, ValueError):
            return False
        return bool(np.allclose(_pose(content.R_w2c, content.t_w2c_mm), recorded, atol=POSE_TOLERANCE))

    @staticmethod
    def _matches(content: SceneContent, recorded: list[dict[str, Any]]) -> bool:
        if len(content.targets) != len(recorded):
            return False
        for placed, gt in zip(content.targets, recorded, strict=True):
            R, t_mm = model_to_camera(placed, content.R_w2c, content.t_w2c_mm)
            if placed.key != gt["obj_id"] or not np.allclose(_pose(R, t_mm), _record_pose(gt), atol=POSE_TOLERANCE):
                return False
        return True

    def surfaces(self, content: SceneContent, look: SceneLook, rng: np.random.Generator, mitsuba: Any
                 ) -> list[Surface]:
        """Targets in drawn metals and plastics; distractors, walls and ground in the rasteriser's colours."""
        world = _pose(content.R_w2c, content.t_w2c_mm)
        surfaces = [Surface(self.meshes[placed.key], _pose(*model_to_camera(placed, content.R_w2c, content.t_w2c_mm)),
                            draw_part_bsdf(rng)[1]) for placed in content.targets]
        for placed, material in zip(content.distractors, look.objects[len(content.targets):], strict=True):
            surfaces.append(Surface(content.distractor_meshes[placed.key],
                                    _pose(*model_to_camera(placed, content.R_w2c, content.t_w2c_mm)),
                                    plastic_bsdf(material.colour, float(rng.uniform(0.05, 0.5)))))
        walls = plastic_bsdf(look.wall.colour, float(rng.uniform(0.1, 0.6)))
        surfaces += [Surface(wall, world, walls) for wall in content.walls]
        half = content.ground_side_mm / 2.0
        corners = [[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]]
        ground = trimesh.Trimesh(vertices=corners, faces=[[0, 1, 2], [0, 2, 3]], process=False)
        repeats = look.ground_repeats
        texcoords = np.array([[0.0, 0.0], [repeats, 0.0], [repeats, repeats], [0.0, repeats]])
        surfaces.append(Surface(ground, world, textured_bsdf(mitsuba, look.ground_texture), texcoords))
        return surfaces


def _copy_annotations(source_scene: Path, out_scene: Path, stem: str, image_folder: str) -> None:
    """Depth and masks of image ``stem`` (everything but its image and record), copied as they are."""
    for folder in source_scene.iterdir():
        if folder.is_dir() and folder.name not in (image_folder, RECORDS_FOLDER):
            (out_scene / folder.name).mkdir(parents=True, exist_ok=True)
            for path in folder.glob(f"{stem}*"):
                copy_file_atomic(path, out_scene / folder.name / path.name)


def _copy_models(source: Path, out: Path) -> None:
    """The models folder's files, ``models_info.json`` last: a copy that has it is complete."""
    out.mkdir(parents=True, exist_ok=True)
    for path in sorted((p for p in source.iterdir() if p.is_file()), key=lambda p: p.name == "models_info.json"):
        copy_file_atomic(path, out / path.name)


def _images(source: Path) -> list[tuple[int, int]]:
    """(scene id, image id) of every image the source split has finished (its records)."""
    images = []
    for scene_dir in sorted(source.iterdir()):
        if scene_dir.is_dir() and scene_dir.name.isdigit() and (scene_dir / RECORDS_FOLDER).is_dir():
            images += [(int(scene_dir.name), int(record.stem))
                       for record in sorted((scene_dir / RECORDS_FOLDER).glob("*.json"))]
    return images


def path_trace_split(source: str | Path, out: str | Path, settings: PathTraceSettings,
                     models_dir: str | Path | None = None, progress: bool = True) -> PathTraceStats:
    """Path trace every image of the rendered split ``source`` that ``out`` lacks; see the module docstring."""
    source, out = Path(source), Path(out)
    marker = source / RENDER_MARKER
    if not marker.is_file():
        raise PopcodeError(f"{source} is not a split popcode rendered (no {RENDER_MARKER}): path tracing replays "
                           "the renderer's scenes")
    source_settings = read_json(marker)
    if PATH_TRACED_KEY in source_settings:
        raise PopcodeError(f"{source} is already path traced; give the split it was made from")
    models_dir = Path(models_dir) if models_dir is not None else source / BUILTIN_MODELS_FOLDER
    models_info = load_models_info(models_dir)
    obj_ids = [int(obj_id) for obj_id in source_settings.get("obj_ids", [])]
    if not obj_ids or any(obj_id not in models_info for obj_id in obj_ids) or \
            models_digest(models_dir, models_info, obj_ids) != source_settings.get("objects"):
        raise PopcodeError(f"the models in {models_dir} are not the ones {source} was rendered with (give the "
                           "models folder it was rendered from with --models-dir)")
    out.mkdir(parents=True, exist_ok=True)
    check_settings(out, {**source_settings, PATH_TRACED_KEY: asdict(settings)})
    if (source / BUILTIN_MODELS_FOLDER).is_dir() and not (out / BUILTIN_MODELS_FOLDER / "models_info.json").is_file():
        _copy_models(source / BUILTIN_MODELS_FOLDER, out / BUILTIN_MODELS_FOLDER)
    todo = [(scene_id, im_id) for scene_id, im_id in _images(source)
            if not image_done(out / f"{scene_id:06d}" / RECORDS_FOLDER / f"{im_id:06d}.json")]
    start = time.perf_counter()
    if todo:
        mitsuba = import_mitsuba()
        meshes = load_scene_meshes(models_dir, obj_ids)
        replay = _SceneReplay(source_settings, meshes) if source_settings.get("kind") == "scenes" else None
        for scene_id, im_id in tqdm(todo, desc="path trace", unit="img", disable=not progress):
            try:
                _path_trace_image(mitsuba, source, out, scene_id, im_id, meshes, replay, source_settings, settings)
            except PopcodeError as error:
                raise PopcodeError(f"{source}: scene {scene_id:06d} image {im_id:06d} cannot be path traced: "
                                   f"{error}") from error
    for scene_id in sorted({scene_id for scene_id, _ in _images(out)}):
        finalize_scene(out / f"{scene_id:06d}")
    return PathTraceStats(len(todo), time.perf_counter() - start)


def _path_trace_image(mitsuba: Any, source: Path, out: Path, scene_id: int, im_id: int,
                      meshes: dict[int, trimesh.Trimesh], replay: _SceneReplay | None, source_settings: dict[str, Any],
                      settings: PathTraceSettings) -> None:
    stem = f"{im_id:06d}"
    source_scene, out_scene = source / f"{scene_id:06d}", out / f"{scene_id:06d}"
    record = read_json(source_scene / RECORDS_FOLDER / f"{stem}.json")
    K = np.asarray(record["scene_camera"]["cam_K"], np.float64).reshape(3, 3)
    size = (int(source_settings["width"]), int(source_settings["height"]))
    look_rng = np.random.default_rng([settings.seed, scene_id, im_id])
    sensor_rng = None
    if replay is None:  # a single part on black, as the rasteriser drew it
        gt = record["scene_gt"][0]
        if gt["obj_id"] not in meshes:
            raise PopcodeError(f"object {gt['obj_id']} is not among the split's objects")
        surfaces = [Surface(meshes[gt["obj_id"]], _record_pose(gt), draw_part_bsdf(look_rng)[1])]
    else:
        content, look, sensor_rng = replay.draw(scene_id * IMAGES_PER_SCENE_FOLDER + im_id, K, record)
        surfaces = replay.surfaces(content, look, look_rng, mitsuba)
    # the lights aim at the parts, or at the world's origin (the bin's floor) where there are none
    aims_mm = [surface.model_to_camera[:3, 3] for surface in surfaces[:len(record["scene_gt"])]] or \
        [content.t_w2c_mm]
    lights = draw_lights(look_rng, np.mean(aims_mm, axis=0))
    linear = path_trace(mitsuba, surfaces, lights, K, size, settings, int(look_rng.integers(2**32)))
    rgb = expose(linear, look_rng)
    gray = bool(source_settings.get("gray", True))
    effects = sensor_preset(source_settings.get("sensor", "none"))
    if effects is not None and sensor_rng is not None:
        image = apply_sensor_effects(rgb, sensor_rng, effects, gray)
    else:
        image = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if gray else rgb
    image_folder = "gray" if gray else "rgb"
    for folder in (image_folder, RECORDS_FOLDER):
        (out_scene / folder).mkdir(parents=True, exist_ok=True)
    write_png_atomic(out_scene / image_folder / f"{stem}.png", image)
    _copy_annotations(source_scene, out_scene, stem, image_folder)
    record_path = f"{RECORDS_FOLDER}/{stem}.json"
    write_bytes_atomic(out_scene / record_path, (source_scene / record_path).read_bytes())  # last: marks it done
