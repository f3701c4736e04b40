"""Physically based images with Mitsuba 3: rough metals and plastics, area lights, interreflections, render noise.

The rasteriser (:mod:`.render`, :mod:`.scene_render`) draws flat Lambert-like shading with one look per
material; a camera sees highlights on rough aluminium, soft shadows and light bounced between parts.
This module renders a list of meshes posed in the OpenCV camera frame (millimetres) with Mitsuba's path
tracer, so that a split can be seen as a physically based renderer sees it (:mod:`.path_traced_split`).
Mitsuba is an optional trainer extra (``pip install '.[pathtrace]'``), never a runtime one.

The ``scalar_rgb`` variant is used: Dr.Jit's LLVM variant aborted the process on this machine's LLVM 15
(an instruction it could not select), and an abort cannot be caught (``bench/results/path-traced.md``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError

MITSUBA_VARIANT = "scalar_rgb"
INSTALL_HINT = "pip install mitsuba (the trainer's extra: pip install '.[pathtrace]' in the repository)"
PART_MATERIALS = ("aluminium", "steel", "grey plastic", "black plastic")  # drawn with equal odds
MAX_SAMPLES = 4096  # per pixel: beyond it an image takes hours on a CPU


@dataclass(frozen=True)
class PathTraceSettings:
    """How an image is path traced; stored in the split it writes, so a rerun cannot mix settings."""

    samples: int = 32  # per pixel: the grain left is part of the look (a camera has grain too)
    max_depth: int = 6  # light paths of up to 5 bounces: interreflections inside the bin
    seed: int = 0  # of the materials and lights; the scene itself is the source split's

    def __post_init__(self) -> None:
        if not 1 <= self.samples <= MAX_SAMPLES or not 2 <= self.max_depth <= 64 or not 0 <= self.seed < 2**62:
            raise PopcodeError(f"path tracing needs 1 <= samples <= {MAX_SAMPLES}, 2 <= max_depth <= 64 and "
                               f"0 <= seed < 2**62, got {self.samples}, {self.max_depth} and {self.seed}")


@dataclass(frozen=True)
class Surface:
    """A mesh in the camera frame (OpenCV axes, mm) and Mitsuba's description of its material."""

    mesh: trimesh.Trimesh
    model_to_camera: np.ndarray  # (4, 4)
    bsdf: dict[str, Any]
    texcoords: np.ndarray | None = None  # (V, 2) for a textured material


def import_mitsuba() -> Any:
    """Mitsuba with the variant set, or one line that says what to install. It renders on ``OMP_NUM_THREADS``
    threads where that is set (as torch and OpenCV do), else on every core."""
    try:
        import drjit
        import mitsuba
    except ImportError as error:
        raise PopcodeError(f"path tracing needs Mitsuba 3, an optional extra: {INSTALL_HINT}") from error
    mitsuba.set_variant(MITSUBA_VARIANT)
    threads = os.environ.get("OMP_NUM_THREADS", "")
    if threads.isdigit() and int(threads) > 0:
        drjit.set_thread_count(int(threads))
    return mitsuba


def draw_part_bsdf(rng: np.random.Generator) -> tuple[str, dict[str, Any]]:
    """An industrial part's material: rough aluminium or steel, grey or black plastic; its name and BSDF."""
    kind = PART_MATERIALS[int(rng.integers(len(PART_MATERIALS)))]
    if kind in ("aluminium", "steel"):
        # Mitsuba has no iron table; chromium's optical constants give steel's darker, bluish reflection.
        return kind, {"type": "roughconductor", "material": "Al" if kind == "aluminium" else "Cr",
                      "alpha": float(rng.uniform(0.05, 0.4))}
    level = rng.uniform(0.25, 0.7) if kind == "grey plastic" else rng.uniform(0.02, 0.08)
    return kind, plastic_bsdf(np.full(3, level), float(rng.uniform(0.05, 0.4)))


def plastic_bsdf(colour: np.ndarray, alpha: float) -> dict[str, Any]:
    """A rough dielectric coat on a diffuse base: plastic, painted metal, a bin's walls."""
    return {"type": "roughplastic", "alpha": alpha,
            "diffuse_reflectance": {"type": "rgb", "value": [float(c) for c in colour]}}


def textured_bsdf(mitsuba: Any, texture_rgb: np.ndarray) -> dict[str, Any]:
    """A diffuse surface with an sRGB texture (``(H, W, 3)`` uint8), repeated as its texture coordinates say."""
    bitmap = mitsuba.Bitmap(np.ascontiguousarray(texture_rgb, dtype=np.float32) / 255.0)
    return {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": bitmap, "raw": False,
                                              "wrap_mode": "repeat"}}


def draw_lights(rng: np.random.Generator, centre_mm: np.ndarray) -> list[dict[str, Any]]:
    """One to three rectangular area lights from the camera's side, aimed at ``centre_mm``, and a dim sky.

    A light's radiance is scaled by its distance and size, so that each brings light of the same order to the
    scene whatever the scene's scale; the exposure (:func:`expose`) sets the image's level afterwards.
    """
    distance_mm = float(np.linalg.norm(centre_mm))
    lights: list[dict[str, Any]] = []
    for _ in range(int(rng.integers(1, 4))):
        offset = np.array([*rng.uniform(-1.0, 1.0, size=2), -rng.uniform(0.0, 0.5)]) * distance_mm
        half_side_mm = rng.uniform(0.05, 0.4) * distance_mm
        to_light_mm = np.linalg.norm(centre_mm - offset)
        radiance = rng.uniform(0.5, 2.0) * (to_light_mm / (2.0 * half_side_mm)) ** 2
        lights.append({"type": "rectangle", "to_world": _look_at(offset, centre_mm, half_side_mm),
                       "emitter": {"type": "area", "radiance": {"type": "rgb", "value": float(radiance)}}})
    lights.append({"type": "constant", "radiance": {"type": "rgb", "value": float(rng.uniform(0.02, 0.3))}})
    return lights


