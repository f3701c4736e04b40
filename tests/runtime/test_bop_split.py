"""The one walk of a split's ground truth: which instances it selects, in what order, and what it refuses."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from popcode_runtime import PopcodeError
from popcode_runtime.bop.detections import ground_truth_boxes
from popcode_runtime.bop.split import scene_ground_truth

R = [1, 0, 0, 0, 1, 0, 0, 0, 1]


def _info(box: list[float], visib_fract: float) -> dict:
    return {"bbox_obj": box, "bbox_visib": [b / 2 for b in box], "visib_fract": visib_fract}


def _scene(folder: Path, gt: dict, info: dict) -> Path:
    folder.mkdir(parents=True)
    (folder / "scene_gt.json").write_text(json.dumps(gt))
    (folder / "scene_gt_info.json").write_text(json.dumps(info))
    return folder


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    """Image 10 before image 2 in the file; image 2 holds a kept, a hidden and a boxless instance."""
    gt = {"10": [{"obj_id": 4, "cam_R_m2c": R, "cam_t_m2c": [0, 0, 500]}],
          "2": [{"obj_id": 3, "cam_R_m2c": R, "cam_t_m2c": [0, 0, 600]},
                {"obj_id": 3, "cam_R_m2c": R, "cam_t_m2c": [0, 0, 700]},
                {"obj_id": 5, "cam_R_m2c": R, "cam_t_m2c": [0, 0, 800]}]}
    info = {"10": [_info([1, 2, 30, 40], 0.5)],
            "2": [_info([5, 6, 20, 10], 1.0), _info([5, 6, 20, 10], 0.05), _info([-1, -1, -1, -1], 0.9)]}
    return _scene(tmp_path / "000007", gt, info)


def test_walk_selects_visible_boxed_instances_in_image_order(scene: Path) -> None:
    walk = list(scene_ground_truth(scene, "bbox_obj", 0.1))
    assert [im_id for im_id, _ in walk] == [2, 10]
    (kept,), (other,) = (selected for _, selected in walk)
    assert (kept.scene_id, kept.im_id, kept.gt_index, kept.obj_id) == (7, 2, 0, 3)
    assert kept.box == (5.0, 6.0, 20.0, 10.0) and kept.visib_fract == 1.0
    assert kept.gt_entry["cam_t_m2c"] == [0, 0, 600] and kept.gt_path == scene / "scene_gt.json"
    assert kept.where == "image 2, object 0"
    assert (other.im_id, other.obj_id, other.box) == (10, 4, (1.0, 2.0, 30.0, 40.0))


def test_walk_keeps_the_object_ids_asked_for_and_the_box_kind(scene: Path) -> None:
    walk = dict(scene_ground_truth(scene, "bbox_visib", 0.0, obj_ids={3}))
    assert walk[10] == []  # an image without a selected instance is still walked
    assert [(gt.gt_index, gt.box) for gt in walk[2]] == [(0, (2.5, 3.0, 10.0, 5.0)), (1, (2.5, 3.0, 10.0, 5.0))]


def test_gt_boxes_are_the_walks_selection(scene: Path) -> None:
    boxes = ground_truth_boxes(scene.parent)
    assert [(b.scene_id, b.im_id, b.obj_id, b.box, b.score) for b in boxes] == [
        (7, 2, 3, (5.0, 6.0, 20.0, 10.0), 1.0), (7, 10, 4, (1.0, 2.0, 30.0, 40.0), 1.0)]
    assert len(ground_truth_boxes(scene.parent, min_visib_fract=0.0)) == 3


@pytest.mark.parametrize(("info", "message"), [
    ({"10": [_info([1, 2, 3, 4], 1.0)]}, r"scene_gt_info.json: key '2' missing \(it is in scene_gt.json\)"),
    ({"10": [_info([1, 2, 3, 4], 1.0)], "2": []}, "image 2 must list the same number of objects"),
    ({"10": [{"bbox_obj": [1, 2, 3, 4]}], "2": [_info([1, 2, 3, 4], 1.0)]},
     "scene_gt_info.json: key 'visib_fract' missing in image 10, object 0"),
    ({"10": [_info([1, 2, 3], 1.0)], "2": [_info([1, 2, 3, 4], 1.0)]},
     r"key 'bbox_obj' in image 10, object 0 must be 4 numbers"),
])
def test_walk_refuses_malformed_ground_truth(tmp_path: Path, info: dict, message: str) -> None:
    gt = {"2": [{"obj_id": 3}], "10": [{"obj_id": 4}]}
    scene = _scene(tmp_path / "000000", gt, info)
    with pytest.raises(PopcodeError, match=message):
        list(scene_ground_truth(scene, "bbox_obj", 0.1))


def test_walk_names_an_instance_without_an_object_id(tmp_path: Path) -> None:
    scene = _scene(tmp_path / "000000", {"0": [{"cam_R_m2c": R}]}, {"0": [_info([1, 2, 3, 4], 1.0)]})
    with pytest.raises(PopcodeError, match="scene_gt.json: key 'obj_id' missing in image 0, object 0"):
        list(scene_ground_truth(scene, "bbox_obj", 0.1))
