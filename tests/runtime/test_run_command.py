"""``popcode run``: a rendered BOP split and boxes -> a BOP19 results CSV, resumed after a kill, scored by evaluate."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import popcode_runtime.inference.image_loop as image_loop
from popcode_runtime import PoseEstimator, read_image
from popcode_runtime.bop.bop19_csv import read_bop19_results
from popcode_runtime.bop.detections import ground_truth_boxes
from popcode_runtime.commands.cli import main
from popcode_trainer.cli import main as trainer_main
from popcode_trainer.data.render import render_builtin_split

MODELS = Path(__file__).resolve().parents[2] / "models"
SHIPPED = [str(MODELS / "builtin-parts-1-2.onnx"), str(MODELS / "builtin-parts-3-6.onnx")]


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The six built-in parts, 2 images each, off-centre in 200 x 150 images."""
    return render_builtin_split(tmp_path_factory.mktemp("run") / "split", 2, size=(200, 150), random_position=True)


def _run(split: Path, out: Path, *options: str) -> int:
    return main(["run", *SHIPPED, "--split", str(split), "--out", str(out), "--quiet", *options])


def _without_time(path: Path) -> list[str]:
    return [line.rsplit(",", 1)[0] for line in path.read_text().splitlines()]


def test_gt_boxes_give_the_runtimes_estimate_of_every_instance(split: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "results.csv"
    assert _run(split, out, "--gt-boxes") == 0
    assert f"wrote {out}: 12 estimates of 12 images" in capsys.readouterr().out
    estimates = read_bop19_results(out)
    boxes = ground_truth_boxes(split)
    assert [(e.scene_id, e.im_id, e.obj_id) for e in estimates] == [(b.scene_id, b.im_id, b.obj_id) for b in boxes]
    estimators = [PoseEstimator(path) for path in SHIPPED]
    for est, box in zip(estimates, boxes, strict=True):
        estimator = next(e for e in estimators if box.obj_id in e.metadata.objects)
        image = split / f"{box.scene_id:06d}" / "gray" / f"{box.im_id:06d}.png"
        K = json.loads((image.parents[1] / "scene_camera.json").read_text())[str(box.im_id)]["cam_K"]
        direct = estimator.predict(read_image(image), [box.box], K=K, obj_ids=[box.obj_id], translation=True)[0]
        np.testing.assert_allclose(est.R_m2c, direct.R_m2c, atol=1e-12)  # the same as predicting the box directly
        np.testing.assert_allclose(est.t_m2c_mm, direct.t_m2c_mm, atol=1e-9)
        assert est.time_s > 0 and est.score == pytest.approx(direct.confidence)  # box score 1 x the confidence
    assert not out.with_name("results.csv.partial").exists()


def test_detections_file_skips_unknown_objects_with_a_count_and_scales_the_score(split: Path, tmp_path: Path,
                                                                                 capsys) -> None:
    boxes = ground_truth_boxes(split)
    entries = [{"scene_id": b.scene_id, "image_id": b.im_id, "category_id": b.obj_id, "bbox": list(b.box),
                "score": 0.5, "time": 0.25} for b in boxes]
    unknown = {"scene_id": 3, "image_id": 0, "category_id": 99, "bbox": [1, 2, 30, 40], "score": 0.9, "time": 0.25}
    entries += [unknown] * 3
    detections = tmp_path / "detections.json"
    detections.write_text(json.dumps(entries))
    out = tmp_path / "results.csv"
    assert _run(split, out, "--detections", str(detections), "--max-images", "5") == 0
    printed = capsys.readouterr().out
    assert "5 estimates of 5 images" in printed and "skipped 3 detections of objects no model knows: object 99 x3" \
        in printed
    estimates = read_bop19_results(out)
    assert all(0.0 <= e.score <= 0.5 for e in estimates) and all(e.time_s > 0.25 for e in estimates)
    assert len({e.score for e in estimates}) > 1  # the detection's 0.5 times each estimate's own confidence


def test_an_interrupted_run_resumes_from_the_last_finished_image(split: Path, tmp_path: Path, monkeypatch,
                                                                 capsys) -> None:
    whole = tmp_path / "whole.csv"
    assert _run(split, whole, "--gt-boxes") == 0
    out = tmp_path / "results.csv"
    calls = {"n": 0}
    real_read = image_loop.read_image

    def killed_at_the_fifth_image(path, *args):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return real_read(path, *args)

    monkeypatch.setattr(image_loop, "read_image", killed_at_the_fifth_image)
    assert _run(split, out, "--gt-boxes") == 130
    monkeypatch.undo()
    partial = out.with_name("results.csv.partial")
    assert not out.exists() and partial.read_text().count("#done") == 4
    with partial.open("a") as handle:
        handle.write("3,0,3,1.0,1 0 0\n#done 3")  # the torn tail of an image that never finished
    capsys.readouterr()
    assert _run(split, out, "--gt-boxes") == 0
    assert "8 images (4 done by an earlier run)" in capsys.readouterr().out
    assert _without_time(out) == _without_time(whole)
    assert not partial.exists()


@pytest.mark.parametrize("content, message", [
    ({"scene_id": 1}, "expected a JSON list of detections"),
    ([{"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0}], "detection 0: 'bbox' must be 4 finite numbers"),
    ([{"scene_id": "1", "image_id": 0, "category_id": 1, "bbox": [0, 0, 5, 5], "score": 1}], "'scene_id' must be"),
    ([{"scene_id": 1, "image_id": 0, "category_id": 1, "bbox": [0, 0, 0, 5], "score": 1}], "has no area"),
    ([{"scene_id": 1, "image_id": 0, "category_id": 1, "bbox": [0, 0, 5, 5], "score": None}], "'score' must be"),
    ([{"scene_id": 1, "image_id": 77, "category_id": 1, "bbox": [0, 0, 5, 5], "score": 1}],
     "1 image(s) that are not in the split, first scene 1 image 77"),
    ([[1, 0, 1]], "detection 0 must be a JSON object"),
    ([{"scene_id": 1, "image_id": 0, "category_id": 99, "bbox": [0, 0, 5, 5], "score": 1}],
     "none of the 1 detections is of an object these models know (detected: objects 99; the models know objects "
     "1, 2, 3, 4, 5, 6)"),
    # found before the first image is estimated, naming the image and the detection (the good box comes first)
    ([{"scene_id": 1, "image_id": 0, "category_id": 1, "bbox": [10, 10, 50, 50], "score": 1},
      {"scene_id": 6, "image_id": 1, "category_id": 6, "bbox": [5000, 10, 50, 50], "score": 1}],
     "scene 6 image 1 (000001.png), the detection of object 6: box (5000.0, 10.0, 50.0, 50.0) lies wholly outside the "
     "200x150 image"),
])
def test_malformed_detections_are_refused_in_one_line(split: Path, tmp_path: Path, capsys, content,
                                                      message: str) -> None:
    detections = tmp_path / "detections.json"
    detections.write_text(json.dumps(content))
    out = tmp_path / "results.csv"
    assert _run(split, out, "--detections", str(detections)) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not out.exists() and not out.with_name("results.csv.partial").exists()


def test_bad_splits_and_outputs_are_refused_in_one_line(split: Path, tmp_path: Path, capsys) -> None:
    uncalibrated = tmp_path / "uncalibrated"
    shutil.copytree(split, uncalibrated)
    (uncalibrated / "000003" / "scene_camera.json").unlink()
    cases = [
        ((uncalibrated, tmp_path / "a.csv", "--gt-boxes"), "scene 3 image 0 has no cam_K"),
        ((tmp_path / "nowhere", tmp_path / "b.csv", "--gt-boxes"), "split folder not found"),
        ((split, tmp_path / "missing" / "c.csv", "--gt-boxes"), "does not exist"),
        ((split, tmp_path / "d.csv", "--detections", str(tmp_path / "none.json")), "missing file"),
        ((split, tmp_path / "e.csv", "--gt-boxes", "--max-images", "0"), "--max-images must be at least 1"),
    ]
    for arguments, message in cases:
        code = _run(*arguments)
        err = capsys.readouterr().err
        assert code == 2 and message in err and err.count("\n") == 1, (message, err)
    done = tmp_path / "done.csv"
    assert _run(split, done, "--gt-boxes") == 0
    assert _run(split, done, "--gt-boxes") == 2
    assert "exists already" in capsys.readouterr().err
    other = tmp_path / "other.csv"
    other.with_name("other.csv.partial").write_text("#popcode-run 0123\n")
    assert _run(split, other, "--gt-boxes") == 2
    assert "other models, detections, split or options" in capsys.readouterr().err


def test_evaluate_scores_the_results_file_as_it_scores_the_models(split: Path, tmp_path: Path) -> None:
    """Detections -> CSV -> the trainer's evaluate: the same scores as evaluating the models directly."""
    results = tmp_path / "gt_boxes.csv"
    assert _run(split, results, "--gt-boxes") == 0
    common = ["--split", str(split), "--models-dir", str(split / "models"), "--no-vsd"]
    assert trainer_main(["evaluate", *SHIPPED, "--name", "direct", "--name", "direct", *common,
                         "--out", str(tmp_path / "direct")]) == 0
    assert trainer_main(["evaluate", str(results), *common, "--out", str(tmp_path / "csv")]) == 0
    direct = json.loads((tmp_path / "direct" / "report.json").read_text())["methods"]["direct"]
    from_csv = json.loads((tmp_path / "csv" / "report.json").read_text())["methods"]["gt_boxes"]
    assert from_csv["per_object"] == direct["per_object"] and from_csv["groups"] == direct["groups"]


def test_existing_outputs_are_refused_unless_overwrite(split: Path, tmp_path: Path, capsys) -> None:
    """One rule in every command: an output that exists is refused in one line naming --overwrite, which replaces
    it; an input is never an output, --overwrite or not."""
    out, pictures = tmp_path / "results.csv", tmp_path / "pictures"
    pictures.mkdir()
    assert _run(split, out, "--gt-boxes", "--max-images", "1") == 0
    assert _run(split, out, "--gt-boxes") == 2
    assert "--out " + str(out) + " exists already; pass --overwrite" in capsys.readouterr().err
    assert _run(split, out, "--gt-boxes", "--overwrite") == 0
    fresh = tmp_path / "fresh.csv"
    assert _run(split, fresh, "--gt-boxes") == 0
    assert _without_time(out) == _without_time(fresh)  # replaced by a whole run, not appended to the first

    stale = pictures / "000001_000000.png"
    stale.write_bytes(b"not yet a picture")
    assert _run(split, tmp_path / "drawn.csv", "--gt-boxes", "--draw", str(pictures)) == 2
    assert f"--draw picture {stale} exists already" in capsys.readouterr().err
    assert not (tmp_path / "drawn.csv.partial").exists()  # refused before anything was written
    assert _run(split, tmp_path / "drawn.csv", "--gt-boxes", "--draw", str(pictures), "--overwrite") == 0
    assert read_image(stale).shape[:2] == (150, 200)
    detections = pictures / "000001_000000.png"  # an input named as one of the pictures: never drawn over
    text = json.dumps([{"scene_id": 1, "image_id": 0, "category_id": 1, "bbox": [10, 10, 50, 50], "score": 1}])
    detections.write_text(text)
    code = _run(split, tmp_path / "drawn2.csv", "--detections", str(detections), "--draw", str(pictures), "--overwrite")
    assert code == 2 and "is the input" in capsys.readouterr().err and detections.read_text() == text

    report = ["evaluate", str(out), "--split", str(split), "--models-dir", str(split / "models"), "--no-vsd",
              "--out", str(tmp_path / "eval")]
    assert trainer_main(report) == 0
    assert trainer_main(report) == 2
    assert "report.md exists already; pass --overwrite" in capsys.readouterr().err
    assert trainer_main([*report, "--overwrite"]) == 0
    (tmp_path / "eval" / "errors_results.csv").unlink()
    (tmp_path / "eval" / "errors_results.csv").symlink_to(split / "000001" / "scene_gt.json")
    assert trainer_main([*report, "--overwrite"]) == 2  # never written through a link, onto an input
    assert "errors_results.csv lies in the input" in capsys.readouterr().err
    (tmp_path / "eval" / "errors_results.csv").unlink()
    os.mkfifo(tmp_path / "eval" / "errors_results.csv")  # a FIFO would hang the write, a rename replace it
    assert trainer_main([*report, "--overwrite"]) == 2 and "is not a regular file" in capsys.readouterr().err
    scored = ["evaluate", str(tmp_path / "eval2" / "results_bop19.csv"), "--name", "results", "--split", str(split),
              "--models-dir",
              str(split / "models"), "--no-vsd", "--bop19-csv", "--out", str(tmp_path / "eval2"), "--overwrite"]
    (tmp_path / "eval2").mkdir()
    shutil.copy(out, tmp_path / "eval2" / "results_bop19.csv")  # scored into the folder it lies in, as its own output
    assert trainer_main(scored) == 2 and "is the input" in capsys.readouterr().err
    twins = ["evaluate", str(out), str(out), "--name", "a/b", "--name", "a_b", "--split", str(split),
             "--models-dir", str(split / "models"), "--no-vsd", "--out", str(tmp_path / "eval3")]
    assert trainer_main(twins) == 2 and "would write the same files" in capsys.readouterr().err
    crossed = ["evaluate", str(out), str(out), "--name", "m", "--name", "m_6d", "--translation", "--bop19-csv",
               "--split", str(split), "--models-dir", str(split / "models"), "--no-vsd", "--out", str(tmp_path / "e4")]
    assert trainer_main(crossed) == 2  # m's 6-D results file is m_6d's rotation-only one
    assert "m_6d_bop19.csv would be written for 'm' and for 'm_6d'" in capsys.readouterr().err
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    assert trainer_main([*report[:-1], str(tmp_path / "dangling")]) == 2
    assert "is not a folder (a file, link or FIFO)" in capsys.readouterr().err
    assert trainer_main([*report[:-1], str(tmp_path / "dangling" / "sub")]) == 2  # a dangling link on the way
    assert "so the report's folder cannot be made" in capsys.readouterr().err
    utf16 = tmp_path / "utf16.csv"
    utf16.write_bytes(out.read_text().encode("utf-16"))
    assert trainer_main(["evaluate", str(utf16), *report[2:-2], "--out", str(tmp_path / "e5")]) == 2
    assert "is not a UTF-8 text file" in capsys.readouterr().err
    inside = ["evaluate", str(out), "--split", str(split), "--models-dir", str(split / "models"), "--no-vsd",
              "--out", str(split / "eval"), "--overwrite"]
    assert trainer_main(inside) == 2 and "lies in the input" in capsys.readouterr().err

    detections = ["detections", "--split", str(split), "--box-noise", "tight", "--out", str(tmp_path / "d.json")]
    assert trainer_main(detections) == 0
    assert trainer_main(detections) == 2 and "exists already" in capsys.readouterr().err
    assert trainer_main([*detections[:-1], str(split / "000001" / "scene_gt.json"), "--overwrite"]) == 2
    assert "lies in the input" in capsys.readouterr().err
