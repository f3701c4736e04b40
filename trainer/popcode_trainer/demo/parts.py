"""The parts a demo runs on: the six built-in ones, or a user's BOP models folder checked before any long work.

A user's folder is read once and every part checked up front, each failure one message that names the part and
the fix (the CLI prints it as one line and exits 2): the folder must hold ``models_info.json`` with each id once,
a mesh per id, in millimetres (a diameter under :data:`MIN_DIAMETER_MM` is a mesh in metres), a declared diameter
within :data:`DIAMETER_TOLERANCE` of the mesh's, centred on its origin, thick enough to be seen at the rendered size
(:func:`median_visible_px`), and with symmetries that map it onto itself (:mod:`popcode_trainer.data.symmetry_check`).

The renderer frames a part by its diameter, which fits a part whose points all lie within half the diameter
of its origin; one reaching further (a T-shaped bracket centred on its bounding box) is rendered a little
further away, so that every view fits (:meth:`Parts.fill_range`), and the report says so.

The run folder keeps its own copy of the models in each split (``<split>/models``, as the built-in parts are
written), so a run's data, models and metrics read one set of files; a rerun whose models folder has changed
since is refused rather than mixed.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_bytes_atomic, write_json_atomic
from popcode_runtime.geometry.rotations import random_rotations

from ..data.bop import load_models_info
from ..data.meshes import load_mesh
from ..data.objects import BUILTIN_PARTS, mesh_diameter_mm
from ..data.render import BUILTIN_MODELS_FOLDER, RenderSettings, camera_matrix, render_builtin_split, render_split
from ..data.scene_content import SceneSettings
from ..data.scene_render import render_cluttered_test_split, render_scene_split
from ..data.symmetry_check import check_object_symmetries

BUILTIN = "builtin"
MODELS_INFO = "models_info.json"
MIN_DIAMETER_MM = 1.0  # a part under a millimetre across is almost surely a mesh written in metres
# A declared diameter may differ from the mesh's (the largest distance between two vertices) by this share of it:
# the BOP thresholds scale with the diameter, so a wrong one moves every score. The BOP toolkit and model_info
# measure it alike (the built-in and own parts' entries lie within 3e-8 of their PLY files' float32 vertices); a
# mesh rescaled by 1 % since its entry was written still passes.
DIAMETER_TOLERANCE = 0.02
CLUTTERED_SENSOR = "industrial"  # the camera of the scene splits, as render_cluttered_test_split renders them
# Thickness check: the part at its smallest in a single-part render (render.RenderSettings' fill_range), in
# pixels of that render; in half of the views it must cover more than MIN_VISIBLE_PX (a 58 px long bar 1.7 px wide).
RENDER_SIDE_PX = 128
SMALLEST_FILL = 0.45
MIN_VISIBLE_PX = 100.0
FIT_MARGIN = 0.99  # of the highest fill at which a part's bounding sphere about its origin just fits
THICKNESS_VIEWS = 64
THICKNESS_POINTS = 40_000
SUPERSAMPLE = 2  # surface points counted on a grid this many times finer than the render's pixels


@dataclass(frozen=True)
class Parts:
    """The objects of a demo run: their ``models_info`` entries and where they come from.

    ``source`` is the user's models folder, None for the built-in parts (whose entries then hold their
    symmetries only: enough to group them and choose their codes; the renders write the full entries).
    """

    models_info: Mapping[int, Mapping[str, Any]]
    source: Path | None = None
    reach_mm: Mapping[int, float] = field(default_factory=dict)  # how far each mesh reaches from its origin

    @property
    def builtin(self) -> bool:
        return self.source is None

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self.models_info)

    def describe(self) -> str:
        """What the report calls them: "the six built-in parts", "the 2 parts of `folder` (objects 1, 2)"."""
        if self.source is None:
            return "the six built-in parts"
        ids = self.obj_ids
        if len(ids) == 1:
            return f"the part of `{self.source}` (object {ids[0]})"
        return f"the {len(ids)} parts of `{self.source}` (objects {', '.join(map(str, ids))})"

    def objects_option(self) -> str:
        """The ``popcode-train demo`` option that selects these parts (empty for the default, the built-in ones)."""
        return "" if self.source is None else f" --objects {self.source}"

    def write_models(self, folder: Path) -> Path:
        """Copy the models into ``folder`` (a split's ``models``); refuses a folder that holds other models."""
        if self.source is None:
            raise PopcodeError("the built-in parts are written by their own renders")
        folder.mkdir(parents=True, exist_ok=True)
        info_path = folder / MODELS_INFO
        entries = {str(obj_id): dict(self.models_info[obj_id]) for obj_id in self.obj_ids}
        if info_path.is_file() and json.loads(info_path.read_text()) != json.loads(json.dumps(entries)):
            raise PopcodeError(f"{folder.parent.parent} was started with other models ({info_path} differs from "
                               f"{self.source / MODELS_INFO}); use another --out, or delete it to start over")
        for obj_id in self.obj_ids:
            name = _mesh_name(obj_id)
            data = (self.source / name).read_bytes()
            copy = folder / name
            if copy.is_file() and copy.read_bytes() != data:
                raise PopcodeError(f"{folder.parent.parent} was started with another mesh of object {obj_id} "
                                   f"({copy} differs from {self.source / name}); use another --out, or delete it "
                                   "to start over")
            if not copy.is_file():
                write_bytes_atomic(copy, data)
        if not info_path.is_file():
            write_json_atomic(info_path, entries)
        return folder

    def fill_range(self) -> tuple[tuple[float, float], str]:
        """The single-part renders' diameter / image side, and a sentence where it is not the renderer's default.

        Centred at fill ``x``, a part reaching ``r`` mm from its origin fits the image in every view while
        ``f r / sqrt(D^2 - r^2)`` (its bounding sphere's image radius, camera distance ``D = f d / (x W)``) stays
        within half the image (:data:`FIT_MARGIN` to spare); the renderer's highest fill is lowered to that.
        """
        low, high = RenderSettings(1).fill_range
        if not self.reach_mm:
            return (low, high), ""
        side = RENDER_SIDE_PX
        focal_px = float(camera_matrix(side, side)[0, 0])
        fill_per_ratio = FIT_MARGIN * focal_px / (side * np.hypot(1.0, 2.0 * focal_px / (side - 1)))
        fits = {obj_id: fill_per_ratio * float(self.models_info[obj_id]["diameter"]) / reach
                for obj_id, reach in self.reach_mm.items()}
        obj_id = min(fits, key=fits.__getitem__)
        if fits[obj_id] >= high:
            return (low, high), ""
        fill = (min(low, fits[obj_id]), fits[obj_id])
        reach = self.reach_mm[obj_id] / float(self.models_info[obj_id]["diameter"])
        return fill, (f"Object {obj_id} reaches {reach:.2f} of its diameter from its origin, so the single-part "
                      f"renders frame every part at {fill[0]:.2f}-{fill[1]:.2f} of the image (diameter / side) instead "
                      f"of {low:g}-{high:g}: every view of it then fits.")

    def render_split(self, out_dir: Path, images_per_object: int, seed: int, progress: bool,
                     shard: tuple[int, int] = (0, 1)) -> Path:
        """Single-part images at random rotations and positions (128 x 128), models in ``out_dir/models``."""
        if self.source is None:
            return render_builtin_split(out_dir, images_per_object, seed=seed, random_position=True,
                                        progress=progress, shard=shard)
        models_dir = self.write_models(out_dir / BUILTIN_MODELS_FOLDER)
        settings = RenderSettings(images_per_object, seed=seed, random_position=True,
                                  fill_range=self.fill_range()[0])
        return render_split(models_dir, out_dir, settings, shard=shard, progress=progress)

    def render_scenes(self, out_dir: Path, scenes: int, seed: int, progress: bool,
                      shard: tuple[int, int] = (0, 1)) -> Path:
        """Cluttered bin scenes (720 x 540, industrial camera), models in ``out_dir/models``."""
        if self.source is None:
            return render_cluttered_test_split(out_dir, scenes, seed=seed, progress=progress, shard=shard)
        models_dir = self.write_models(out_dir / BUILTIN_MODELS_FOLDER)
        render_scene_split(models_dir, out_dir, SceneSettings(scenes, seed=seed, sensor=CLUTTERED_SENSOR),
                           shard=shard, progress=progress)
        return out_dir


def builtin_parts() -> Parts:
    return Parts({part.obj_id: part.symmetries for part in BUILTIN_PARTS})


def load_parts(objects: str | Path) -> Parts:
    """``"builtin"`` or a models folder, checked (:func:`check_models_folder`)."""
    return builtin_parts() if str(objects) == BUILTIN else check_models_folder(Path(objects))


def _mesh_name(obj_id: int) -> str:
    return f"obj_{obj_id:06d}.ply"


def _top_level_keys(path: Path) -> list[str]:
    """The keys of the JSON object in ``path`` in file order, repeats kept (a dict would drop them silently)."""
    objects: list[list[str]] = []

    def keep(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        objects.append([key for key, _ in pairs])
        return dict(pairs)

    try:
        json.loads(path.read_text(), object_pairs_hook=keep)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise PopcodeError(f"{path} is not valid JSON: {error}") from error
    return objects[-1] if objects else []  # the outermost object closes last


def _check_unique_ids(path: Path) -> None:
    seen: dict[int, str] = {}
    for key in _top_level_keys(path):
        try:
            obj_id = int(key)
        except ValueError:
            continue  # load_models_info names keys that are not ids
        if obj_id in seen:
            raise PopcodeError(f"{path}: object {obj_id} is listed twice (keys {seen[obj_id]!r} and {key!r}); "
                               "give each part its own id and mesh obj_XXXXXX.ply")
        seen[obj_id] = key


def check_models_folder(models_dir: Path) -> Parts:
    """Every part of a BOP models folder checked as the module docstring lists; returns them."""
    if not models_dir.is_dir():
        raise PopcodeError(f"--objects: no such models folder {models_dir} (or use '{BUILTIN}')")
    info_path = models_dir / MODELS_INFO
    if not info_path.is_file():
        raise PopcodeError(f"{models_dir} has no {MODELS_INFO}: a BOP models folder lists each part's id, diameter, "
                           "box and symmetries there; write it with popcode_trainer.data.objects.model_info "
                           "(README: Training on your own CAD models)")
    models_info = load_models_info(models_dir)  # first: it refuses files too large or not JSON
    _check_unique_ids(info_path)
    if not models_info:
        raise PopcodeError(f"{info_path} lists no parts")
    reach_mm = {obj_id: check_part(models_dir, obj_id, models_info[obj_id]) for obj_id in sorted(models_info)}
    return Parts(models_info, models_dir, reach_mm)


def check_part(models_dir: Path, obj_id: int, info: Mapping[str, Any]) -> float:
    """One part's mesh file, units, placement, thickness and declared symmetries (PopcodeError naming the fix);
    returns how far the mesh reaches from its origin [mm]."""
    path = models_dir / _mesh_name(obj_id)
    name = f"object {obj_id} ({path})"
    if not path.is_file():
        raise PopcodeError(f"object {obj_id}: no mesh {path}; {MODELS_INFO} lists it, so its mesh must be "
                           f"{_mesh_name(obj_id)} (obj_ and the id in six digits), or remove its entry")
    diameter = float(info["diameter"])  # a positive number: load_models_info refuses text and true/false
    mesh = load_mesh(path)
    _check_units(name, diameter, float(np.linalg.norm(mesh.extents)))
    _check_diameter(name, diameter, mesh_diameter_mm(mesh))
    reach = float(np.linalg.norm(mesh.vertices, axis=1).max())
    if reach > diameter * (1.0 + 1e-6):
        raise PopcodeError(f"{name}: the mesh reaches {reach:.4g} mm from its origin, more than its diameter "
                           f"{diameter:.4g} mm: centre the mesh on its origin (or fix the diameter)")
    visible = median_visible_px(mesh, diameter)
    if visible < MIN_VISIBLE_PX:
        raise PopcodeError(
            f"{name}: too thin to see: rendered {SMALLEST_FILL * RENDER_SIDE_PX:.0f} px across, it covers "
            f"{visible:.0f} px in half of the views (under {MIN_VISIBLE_PX:g}): a line a pixel or two wide, whose "
            "rotation a network cannot read; leave it out of models_info.json, or check the mesh's units and "
            "thickness")
    check_object_symmetries(path, info, obj_id, mesh)
    return reach


def _check_units(name: str, diameter_mm: float, span: float) -> None:
    """Millimetres in the mesh (``span``: its bounding-box diagonal) and in the declared diameter."""
    if span < MIN_DIAMETER_MM:
        raise PopcodeError(f"{name}: the mesh is {span:.3g} across: it looks like metres; scale the mesh by 1000 "
                           f"(and a diameter of {diameter_mm:g} in {MODELS_INFO} with it if it is in metres too): "
                           "BOP models are in millimetres")
    if diameter_mm < MIN_DIAMETER_MM:
        raise PopcodeError(f"{name}: diameter {diameter_mm:g} in {MODELS_INFO} looks like metres while the mesh spans "
                           f"{span:.4g} mm; write the diameter in millimetres")


def _check_diameter(name: str, declared_mm: float, measured_mm: float) -> None:
    """A declared diameter within :data:`DIAMETER_TOLERANCE` of the mesh's, smaller or larger."""
    if abs(declared_mm - measured_mm) > DIAMETER_TOLERANCE * measured_mm:
        side = "smaller" if declared_mm < measured_mm else "larger"
        raise PopcodeError(f"{name}: diameter {declared_mm:g} mm in {MODELS_INFO} is {side} than the mesh's "
                           f"{measured_mm:.6g} mm (the largest distance between two of its vertices) by more than "
                           f"{100 * DIAMETER_TOLERANCE:g} %: set it to {measured_mm:.6g} "
                           "(popcode_trainer.data.objects.model_info computes it)")


def median_visible_px(mesh: trimesh.Trimesh, diameter_mm: float, views: int = THICKNESS_VIEWS) -> float:
    """The median over seeded random views of the pixels the part covers when its diameter spans
    ``SMALLEST_FILL * RENDER_SIDE_PX`` pixels (orthographic; surface points binned on a grid
    :data:`SUPERSAMPLE` times finer than a pixel, so a bar under a pixel wide counts as under a pixel)."""
    points = np.asarray(trimesh.sample.sample_surface(mesh, THICKNESS_POINTS, seed=0)[0])
    cells_per_mm = SUPERSAMPLE * SMALLEST_FILL * RENDER_SIDE_PX / diameter_mm
    areas = []
    for R in random_rotations(views, np.random.default_rng(0)):
        cells = np.floor((points @ R[:2].T) * cells_per_mm).astype(np.int64)
        cells -= cells.min(axis=0)
        covered = np.zeros(cells.max(axis=0) + 1, dtype=bool)
        covered[cells[:, 0], cells[:, 1]] = True
        areas.append(np.count_nonzero(covered) / SUPERSAMPLE**2)
    return float(np.median(areas))
