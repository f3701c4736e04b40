"""The generated pretraining parts (data.generated_parts): every kind drawn, reproducible, each declared symmetry
exact and the look-alike parts nearly symmetric but declared without it, in a folder the demo's checks accept."""

from __future__ import annotations

import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import trimesh
from mesh_distance import surface_distance_mm

from popcode_runtime import symmetry_transforms
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.symmetries import SymmetryClass, symmetry_class
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.generated_parts import KINDS, generate_parts, kinds_of, write_generated_models
from popcode_trainer.data.near_symmetry import LookAlikeWarning, look_alike_symmetries
from popcode_trainer.data.objects import BUILTIN_PARTS, build_part
from popcode_trainer.data.surface_sample import surface_sample
from popcode_trainer.data.symmetry_check import _anchors_mm
from popcode_trainer.demo.parts import check_models_folder
from tools.own_parts import TUNING_PARTS, VALIDATION_PARTS, build_own_part

SYMMETRIC_TOL = 0.001  # of the diameter: circles and repeated features map onto themselves, only rounding remains
COUNT = 24


@pytest.fixture(scope="module")
def parts() -> list:
    return generate_parts(COUNT, seed=11)


def test_the_same_seed_draws_the_same_parts_and_another_seed_others(parts: list) -> None:
    again = generate_parts(COUNT, seed=11)
    assert [p.kind for p in again] == [p.kind for p in parts]
    for first, second in zip(parts, again, strict=True):
        np.testing.assert_array_equal(first.mesh.vertices, second.mesh.vertices)
    other = generate_parts(COUNT, seed=12)
    assert any(len(a.mesh.vertices) != len(b.mesh.vertices) or not np.allclose(a.mesh.vertices, b.mesh.vertices)
               for a, b in zip(parts, other, strict=True))


def test_every_kind_is_drawn_with_its_symmetry_class(parts: list) -> None:
    assert set(Counter(p.kind for p in parts)) == set(KINDS)
    expected = {"continuous": SymmetryClass.CONTINUOUS, "none": SymmetryClass.NONE, "look_alike": SymmetryClass.NONE,
                "discrete": SymmetryClass.DISCRETE}
    for part in parts:
        assert symmetry_class(part.symmetries) is expected[part.kind], (part.obj_id, part.family)
    assert [p.obj_id for p in parts] == list(range(1, COUNT + 1))
    assert {p.kind for p in generate_parts(30, seed=3, kinds=("none", "look_alike"))} == {"none", "look_alike"}


@pytest.mark.slow
def test_declared_symmetries_map_each_mesh_onto_itself(parts: list) -> None:
    for part in parts:
        info = {**part.symmetries, "diameter": float(np.linalg.norm(part.mesh.extents))}
        points, _ = trimesh.sample.sample_surface(part.mesh, 96, seed=part.obj_id)
        transforms = symmetry_transforms(info, max_sym_disc_step=0.3)
        assert len(transforms.R) > 1 or part.kind in ("none", "look_alike")
        for R, t in zip(transforms.R, transforms.t_mm, strict=True):
            distance = surface_distance_mm(part.mesh, points @ R.T + t)
            assert distance.max() < SYMMETRIC_TOL * info["diameter"], (part.obj_id, part.family)


def test_look_alike_parts_nearly_have_a_symmetry(parts: list) -> None:
    """The feature that breaks each look-alike part's symmetry is small: the near-symmetry finder reports it."""
    look_alikes = [p for p in parts if p.kind == "look_alike"]
    assert look_alikes
    for part in look_alikes:
        diameter = float(np.linalg.norm(part.mesh.extents))
        sample = surface_sample(part.mesh, diameter, str(part.obj_id))
        assert look_alike_symmetries(sample, {"diameter": diameter}, _anchors_mm({}, diameter)), part.family


@pytest.mark.slow
def test_the_folder_passes_the_demo_checks(parts: list, tmp_path: Path) -> None:
    folder = write_generated_models(parts[:8], tmp_path / "models")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LookAlikeWarning)
        checked = check_models_folder(folder)
    assert checked.obj_ids == list(range(1, 9))
    assert kinds_of(folder) == {p.obj_id: p.kind for p in parts[:8]}
    assert set(load_models_info(folder)) == set(range(1, 9))


def test_no_generated_part_is_a_held_out_part() -> None:
    """Built-in, tuning and validation parts are not among the generated ones (no mesh of the same size and shape)."""
    held_out = [build_part(p.obj_id) for p in BUILTIN_PARTS]
    held_out += [build_own_part(p) for p in (*TUNING_PARTS, *VALIDATION_PARTS)]
    signatures = {(len(m.vertices), round(float(m.volume), -1)) for m in held_out}
    for part in generate_parts(200, seed=0, kinds=("discrete", "none", "look_alike")):
        assert (len(part.mesh.vertices), round(float(part.mesh.volume), -1)) not in signatures


@pytest.mark.parametrize(("count", "kinds"), [(0, KINDS), (10_001, KINDS), (3, ("cubes",)), (3, ())])
def test_bad_requests_are_refused(count: int, kinds: tuple) -> None:
    with pytest.raises(PopcodeError, match="parts|kinds"):
        generate_parts(count, seed=0, kinds=kinds)
