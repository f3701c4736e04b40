"""What the evaluation tests' scene fixtures (conftest.py) are made of, importable by the tests themselves."""

from __future__ import annotations

from pathlib import Path

from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER

SCENE_OBJECTS = [3, 6]  # a 2-fold symmetric part and one without symmetry
SCENE_SIZE = (160, 120)


def scene_objects(scenes: Path) -> dict[int, dict]:
    """The ``models_info`` entries of :data:`SCENE_OBJECTS`."""
    info = load_models_info(scenes / BUILTIN_MODELS_FOLDER)
    return {obj_id: info[obj_id] for obj_id in SCENE_OBJECTS}
