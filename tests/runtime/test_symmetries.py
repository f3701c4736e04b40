import numpy as np
import pytest
from symmetry_cases import CASES

from popcode_runtime import PopcodeError, SymmetryClass, symmetry_class, symmetry_rotations, symmetry_transforms
from popcode_runtime.geometry.symmetries import continuous_axis


def test_classes():
    assert symmetry_class(CASES["none"]) is SymmetryClass.NONE
    assert symmetry_class(CASES["two_fold"]) is SymmetryClass.DISCRETE
    assert symmetry_class(CASES["four_fold"]) is SymmetryClass.DISCRETE
    assert symmetry_class(CASES["continuous"]) is SymmetryClass.CONTINUOUS
    assert symmetry_class(CASES["continuous_flip"]) is SymmetryClass.CONTINUOUS


@pytest.mark.parametrize("name,count", [("none", 1), ("two_fold", 2), ("four_fold", 4)])
def test_discrete_transforms_identity_first(name, count):
    transforms = symmetry_transforms(CASES[name])
    assert len(transforms) == count
    np.testing.assert_allclose(transforms.R[0], np.eye(3))
    np.testing.assert_allclose(transforms.t_mm[0], 0.0)
    np.testing.assert_allclose(symmetry_rotations(CASES[name]), transforms.R)


def test_continuous_discretised_as_bop_toolkit():
    # ceil(pi / 0.01) = 315 steps of 2 pi / 315 about the axis, times (1 + discrete symmetries).
    plain = symmetry_transforms(CASES["continuous"], max_sym_disc_step=0.01)
    assert len(plain) == 315
    np.testing.assert_allclose(plain.R[0], np.eye(3), atol=1e-12)
    step = 2 * np.pi / 315
    np.testing.assert_allclose(plain.R[1][:2, :2], [[np.cos(step), -np.sin(step)], [np.sin(step), np.cos(step)]],
                               atol=1e-12)
    flip = symmetry_transforms(CASES["continuous_flip"], max_sym_disc_step=0.01)
    assert len(flip) == 630
    # Every transform keeps the z axis up to sign: the flip maps z to -z.
    z = flip.R @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(np.abs(z[:, 2]), 1.0, atol=1e-12)
    assert (z[:, 2] < 0).sum() == 315
    assert len(symmetry_rotations(CASES["continuous_flip"])) == 2


def test_continuous_offset_gives_translation():
    info = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [10.0, 0, 0]}]}
    transforms = symmetry_transforms(info, max_sym_disc_step=0.5)
    # The offset point lies on the axis, so every transform fixes it.
    moved = transforms.R @ np.array([10.0, 0, 0]) + transforms.t_mm
    np.testing.assert_allclose(moved, np.broadcast_to([10.0, 0, 0], moved.shape), atol=1e-9)


def test_continuous_axis():
    np.testing.assert_allclose(continuous_axis(CASES["continuous_flip"]), [0, 0, 1])
    with pytest.raises(PopcodeError, match="no continuous symmetry"):
        continuous_axis(CASES["two_fold"])


@pytest.mark.parametrize(
    "info,message",
    [
        ({"symmetries_discrete": [[1, 0, 0]]}, "16"),
        ({"symmetries_discrete": [np.diag([1.0, 1.0, -1.0, 1.0]).reshape(-1).tolist()]}, "proper rotation"),
        ({"symmetries_continuous": [{"offset": [0, 0, 0]}]}, "axis"),
        ({"symmetries_continuous": [{"axis": [0, 0, 0], "offset": [0, 0, 0]}]}, "zero"),
    ],
)
def test_malformed_entries_are_named(info, message):
    with pytest.raises(PopcodeError, match=message):
        symmetry_transforms(info)
