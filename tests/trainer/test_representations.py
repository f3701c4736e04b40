"""Each representation: a perfect output has (near) zero loss and decodes to the ground truth up to symmetry."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from symmetry_cases import CASES

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.rotations import allocentric_to_egocentric, random_rotations, sixd_to_matrix
from popcode_runtime.model.metadata import Representation, RotationFrame
from popcode_trainer.train.config import Config
from popcode_trainer.train.representations import (
    HYBRID_CE_WEIGHT,
    MultiHypothesisRepresentation,
    PerObjectPopulationCodes,
    build_representation,
    code_layout,
)

SMALL = dict(n_axes=42, n_angles=12, sigma_deg=30.0)
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def instances(R: np.ndarray, obj_id: int = 1) -> list[SimpleNamespace]:
    boxes = [(40.0 + 30 * i, 300.0 - 20 * i, 80.0, 60.0) for i in range(len(R))]
    return [SimpleNamespace(obj_id=obj_id, R_m2c=r, K=K, box=b) for r, b in zip(R, boxes, strict=True)]


def perfect_output(rep, targets: np.ndarray) -> np.ndarray:
    """What a perfect network would output for these targets."""
    if rep.name == Representation.ONE_HOT:
        logits = np.zeros((len(targets), rep.output_dim), np.float32)
        logits[np.arange(len(targets)), targets[:, 0].astype(int)] = 20.0
        return logits
    if rep.name == Representation.SINGLE_VARIABLE:
        return targets[:, : rep.output_dim]
    if rep.name == Representation.MULTI_HYPOTHESIS:
        return np.tile(targets, (1, rep.metadata.num_hypotheses))
    return targets


@pytest.mark.parametrize("case", ["none", "two_fold", "four_fold", "continuous", "continuous_flip"])
@pytest.mark.parametrize("name", Representation.values())
@pytest.mark.parametrize("frame", RotationFrame.values())
def test_perfect_output_decodes_to_ground_truth(name: str, case: str, frame: str) -> None:
    grid = dict(n_axes=162, n_angles=24, sigma_deg=20.0)
    rep = build_representation(name, {1: CASES[case]}, rotation_frame=frame, num_hypotheses=4, **grid)
    rng = np.random.default_rng(0)
    R_true = random_rotations(16, rng)
    batch = instances(R_true)
    targets = np.stack([rep.target(inst) for inst in batch])
    assert targets.dtype == np.float32
    output = perfect_output(rep, targets)

    loss = rep.loss(torch.from_numpy(output), torch.from_numpy(targets), progress=0.5)
    assert float(loss) < 1e-5

    R_frame = rep.decode(output).R
    if frame == RotationFrame.ALLOCENTRIC:
        centres = np.array([[b.box[0] + b.box[2] / 2, b.box[1] + b.box[3] / 2] for b in batch])
        R_pred = allocentric_to_egocentric(R_frame, K, centres)
    else:
        R_pred = R_frame
    errors_deg = np.degrees(rep.errors_rad(R_pred, R_true, np.ones(16, int)))
    # The grid representations decode to a nearby grid rotation (axes ~16 deg, angles 15 deg apart).
    tolerance = 25.0 if name in (Representation.POPULATION_CODE, Representation.ONE_HOT) else 1e-3
    assert errors_deg.max() < tolerance


@pytest.mark.parametrize("name", [Representation.POPULATION_CODE, Representation.ONE_HOT])
def test_grid_rotation_decodes_exactly(name: str) -> None:
    rep = build_representation(name, {1: CASES["two_fold"]}, **SMALL)
    R_true = rep.code.preferred_rotations(np.array([5, 77, 130, 400]))
    targets = np.stack([rep.target_from_rotation(R, 1) for R in R_true]).astype(np.float32)
    R_pred = rep.decode(perfect_output(rep, targets)).R
    assert np.degrees(rep.errors_rad(R_pred, R_true, np.ones(4, int))).max() < 1e-4


def test_single_variable_loss_takes_the_nearest_symmetric_pose() -> None:
    rep = build_representation(Representation.SINGLE_VARIABLE, {1: CASES["two_fold"]}, **SMALL)
    R = random_rotations(1, np.random.default_rng(1))[0]
    target = rep.target_from_rotation(R, 1).astype(np.float32)
    flipped = target[6:12]  # the symmetric pose R S_1
    loss = rep.loss(torch.from_numpy(flipped[None]), torch.from_numpy(target[None]), 0.0)
    assert float(loss) < 1e-6
    assert np.allclose(sixd_to_matrix(flipped), R @ rep.symmetries(1)[1], atol=1e-5)


def test_multi_hypothesis_epsilon_anneals() -> None:
    assert MultiHypothesisRepresentation.epsilon(0.0) == pytest.approx(0.05)
    assert MultiHypothesisRepresentation.epsilon(1.0) == pytest.approx(0.01)


def test_population_code_target_has_a_peak_per_symmetric_pose() -> None:
    rep = build_representation(Representation.POPULATION_CODE, {1: CASES["four_fold"]}, **SMALL)
    target = rep.target_from_rotation(rep.code.preferred_rotations(np.array(100)), 1)
    assert target.shape == (42 * 12,)
    assert target.max() >= 1.0


def test_unknown_representation_names_the_choices() -> None:
    with pytest.raises(PopcodeError, match="population_code"):
        build_representation("popcode", {1: CASES["none"]}, **SMALL)


def test_mixing_continuous_and_discrete_objects_is_refused() -> None:
    with pytest.raises(PopcodeError, match=r"continuous symmetry.*cannot share.*data.obj_ids='\[1\]'.*"
                                           r"data.obj_ids='\[2\]'"):
        code_layout({1: CASES["continuous"], 2: CASES["two_fold"]}, **SMALL)


def test_pooled_continuous_objects_must_share_the_axis() -> None:
    tilted = {**CASES["continuous"], "symmetries_continuous": [{"axis": [1, 0, 0], "offset": [0, 0, 0]}]}
    with pytest.raises(PopcodeError, match="different model axes"):
        code_layout({1: CASES["continuous"], 2: tilted}, **SMALL)


def test_discrete_and_asymmetric_objects_share_the_full_code() -> None:
    layout = code_layout({5: CASES["two_fold"], 6: CASES["none"]}, **SMALL)
    assert not layout.axis_only


def test_per_object_codes_give_each_kind_its_own_layout_and_training_target() -> None:
    objects = {1: CASES["continuous"], 2: CASES["four_fold"]}
    codes = PerObjectPopulationCodes(objects, **SMALL)
    assert codes.layout(1).axis_only and codes.layout(1).size == 42
    assert not codes.layout(2).axis_only and codes.layout(2).size == 42 * 12
    R = random_rotations(2, np.random.default_rng(3))
    for obj_id, info in objects.items():
        alone = build_representation(Representation.POPULATION_CODE, {obj_id: info}, **SMALL)
        for instance in instances(R, obj_id):
            np.testing.assert_array_equal(codes.target(instance), alone.target(instance))
    with pytest.raises(PopcodeError, match="not one of the objects"):
        codes.target(instances(R, 7)[0])


@pytest.mark.parametrize("name", Representation.values())
def test_batched_targets_equal_one_at_a_time(name: str) -> None:
    """A data-loader batch mixes objects; its targets are built per object in one call, in batch order."""
    rep = build_representation(name, {1: CASES["four_fold"], 2: CASES["none"]}, n_axes=162, n_angles=24,
                               sigma_deg=20.0, num_hypotheses=4)
    rng = np.random.default_rng(3)
    batch = [*instances(random_rotations(5, rng), 2), *instances(random_rotations(4, rng), 1)]
    batch = [batch[i] for i in rng.permutation(len(batch))]
    batched = rep.targets(batch)
    assert batched.dtype == np.float32 and len(batched) == len(batch)
    for row, inst in zip(batched, batch, strict=True):
        np.testing.assert_allclose(row, rep.target_from_rotation(inst.R_m2c, inst.obj_id), rtol=1e-6, atol=1e-7)


def test_cross_entropy_loss_is_least_at_the_normalised_code() -> None:
    """The logits log(code) are optimal: the loss is then the code's entropy, and anything else costs more."""
    rep = build_representation(Representation.POPULATION_CODE, {1: CASES["four_fold"]}, loss="cross_entropy",
                               **SMALL)
    R = random_rotations(6, np.random.default_rng(4))
    target = torch.from_numpy(rep.targets(instances(R)))
    best = torch.log(target).requires_grad_()
    loss = rep.loss(best, target, 0.5)
    loss.backward()
    assert float(best.grad.abs().max()) < 1e-6
    for scale in (0.5, 2.0):
        assert float(rep.loss(scale * torch.log(target), target, 0.5)) > float(loss)
    assert float(rep.loss(best + 3.0, target, 0.5)) == pytest.approx(float(loss), abs=1e-5)  # softmax: shift-free
    decoded = rep.decode(best.detach().numpy())
    assert np.degrees(rep.errors_rad(decoded.R, R, np.ones(len(R), int))).max() < 20.0  # the grid's resolution
    assert np.all(decoded.activation > 0)


