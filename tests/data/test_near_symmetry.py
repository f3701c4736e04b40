"""Look-alike poses: symmetries a mesh nearly has without declaring them are found and reported."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_trainer.data import symmetry_check
from popcode_trainer.data.near_symmetry import LookAlike, look_alike_rotations, look_alike_symmetries
from popcode_trainer.data.objects import BUILTIN_PARTS, build_part, model_info
from popcode_trainer.data.surface_sample import SurfaceSample, diameter_mm, surface_distance, surface_sample
from popcode_trainer.data.symmetry_check import _anchors_mm, check_object_symmetries


def _plate_with_pin() -> trimesh.Trimesh:
    """A square plate, 4-fold about z but for one small pin near a corner."""
    pin = trimesh.creation.cylinder(radius=2, height=6, transform=trimesh.transformations.translation_matrix(
        (24, 24, 7)))
    return trimesh.util.concatenate([trimesh.creation.box(extents=(60, 60, 10)), pin])


def _look_alikes(mesh: trimesh.Trimesh, info: dict) -> list:
    diameter = diameter_mm(mesh, info)
    return look_alike_symmetries(surface_sample(mesh, diameter, "test"), info, _anchors_mm(info, diameter))


def test_a_plate_with_one_pin_looks_four_fold_about_z() -> None:
    mesh = _plate_with_pin()
    found = {(l.order, tuple(np.round(np.abs(l.axis), 3))): l for l in _look_alikes(mesh, model_info(mesh, {}))}
    assert (4, (0.0, 0.0, 1.0)) in found
    assert found[(4, (0.0, 0.0, 1.0))].distance_mm < 0.02 * np.linalg.norm(mesh.extents)
    assert not any(order == 3 for order, _ in found)  # no 3-fold look-alike on a square


@pytest.mark.slow
def test_declared_symmetries_and_built_in_parts_give_no_look_alike() -> None:
    for part in BUILTIN_PARTS:
        mesh = build_part(part.obj_id)
        assert _look_alikes(mesh, model_info(mesh, part.symmetries)) == [], part.name
    bracket = next(p for p in BUILTIN_PARTS if not p.symmetries)  # asymmetric: nothing looks alike either
    assert _look_alikes(build_part(bracket.obj_id), model_info(build_part(bracket.obj_id), {})) == []


def test_a_distance_asked_within_a_bound_is_the_full_one_up_to_it() -> None:
    """Turns about the look-alike axis of the plate with a pin, from fitting to far off: the bounded distance is
    the full one where that is within the bound (the pin's samples, farther, looked up in full), and more than
    the bound where it is not."""
    mesh = _plate_with_pin()
    sample = surface_sample(mesh, diameter_mm(mesh, {}), "test")
    within = 0.02
    full, bounded, farthest = [], [], []
    for degrees in np.linspace(85.0, 95.0, 21):
        R = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.radians(degrees))
        for percentile in (90.0, 99.0):
            full.append(surface_distance(sample, R, np.zeros(3), percentile))
            bounded.append(surface_distance(sample, R, np.zeros(3), percentile, within=within))
            farthest.append(surface_distance(sample, R, np.zeros(3), 100.0))
    full, bounded, farthest = np.array(full), np.array(bounded), np.array(farthest)
    fits = full <= within
    assert np.array_equal(bounded[fits], full[fits]) and (farthest[fits] > within).any()
    assert np.all(bounded[~fits] > within) and np.isinf(bounded).any()


def test_a_percentile_between_a_near_and_a_far_sample_is_not_cut_by_the_bound() -> None:
    """900 samples on the surface and 100 far off: the 90th percentile lies a tenth of the way to the far ones,
    within the bound though its upper neighbour is beyond it."""
    near, far = np.zeros((900, 3)), np.tile([1000.0, 0.0, 0.0], (100, 1))
    sample = SurfaceSample(np.concatenate([near, far]), cKDTree(near[:1]), 10_000.0, np.zeros(3))
    assert surface_distance(sample, np.eye(3), np.zeros(3), 90.0, within=0.02) == pytest.approx(0.01)
    assert surface_distance(sample, np.eye(3), np.zeros(3), 90.0, within=0.005) > 0.005


def test_the_symmetry_check_warns_with_the_fix(tmp_path: Path) -> None:
    mesh = _plate_with_pin()
    path = tmp_path / "obj_000009.ply"
    mesh.export(path)
    info = json.loads(json.dumps(model_info(mesh, {})))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_object_symmetries(path, info, 9)
    texts = [str(w.message) for w in caught]
    assert any("object 9 looks 4-fold symmetric about z" in t and "declare it" in t and "--top-k" in t for t in texts)


def test_a_copy_in_another_folder_warns_again_without_sampling_again(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Each split holds its own copy of the models: a copy of a file that passed is not sampled again, yet warns
    as the first did; a mesh with other bytes is checked anew."""
    mesh = _plate_with_pin()
    info = json.loads(json.dumps(model_info(mesh, {})))
    paths = []
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        paths.append(tmp_path / folder / "obj_000009.ply")
        mesh.export(paths[-1])
    with warnings.catch_warnings(record=True) as first:
        warnings.simplefilter("always")
        check_object_symmetries(paths[0], info, 9)

    def no_second_look(*args: object) -> None:
        raise AssertionError("sampled again")

    monkeypatch.setattr(symmetry_check, "surface_sample", no_second_look)
    with warnings.catch_warnings(record=True) as second:
        warnings.simplefilter("always")
        check_object_symmetries(paths[1], info, 9)
    assert [str(w.message) for w in second] == [str(w.message) for w in first]
    assert any("object 9 looks 4-fold symmetric about z" in str(w.message) for w in second)
    mesh.apply_translation((0.5, 0.0, 0.0))
    (tmp_path / "c").mkdir()
    mesh.export(tmp_path / "c" / "obj_000009.ply")
    with pytest.raises(AssertionError, match="sampled again"):
        check_object_symmetries(tmp_path / "c" / "obj_000009.ply", info, 9)


@pytest.mark.parametrize("angle_deg", [0.0, 30.0])
def test_look_alikes_follow_the_part_when_it_is_turned(angle_deg: float) -> None:
    turn = trimesh.transformations.rotation_matrix(np.deg2rad(angle_deg), (1, 0, 0))
    mesh = _plate_with_pin()
    mesh.apply_transform(turn)
    found = [l for l in _look_alikes(mesh, model_info(mesh, {})) if l.order == 4]
    assert len(found) == 1
    assert abs(abs(float(found[0].axis @ (turn[:3, :3] @ np.array([0.0, 0.0, 1.0])))) - 1.0) < 1e-2


def test_look_alike_poses_are_the_group_the_turns_and_the_declared_symmetries_make() -> None:
    """Each pose once: a look-alike quarter turn about z over a declared half turn about z makes 4 poses, not 8;
    over a declared quarter turn about x it makes the cube's 24 rotations (not the 16 of a plain product)."""
    def turns(axis: tuple[float, float, float], order: int) -> np.ndarray:
        return np.stack([axis_angle_to_matrix(np.array(axis, float), 2 * np.pi * k / order) for k in range(order)])

    quarter_z = LookAlike(4, np.array([0.0, 0.0, 1.0]), 0.5, 100.0)
    about_z = look_alike_rotations([quarter_z], turns((0, 0, 1), 2))
    assert len(about_z) == 4 and np.allclose(about_z[0], np.eye(3))
    cube = look_alike_rotations([quarter_z], turns((1, 0, 0), 4))
    assert len(cube) == 24
    assert np.abs(cube[:, None] - cube[None]).max(axis=(2, 3))[~np.eye(24, dtype=bool)].min() > 0.1  # all distinct
