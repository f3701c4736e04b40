"""Cluttered scenes as a BOP split: several parts (with repeats) and distractors in a bin, seen from above.

Image ``k`` of a render is scene folder ``k // 1000``, image ``k % 1000`` (as BlenderProc's
``train_pbr``), belongs to shard ``k % n`` and draws everything (parts, their poses, distractors,
bin, textures, lights, camera, sensor) from a generator seeded by ``(seed, k)``: any shard split
renders the same images. Records, atomic writes and resume work as in :mod:`.render`.

What an image holds is drawn by :mod:`.scene_content`; annotations are computed as the BOP toolkit's
``calc_gt_masks`` and ``calc_gt_info`` compute them (:mod:`.scene_annotation`). A draw in which no target is
visible (rare: the camera aims at the bin) is drawn again, up to :data:`MAX_CAMERA_TRIES` times;
after that it is written as it is, every instance with ``visib_fract`` 0, which readers skip.

A share of the images (``SceneSettings.empty_share``, :func:`empty_image`) holds no part: the image's first draw
with its parts taken out, half of them with their distractors; their ``scene_gt`` and ``scene_gt_info`` lists are
empty. They teach a detector what to leave alone; the pose models' readers find no instance in them.

Masks and visibility are ground truth, computed from the exact rendered depth. The depth written to
``depth/`` is what the sensor preset's depth camera measures (:mod:`.depth_noise`: noise, holes,
quantisation; exact with ``none``), as a real split's depth is; ``px_count_valid`` counts the written
depth's measured pixels, as the toolkit counts a real split's. The preset's depth noise is recorded
in the split's settings (``popcode_render.json``, ``depth_noise``); a split without that entry has
exact depth.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_png_atomic

from .bop import load_models_info, model_path
from .depth_noise import apply_depth_noise, depth_noise_preset
from .gl import CentreSampledDepth, PixelRegion, delete_offscreen, gl_pose, import_pyrender, offscreen, pyrender_camera
from .meshes import load_mesh
from .objects import write_builtin_models
from .render import (
    BUILTIN_MODELS_FOLDER,
    DEPTH_SCALE_MM,
    RECORDS_FOLDER,
    ImageRecords,
    add_lights,
    camera_matrix,
    check_settings,
    finalize_scene,
    image_done,
    models_digest,
)
from .scene_annotation import instance_gt_info, moved_box
from .scene_content import Layouts, SceneContent, SceneSettings
from .scene_layout import model_to_camera
from .scene_look import MaterialDraw, SceneLook, draw_scene_look
from .sensor import apply_sensor_effects, sensor_preset

IMAGES_PER_SCENE_FOLDER = 1000
MAX_CAMERA_TRIES = 10
MARGIN_PX = 2  # around the projected mesh: far more than OpenGL's rounding of vertex positions


def _textured_quad(pyrender: Any, side_mm: float, texture_rgb: np.ndarray, repeats: float) -> Any:
    """A square of ``side_mm`` in the plane z = 0, facing +z, with a tiled texture."""
    half = side_mm / 2.0
    positions = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], np.float32)
    uv = np.array([[0, 0], [repeats, 0], [repeats, repeats], [0, repeats]], np.float32)
    material = pyrender.MetallicRoughnessMaterial(
        baseColorTexture=pyrender.Texture(source=texture_rgb, source_channels="RGB"),
        metallicFactor=0.0, roughnessFactor=0.9)
    primitive = pyrender.Primitive(positions=positions, normals=np.tile([0.0, 0.0, 1.0], (4, 1)).astype(np.float32),
                                   texcoord_0=uv, indices=np.array([[0, 1, 2], [0, 2, 3]]), material=material)
    return pyrender.Mesh([primitive])


def _material(pyrender: Any, draw: MaterialDraw) -> Any:
    return pyrender.MetallicRoughnessMaterial(baseColorFactor=[*draw.colour, 1.0], metallicFactor=draw.metallic,
                                              roughnessFactor=draw.roughness)


def _depth_mesh(pyrender: Any, mesh: trimesh.Trimesh) -> Any:
    """Positions and triangles only: what a depth pass needs, cheap to make per image."""
    return pyrender.Mesh([pyrender.Primitive(positions=np.asarray(mesh.vertices, np.float32),
                                             indices=np.asarray(mesh.faces))])


class _SceneRenderer:
    """Colour and depth of a whole scene, and the depth of each target alone (in and around the image).

    Each pyrender renderer keeps its own meshes (a mesh's GL buffers belong to one renderer), and
    all three share the OpenGL context of one offscreen renderer (see :class:`.gl.CentreSampledDepth`).
    """

    def __init__(self, width: int, height: int) -> None:
        self.pyrender = import_pyrender()
        self.width, self.height = width, height
        self._offscreen = offscreen(width, height)
        self._depth = CentreSampledDepth(self._offscreen, width, height)
        self._wide_depth = CentreSampledDepth(self._offscreen, 3 * width, 3 * height)
        self._near_far_mm = (1.0, 2.0)  # of the current image

    def render(self, content: SceneContent, look: SceneLook, meshes: dict[int, trimesh.Trimesh], K: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, PixelRegion]], list[tuple[int, list]]]:
        """Colour ``(H, W, 3)`` uint8, scene depth [mm], each target's depth alone [mm] in the region of
        the image that it can cover (nothing outside), and its whole silhouette's pixel count and box
        (from a 3x larger image when the border cuts it)."""
        pyrender = self.pyrender
        meshes = {**meshes, **content.distractor_meshes}
        colour_scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 1.0], ambient_light=np.full(3, look.ambient))
        depth_scene = pyrender.Scene()
        poses_c = []  # (trimesh, GL pose) of everything but the ground
        for placed in [*content.targets, *content.distractors]:
            R_m2c, t_m2c_mm = model_to_camera(placed, content.R_w2c, content.t_w2c_mm)
            poses_c.append((meshes[placed.key], gl_pose(R_m2c, t_m2c_mm)))
        materials = [_material(pyrender, draw) for draw in look.objects]
        wall_material = _material(pyrender, look.wall)
        world_gl = gl_pose(content.R_w2c, content.t_w2c_mm)
        for wall in content.walls:
            poses_c.append((wall, world_gl))
        target_nodes = []
        for index, (mesh, pose) in enumerate(poses_c):
            material = materials[index] if index < len(materials) else wall_material
            colour_scene.add(pyrender.Mesh.from_trimesh(mesh, material=material, smooth=False), pose=pose)
            node = depth_scene.add(_depth_mesh(pyrender, mesh), pose=pose)
            if index < len(content.targets):
                target_nodes.append(node)
        ground = trimesh.creation.box(extents=[content.ground_side_mm, content.ground_side_mm, 1.0],
                                      transform=trimesh.transformations.translation_matrix([0.0, 0.0, -0.5]))
        colour_scene.add(_textured_quad(pyrender, content.ground_side_mm, look.ground_texture, look.ground_repeats),
                         pose=world_gl)
        depth_scene.add(_depth_mesh(pyrender, ground), pose=world_gl)
        add_lights(pyrender, colour_scene, look.lights)
        corners_c = _corners_in_camera(content, meshes, poses_c)
        near_mm, far_mm = max(corners_c.min(), 1.0), corners_c.max()
        self._near_far_mm = (near_mm, far_mm)
        camera = self._camera(K)
        for scene in (colour_scene, depth_scene):
            scene.add(camera, pose=np.eye(4))
        colour, _ = self._offscreen.render(colour_scene)
        self._depth.scene = depth_scene
        depth_scene_mm = self._depth.render()
        alone_mm, whole = [], []
        for node, (mesh, pose) in zip(target_nodes, poses_c[:len(target_nodes)], strict=True):
            for other in depth_scene.mesh_nodes:
                other.mesh.is_visible = other is node
            # Reading the framebuffer back is most of a depth pass on a CPU: draw and read only the region.
            region = _covered_region(mesh, pose, K, camera.znear, (self.width, self.height))
            depth_mm = self._depth.render(region)
            region = region or (0, 0, self.width, self.height)
            alone_mm.append((depth_mm, region))
            whole.append(self._whole_silhouette(mesh, pose, K, depth_mm, region))
        return colour, depth_scene_mm, alone_mm, whole

    def _camera(self, K: np.ndarray) -> Any:
        near_mm, far_mm = self._near_far_mm
        return pyrender_camera(self.pyrender, K, (far_mm - near_mm) / 2.0 + 1.0, (far_mm + near_mm) / 2.0)

    def _whole_silhouette(self, mesh: trimesh.Trimesh, pose_gl: np.ndarray, K: np.ndarray, alone_mm: np.ndarray,
                          region: PixelRegion) -> tuple[int, list]:
        """Pixel count and box of the whole silhouette: the BOP toolkit renders 3x larger to count what the border
        cuts off; that is only needed when the silhouette touches the border or lies outside the image.
        ``alone_mm`` is the depth of the mesh in ``region`` of the image."""
        mask = alone_mm > 0
        x0, y0, x1, y1 = region
        if mask.any() and not ((x0 == 0 and mask[:, 0].any()) or (y0 == 0 and mask[0].any())
                               or (x1 == self.width and mask[:, -1].any()) or (y1 == self.height and mask[-1].any())):
            return int(mask.sum()), moved_box(mask, x0, y0)
        wide_K = K.copy()
        wide_K[:2, 2] += [self.width, self.height]
        camera = self._camera(wide_K)
        scene = self.pyrender.Scene()
        scene.add(_depth_mesh(self.pyrender, mesh), pose=pose_gl)
        scene.add(camera, pose=np.eye(4))
        self._wide_depth.scene = scene
        wide_region = _covered_region(mesh, pose_gl, wide_K, camera.znear, (3 * self.width, 3 * self.height))
        wide_mask = self._wide_depth.render(wide_region) > 0
        x0, y0, _, _ = wide_region or (0, 0, 0, 0)
        return int(wide_mask.sum()), moved_box(wide_mask, x0 - self.width, y0 - self.height)

    def close(self) -> None:
        self._wide_depth.delete()
        self._depth.delete()
        delete_offscreen(self._offscreen)


def _covered_region(mesh: trimesh.Trimesh, pose_gl: np.ndarray, K: np.ndarray, znear_mm: float,
                    size: tuple[int, int]) -> PixelRegion | None:
    """Every pixel that ``mesh`` in ``pose_gl`` can cover in an image of ``size`` (width, height): the box
    of its projected vertices plus :data:`MARGIN_PX`, clipped to the image (empty when it lies outside).

    Pixel ``i`` samples ``x = i`` of ``K`` (see :func:`.gl.pyrender_camera`). None when a vertex is not
    beyond the near plane: OpenGL clips such a mesh, and its projected vertices bound nothing.
    """
    in_camera = np.asarray(mesh.vertices) @ pose_gl[:3, :3].T + pose_gl[:3, 3]
    z_mm = -in_camera[:, 2]  # GL looks along -z
    if z_mm.min() <= znear_mm:
        return None
    u = K[0, 0] * in_camera[:, 0] / z_mm + K[0, 2]
    v = -K[1, 1] * in_camera[:, 1] / z_mm + K[1, 2]  # GL's y is up, the image's rows go down
    width, height = size
    x0 = int(np.clip(np.floor(u.min()) - MARGIN_PX, 0, width))
    y0 = int(np.clip(np.floor(v.min()) - MARGIN_PX, 0, height))
    x1 = int(np.clip(np.ceil(u.max()) + 1 + MARGIN_PX, x0, width))
    y1 = int(np.clip(np.ceil(v.max()) + 1 + MARGIN_PX, y0, height))
    return x0, y0, x1, y1


def _corners_in_camera(content: SceneContent, meshes: dict[int, trimesh.Trimesh],
                       poses_c: list[tuple[trimesh.Trimesh, np.ndarray]]) -> np.ndarray:
    """Camera z [mm] of every object's bounding box corners and of the ground's: the near and far planes."""
    half = content.ground_side_mm / 2.0
    ground_w = np.array([[sx * half, sy * half, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    depths = [(ground_w @ content.R_w2c.T + content.t_w2c_mm)[:, 2]]
    for mesh, pose_gl in poses_c:
        corners = trimesh.bounds.corners(mesh.bounds)
        depths.append(-(corners @ pose_gl[:3, :3].T + pose_gl[:3, 3])[:, 2])  # GL looks along -z
    return np.concatenate(depths)


def _folders(gray: bool) -> tuple[str, ...]:
    return ("gray" if gray else "rgb", "depth", "mask", "mask_visib", RECORDS_FOLDER)


def _location(k: int) -> tuple[int, int]:
    """Scene folder and image id of the render's image ``k``."""
    return k // IMAGES_PER_SCENE_FOLDER, k % IMAGES_PER_SCENE_FOLDER


def _camera_image(colour: np.ndarray, rng: np.random.Generator, settings: SceneSettings) -> np.ndarray:
    """The rendered colour as the split's camera delivers it: its sensor's effects, grey or colour."""
    effects = sensor_preset(settings.sensor)
    if effects is not None:
        return apply_sensor_effects(colour, rng, effects, settings.gray)
    return cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY) if settings.gray else colour


