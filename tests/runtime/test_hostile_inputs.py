"""Issue 19's catalogue: every hostile input ends in one clear line (exit 2 or ``PopcodeError``), never a traceback."""

from __future__ import annotations

import io
import json
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import onnx
import pytest
from hostile_cases import API_CASES, CLI_CASES, api_problem, cli_problem
from hostile_files import write_hostile_files

from popcode_runtime import PoseEstimator
from popcode_runtime.commands.cli import main
from popcode_runtime.geometry.rotations import geodesic_angle
from tools.fuzz import FuzzReport, UnhandledCallError, fuzz, read_cases, save_cases, try_call


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return write_hostile_files(tmp_path_factory.mktemp("hostile"))


def test_the_catalogue_has_at_least_100_cases():
    assert len(CLI_CASES) + len(API_CASES) >= 100
    assert len({case.id for case in CLI_CASES}) == len(CLI_CASES)
    assert len({case_id for case_id, _, _ in API_CASES}) == len(API_CASES)


@pytest.mark.parametrize("case", CLI_CASES, ids=lambda case: case.id)
def test_cli_refuses_in_one_line(case, folder):
    assert cli_problem(case, folder) is None


@pytest.mark.parametrize(("call", "expect"), [case[1:] for case in API_CASES], ids=[case[0] for case in API_CASES])
def test_api_raises_popcode_error(call, expect, folder):
    assert api_problem(call, expect, folder) is None


