"""2-D detection scores against a tiny BOP split written here by hand: COCO's AP as the BOP toolkit computes it,
the ignore flag of instances under 10 % visible, recall per visible fraction, and the command."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.detections import Detection
from popcode_trainer.cli import main
from popcode_trainer.metrics.detection_scores import VISIBILITY_BINS, detection_scores

WIDTH, HEIGHT = 160, 120


def instance(obj_id: int, box: tuple[int, int, int, int], visib_fract: float = 1.0,
             bbox_visib: tuple[int, int, int, int] | None = None) -> dict:
    """One object instance: its ``scene_gt_info.json`` boxes (``calc_2d_bbox``: w from first to last pixel)."""
    return {"obj_id": obj_id, "bbox_obj": list(box), "bbox_visib": list(bbox_visib or box),
            "visib_fract": visib_fract, "px_count_visib": max(1, int(visib_fract * box[2] * box[3]))}


def write_split(folder: Path, scenes: dict[int, dict[int, list[dict]]]) -> Path:
    """A BOP split of black PNG images with the given instances per scene and image."""
    for scene_id, images in scenes.items():
        scene = folder / f"{scene_id:06d}"
        (scene / "rgb").mkdir(parents=True)
        gt, info, camera = {}, {}, {}
        for im_id, instances in images.items():
            cv2.imwrite(str(scene / "rgb" / f"{im_id:06d}.png"), np.zeros((HEIGHT, WIDTH), np.uint8))
            camera[str(im_id)] = {"cam_K": [500.0, 0, WIDTH / 2, 0, 500.0, HEIGHT / 2, 0, 0, 1]}
            gt[str(im_id)] = [{"obj_id": one["obj_id"], "cam_R_m2c": np.eye(3).ravel().tolist(),
                               "cam_t_m2c": [0, 0, 600]} for one in instances]
            info[str(im_id)] = [{key: one[key] for key in ("bbox_obj", "bbox_visib", "visib_fract", "px_count_visib")}
                                for one in instances]
        for name, data in (("scene_gt", gt), ("scene_gt_info", info), ("scene_camera", camera)):
            (scene / f"{name}.json").write_text(json.dumps(data))
    return folder


def hit(scene_id: int, im_id: int, one: dict, score: float = 0.9, dx: float = 0.0) -> Detection:
    """A detection of ``one``'s box in COCO's convention (w counts pixels, one more than BOP's), shifted by dx."""
    x, y, w, h = one["bbox_obj"]
    return Detection(scene_id, im_id, one["obj_id"], (x + dx, y, w + 1.0, h + 1.0), score, 0.05)


A, B = instance(1, (10, 10, 19, 19)), instance(2, (60, 40, 29, 19))
FEW_VISIBLE = instance(1, (100, 60, 19, 19), visib_fract=0.05)


@pytest.fixture
def split(tmp_path: Path) -> Path:
    return write_split(tmp_path / "split", {0: {0: [A, B], 1: [B]}, 2: {5: [A]}})


def perfect() -> list[Detection]:
    return [hit(0, 0, A), hit(0, 0, B), hit(0, 1, B), hit(2, 5, A)]


def test_perfect_detections_score_one_and_pycocotools_stays_quiet(split: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    scores = detection_scores(split, perfect())
    assert capsys.readouterr().out == ""
    assert [scores.coco[name] for name in ("AP", "AP50", "AP75", "AR100")] == pytest.approx([1.0] * 4)
    assert scores.coco["AP_large"] is None  # no instance over 96² px: COCO's -1
    assert scores.ap_per_object == pytest.approx({1: 1.0, 2: 1.0})
    assert (scores.images, scores.instances, scores.ignored_instances, scores.detections) == (3, 4, 0, 4)
    assert scores.recall_goal.recall == 1.0 and scores.recall_by_visibility[-1].found == 4
    assert scores.mean_time_per_image_s == pytest.approx(0.05)


def test_a_box_at_iou_0_6_counts_at_ap50_not_at_ap75(tmp_path: Path) -> None:
    split = write_split(tmp_path / "split", {0: {0: [A]}})
    # 20 x 20 px shifted by 4.8 px: IoU 304 / 496 = 0.61, a hit at the thresholds 0.5, 0.55 and 0.6 of ten
    scores = detection_scores(split, [hit(0, 0, A, dx=4.8)])
    assert scores.coco["AP50"] == pytest.approx(1.0) and scores.coco["AP75"] == 0.0
    assert scores.coco["AP"] == pytest.approx(0.3)
    assert scores.recall_goal.found == 1


def test_a_missed_instance_lowers_the_recall_of_its_visible_fraction(tmp_path: Path) -> None:
    low, mid, high = instance(1, (10, 10, 19, 19), 0.2), instance(2, (60, 10, 19, 19), 0.4), \
        instance(3, (10, 60, 19, 19), 0.95)
    split = write_split(tmp_path / "split", {0: {0: [low, mid, high]}})
    scores = detection_scores(split, [hit(0, 0, high), hit(0, 0, low)])
    by_bin = {(r.low, r.high): (r.instances, r.found) for r in scores.recall_by_visibility}
    assert by_bin == {(0.1, 0.3): (1, 1), (0.3, 0.5): (1, 0), (0.5, 0.7): (0, 0), (0.7, 0.9): (0, 0),
                      (0.9, 1.0): (1, 1)}
    assert scores.recall_by_visibility[2].recall is None
    assert (scores.recall_goal.instances, scores.recall_goal.found) == (2, 1)
    assert scores.ap_per_object == pytest.approx({1: 1.0, 2: 0.0, 3: 1.0}) and scores.coco["AP"] == pytest.approx(2 / 3)


def test_the_recall_counts_only_detections_scored_at_least_min_score(split: Path) -> None:
    weak = [hit(0, 0, A, score=0.3), hit(0, 0, B), hit(0, 1, B), hit(2, 5, A)]
    assert detection_scores(split, weak).recall_goal.found == 4
    assert detection_scores(split, weak, min_score=0.5).recall_goal.found == 3


def test_false_positives_lower_ap_only_when_they_outrank_the_hits(split: Path) -> None:
    wrong_place = Detection(0, 1, 2, (110.0, 80.0, 30.0, 20.0), 0.95)
    assert detection_scores(split, [*perfect(), wrong_place]).coco["AP"] < 1.0
    behind = Detection(0, 1, 2, (110.0, 80.0, 30.0, 20.0), 0.1)
    assert detection_scores(split, [*perfect(), behind]).coco["AP"] == pytest.approx(1.0)


def test_a_box_on_an_image_without_parts_is_a_false_positive(tmp_path: Path) -> None:
    """``render --empty-share`` writes images whose ground truth is an empty list: they are scored, with no
    instance, so every box on them is a false positive."""
    split = write_split(tmp_path / "split", {0: {0: [A, B], 1: []}})
    on_empty = Detection(0, 1, 1, (10.0, 10.0, 20.0, 20.0), 0.95)
    scores = detection_scores(split, [hit(0, 0, A), hit(0, 0, B), on_empty])
    assert (scores.images, scores.instances, scores.detections) == (2, 2, 3)
    assert scores.ap_per_object[1] < 1.0 and scores.ap_per_object[2] == pytest.approx(1.0)
    assert scores.recall_goal.found == 2


def test_an_instance_under_10_percent_visible_is_ignored(tmp_path: Path) -> None:
    split = write_split(tmp_path / "split", {0: {0: [A, FEW_VISIBLE]}})
    missed = detection_scores(split, [hit(0, 0, A)])
    found = detection_scores(split, [hit(0, 0, A, score=0.5), hit(0, 0, FEW_VISIBLE)])
    for scores in (missed, found):  # neither a miss nor, found above the hits, a false positive
        assert scores.coco["AP"] == pytest.approx(1.0) and scores.coco["AR100"] == pytest.approx(1.0)
        assert (scores.instances, scores.ignored_instances) == (2, 1)


def test_the_amodal_box_is_clipped_to_the_image_and_modal_is_the_visible_one(tmp_path: Path) -> None:
    cut = instance(1, (-10, 100, 40, 40), 0.5, bbox_visib=(0, 100, 20, 19))
    split = write_split(tmp_path / "split", {0: {0: [cut]}})
    inside = Detection(0, 0, 1, (0.0, 100.0, 31.0, 20.0), 0.9)  # x 0..30, y 100..119
    assert detection_scores(split, [inside]).coco["AP"] == pytest.approx(1.0)
    visible = Detection(0, 0, 1, (0.0, 100.0, 21.0, 20.0), 0.9)
    assert detection_scores(split, [visible], box="modal").coco["AP"] == pytest.approx(1.0)
    assert detection_scores(split, [visible]).coco["AP"] < 0.9


def test_no_detections_score_zero(split: Path) -> None:
    scores = detection_scores(split, [])
    assert scores.coco["AP"] == scores.coco["AR100"] == 0.0 and scores.recall_goal.found == 0
    assert scores.mean_time_per_image_s is None and scores.ap_per_object == {1: 0.0, 2: 0.0}


@pytest.mark.parametrize(("scenes", "detections", "message"), [
    ({0: {0: [A]}}, [hit(0, 7, A)], r"1 detections are of images that .* does not annotate \(first: scene 0, "
                                    r"image 7\)"),
    ({0: {0: [A]}}, [hit(3, 0, A)], "first: scene 3, image 0"),
    ({0: {0: []}}, [], r"no ground-truth instance at least 10% visible in its 1 annotated images"),
    ({0: {0: [FEW_VISIBLE]}}, [], "no ground-truth instance at least 10% visible"),
    ({0: {0: [A, B]}}, [hit(0, 0, A), Detection(0, 0, 2, (60.0, 40.0, 30.0, 20.0), 0.9, 0.2)],
     r"scene 0, image 0: detections give the image's time as 0.05 s and 0.2 s"),
])
def test_bad_input_is_refused(tmp_path: Path, scenes: dict, detections: list[Detection], message: str) -> None:
    split = write_split(tmp_path / "split", scenes)
    with pytest.raises(PopcodeError, match=message):
        detection_scores(split, detections)


def test_bad_arguments_are_refused(split: Path) -> None:
    with pytest.raises(PopcodeError, match=r"box must be one of \['amodal', 'modal'\], got 'bbox_obj'"):
        detection_scores(split, [], box="bbox_obj")
    with pytest.raises(PopcodeError, match=r"min_score must lie in \[0, 1\], got 2"):
        detection_scores(split, [], min_score=2.0)


def detections_file(path: Path, detections: list[Detection]) -> Path:
    path.write_text(json.dumps([{"scene_id": d.scene_id, "image_id": d.im_id, "category_id": d.obj_id,
                                 "bbox": list(d.box), "score": d.score, "time": d.time_s} for d in detections]))
    return path


def test_the_command_prints_a_table_and_writes_json(split: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    found = detections_file(tmp_path / "dets.json", perfect()[:3])
    out = tmp_path / "scores.json"
    assert main(["evaluate-detections", "--split", str(split), "--detections", str(found), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| AP50 | 0.752 |" in text and "| 2 | 1.000 |" in text and "| 0.9–1 | 4 | 3 | 0.750 |" in text
    assert f"wrote {out}" in text
    written = json.loads(out.read_text())
    # object 1: one of two found, precision 1 at 51 of COCO's 101 recall steps (0, 0.01, ..., 0.5)
    assert written["ap_per_object"] == pytest.approx({"1": 51 / 101, "2": 1.0})
    assert written["AP50"] == pytest.approx((51 / 101 + 1.0) / 2) and written["AR100"] == 0.75
    assert [r["visib_fract"] for r in written["recall_iou50_by_visibility"]] == [list(b) for b in VISIBILITY_BINS]

    assert main(["evaluate-detections", "--split", str(split), "--detections", str(found), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == written


@pytest.mark.parametrize(("extra", "message"), [
    (["--out", "{out}"], "scores.json exists already; pass --overwrite"),
    (["--min-score", "1.5"], r"--min-score must lie in \[0, 1\], got 1.5"),
    (["--detections", "{other}"], "1 detections are of images that"),
])
def test_the_command_refuses_bad_input_in_one_line(split: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                   extra: list[str], message: str) -> None:
    found = detections_file(tmp_path / "dets.json", perfect())
    other = detections_file(tmp_path / "other.json", [hit(9, 0, A)])
    (tmp_path / "scores.json").write_text("{}")
    args = ["evaluate-detections", "--split", str(split), "--detections", str(found)]
    args += [arg.format(out=tmp_path / "scores.json", other=other) for arg in extra]
    assert main(args) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    error = captured.err.strip()
    assert len(error.splitlines()) == 1 and error.startswith("popcode-train: error:")
    assert re.search(message, error), error


def test_detections_of_an_object_the_split_lacks_are_named_not_scored(split: Path, tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """An object with no ground truth has no AP: its detections are left out and counted, in text and JSON, rather
    than scored without a word (issue 62)."""
    other = Detection(0, 0, 99, (10.0, 10.0, 20.0, 20.0), 0.95)
    found = detections_file(tmp_path / "dets.json", [*perfect(), other, other])
    assert main(["evaluate-detections", "--split", str(split), "--detections", str(found)]) == 0
    text = capsys.readouterr().out
    assert "2 detections of object 99, which the split does not annotate, are not scored" in text
    assert "| 99 |" not in text
    assert main(["evaluate-detections", "--split", str(split), "--detections", str(found), "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["unannotated_detections"] == {"99": 2} and set(scores["ap_per_object"]) == {"1", "2"}
    assert scores["AP"] == pytest.approx(1.0)