def empty_image(k: int, share: float) -> bool | None:
    """Whether image ``k`` of a split with ``share`` of its images empty holds no part: None when it holds parts,
    else whether it keeps its distractors. Spread evenly by index (of the first n images, ``floor(n * share)`` are
    empty; every shard split draws the same) and alternating, so half the empty images are an empty bin."""
    empties_before = math.floor(k * share)
    if math.floor((k + 1) * share) == empties_before:
        return None
    return empties_before % 2 == 0


def emptied_world(layouts: Layouts, rng: np.random.Generator, K: np.ndarray,
                   keep_distractors: bool) -> tuple[SceneContent, SceneLook]:
    """The first draw of an image's world and look with its target parts taken out (its distractors too unless
    ``keep_distractors``), each object that stays with its own material."""
    content = layouts.draw(rng, K)
    look = draw_scene_look(rng, len(content.targets) + len(content.distractors))
    kept = content.distractors if keep_distractors else []
    look = replace(look, objects=look.objects[len(content.targets):][:len(kept)])  # targets' come first
    return replace(content, targets=[], distractors=kept), look


def _render_parts(renderer: _SceneRenderer, layouts: Layouts, meshes: dict[int, trimesh.Trimesh], k: int,
                  settings: SceneSettings, rng: np.random.Generator, K: np.ndarray
                  ) -> tuple[SceneContent, np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray, dict]]]:
    """Image ``k``'s world, colour, scene depth [mm] and each target's masks and ``scene_gt_info``, drawn again
    while no target is visible."""
    for _ in range(MAX_CAMERA_TRIES):  # a draw that shows no target (rare) is drawn again
        content = layouts.draw(rng, K)
        look = draw_scene_look(rng, len(content.targets) + len(content.distractors))
        colour, depth_scene_mm, alone_mm, whole = renderer.render(content, look, meshes, K)
        results = [instance_gt_info(alone, depth_scene_mm, K, settings.visib_delta_mm, count, box, region)
                   for (alone, region), (count, box) in zip(alone_mm, whole, strict=True)]
        if any(info["px_count_visib"] for _, _, info in results):
            return content, colour, depth_scene_mm, results
    raise PopcodeError(f"scene image {k}: no target part is visible in {MAX_CAMERA_TRIES} draws of the bin; are "
                       "the models in millimetres and the bin (--bin-size-mm) in proportion to them?")


