"""``popcode detect`` and ``popcode run --detector`` on a split (issue 62): one writer per ``--out``, ``--quiet``
prints nothing but errors, and what the outputs refuse is refused before the detector's progress lines."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from popcode_runtime.base.output_lock import OutputLock
from popcode_runtime.commands.cli import main
from popcode_runtime.model.detector_metadata import DetectorMetadata
from tests.onnx_models import fixed_detector, save
from tools.paths import SHIPPED_MODELS

WIDTH, HEIGHT = 64, 48


@pytest.fixture()
def detector(tmp_path):
    metadata = DetectorMetadata(obj_ids=(3,), input_width=WIDTH, input_height=HEIGHT)
    boxes, scores = np.array([[8, 8, 24, 24]], np.float32), np.array([[0.9]], np.float32)
    return save(fixed_detector(boxes, scores, metadata), tmp_path / "det.onnx")


@pytest.fixture()
def split(tmp_path):
    images = tmp_path / "split" / "000000" / "gray"
    images.mkdir(parents=True)
    for im_id in range(2):
        cv2.imwrite(str(images / f"{im_id:06d}.png"), np.full((HEIGHT, WIDTH), 128, np.uint8))
    camera = {"cam_K": [60.0, 0.0, 31.5, 0.0, 60.0, 23.5, 0.0, 0.0, 1.0], "depth_scale": 1.0}
    (images.parent / "scene_camera.json").write_text(json.dumps({str(im_id): camera for im_id in range(2)}))
    return images.parents[1]


def test_a_second_detect_into_the_same_out_is_refused_in_one_line(detector, split, tmp_path, capsys):
    out = tmp_path / "detections.json"
    with OutputLock(tmp_path / "detections.json.lock", "held by the test"):
        assert main(["detect", str(detector), "--split", str(split), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err == (f"popcode: error: another popcode detect or run is writing {out} (it holds "
                            "detections.json.lock); wait for it or choose another --out\n")
    assert not out.exists() and captured.out == ""
    assert main(["detect", str(detector), "--split", str(split), "--out", str(out)]) == 0  # the lock is released
    assert out.is_file() and not (tmp_path / "detections.json.lock").exists()


def test_quiet_prints_nothing_but_the_boxes(detector, split, tmp_path, capsys):
    out = tmp_path / "detections.json"
    assert main(["detect", str(detector), "--split", str(split), "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr() == ("", "") and out.is_file()
    image = split / "000000" / "gray" / "000000.png"
    assert main(["detect", str(detector), str(image), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "object 3: box [8.0, 8.0, 16.0, 16.0], score 0.900\n" and captured.err == ""
    assert main(["detect", str(detector), str(image)]) == 0
    assert "1 detections in " in capsys.readouterr().err  # without --quiet: the count and the time


def _foreign_partial(out):
    out.with_name(out.name + ".partial").write_text("#popcode-run " + "0" * 32 + "\n")


def _picture(draw):
    draw.mkdir()
    (draw / "000000_000000.png").write_bytes(b"an earlier picture")


@pytest.mark.parametrize(("prepare", "draws", "expect"), [
    (lambda out, draw: out.write_text("an earlier run's results\n"), False, "exists already; pass --overwrite"),
    (lambda out, draw: _foreign_partial(out), False, "holds the partial results of a run with other models"),
    (lambda out, draw: _picture(draw), True, "--draw picture"),
], ids=["out-exists", "partial-of-another-run", "draw-picture-exists"])
def test_run_refuses_its_outputs_before_the_detector_runs(detector, split, tmp_path, capsys, prepare, draws, expect):
    """Refusals that need no detection come before the detector's progress lines, alone on stderr."""
    out, draw = tmp_path / "results.csv", tmp_path / "draw"
    prepare(out, draw)
    argv = ["run", str(SHIPPED_MODELS[1]), "--split", str(split), "--detector", str(detector), "--out", str(out)]
    assert main(argv + (["--draw", str(draw)] if draws else [])) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("popcode: error: ") and expect in err, err
