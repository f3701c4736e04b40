import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx_models import linear_model, save
from symmetry_cases import CASES

from popcode_runtime import CodeLayout, ModelMetadata, PopulationCode, Representation, symmetry_rotations
from popcode_runtime.commands.cli import main
from popcode_runtime.geometry.rotations import random_rotations

LAYOUT = CodeLayout(n_axes=162, n_angles=12)


@pytest.fixture
def model(tmp_path):
    R = random_rotations(1, np.random.default_rng(3))[0]
    bias = PopulationCode(LAYOUT).encode(R, symmetry_rotations(CASES["two_fold"]))
    meta = ModelMetadata(representation=Representation.POPULATION_CODE, code=LAYOUT, objects={7: CASES["two_fold"]},
                         training={"dataset": "cli-test", "epochs": 1})
    return save(linear_model(bias, weight_scale=0.5, metadata=meta), tmp_path / "model.onnx")


@pytest.fixture
def image(tmp_path):
    path = tmp_path / "scene.png"
    cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 256, size=(240, 320), dtype=np.uint8))
    return path


def test_predict_json(model, image, capsys):
    assert main(["predict", str(model), str(image), "--box", "10,20,60,50", "--box", "150,100,80,90", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["predictions"]) == 2
    R = np.array(out["predictions"][0]["R_m2c"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert out["predictions"][1]["box"] == [150.0, 100.0, 80.0, 90.0]


def test_predict_text_and_code(model, image, capsys):
    assert main(["predict", str(model), str(image), "--box", "10,20,60,50", "--threads", "1"]) == 0
    text = capsys.readouterr().out
    assert "box 0" in text and "deg about" in text
    assert main(["predict", str(model), str(image), "--box", "10,20,60,50", "--json", "--code"]) == 0
    assert len(json.loads(capsys.readouterr().out)["predictions"][0]["code"]) == LAYOUT.size


def test_info(model, capsys):
    assert main(["info", str(model)]) == 0
    text = capsys.readouterr().out
    assert "population_code" in text and "162 axes x 12 angles" in text and "object 7" in text
    assert "discrete" in text
    assert main(["info", str(model), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["output_dim"] == LAYOUT.size and info["popcode.training"]["dataset"] == "cli-test"


def test_info_keeps_long_training_settings_to_json(capsys):
    shipped = Path(__file__).parents[2] / "models" / "builtin-parts-3-6.onnx"
    assert main(["info", str(shipped)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert all(len(line) <= 140 for line in lines), max(lines, key=len)
    config_line = next(line for line in lines if line.startswith("training.config"))
    assert "settings (data, " in config_line and "--json" in config_line
    assert main(["info", str(shipped), "--json"]) == 0
    assert "data" in json.loads(capsys.readouterr().out)["popcode.training"]["config"]


def test_info_of_a_detector_says_what_it_finds_and_how_it_was_trained(capsys):
    detector = Path(__file__).parents[2] / "models" / "builtin-parts-detector.onnx"
    assert main(["info", str(detector)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert all(len(line) <= 140 for line in lines), max(lines, key=len)
    assert "kind             detector (popcode detect, popcode run --detector, popcode predict --detector)" in lines
    assert "objects          1, 2, 3, 4, 5, 6" in lines and "input            384x288 grey frame" in "\n".join(lines)
    config_line = next(line for line in lines if line.startswith("training.config"))
    assert "settings (input_width, " in config_line and ", ..." in config_line and "--json" in config_line
    # what it began from, which weights it carries, its epochs (the snapshot shipped) and its revision
    assert "first weights    random weights (detector.init 'none')" in lines
    assert "training.weights  moving average of the steps" in lines and "training.epochs   30" in lines
    assert ("training.git_revision 191ba4824a0c595af0e651d68a94945351715d6c+dirty (exported from a tree with "
            "uncommitted changes beside that commit)") in lines
    assert main(["info", str(detector), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "detector" and info["obj_ids"] == [1, 2, 3, 4, 5, 6]
    assert info["training"]["config"]["input_width"] == info["input"]["width"] == 384


def test_info_of_a_detector_names_the_start_it_was_trained_from(tmp_path, capsys):
    from onnx_models import fixed_detector

    from popcode_runtime.model.detector_metadata import DetectorMetadata

    start = "the shipped detector start detector-start-e855fe97f1.pt (200 generated parts)"
    for training, first in (({"first_weights": start, "git_revision": "abc"}, start), ({}, "not recorded")):
        metadata = DetectorMetadata(obj_ids=(1,), input_width=64, input_height=48, training=training)
        path = save(fixed_detector(np.zeros((1, 4), np.float32), np.zeros((1, 1), np.float32), metadata),
                    tmp_path / "det.onnx")
        assert main(["info", str(path)]) == 0
        lines = capsys.readouterr().out.splitlines()
        assert f"first weights    {first}" in lines and not any("training.first_weights" in line for line in lines)


def test_bench_json(model, capsys):
    assert main(["bench", str(model), "--batch", "1", "--batch", "4", "--iterations", "3", "--warmup", "1",
                 "--threads", "1", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    rows = {(r["stage"], r["batch"]) for r in report["results"]}
    assert rows == {("end-to-end", 1), ("inference", 1), ("end-to-end", 4), ("inference", 4)}
    for row in report["results"]:
        assert 0 < row["median_ms"] <= row["p90_ms"] <= row["p99_ms"]
        assert row["iterations"] == 3
    assert report["machine"]["cores"] >= 1


@pytest.mark.parametrize(
    "argv_tail,message",
    [
        (["--box", "1000,1000,10,10"], "wholly outside"),
        (["--box", "10,10,0,10"], "empty"),
        (["--box", "10,10,20,20", "--K", "1,2,3"], "camera matrix"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(model, image, capsys, argv_tail, message):
    assert main(["predict", str(model), str(image), *argv_tail]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and err.startswith("popcode: error:")


def test_bad_files_are_one_line(tmp_path, model, image, capsys):
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x00garbage")
    assert main(["info", str(junk)]) == 2
    assert "cannot load" in capsys.readouterr().err
    text_file = tmp_path / "notes.png"
    text_file.write_text("hello")
    assert main(["predict", str(model), str(text_file), "--box", "1,1,5,5"]) == 2
    assert "cannot read image" in capsys.readouterr().err


def test_malformed_box_is_a_usage_error(model, image, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["predict", str(model), str(image), "--box", "1,2,3"])
    assert exit_info.value.code == 2
    assert "needs 4 numbers" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["predict", "info", "bench"])
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    assert "usage: popcode " + command in capsys.readouterr().out