def test_hybrid_loss_adds_weighted_cross_entropy_and_decodes_its_output_as_a_code() -> None:
    """``mse+cross_entropy``: MSE on the output plus the weighted cross entropy of the same output as logits;
    its output is decoded as the MSE model's is, with no softmax."""
    layout = {1: CASES["four_fold"]}
    hybrid, mse, ce = (build_representation(Representation.POPULATION_CODE, layout, loss=kind, **SMALL)
                       for kind in ("mse+cross_entropy", "mse", "cross_entropy"))
    R = random_rotations(6, np.random.default_rng(5))
    target = torch.from_numpy(hybrid.targets(instances(R)))
    output = target + 0.05 * torch.randn(target.shape, generator=torch.Generator().manual_seed(0))
    expected = float(mse.loss(output, target, 0.5)) + HYBRID_CE_WEIGHT * float(ce.loss(output, target, 0.5))
    assert float(hybrid.loss(output, target, 0.5)) == pytest.approx(expected, rel=1e-6)
    decoded, as_mse = hybrid.decode(target.numpy()), mse.decode(target.numpy())
    np.testing.assert_array_equal(decoded.R, as_mse.R)
    np.testing.assert_array_equal(decoded.activation, as_mse.activation)
    assert not np.allclose(ce.decode(target.numpy()).activation, as_mse.activation)  # CE's softmax would differ


def test_cross_entropy_is_only_for_the_population_code() -> None:
    with pytest.raises(PopcodeError, match="applies to the population code"):
        build_representation(Representation.SINGLE_VARIABLE, {1: CASES["none"]}, loss="cross_entropy", **SMALL)
    with pytest.raises(PopcodeError, match="unknown population-code loss 'l1'"):
        build_representation(Representation.POPULATION_CODE, {1: CASES["none"]}, loss="l1", **SMALL)


def test_a_baseline_with_the_population_codes_loss_is_told_the_fix() -> None:
    with pytest.raises(PopcodeError, match="train.loss.*applies to the population code.*--set train.loss="):
        Config.from_dict({"train": {"representation": "single_variable", "loss": "mse+cross_entropy"}})
