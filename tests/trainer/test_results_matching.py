"""``popcode-train evaluate`` scores a results file as the BOP toolkit does: missed instances, extras, repeats."""

from __future__ import annotations

import csv
import itertools
import json
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest

from popcode_runtime.bop.bop19_csv import PoseEstimate, read_bop19_results, write_bop19_results
from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_trainer.cli import main
from popcode_trainer.data.objects import write_builtin_models
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.eval.pipeline.evaluate import evaluate_models, evaluate_rotations
from popcode_trainer.eval.pipeline.results_file import ResultsMethod, read_results_method
from popcode_trainer.eval.pipeline.results_matching import credited_errors
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.pipeline.split_metrics import SplitMetrics

WIDTH, HEIGHT = 160, 120
K = [200.0, 0.0, 79.5, 0.0, 200.0, 59.5, 0.0, 0.0, 1.0]
TWO_OF_SIX = 0  # the image with two instances of part 6 (no symmetry)


def _turn(degrees: float, axis: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    return axis_angle_to_matrix(np.array(axis), np.radians(degrees))


# image -> (object, rotation, translation [mm], visib_fract); split order is this order. Image 2's part 6 is
# 5 % visible: no target, as in BOP19, so an estimate of it counts nowhere.
GROUND_TRUTH = {
    TWO_OF_SIX: [(6, _turn(0.0), (-60.0, 0.0, 600.0), 1.0), (6, _turn(90.0), (60.0, 0.0, 600.0), 0.8)],
    1: [(6, _turn(30.0, (1.0, 0.0, 0.0)), (0.0, 0.0, 600.0), 1.0), (3, _turn(45.0), (50.0, 30.0, 700.0), 0.5)],
    2: [(3, _turn(120.0, (1.0, 1.0, 0.0)), (0.0, 0.0, 650.0), 0.9), (6, _turn(10.0), (40.0, 0.0, 600.0), 0.05)],
}
TARGETS = [(im_id, obj_id, R, t) for im_id, rows in GROUND_TRUTH.items() for obj_id, R, t, visib in rows
           if visib >= 0.1]


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One scene of three blank images (only their size is read) with :data:`GROUND_TRUTH`, parts 3 and 6."""
    root = tmp_path_factory.mktemp("matching")
    write_builtin_models(root / "models")
    scene = root / "split" / "000001"
    (scene / "gray").mkdir(parents=True)
    gt, info, camera = {}, {}, {}
    for im_id, rows in GROUND_TRUTH.items():
        cv2.imwrite(str(scene / "gray" / f"{im_id:06d}.png"), np.zeros((HEIGHT, WIDTH), np.uint8))
        camera[str(im_id)] = {"cam_K": K, "depth_scale": 1.0}
        gt[str(im_id)] = [{"obj_id": obj_id, "cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": list(t)}
                          for obj_id, R, t, _ in rows]
        info[str(im_id)] = [{"bbox_obj": [20, 20, 40, 40], "bbox_visib": [20, 20, 40, 40], "visib_fract": visib}
                            for *_, visib in rows]
    for name, data in (("scene_gt", gt), ("scene_gt_info", info), ("scene_camera", camera)):
        (scene / f"{name}.json").write_text(json.dumps(data))
    return root / "split"


def _estimate(im_id: int, obj_id: int, R: np.ndarray, score: float, turn_deg: float = 0.0,
              scene_id: int = 1) -> PoseEstimate:
    """An estimate of ``R`` turned by ``turn_deg`` about x (its translation is never scored: rotation only)."""
    return PoseEstimate(scene_id, im_id, obj_id, score, _turn(turn_deg, (1.0, 0.0, 0.0)) @ R,
                        np.array([0.0, 0.0, 600.0]), 0.01)


def _write(path: Path, estimates: list[PoseEstimate]) -> Path:
    write_bop19_results(path, estimates)
    return path


def _evaluate(split: Path, results: Path, out: Path, capsys: pytest.CaptureFixture[str],
              *options: str) -> tuple[dict, str]:
    """Exit 0, and the method's report.json entry and the printed output."""
    code = main(["evaluate", str(results), "--name", "m", "--split", str(split), "--models-dir",
                 str(split.parent / "models"), "--no-vsd", "--out", str(out), *options])
    printed = capsys.readouterr().out
    assert code == 0
    return json.loads((out / "report.json").read_text())["methods"]["m"], printed


# Turns about x per target, in split order: from right at every threshold to wrong at every one.
TURNS_DEG = (0.5, 4.0, 9.0, 2.0, 40.0)


def _one_per_instance() -> list[PoseEstimate]:
    return [_estimate(im_id, obj_id, R, 0.9, turn) for (im_id, obj_id, R, _), turn in zip(TARGETS, TURNS_DEG,
                                                                                          strict=True)]


def test_one_estimate_per_instance_scores_exactly_as_its_rotations(split: Path, tmp_path: Path) -> None:
    """The ground-truth-box protocol is unchanged: each instance's error is its own estimate's."""
    eval_split = read_eval_split([split], split.parent / "models")
    assert len(eval_split.instances) == len(TARGETS)
    estimates = _one_per_instance()
    method = read_results_method(_write(tmp_path / "gt_boxes.csv", estimates[::-1]), "gt_boxes")
    from_file = evaluate_models([method], eval_split, vsd=False, progress=False)[0]
    metrics = SplitMetrics(eval_split, vsd=False)
    try:
        direct = evaluate_rotations("direct", np.stack([est.R_m2c for est in estimates]), metrics)
    finally:
        metrics.close()
    for name in ("mssd_mm", "mspd_px", "adi_mm"):
        np.testing.assert_array_equal(getattr(from_file.errors, name), getattr(direct.errors, name))
    assert from_file.groups == direct.groups and from_file.per_object == direct.per_object
    np.testing.assert_array_equal(from_file.R_est, direct.R_est)
    assert from_file.matching is not None and from_file.matching.without_estimate == 0
    assert 0.0 < from_file.groups["All objects"]["MSSD"] < 1.0  # some right, some wrong: a real test


def test_a_missed_instance_is_wrong_and_counted(split: Path, tmp_path: Path, capsys) -> None:
    truth = [_estimate(im_id, obj_id, R, 1.0) for im_id, obj_id, R, _ in TARGETS]
    whole, _ = _evaluate(split, _write(tmp_path / "all.csv", truth), tmp_path / "all", capsys)
    missed = tmp_path / "missed"
    short, printed = _evaluate(split, _write(tmp_path / "missed.csv", truth[1:]), missed, capsys, "--bop19-csv")
    count = len(TARGETS)
    for metric in ("MSSD", "MSPD", "ADI"):
        assert whole["groups"]["All objects"][metric] == 1.0
        assert short["groups"]["All objects"][metric] == pytest.approx(1.0 - 1.0 / count, abs=1e-12)
    assert f"m: 1 of {count} instances had no estimate (scored wrong); estimates ignored: 0 beyond" in printed
    rows = list(csv.DictReader((missed / "errors_m.csv").open()))
    assert rows[0]["mssd_mm"] == "inf" and rows[0]["re_deg"] == "nan"  # the missed one: wrong, no rotation
    assert all(float(row["mssd_mm"]) < 1e-9 for row in rows[1:])
    assert len(read_bop19_results(missed / "m_bop19.csv")) == count - 1  # no line for the missed instance


def test_an_extra_low_scored_false_positive_changes_nothing(split: Path, tmp_path: Path, capsys) -> None:
    estimates = _one_per_instance()
    plain, _ = _evaluate(split, _write(tmp_path / "plain.csv", estimates), tmp_path / "plain", capsys)
    im_id, obj_id, R, _ = TARGETS[2]  # the single part 6 of image 1
    false_positive = _estimate(im_id, obj_id, R, 0.1, 120.0)
    extra, printed = _evaluate(split, _write(tmp_path / "extra.csv", [false_positive, *estimates]),
                               tmp_path / "extra", capsys)
    for key in ("groups", "per_object", "tightest", "by_visibility"):
        assert extra[key] == plain[key]
    assert "0 of 5 instances had no estimate" in printed and "estimates ignored: 1 beyond" in printed
    # Scored above the right estimate, the same false positive is the one kept (the toolkit's top n by score).
    first, _ = _evaluate(split, _write(tmp_path / "first.csv", [*estimates, _estimate(im_id, obj_id, R, 0.95, 120.0)]),
                         tmp_path / "first", capsys)
    assert first["per_object"]["6"]["MSSD"] < plain["per_object"]["6"]["MSSD"]


@pytest.mark.parametrize("scores", [(0.9, 0.8), (0.8, 0.9)])
def test_two_estimates_of_one_object_in_one_image_find_their_instances_in_any_order(split: Path, tmp_path: Path,
                                                                                    capsys, scores) -> None:
    truth = [_estimate(im_id, obj_id, R, 1.0) for im_id, obj_id, R, _ in TARGETS]
    truth[0], truth[1] = (_estimate(TWO_OF_SIX, 6, TARGETS[1][2], scores[0]),
                          _estimate(TWO_OF_SIX, 6, TARGETS[0][2], scores[1]))  # swapped: the second's first
    scored, _ = _evaluate(split, _write(tmp_path / "swapped.csv", truth), tmp_path / "swapped", capsys)
    assert all(value == 1.0 for value in scored["groups"]["All objects"].values())
    rows = list(csv.DictReader((tmp_path / "swapped" / "errors_m.csv").open()))
    assert [float(row["re_deg"]) for row in rows[:2]] == pytest.approx([0.0, 0.0], abs=1e-6)


def test_only_false_positives_of_objects_without_an_instance_score_zero(split: Path, tmp_path: Path,
                                                                         capsys) -> None:
    R = np.eye(3)
    estimates = [_estimate(TWO_OF_SIX, 3, R, 0.9),  # no part 3 in that image
                 _estimate(2, 6, GROUND_TRUTH[2][1][1], 0.9),  # 5 % visible: not a target
                 _estimate(1, 99, R, 0.9)]  # an object the split does not have
    out = tmp_path / "none"
    scored, printed = _evaluate(split, _write(tmp_path / "none.csv", estimates), out, capsys, "--bop19-csv")
    assert all(value == 0.0 for value in scored["groups"]["All objects"].values())
    assert scored["confidence"] is None  # no estimate to judge
    assert ("m: 5 of 5 instances had no estimate (scored wrong); estimates ignored: 0 beyond their image and "
            "object's instance count, 3 of an image and object without an instance to score") in printed
    assert read_bop19_results(out / "m_bop19.csv") == []


def test_depth_metrics_are_matched_per_tau_too(tmp_path: Path) -> None:
    """Cluttered scenes with depth, a part repeated in an image: near estimates score as their rotations do, in
    VSD (each tau on its own), e_VSD<0.3 and VSS as well; a missed instance costs 1/N of each."""
    scenes = render_cluttered_test_split(tmp_path / "scenes", scenes=3, size=(WIDTH, HEIGHT), obj_ids=[3, 6],
                                         parts=(2, 3))
    eval_split = read_eval_split([scenes], scenes / "models")
    instances = eval_split.instances
    assert max(Counter((inst.im_id, inst.obj_id) for inst in instances).values()) >= 2
    turns = np.linspace(0.5, 12.0, len(instances))
    estimates = [_estimate(inst.im_id, inst.obj_id, inst.R_m2c, 0.5, turn, inst.scene_id)
                 for inst, turn in zip(instances, turns, strict=True)]
    methods = [ResultsMethod("near", tmp_path / "near.csv", tuple(estimates[::-1])),
               ResultsMethod("missed", tmp_path / "missed.csv", tuple(estimates[1:]))]
    near, missed = evaluate_models(methods, eval_split, vsd=True, progress=False)
    metrics = SplitMetrics(eval_split, vsd=True)
    try:
        direct = evaluate_rotations("direct", np.stack([est.R_m2c for est in estimates]), metrics)
    finally:
        metrics.close()
    for name in ("mssd_mm", "mspd_px", "adi_mm", "vsd", "vsd_single_tau", "vss"):
        np.testing.assert_array_equal(getattr(near.errors, name), getattr(direct.errors, name))
        np.testing.assert_array_equal(getattr(missed.errors, name)[1:], getattr(direct.errors, name)[1:])
        assert np.isinf(getattr(missed.errors, name)[0]).all()  # the missed one: wrong at every tau and threshold
    assert near.groups == direct.groups and 0.0 < near.groups["All objects"]["VSD"] < 1.0
    assert missed.groups["All objects"]["VSD"] < near.groups["All objects"]["VSD"]


def _toolkit_matched(errors: np.ndarray, threshold: float) -> set[int]:
    """The instances the BOP toolkit's greedy matching finds at ``threshold``, written out on its own: estimates
    in row order, each taking the unmatched instance of lowest error strictly below the threshold, the first of
    equals."""
    matched: set[int] = set()
    for row in errors:
        best, best_error = None, threshold
        for instance, error in enumerate(row):
            if instance not in matched and error < best_error:
                best, best_error = instance, error
        if best is not None:
            matched.add(best)
    return matched


def test_credited_errors_give_the_toolkits_matching_at_every_threshold() -> None:
    rng = np.random.default_rng(7)
    for estimates, instances in itertools.product(range(4), range(1, 5)):
        for _ in range(40):
            errors = rng.integers(0, 6, size=(min(estimates, instances), instances)).astype(float)  # with ties
            errors[rng.random(errors.shape) < 0.1] = np.inf
            credited = credited_errors(errors)
            for threshold in np.arange(-0.5, 7.0, 0.5):
                assert set(np.flatnonzero(credited < threshold)) == _toolkit_matched(errors, threshold), errors


def test_a_later_estimate_is_credited_where_the_first_finds_nothing() -> None:
    """Below 14 the first estimate matches nothing and the second takes instance 0; from 14 on the first takes
    it and the second has only instance 1 left, at 28: a single assignment would miss instance 0 below 14."""
    np.testing.assert_array_equal(credited_errors(np.array([[14.0, 16.0], [2.0, 28.0]])), [2.0, 28.0])
