"""metrics.look_alike_share: of the estimates that found a look-alike part's shape, the share that found its pose."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from popcode_runtime.geometry.rotations import axis_angle_to_matrix, random_rotations
from popcode_trainer.demo.look_alike_section import look_alike_markdown
from popcode_trainer.metrics.look_alike_share import look_alike_shares

Z = np.array([0.0, 0.0, 1.0])
QUARTERS = np.stack([axis_angle_to_matrix(Z, k * np.pi / 2) for k in range(4)])  # a part that looks 4-fold about z


def test_right_look_alike_and_lost_estimates_are_told_apart() -> None:
    R_true = random_rotations(10, np.random.default_rng(0))
    small = axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.radians(5.0))
    R_est = np.concatenate([R_true[:3] @ small,  # right, 5 deg off
                            R_true[3:8] @ QUARTERS[1:2].repeat(5, 0),  # a look-alike pose
                            R_true[8:] @ axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.radians(60.0))])  # lost
    obj_ids = np.array([1] * 10)
    models_info = {1: {"diameter": 50.0}, 2: {"diameter": 50.0}}
    (share,) = look_alike_shares(R_est, R_true, obj_ids, models_info, {1: QUARTERS, 2: QUARTERS})  # 2 is not shown
    assert (share.obj_id, share.poses, share.found_shape) == (1, 4, 8)
    assert math.isclose(share.right_share, 3 / 8)


def test_a_part_whose_shape_was_never_found_has_no_share() -> None:
    R_true = random_rotations(2, np.random.default_rng(1))
    flipped = R_true @ axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.pi)
    (share,) = look_alike_shares(flipped, R_true, np.array([1, 1]), {1: {"diameter": 9.0}}, {1: QUARTERS})
    assert share.found_shape == 0 and math.isnan(share.right_share)


def test_the_demo_section_lists_each_look_alike_part_per_split() -> None:
    R_true = random_rotations(4, np.random.default_rng(2))
    instances = [SimpleNamespace(R_m2c=R) for R in R_true]
    split = SimpleNamespace(instances=instances, models_info={1: {"diameter": 50.0}})
    clean = SimpleNamespace(name="population_code", R_est=R_true.copy(), split=split,
                            errors=SimpleNamespace(obj_id=np.ones(4, dtype=int)), look_alikes={1: QUARTERS})
    cluttered = SimpleNamespace(**{**vars(clean), "R_est": R_true @ QUARTERS[2:3].repeat(4, 0)})
    text = look_alike_markdown(clean, cluttered)
    assert "| 1 | 4 | 100 % of 4 | 0 % of 4 |" in text
    assert look_alike_markdown(SimpleNamespace(**{**vars(clean), "look_alikes": {}})) == ""
