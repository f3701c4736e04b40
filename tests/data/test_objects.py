"""The built-in parts: models_info is right and every declared symmetry is real, no more and no less."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from mesh_distance import surface_distance_mm

from popcode_runtime import symmetry_rotations, symmetry_transforms
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, geodesic_angle
from popcode_runtime.geometry.symmetries import SymmetryClass, continuous_axis, symmetry_class
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.objects import BUILTIN_PARTS, build_part, write_builtin_models

SYMMETRIC_TOL = 0.002  # of the diameter: facets of revolved surfaces deviate by far less
ASYMMETRIC_MIN = 0.05  # of the diameter: a non-symmetry moves some surface point at least this far


def _candidates() -> list[np.ndarray]:
    """Rotations a part of this kind could plausibly be symmetric under."""
    axes = [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
    rotations = [axis_angle_to_matrix(np.array(axis, float), np.deg2rad(angle))
                 for axis in axes for angle in (45, 90, 180, 270)]
    rotations += [axis_angle_to_matrix(np.array([1.0, 1.0, 1.0]), 2 * np.pi / 3),
                  axis_angle_to_matrix(np.array([1.0, 1.0, 0.0]), np.pi),
                  axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.deg2rad(37))]
    return rotations


def _declared(R: np.ndarray, info: dict) -> bool:
    discrete = symmetry_rotations(info)
    if symmetry_class(info) is SymmetryClass.CONTINUOUS:
        axis = continuous_axis(info)
        return any(np.linalg.norm(R @ S.T @ axis - axis) < 1e-6 for S in discrete)
    return any(geodesic_angle(R, S) < 1e-6 for S in discrete)


def _max_surface_distance(mesh: trimesh.Trimesh, points: np.ndarray, R: np.ndarray, t: np.ndarray) -> float:
    """How far the transformed surface samples lie from the surface (0 when R, t is a symmetry)."""
    distance = surface_distance_mm(mesh, points @ R.T + t)
    return float(distance.max())


@pytest.fixture(scope="module")
def models_info(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return load_models_info(write_builtin_models(tmp_path_factory.mktemp("models")))


def test_parts_cover_every_symmetry_class(models_info: dict) -> None:
    classes = {symmetry_class(info) for info in models_info.values()}
    assert classes == set(SymmetryClass)
    flips = [obj_id for obj_id, info in models_info.items()
             if symmetry_class(info) is SymmetryClass.CONTINUOUS and len(symmetry_rotations(info)) > 1]
    assert flips, "one part must have a continuous symmetry plus a flip"
    orders = {len(symmetry_rotations(info)) for info in models_info.values()
              if symmetry_class(info) is SymmetryClass.DISCRETE}
    assert {2, 4} <= orders


@pytest.mark.parametrize("part", BUILTIN_PARTS, ids=lambda part: part.name)
def test_models_info_matches_mesh(part, models_info: dict) -> None:
    mesh = build_part(part.obj_id)
    info = models_info[part.obj_id]
    assert len(mesh.vertices) < 5000
    np.testing.assert_allclose([info["min_x"], info["min_y"], info["min_z"]], mesh.bounds[0])
    np.testing.assert_allclose([info["size_x"], info["size_y"], info["size_z"]], mesh.extents)
    vertices = mesh.vertices
    pairwise = np.linalg.norm(vertices[:, None] - vertices[None], axis=-1)
    assert info["diameter"] == pytest.approx(pairwise.max())


@pytest.mark.parametrize("part", BUILTIN_PARTS, ids=lambda part: part.name)
def test_declared_symmetries_are_real_and_complete(part, models_info: dict) -> None:
    mesh = build_part(part.obj_id)
    info = models_info[part.obj_id]
    diameter = info["diameter"]
    points, _ = trimesh.sample.sample_surface(mesh, 128, seed=part.obj_id)
    transforms = symmetry_transforms(info, max_sym_disc_step=0.3)  # a few steps of each continuous one
    for R, t in zip(transforms.R, transforms.t_mm, strict=True):
        assert _max_surface_distance(mesh, points, R, t) < SYMMETRIC_TOL * diameter
    for R in _candidates():
        distance = _max_surface_distance(mesh, points, R, np.zeros(3))
        if _declared(R, info):
            assert distance < SYMMETRIC_TOL * diameter
        else:
            assert distance > ASYMMETRIC_MIN * diameter, f"undeclared symmetry of {part.name}"