def _render_image(renderer: _SceneRenderer, layouts: Layouts, meshes: dict[int, trimesh.Trimesh], out_dir: Path,
                  k: int, settings: SceneSettings, records: ImageRecords) -> int:
    """Render and write image ``k`` with its masks and record; returns how many targets it shows."""
    rng = np.random.default_rng([settings.seed, k])
    K = camera_matrix(settings.width, settings.height)
    keep_distractors = empty_image(k, settings.empty_share)
    if keep_distractors is not None:  # the first draw with its parts taken out, as render_emptied_scenes makes it
        content, look = emptied_world(layouts, rng, K, keep_distractors)
        colour, depth_scene_mm, _, _ = renderer.render(content, look, meshes, K)
        results = []
    else:
        content, colour, depth_scene_mm, results = _render_parts(renderer, layouts, meshes, k, settings, rng, K)
    scene_id, im_id = _location(k)
    scene_dir = out_dir / f"{scene_id:06d}"
    stem = f"{im_id:06d}"
    write_png_atomic(scene_dir / ("gray" if settings.gray else "rgb") / f"{stem}.png",
                     _camera_image(colour, rng, settings), records.files)
    # Drawn after every annotation: the ground truth above stays the exact depth's (module docstring).
    depth_noise = depth_noise_preset(settings.sensor)
    measured_mm = depth_scene_mm if depth_noise is None else apply_depth_noise(depth_scene_mm, K, colour, rng,
                                                                               depth_noise)
    depth_png = np.clip(np.round(measured_mm / DEPTH_SCALE_MM), 0, 65535).astype(np.uint16)
    write_png_atomic(scene_dir / "depth" / f"{stem}.png", depth_png, records.files)
    if depth_noise is not None:
        for mask, _, info in results:
            info["px_count_valid"] = int((depth_png[mask] > 0).sum())
    scene_gt = []
    for gt_index, (placed, (mask, mask_visib, _)) in enumerate(zip(content.targets, results, strict=True)):
        write_png_atomic(scene_dir / "mask" / f"{stem}_{gt_index:06d}.png", mask.astype(np.uint8) * 255,
                         records.files)
        write_png_atomic(scene_dir / "mask_visib" / f"{stem}_{gt_index:06d}.png", mask_visib.astype(np.uint8) * 255,
                         records.files)
        R_m2c, t_m2c_mm = model_to_camera(placed, content.R_w2c, content.t_w2c_mm)
        scene_gt.append({"cam_R_m2c": R_m2c.ravel().tolist(), "cam_t_m2c": t_m2c_mm.tolist(), "obj_id": placed.key})
    record = {
        "scene_gt": scene_gt,
        "scene_gt_info": [info for _, _, info in results],
        "scene_camera": {"cam_K": K.ravel().tolist(), "depth_scale": DEPTH_SCALE_MM,
                         "cam_R_w2c": content.R_w2c.ravel().tolist(), "cam_t_w2c": content.t_w2c_mm.tolist()},
    }
    records.done(scene_dir / RECORDS_FOLDER / f"{stem}.json", record)
    return len(scene_gt)