def test_leading_minus_values_are_read_as_numbers(folder, capsys):
    assert main(["predict", str(folder / "model.onnx"), str(folder / "scene.png"), "--box", "-50,8,66,58",
                 "--K", "-.5e3,500,80,60", "--json"]) == 2  # parsed: the K is refused for its value, not by argparse
    assert "focal lengths must be positive" in capsys.readouterr().err
    assert main(["predict", str(folder / "model.onnx"), str(folder / "scene.png"), "--box", "-50,8,66,58",
                 "--K", "500,500,80,60", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["predictions"][0]["box"] == [-50.0, 8.0, 66.0, 58.0]


@pytest.mark.parametrize("command", [["info", "{folder}/model.onnx", "--json"], ["info", "{folder}/model.onnx"],
                                     ["predict", "{folder}/model.onnx", "{folder}/scene.png", "--box", "1,2,30,40",
                                      "--json"]], ids=["info-json", "info", "predict-json"])
def test_broken_pipe_is_quiet(command, folder, monkeypatch, capsys):
    """``popcode ... | head``: the reader left, so the command stops without a traceback (exit 141, as SIGPIPE)."""
    class ClosedPipe(io.StringIO):
        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr("sys.stdout", ClosedPipe())
    assert main([part.replace("{folder}", str(folder)) for part in command]) == 141
    assert capsys.readouterr().err == ""


def test_one_estimator_shared_by_eight_threads_gives_the_serial_answers(folder):
    """The runtime README promises that one PoseEstimator may serve several Python threads."""
    estimator = PoseEstimator(folder / "model.onnx", threads=1)
    image = cv2.imread(str(folder / "scene.png"), cv2.IMREAD_GRAYSCALE)
    boxes = np.random.default_rng(8).uniform([0, 0, 10, 10], [120, 90, 60, 50], size=(40, 4)).tolist()
    serial = [estimator.predict(image, [box], top_k=2)[0].R_m2c for box in boxes]  # the same calls, one thread

    def one_at_a_time(worker: int) -> list[tuple[int, np.ndarray]]:
        order = [(worker * 7 + step) % len(boxes) for step in range(25)]
        return [(k, estimator.predict(image, [boxes[k]], top_k=2)[0].R_m2c) for k in order]

    with ThreadPoolExecutor(max_workers=8) as pool:
        results = [pair for found in pool.map(one_at_a_time, range(8)) for pair in found]
    assert len(results) == 200
    assert all(np.array_equal(R, serial[k]) for k, R in results)


def test_fixed_batch_model_runs_in_chunks_of_its_batch(folder, tmp_path):
    model = onnx.load(str(folder / "model.onnx"))
    for value_info in (model.graph.input[0], model.graph.output[0]):
        value_info.type.tensor_type.shape.dim[0].dim_value = 1
    onnx.save(model, str(tmp_path / "batch1.onnx"))
    fixed, dynamic = PoseEstimator(tmp_path / "batch1.onnx", threads=1), PoseEstimator(folder / "model.onnx")
    assert fixed.chunk_size == 1
    image = cv2.imread(str(folder / "scene.png"), cv2.IMREAD_GRAYSCALE)
    boxes = [[10, 10, 40, 40], [60, 30, 50, 70], [100, 50, 30, 30]]
    for a, b in zip(fixed.predict(image, boxes), dynamic.predict(image, boxes), strict=True):
        np.testing.assert_allclose(a.R_m2c, b.R_m2c, atol=1e-6)
    assert main(["bench", str(tmp_path / "batch1.onnx"), "--batch", "4", "--iterations", "2", "--warmup", "0",
                 "--threads", "1", "--json"]) == 0


def test_many_boxes_are_chunked_not_failed(folder):
    estimator = PoseEstimator(folder / "model.onnx", threads=1)
    image = cv2.imread(str(folder / "scene.png"), cv2.IMREAD_GRAYSCALE)
    boxes = np.random.default_rng(1).uniform([0, 0, 5, 5], [100, 80, 60, 40], size=(1000, 4))
    predictions = estimator.predict(image, boxes)
    assert len(predictions) == 1000 and estimator.chunk_size < 1000
    R = np.stack([p.R_m2c for p in predictions])
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
    first = estimator.predict(image, boxes[:1])[0].R_m2c
    assert geodesic_angle(first, predictions[0].R_m2c) < 1e-6


def test_models_without_a_layout_digest_still_load(folder, tmp_path):
    model = onnx.load(str(folder / "model.onnx"))
    code = next(p for p in model.metadata_props if p.key == "popcode.code")
    assert "digest" in json.loads(code.value)
    code.value = json.dumps({k: v for k, v in json.loads(code.value).items() if k != "digest"})
    onnx.save(model, str(tmp_path / "old.onnx"))
    assert PoseEstimator(tmp_path / "old.onnx").metadata.code == PoseEstimator(folder / "model.onnx").metadata.code


def test_fuzzing_predict_finds_nothing_unhandled(folder):
    """Forty Hypothesis examples of random, mostly hostile, calls from a fixed seed: each returns valid rotations or
    raises PopcodeError; a call that hangs is cut off by the fuzz's own watchdog and counted as unhandled, so no
    duration is asserted here."""
    report = fuzz(PoseEstimator(folder / "model.onnx", threads=1), calls=40, seed=19)
    assert report.unhandled == [] and report.shrunk == []
    assert report.returned > 5 and report.refused > 5  # both paths exercised
    assert report.returned + report.refused == report.calls == 40  # every call came back, none was cut off


@pytest.mark.parametrize("case", read_cases(), ids=lambda case: str(sorted(case)))
def test_the_saved_shrunk_fuzz_failures_are_handled(case, folder):
    """Each call the fuzz once failed on, shrunk and saved in tests/fuzz_cases.json, replayed on a model of the same
    objects: it now returns valid rotations or refuses in one line."""
    try_call(PoseEstimator(folder / "model.onnx", threads=1), case, FuzzReport())


class _FailsOnColour:
    """An estimator with a planted bug: any colour image with more than one pixel raises a plain ValueError."""

    def __init__(self, metadata):
        self.metadata = metadata

    def predict(self, image, **arguments):
        if isinstance(image, np.ndarray) and image.ndim == 3 and image.shape[0] * image.shape[1] > 1:
            raise ValueError("planted")
        return []


def test_a_fuzz_failure_is_shrunk_saved_and_replayed(folder, tmp_path):
    """Hypothesis shrinks the planted bug's failing call to the smallest one (a 2-pixel image with channels, every other
    argument at its plainest); saved, it reads back equal and fails again when replayed."""
    buggy = _FailsOnColour(PoseEstimator(folder / "model.onnx").metadata)
    report = fuzz(buggy, calls=200, seed=19)
    assert report.unhandled == ["ValueError: planted"] and len(report.shrunk) == 1
    shrunk = report.shrunk[0]
    assert shrunk["image"].ndim == 3 and shrunk["image"].shape[0] * shrunk["image"].shape[1] == 2
    assert not shrunk["image"].any()
    assert {key: value for key, value in shrunk.items() if key != "image"} == {
        "boxes": [[0.0, 0.0, 2.0, 2.0]], "K": [100.0, 100.0, 0.0, 0.0], "translation": False, "return_code": False,
        "top_k": 1}  # each the first (plainest) choice of its strategy, the smallest box
    save_cases(report, "model.onnx", tmp_path / "cases.json")
    (replayed,) = read_cases(tmp_path / "cases.json")
    assert replayed.keys() == shrunk.keys() and replayed["image"].dtype == shrunk["image"].dtype
    np.testing.assert_array_equal(replayed["image"], shrunk["image"])
    with pytest.raises(UnhandledCallError, match="planted"):
        try_call(buggy, replayed, FuzzReport())


def test_the_fuzz_counts_a_call_that_hangs_as_unhandled(folder):
    """The watchdog that replaces a timer in the test above: a call still running at its limit is cut off and
    counted as unhandled, and Hypothesis shrinks it like any other failure."""
    class Hanging:
        metadata = PoseEstimator(folder / "model.onnx").metadata

        def predict(self, **arguments: object) -> None:
            time.sleep(60)  # far past the limit: the watchdog, not the sleep, ends the call

    report = fuzz(Hanging(), calls=3, seed=19, limit_s=0.05)
    assert report.returned == report.refused == 0 and report.calls >= 1
    assert report.unhandled == ["hang: still running after 0.05 s"]
    assert report.shrunk[0]["image"].shape == (1, 1)  # the smallest call that hangs


def test_a_torn_image_is_one_line_on_the_terminal_too(folder, tmp_path, capfd):
    """OpenCV's decoders log their complaint to file descriptor 2 themselves, beside popcode's own line."""
    torn = tmp_path / "torn.png"
    torn.write_bytes((folder / "scene.png").read_bytes()[:30])  # the signature and half of the first chunk
    capfd.readouterr()
    assert main(["predict", str(folder / "model.onnx"), str(torn), "--box", "1,2,30,40"]) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and err.startswith("popcode: error: cannot read image"), err
