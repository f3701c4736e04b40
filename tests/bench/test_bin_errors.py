"""``python -m experiments.bin_errors``: each instance's error and its overlapping same-part neighbours, counted per
group (:mod:`tools.error_sources`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from onnx_models import linear_model, save
from user_commands import run_module

from popcode_runtime.bop.split import scene_folders, scene_ground_truth
from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.geometry.rotations import geodesic_angle
from popcode_runtime.model.metadata import ModelMetadata, Representation
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.data.scene_render import render_cluttered_test_split
from tools.error_sources import FLIP_DEG, GROSS_DEG, NEIGHBOUR_DEG, box_overlap, summary

ASYMMETRIC_PART = 6  # no symmetry: its error is the plain angle to the pose


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Bins of the asymmetric part alone, four to six of it each: repeats that overlap."""
    return render_cluttered_test_split(tmp_path_factory.mktemp("scenes"), scenes=2, size=(160, 120),
                                       obj_ids=[ASYMMETRIC_PART], parts=(4, 6))


@pytest.fixture(scope="module")
def identity_model(scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A population code that answers the identity rotation for any crop."""
    info = load_models_info(scenes / BUILTIN_MODELS_FOLDER)
    layout = CodeLayout(n_axes=162, n_angles=12, sigma_deg=30.0)
    meta = ModelMetadata(Representation.POPULATION_CODE, layout, {ASYMMETRIC_PART: info[ASYMMETRIC_PART]})
    bias = PopulationCode(layout).encode(np.eye(3))
    return save(linear_model(bias, metadata=meta), tmp_path_factory.mktemp("m") / "identity.onnx")


def _expected(scenes: Path) -> list[tuple[float, float | None]]:
    """Each instance's angle to the identity and the smallest of its overlapping neighbours', by hand."""
    expected = []
    for scene_dir in scene_folders(scenes):
        everyone = dict(scene_ground_truth(scene_dir, "bbox_obj", 0.0))
        for im_id, targets in scene_ground_truth(scene_dir, "bbox_obj", 0.1):
            for target in targets:
                def angle(gt) -> float:
                    return float(np.degrees(geodesic_angle(np.eye(3), np.reshape(gt.gt_entry["cam_R_m2c"], (3, 3)))))
                neighbours = [angle(o) for o in everyone[im_id] if o.gt_index != target.gt_index
                              and box_overlap(target.box, o.box) > 0.05]
                expected.append((angle(target), min(neighbours) if neighbours else None))
    return expected


@pytest.mark.slow
def test_every_instance_and_its_neighbours_are_counted(scenes: Path, identity_model: Path, tmp_path: Path) -> None:
    printed = run_module("experiments.bin_errors", "--model", identity_model, "--split", scenes, "--out", tmp_path,
                         "--name", "t").stdout
    payload = json.loads((tmp_path / "t.json").read_text())
    expected = _expected(scenes)
    assert any(neighbour is not None for _, neighbour in expected), "the fixture's bins should hold overlaps"
    result = payload["splits"][scenes.name]["all"]
    assert result["instances"] == len(expected)
    assert result["median_error_deg"] == pytest.approx(np.median([e for e, _ in expected]), abs=1e-3)
    gross = [(e, n) for e, n in expected if e > GROSS_DEG]
    assert result["gross"] == len(gross)
    assert result["flips"] == sum(e > FLIP_DEG for e, _ in gross)
    assert result["gross_with_neighbour"] == sum(n is not None for _, n in gross)
    assert result["neighbour_reads"] == sum(n is not None and n < NEIGHBOUR_DEG for _, n in gross)
    assert "cpu" in payload["machine"]
    assert f"| all | {len(expected)} |" in (tmp_path / "t.md").read_text()
    assert printed == (tmp_path / "t.md").read_text()  # the table it prints is the one it writes


def test_box_overlap_is_the_share_of_the_target_covered() -> None:
    assert box_overlap((0, 0, 10, 10), (5, 0, 10, 10)) == pytest.approx(0.5)
    assert box_overlap((0, 0, 10, 10), (-5, -5, 30, 30)) == pytest.approx(1.0)
    assert box_overlap((0, 0, 10, 10), (20, 20, 5, 5)) == 0.0


def test_a_wrong_pose_is_a_neighbour_read_only_near_a_neighbour_and_a_flip_only_far_off() -> None:
    rows = [{"obj_id": 1, "visib_fract": 1.0, "box_px": 100, "error_deg": 10.0, "neighbour_deg": 1.0},  # right
            {"obj_id": 1, "visib_fract": 1.0, "box_px": 100, "error_deg": 90.0, "neighbour_deg": 5.0},  # read
            {"obj_id": 1, "visib_fract": 1.0, "box_px": 100, "error_deg": 90.0, "neighbour_deg": 60.0},
            {"obj_id": 1, "visib_fract": 1.0, "box_px": 100, "error_deg": 170.0, "neighbour_deg": None}]  # flip
    assert summary(rows) == {"instances": 4, "median_error_deg": 90.0, "gross": 3, "flips": 1,
                             "gross_with_neighbour": 2, "neighbour_reads": 1, "median_box_px": 100.0}