@dataclass(frozen=True)
class SceneRenderStats:
    """What one call rendered, for the speed report."""

    images: int
    instances: int
    seconds: float


def load_scene_meshes(models_dir: Path, obj_ids: Sequence[int]) -> dict[int, trimesh.Trimesh]:
    """Every part's mesh, checked: a mesh without volume in any direction cannot be dropped into a bin."""
    meshes = {}
    for obj_id in obj_ids:
        path = model_path(models_dir, obj_id)
        mesh = load_mesh(path)
        extent_mm = np.ptp(np.asarray(mesh.vertices), axis=0)
        if not np.isfinite(extent_mm).all() or extent_mm.max() <= 0:
            raise PopcodeError(f"model {path} has degenerate bounds (extent {extent_mm.tolist()} mm)")
        meshes[obj_id] = mesh
    return meshes


def render_scene_split(models_dir: str | Path, out_dir: str | Path, settings: SceneSettings,
                       obj_ids: Sequence[int] | None = None, shard: tuple[int, int] = (0, 1),
                       progress: bool = True) -> SceneRenderStats:
    """Render this shard's missing scene images of ``obj_ids`` (default: every model) into the BOP split ``out_dir``."""
    models_dir, out_dir = Path(models_dir), Path(out_dir)
    models_info = load_models_info(models_dir)
    obj_ids = sorted(models_info) if obj_ids is None else sorted({int(obj_id) for obj_id in obj_ids})
    unknown = [obj_id for obj_id in obj_ids if obj_id not in models_info]
    if unknown or not obj_ids:
        raise PopcodeError(f"object ids {unknown or '[]'} are not in {models_dir / 'models_info.json'} "
                           f"(it lists {sorted(models_info)})")
    out_dir.mkdir(parents=True, exist_ok=True)
    check_settings(out_dir, {**_settings_record(settings), "obj_ids": obj_ids, "kind": "scenes",
                             **_depth_noise_record(settings.sensor),
                             "objects": models_digest(models_dir, models_info, obj_ids)})
    shard_index, shard_count = shard
    todo = [k for k in range(shard_index, settings.scenes, shard_count)
            if not image_done(out_dir / f"{_location(k)[0]:06d}" / RECORDS_FOLDER / f"{_location(k)[1]:06d}.json")]
    start, instances = time.perf_counter(), 0
    if todo:
        meshes = load_scene_meshes(models_dir, obj_ids)  # every mesh read and checked before GL starts
        layouts = Layouts(meshes, settings)
        for scene_id in sorted({_location(k)[0] for k in todo}):
            for folder in _folders(settings.gray):
                (out_dir / f"{scene_id:06d}" / folder).mkdir(parents=True, exist_ok=True)
        renderer = _SceneRenderer(settings.width, settings.height)
        try:
            # settings under which no part can be seen show in the first image: the bar opens after it, so their
            # refusal is the only line
            with ImageRecords() as records:
                instances += _render_image(renderer, layouts, meshes, out_dir, todo[0], settings, records)
                for k in tqdm(todo[1:], desc="render scenes", unit="img", disable=not progress, initial=1,
                              total=len(todo)):
                    instances += _render_image(renderer, layouts, meshes, out_dir, k, settings, records)
        finally:
            renderer.close()
    seconds = time.perf_counter() - start
    for scene_id in range(_location(settings.scenes - 1)[0] + 1):
        if (out_dir / f"{scene_id:06d}" / RECORDS_FOLDER).is_dir():
            finalize_scene(out_dir / f"{scene_id:06d}")
    return SceneRenderStats(len(todo), instances, seconds)


