"""Recall over thresholds, BOP19 averaging and the ambiguity tables on constructed error lists."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from symmetry_cases import CASES

from popcode_runtime.base.errors import PopcodeError
from popcode_trainer.eval.reporting.tables import (
    ambiguity_markdown,
    methods_markdown,
    per_object_markdown,
    to_json,
)
from popcode_trainer.metrics.recall import (
    GROUPS,
    InstanceErrors,
    Thresholds,
    ambiguous_objects,
    group_scores,
    metric_scores,
    recall,
    scores_per_object,
    tightest_recalls,
    tightest_thresholds,
)


def test_default_thresholds_are_the_bop19_ones():
    th = Thresholds()
    np.testing.assert_array_equal(th.mssd_fractions, np.arange(0.05, 0.51, 0.05))
    np.testing.assert_array_equal(th.vsd_taus, np.arange(0.05, 0.51, 0.05))
    np.testing.assert_array_equal(th.mspd_px_at_640, np.arange(5, 51, 5))
    assert len(th.vsd_thetas) == 10 and th.vsd_delta_mm == 15.0
    assert (th.vsd_single_tau_mm, th.vsd_single_theta, th.adi_fraction) == (20.0, 0.3, 0.05)


def test_recall_is_strictly_below_the_threshold():
    errors = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_array_equal(recall(errors, [0.1, 0.2, 0.35, 1.0]), [0.0, 0.25, 0.75, 1.0])


def test_recall_of_no_instances_is_nan():
    assert np.isnan(recall(np.zeros(0), [0.5])).all()


def _errors(obj_id, mssd_fraction, mspd_px=None, width=640.0, vsd=None) -> InstanceErrors:
    obj_id = np.asarray(obj_id)
    mssd_mm = 100.0 * np.asarray(mssd_fraction, float)  # every object is 100 mm across
    return InstanceErrors(
        obj_id=obj_id,
        image_width_px=np.full(len(obj_id), width),
        mssd_mm=mssd_mm,
        mspd_px=np.asarray(mspd_px if mspd_px is not None else np.zeros(len(obj_id)), float),
        adi_mm=mssd_mm / 2,
        vsd=vsd,
    )


DIAMETERS = {1: 100.0, 2: 100.0, 3: 100.0}


def test_mssd_average_recall_over_ten_thresholds():
    # Below 0.05 passes all 10 thresholds, 0.12 passes 8 (0.15 ... 0.5), exactly 0.5 passes none.
    scores = metric_scores(_errors([1, 1, 1], [0.0, 0.12, 0.5]), DIAMETERS)
    assert scores["MSSD"] == pytest.approx((10 + 8 + 0) / 30)
    assert scores["ADI"] == pytest.approx(1 / 3)  # ADI = 0, 6, 25 mm against 5 mm
    assert "VSD" not in scores


def test_mspd_thresholds_scale_with_image_width():
    # 12 px in a 1280 px wide image is 6 px at 640: it passes 10 ... 50 (9 thresholds), not 5.
    scores = metric_scores(_errors([1], [0.0], mspd_px=[12.0], width=1280.0), DIAMETERS)
    assert scores["MSPD"] == pytest.approx(0.9)


def test_vsd_average_recall_over_taus_and_thetas():
    th = Thresholds(vsd_taus=(0.1, 0.2), vsd_thetas=(0.3, 0.5))
    vsd = np.array([[0.4, 0.2], [0.6, 0.1]])  # per instance, one error per tau
    scores = metric_scores(_errors([1, 1], [0.0, 0.0], vsd=vsd), DIAMETERS, th)
    # theta 0.3: [F, T; F, T] -> 2/4; theta 0.5: [T, T; F, T] -> 3/4.
    assert scores["VSD"] == pytest.approx(5 / 8)


def test_tightest_recalls_count_errors_strictly_below_the_first_threshold():
    # MSSD 4.99, 5, 5.01 and 0 mm of a 100 mm object: only 4.99 and 0 are below 5 % (5 mm exactly is not).
    # MSPD in a 1280 px wide image: 9.98, 10, 10.02 and 30 px are 4.99, 5, 5.01 and 15 px at 640: only the first.
    # VSD: the first column is the 5 % tau; 0.04 is below theta 0.05, 0.05 is not, nor 0.9 (whatever the others).
    vsd = np.ones((4, 10))
    vsd[:, 0] = [0.04, 0.05, 0.9, 0.05]
    vsd[1:, 1:] = 0.0
    errors = InstanceErrors(
        obj_id=np.array([1, 1, 2, 2]), image_width_px=np.full(4, 1280.0), mssd_mm=np.array([4.99, 5.0, 5.01, 0.0]),
        mspd_px=np.array([9.98, 10.0, 10.02, 30.0]), adi_mm=np.zeros(4), vsd=vsd,
    )
    tightest = tightest_recalls(errors, DIAMETERS)
    assert tightest == {"VSD": 1 / 4, "MSSD": 2 / 4, "MSPD": 1 / 4}
    assert list(tightest) == ["VSD", "MSSD", "MSPD"]  # the column order of METRICS
    # The BOP19 average is kinder: 5 and 5.01 mm still pass the nine thresholds from 10 % on.
    assert metric_scores(errors, DIAMETERS)["MSSD"] == pytest.approx((10 + 9 + 9 + 10) / 40)
    assert tightest_recalls(errors.select(np.array([True, True, False, False])), DIAMETERS)["MSSD"] == 1 / 2


def test_tightest_is_the_smallest_threshold_and_follows_custom_thresholds():
    th = Thresholds(mssd_fractions=(0.2, 0.1), mspd_px_at_640=(20.0, 10.0), vsd_taus=(0.3, 0.1), vsd_thetas=(0.4,))
    assert tightest_thresholds(th) == {"mssd_fractions": 0.1, "mspd_px_at_640": 10.0, "vsd_taus": 0.1,
                                       "vsd_thetas": 0.4}
    assert tightest_thresholds() == {"mssd_fractions": 0.05, "mspd_px_at_640": 5.0, "vsd_taus": 0.05,
                                     "vsd_thetas": 0.05}
    # The second column is tau 0.1: 0.3 < 0.4 passes, the first column's 0.5 would not.
    errors = _errors([1], [0.15], mspd_px=[9.0], vsd=np.array([[0.5, 0.3]]))
    assert tightest_recalls(errors, DIAMETERS, th) == {"VSD": 1.0, "MSSD": 0.0, "MSPD": 1.0}
    assert "VSD" not in tightest_recalls(_errors([1], [0.0]), DIAMETERS)
    with pytest.raises(PopcodeError, match="one per tau"):
        tightest_recalls(_errors([1], [0.0], vsd=np.zeros((1, 3))), DIAMETERS)


def test_group_scores_of_tightest_recalls_by_ambiguity():
    errors = _errors([1, 1, 2, 2, 2], [0.0, 0.05, 0.0, 0.049, 0.2], mspd_px=[0.0, 0.0, 0.0, 0.0, 5.0])
    groups = group_scores(errors, DIAMETERS, {1: False, 2: True}, score=tightest_recalls)
    assert groups["Without ambiguity"] == {"MSSD": 1 / 2, "MSPD": 1.0}
    assert groups["With ambiguity"] == {"MSSD": 2 / 3, "MSPD": 2 / 3}
    assert groups["All objects"] == {"MSSD": 3 / 5, "MSPD": 4 / 5}
    per_object = group_scores(errors, DIAMETERS, {1: False, 2: True}, average="objects", score=tightest_recalls)
    assert per_object["All objects"]["MSSD"] == pytest.approx((1 / 2 + 2 / 3) / 2)


def test_vsd_errors_must_have_one_column_per_tau():
    with pytest.raises(PopcodeError, match="one per tau"):
        metric_scores(_errors([1], [0.0], vsd=np.zeros((1, 3))), DIAMETERS)


def test_missing_diameter_and_mismatched_lengths_are_reported():
    with pytest.raises(PopcodeError, match="object ids \\[7\\]"):
        metric_scores(_errors([7], [0.0]), DIAMETERS)
    with pytest.raises(PopcodeError, match="instances"):
        InstanceErrors(np.array([1, 2]), np.full(2, 640.0), np.zeros(1), np.zeros(2), np.zeros(2))


def test_group_scores_split_by_symmetry_class():
    models_info = {1: CASES["none"], 2: CASES["two_fold"], 3: CASES["continuous"]}
    ambiguous = ambiguous_objects(models_info)
    assert ambiguous == {1: False, 2: True, 3: True}
    errors = _errors([1, 1, 2, 3, 3, 3, 3], [0.0, 0.9, 0.0, 0.0, 0.0, 0.0, 0.9])
    pooled = group_scores(errors, DIAMETERS, ambiguous)
    assert list(pooled) == list(GROUPS)
    assert pooled["Without ambiguity"]["MSSD"] == pytest.approx(0.5)
    assert pooled["With ambiguity"]["MSSD"] == pytest.approx(4 / 5)
    assert pooled["All objects"]["MSSD"] == pytest.approx(5 / 7)
    per_object = group_scores(errors, DIAMETERS, ambiguous, average="objects")
    assert per_object["With ambiguity"]["MSSD"] == pytest.approx((1.0 + 0.75) / 2)
    assert per_object["All objects"]["MSSD"] == pytest.approx((0.5 + 1.0 + 0.75) / 3)


def test_group_without_objects_is_nan_and_null_in_json():
    groups = group_scores(_errors([1], [0.0]), DIAMETERS, {1: False})
    assert math.isnan(groups["With ambiguity"]["MSSD"])
    assert json.loads(to_json({"model": groups}))["model"]["With ambiguity"]["MSSD"] is None


def test_unknown_object_in_grouping_is_reported():
    with pytest.raises(PopcodeError, match="symmetry information"):
        group_scores(_errors([3], [0.0]), DIAMETERS, {1: False})


def test_ambiguity_markdown_has_a_section_per_group_and_a_row_per_method():
    ambiguous = {1: False, 2: True}
    errors = _errors([1, 2], [0.0, 0.3])
    worse = _errors([1, 2], [0.3, 0.3])
    text = ambiguity_markdown({
        "Population Code": group_scores(errors, DIAMETERS, ambiguous),
        "Single Variable": group_scores(worse, DIAMETERS, ambiguous),
    })
    for group in GROUPS:
        assert f"**{group}**" in text
    assert text.count("| Method | MSSD | MSPD | ADI |") == 3
    assert text.count("| Population Code |") == 3 and text.count("| Single Variable |") == 3
    assert "| Population Code | **100.00%** | **100.00%** | **100.00%** |" in text


def test_per_object_markdown_has_objects_as_columns():
    per_object = scores_per_object(_errors([1, 2, 2], [0.0, 0.0, 0.9]), DIAMETERS)
    text = per_object_markdown({"PC": per_object}, "MSSD", {1: 1, 2: 2})
    lines = text.split("\n")
    assert lines[0] == "| MSSD / object | 1 | 2 |"
    assert lines[2] == "| Test instances | 1 | 2 |"
    assert lines[3] == "| PC | 100.00% | 50.00% |"


def test_methods_markdown_marks_missing_scores():
    text = methods_markdown({"a": {"MSSD": 0.5, "VSD": 0.25}, "b": {"MSSD": 0.75}})
    assert text.split("\n")[0] == "| Method | VSD | MSSD |"
    assert "| b | – | **75.00%** |" in text