def _look_at(origin_mm: np.ndarray, target_mm: np.ndarray, half_side_mm: float) -> Any:
    """A rectangle's (local ``[-1, 1]^2`` in z = 0, facing +z) placement: at ``origin_mm``, facing ``target_mm``."""
    import mitsuba

    up = [0.0, 1.0, 0.0] if abs(target_mm[1] - origin_mm[1]) < 0.9 * np.linalg.norm(target_mm - origin_mm) \
        else [1.0, 0.0, 0.0]
    return mitsuba.ScalarTransform4f().look_at(origin=[float(v) for v in origin_mm],
                                               target=[float(v) for v in target_mm], up=up).scale(
        [half_side_mm, half_side_mm, 1.0])


def _mesh(mitsuba: Any, name: str, surface: Surface) -> Any:
    """A Mitsuba mesh of ``surface`` with its vertices moved into the camera frame (flat shaded: no normals)."""
    vertices = np.asarray(surface.mesh.vertices, np.float64) @ surface.model_to_camera[:3, :3].T \
        + surface.model_to_camera[:3, 3]
    faces = np.asarray(surface.mesh.faces, np.uint32)
    properties = mitsuba.Properties()
    properties["bsdf"] = mitsuba.load_dict(surface.bsdf)
    mesh = mitsuba.Mesh(name, vertex_count=len(vertices), face_count=len(faces), props=properties,
                        has_vertex_normals=False, has_vertex_texcoords=surface.texcoords is not None)
    parameters = mitsuba.traverse(mesh)
    floats, indices = type(parameters["vertex_positions"]), type(parameters["faces"])
    parameters["vertex_positions"] = floats(vertices.astype(np.float32).ravel())
    parameters["faces"] = indices(faces.ravel())
    if surface.texcoords is not None:
        parameters["vertex_texcoords"] = floats(np.asarray(surface.texcoords, np.float32).ravel())
    parameters.update()
    return mesh


def _camera(K: np.ndarray, width: int, height: int, near_far_mm: tuple[float, float], samples: int) -> dict[str, Any]:
    """Mitsuba's pinhole with intrinsics ``K`` whose pixel ``i`` samples ``x = i`` (BOP's convention).

    Mitsuba's camera looks along +z with +x to the image's left and +y up: turned half a turn about z, its
    frame is OpenCV's. Its film's pixel ``i`` spans ``[i, i + 1)``, so the principal point moves half a pixel.
    """
    import mitsuba

    return {
        "type": "perspective", "fov_axis": "x", "fov": float(np.degrees(2.0 * np.arctan(width / (2.0 * K[0, 0])))),
        "principal_point_offset_x": float((K[0, 2] + 0.5 - width / 2.0) / width),
        "principal_point_offset_y": float((K[1, 2] + 0.5 - height / 2.0) / height),
        "near_clip": float(near_far_mm[0]), "far_clip": float(near_far_mm[1]),
        "to_world": mitsuba.ScalarTransform4f(np.diag([-1.0, -1.0, 1.0, 1.0])),
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": int(samples)},
    }


def path_trace(mitsuba: Any, surfaces: list[Surface], lights: list[dict[str, Any]], K: np.ndarray,
               size: tuple[int, int], settings: PathTraceSettings, image_seed: int) -> np.ndarray:
    """Linear RGB radiance ``(H, W, 3)`` float32 of ``surfaces`` seen through ``K``; emitters themselves unseen."""
    width, height = size
    corners = np.concatenate([trimesh.bounds.corners(s.mesh.bounds) @ s.model_to_camera[:3, :3].T
                              + s.model_to_camera[:3, 3] for s in surfaces])
    near_mm = max(float(corners[:, 2].min()) * 0.5, 1e-3)
    far_mm = max(float(corners[:, 2].max()) * 2.0, near_mm * 10.0)
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": settings.max_depth, "hide_emitters": True},
        "sensor": _camera(K, width, height, (near_mm, far_mm), settings.samples),
    }
    for index, surface in enumerate(surfaces):
        scene[f"surface_{index}"] = _mesh(mitsuba, f"surface_{index}", surface)
    for index, light in enumerate(lights):
        scene[f"light_{index}"] = light
    image = np.array(mitsuba.render(mitsuba.load_dict(scene), seed=image_seed % 2**32), dtype=np.float32)
    if not np.isfinite(image).all():
        raise PopcodeError("the path tracer returned non-finite radiance")
    return image[..., :3]


def expose(linear_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """An 8-bit sRGB image as a camera's auto-exposure makes it: the brightest 1 % of the lit pixels at or
    above white (highlights clip), then the sRGB curve. A black image stays black."""
    luminance = linear_rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    lit = luminance[luminance > 0]
    reference = float(np.percentile(lit, 99)) if lit.size else 1.0
    scaled = np.clip(linear_rgb * (rng.uniform(0.75, 1.1) / max(reference, 1e-12)), 0.0, 1.0)
    srgb = np.where(scaled <= 0.0031308, 12.92 * scaled, 1.055 * np.power(scaled, 1.0 / 2.4) - 0.055)
    return np.round(255.0 * srgb).astype(np.uint8)