def _plain(settings: dict[str, Any]) -> dict[str, Any]:
    return {key: list(value) if isinstance(value, tuple) else value for key, value in settings.items()}


def _settings_record(settings: SceneSettings) -> dict[str, Any]:
    """The settings as the split records them; a split without empty images has no ``empty_share`` entry, as
    splits made before the option existed, so either can be completed."""
    record = _plain(asdict(settings))
    if not settings.empty_share:
        del record["empty_share"]
    return record


def _depth_noise_record(sensor: str) -> dict[str, Any]:
    """The sensor's depth noise for the split's settings; nothing for exact depth, as splits made before depth
    noise existed (whose depth is exact whatever their sensor) say by not having it."""
    noise = depth_noise_preset(sensor)
    return {} if noise is None else {"depth_noise": _plain(asdict(noise))}


def render_cluttered_test_split(out_dir: str | Path, scenes: int = 40, size: tuple[int, int] = (720, 540),
                                seed: int = 1015, sensor: str = "industrial", progress: bool = False,
                                obj_ids: Sequence[int] | None = None, shard: tuple[int, int] = (0, 1),
                                **settings: Any) -> Path:
    """A cluttered test split of the built-in parts (models in ``out_dir/models``) with a fixed seed; for the demo.

    ``obj_ids`` picks the parts that appear as targets (default: all six); ``settings`` are further
    :class:`SceneSettings` fields. The seed differs from the training renders' so no test scene
    repeats a training one. Rerunning completes an interrupted render. Returns ``out_dir``.
    """
    out_dir = Path(out_dir)
    models_dir = write_builtin_models(out_dir / BUILTIN_MODELS_FOLDER)
    scene_settings = SceneSettings(scenes, width=size[0], height=size[1], seed=seed, sensor=sensor, **settings)
    render_scene_split(models_dir, out_dir, scene_settings, obj_ids=obj_ids, shard=shard, progress=progress)
    return out_dir


