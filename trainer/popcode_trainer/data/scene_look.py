"""How a scene image looks in the rasteriser (materials, ground texture, lights), drawn as plain data.

The draws are separate from building the pyrender scene so that another renderer can replay a scene:
:mod:`.path_traced_split` draws the same content and look from an image's generator, in the same order
as :mod:`.scene_render` does, and lands on exactly the generator state the sensor effects were drawn with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from popcode_runtime.geometry.rotations import rotation_between

from .augment import procedural_texture

SCENE_LIGHT_INTENSITY = (0.6, 2.5)  # a lit floor and walls add light: dimmer lamps than single objects get


@dataclass(frozen=True)
class MaterialDraw:
    """pyrender's metallic-roughness parameters of one object."""

    colour: np.ndarray  # (3,) linear RGB in [0, 1]
    metallic: float
    roughness: float


@dataclass(frozen=True)
class LightDraw:
    """A white directional light: its node's pose in the camera frame (light travels along its -z)."""

    pose: np.ndarray  # (4, 4)
    intensity: float


@dataclass(frozen=True)
class SceneLook:
    """Everything random about a scene image's appearance, in the order it is drawn."""

    ambient: float
    wall: MaterialDraw
    objects: list[MaterialDraw]  # targets, then distractors
    ground_texture: np.ndarray  # (256, 256, 3) uint8
    ground_repeats: float  # texture tiles along a side of the ground
    lights: list[LightDraw]


def draw_material(rng: np.random.Generator) -> MaterialDraw:
    """Mostly grey plastic or metal like T-LESS parts, sometimes coloured."""
    colour = np.full(3, rng.uniform(0.3, 0.9)) if rng.random() < 0.6 else rng.uniform(0.15, 0.9, size=3)
    metallic = rng.uniform(0.0, 0.5)
    return MaterialDraw(colour, metallic, rng.uniform(0.3, 0.9))


def draw_lights(rng: np.random.Generator, intensity_range: tuple[float, float]) -> list[LightDraw]:
    """One to three white directional lights from the camera's side (camera at the origin)."""
    lights = []
    for _ in range(rng.integers(1, 4)):
        # Light travels along -z of its node: point it into the scene from the camera's side.
        direction = rng.normal(size=3)
        direction[2] = -abs(direction[2]) - 0.5
        pose = np.eye(4)
        pose[:3, :3] = rotation_between(np.array([0.0, 0.0, -1.0]), direction)
        lights.append(LightDraw(pose, rng.uniform(*intensity_range)))
    return lights


def random_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A procedural texture between two random colours, ``(size, size, 3)`` uint8."""
    weight = np.clip(procedural_texture(rng, size), 0.0, 1.0)[..., None]
    colours = rng.uniform(0.05, 0.95, size=(2, 3))
    return np.round(255 * (weight * colours[0] + (1 - weight) * colours[1])).astype(np.uint8)


def draw_scene_look(rng: np.random.Generator, objects: int) -> SceneLook:
    """The look of a scene of ``objects`` targets and distractors (walls share one material)."""
    ambient = rng.uniform(0.05, 0.3)
    wall = draw_material(rng)
    materials = [draw_material(rng) for _ in range(objects)]
    texture = random_texture(rng)
    return SceneLook(ambient, wall, materials, texture, rng.uniform(2.0, 8.0),
                     draw_lights(rng, SCENE_LIGHT_INTENSITY))
