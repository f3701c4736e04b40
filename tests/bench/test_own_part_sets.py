"""tools/own_parts.py's validation and tuning parts: closed parts whose declared symmetries are exactly the ones they
have, the near-symmetric one the only one the near-symmetry finder reports, in a folder the demo accepts."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trimesh
from mesh_distance import surface_distance_mm

from popcode_runtime import symmetry_transforms
from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.meshes import load_mesh
from popcode_trainer.data.near_symmetry import look_alike_symmetries
from popcode_trainer.data.surface_sample import surface_distance, surface_sample
from popcode_trainer.data.symmetry_check import TOLERANCE, _anchors_mm, check_symmetries
from popcode_trainer.demo.parts import check_models_folder
from tools import own_parts
from tools.own_parts import OwnPart

SYMMETRIC_TOL = 0.001  # of the diameter: every circle's vertices map onto themselves, so only rounding remains


@dataclass(frozen=True)
class PartSet:
    name: str  # as ``python -m tools.own_parts NAME`` calls it
    parts: tuple[OwnPart, ...]
    look_alike_order: int  # of the near-symmetric part's undeclared rotation about z


SETS = (PartSet("validation", own_parts.VALIDATION_PARTS, 4), PartSet("tuning", own_parts.TUNING_PARTS, 2))


@pytest.fixture(scope="module", params=SETS, ids=lambda part_set: part_set.name)
def part_set(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[PartSet, Path]:
    chosen: PartSet = request.param
    return chosen, own_parts.main([chosen.name, "--out", str(tmp_path_factory.mktemp(chosen.name) / "models")])


def _mesh(models: Path, obj_id: int) -> trimesh.Trimesh:
    return load_mesh(models / f"obj_{obj_id:06d}.ply")


def test_closed_parts_in_millimetres(part_set: tuple[PartSet, Path]) -> None:
    chosen, models = part_set
    models_info = load_models_info(models)
    assert sorted(models_info) == [part.obj_id for part in chosen.parts] == list(range(1, len(chosen.parts) + 1))
    for obj_id, info in models_info.items():
        mesh = _mesh(models, obj_id)
        assert mesh.is_watertight and mesh.volume > 0, obj_id
        assert 40 <= info["diameter"] <= 120, obj_id
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)  # centred on the bounding box


def test_declared_symmetries_map_the_mesh_onto_itself(part_set: tuple[PartSet, Path]) -> None:
    chosen, models = part_set
    for part in chosen.parts:
        mesh, info = _mesh(models, part.obj_id), load_models_info(models)[part.obj_id]
        points, _ = trimesh.sample.sample_surface(mesh, 128, seed=part.obj_id)
        transforms = symmetry_transforms(info, max_sym_disc_step=0.3)  # a few steps of a continuous symmetry
        for R, t in zip(transforms.R, transforms.t_mm, strict=True):
            distance = surface_distance_mm(mesh, points @ R.T + t)
            assert distance.max() < SYMMETRIC_TOL * info["diameter"], part.name
        check_symmetries(mesh, info, part.name)  # the project's check: each one, and a closed group


def test_only_the_near_symmetric_part_has_look_alike_poses(part_set: tuple[PartSet, Path]) -> None:
    chosen, models = part_set
    models_info = load_models_info(models)
    assert sum(part.near_symmetric for part in chosen.parts) == 1
    for part in chosen.parts:
        mesh, info = _mesh(models, part.obj_id), models_info[part.obj_id]
        sample = surface_sample(mesh, info["diameter"], part.name)
        found = look_alike_symmetries(sample, info, _anchors_mm(info, info["diameter"]))
        if not part.near_symmetric:
            assert found == [], [look_alike.describe(part.name) for look_alike in found]
            continue
        order = chosen.look_alike_order
        assert [(look_alike.order, tuple(np.abs(look_alike.axis).round(3))) for look_alike in found] == \
            [(order, (0, 0, 1))]
        for turn in range(1, order):  # yet the feature breaks the symmetry by the symmetry check's measure
            R = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), 2 * np.pi * turn / order)
            assert surface_distance(sample, R, np.zeros(3)) > 1.5 * TOLERANCE


def test_the_demo_accepts_the_folder_and_warns_of_the_look_alike(part_set: tuple[PartSet, Path]) -> None:
    """``popcode-train demo --objects DIR`` checks the folder so: units, centring, thickness and symmetries."""
    chosen, models = part_set
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parts = check_models_folder(models)
    assert parts.obj_ids == [part.obj_id for part in chosen.parts]
    look_alikes = [str(warning.message) for warning in caught if "looks" in str(warning.message)]
    near = next(part.obj_id for part in chosen.parts if part.near_symmetric)
    assert len(look_alikes) == 1, look_alikes
    assert look_alikes[0].startswith(f"object {near} looks {chosen.look_alike_order}-fold symmetric about z")