def render_emptied_scenes(models_dir: str | Path, settings: SceneSettings, indices: Sequence[int],
                          keep_distractors: bool) -> list[np.ndarray]:
    """Image ``k`` (for each of ``indices``) of the scene split that ``settings`` renders, with its target parts
    taken out (its distractors too unless ``keep_distractors``): the frames on which a detector should find nothing.

    The world is image ``k``'s first draw, with the same bin, camera, lights, materials and sensor effects, so
    where no part lay or shaded the frame is the split's image (an image whose first draw showed no part, which
    the split draws again, differs). Distractors stay where they came to rest, on the parts or beside them.
    ``settings.bin`` must hold: the walls and the ground bound the camera's near and far planes.
    """
    if not settings.bin:
        raise PopcodeError("an emptied scene needs its bin walls (settings.bin)")
    models_dir = Path(models_dir)
    meshes = load_scene_meshes(models_dir, sorted(load_models_info(models_dir)))
    layouts = Layouts(meshes, settings)
    K = camera_matrix(settings.width, settings.height)
    renderer = _SceneRenderer(settings.width, settings.height)
    frames = []
    try:
        for k in indices:
            rng = np.random.default_rng([settings.seed, k])
            colour = renderer.render(*emptied_world(layouts, rng, K, keep_distractors), meshes, K)[0]
            frames.append(_camera_image(colour, rng, settings))
    finally:
        renderer.close()
    return frames
