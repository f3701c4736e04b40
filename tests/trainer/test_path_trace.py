"""``popcode-train path-trace``: a rendered split seen by Mitsuba's path tracer, paired with the rendered one
instance by instance (same silhouettes, copied ground truth, same sensor draw), resumed, and refused in one line."""

from __future__ import annotations

import io
import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hostile_cases import error_lines, refused_in_one_line, run_cli

from popcode_runtime.base.errors import PopcodeError
from popcode_trainer.cli import main as trainer
from popcode_trainer.data.path_trace import PathTraceSettings
from popcode_trainer.data.path_traced_split import path_trace_split
from popcode_trainer.data.render import RECORDS_FOLDER
from popcode_trainer.demo.steps import (
    PipelineSize,
    render_splits,
    scene_split_of,
    small_config,
    traced_split_of,
    training_config,
)

SAMPLES = ["--samples", "4"]


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A clean split (two images a part) and a small bin split with the industrial camera's effects."""
    root = tmp_path_factory.mktemp("path_trace")
    assert trainer(["render", "--objects", "builtin", "--out", str(root / "clean"), "--images", "2", "--seed", "3",
                    "--quiet"]) == 0
    assert trainer(["render", "--objects", "builtin", "--out", str(root / "bin"), "--scenes", "3", "--size", "160",
                    "120", "--seed", "3", "--sensor", "industrial", "--quiet"]) == 0
    return {"clean": root / "clean", "bin": root / "bin", "root": root}


@pytest.fixture(scope="module")
def traced(rendered: dict[str, Path]) -> dict[str, Path]:
    out = {}
    for name in ("clean", "bin"):
        out[name] = rendered["root"] / f"{name}_traced"
        assert trainer(["path-trace", "--split", str(rendered[name]), "--out", str(out[name]), *SAMPLES,
                        "--quiet"]) == 0
    return out


def _images(split: Path) -> list[Path]:
    return sorted(split.glob("*/gray/*.png"))


@pytest.mark.slow
def test_a_part_is_traced_where_the_rasteriser_drew_it(rendered: dict[str, Path], traced: dict[str, Path]) -> None:
    """On black, the path-traced part covers the rendered silhouette: camera, pose and pixel centres agree (a
    mirrored camera fails the overlap; a principal point off by half a pixel, the centroid)."""
    images = _images(traced["clean"])
    assert len(images) == 12
    for image_path in images:
        mask_path = rendered["clean"] / image_path.parents[1].name / "mask_visib" / f"{image_path.stem}_000000.png"
        traced_image = cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE)
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) > 0
        drawn = traced_image > 0
        overlap = (drawn & mask).sum() / (drawn | mask).sum()
        centroid_shift = np.array(np.nonzero(drawn)).mean(axis=1) - np.array(np.nonzero(mask)).mean(axis=1)
        assert overlap > 0.9 and np.abs(centroid_shift).max() < 0.4, (image_path, overlap, centroid_shift)
        rasterised = cv2.imread(str(rendered["clean"] / image_path.relative_to(traced["clean"])), cv2.IMREAD_GRAYSCALE)
        assert not np.array_equal(traced_image, rasterised)


def test_the_ground_truth_is_copied_so_scores_pair_up(rendered: dict[str, Path], traced: dict[str, Path]) -> None:
    for name in ("clean", "bin"):
        source, out = rendered[name], traced[name]
        for table in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"):
            for path in source.glob(f"*/{table}"):
                assert json.loads((out / path.relative_to(source)).read_text()) == json.loads(path.read_text())
        copied = sorted(path.relative_to(source) for path in source.glob("*/mask_visib/*.png"))
        assert copied and copied == sorted(path.relative_to(out) for path in out.glob("*/mask_visib/*.png"))
        settings = json.loads((out / "popcode_render.json").read_text())
        assert settings["path_traced"] == {"samples": 4, "max_depth": 6, "seed": 0}
        assert (out / "models" / "models_info.json").is_file()


def test_a_bin_is_replayed_with_its_walls_distractors_and_sensor(rendered: dict[str, Path],
                                                                  traced: dict[str, Path]) -> None:
    """The bin's world is drawn again, not only its parts: the traced frame shows no black where the rendered one
    shows floor and walls, and both carry the camera's grain."""
    for image_path in _images(traced["bin"]):
        traced_image = cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        assert traced_image.shape == (120, 160)
        assert (traced_image < 3).mean() < 0.2  # black would mean an empty world behind the parts
        assert np.abs(np.diff(traced_image, axis=1)).mean() > 1.0  # sensor noise and render noise


def test_bins_without_parts_are_traced_too(tmp_path: Path) -> None:
    """A split of emptied bins (``--empty-share``: a detector's negatives, one with its distractors, one bare) is
    replayed from its camera, not refused for holding no part: the traced frames show the bin, no instance."""
    source, out = tmp_path / "empty", tmp_path / "empty_traced"
    assert trainer(["render", "--objects", "builtin", "--out", str(source), "--scenes", "2", "--size", "160", "120",
                    "--seed", "5", "--empty-share", "1", "--quiet"]) == 0
    assert trainer(["path-trace", "--split", str(source), "--out", str(out), "--samples", "2", "--quiet"]) == 0
    images = _images(out)
    assert len(images) == 2
    for image_path in images:
        assert (cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE) < 3).mean() < 0.2
    assert all(not gt for gt in json.loads((out / "000000" / "scene_gt.json").read_text()).values())
    record = source / "000000" / RECORDS_FOLDER / "000001.json"
    edited = json.loads(record.read_text())
    del edited["scene_camera"]["cam_t_w2c"]  # a record without its camera's pose: named, not a traceback
    record.write_text(json.dumps(edited))
    code, _, stderr = run_cli(["path-trace", "--split", str(source), "--out", str(tmp_path / "again"), "--samples",
                               "2", "--quiet"], trainer)
    assert refused_in_one_line(code, stderr, "scene 000000 image 000001 cannot be path traced")


@pytest.mark.slow
def test_an_interrupted_trace_resumes_with_what_is_missing(rendered: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "resumed"
    settings = PathTraceSettings(samples=2)
    assert path_trace_split(rendered["bin"], out, settings, progress=False).images == 3
    image = out / "000000" / "gray" / "000001.png"
    first = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    (out / "000000" / ".popcode_records" / "000001.json").unlink()  # as if stopped before its record was written
    again = path_trace_split(rendered["bin"], out, settings, progress=False)
    assert again.images == 1, again
    retraced = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    # The same scene, materials and lights: closer to the first trace than the same scene under other materials and
    # lights (look seed 1) is, once each pixel's render noise and grain are averaged over 21 x 21 (in a full suite
    # run, a retrace's 2-sample noise has differed from the first's, alone it has not).
    other = tmp_path / "other_look"
    path_trace_split(rendered["bin"], other, PathTraceSettings(samples=2, seed=1), progress=False)
    other_look = cv2.imread(str(other / "000000" / "gray" / "000001.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    same = np.abs(cv2.blur(retraced, (21, 21)) - cv2.blur(first, (21, 21))).mean()
    apart = np.abs(cv2.blur(other_look, (21, 21)) - cv2.blur(first, (21, 21))).mean()
    assert same < 0.5 * apart, (same, apart)
    assert json.loads((out / "000000" / "scene_gt.json").read_text()).keys() == {"0", "1", "2"}


def _refusal(argv: list[str], monkeypatch: pytest.MonkeyPatch) -> str:
    stderr = io.StringIO()
    monkeypatch.setattr("sys.stderr", stderr)
    assert trainer(argv) == 2
    lines = error_lines(stderr.getvalue())
    assert len(lines) == 1, stderr.getvalue()
    return lines[0]


def test_an_edited_scene_is_named_not_skipped(rendered: dict[str, Path], tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    source = tmp_path / "edited"
    shutil.copytree(rendered["bin"], source)
    record_path = source / "000000" / ".popcode_records" / "000002.json"
    record = json.loads(record_path.read_text())
    record["scene_gt"][0]["cam_t_m2c"][0] += 5.0
    record_path.write_text(json.dumps(record))
    line = _refusal(["path-trace", "--split", str(source), "--out", str(tmp_path / "out"), *SAMPLES, "--quiet"],
                    monkeypatch)
    assert "scene 000000 image 000002 cannot be path traced" in line and "recorded poses" in line
    assert (tmp_path / "out" / "000000" / ".popcode_records" / "000001.json").is_file()  # what came before is kept


@pytest.mark.parametrize(("case", "expect"), [
    ("not-a-split", "is not a split popcode rendered"),
    ("already-traced", "is already path traced"),
    ("other-models", "are not the ones"),
    ("samples-zero", "samples"),
    ("out-is-split", "is the input"),
    ("other-settings", "was rendered with other settings"),
])
def test_bad_input_is_refused_in_one_line(case: str, expect: str, rendered: dict[str, Path],
                                          traced: dict[str, Path], tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    split, out, extra = rendered["clean"], tmp_path / "out", []
    if case == "not-a-split":
        split = tmp_path / "plain"
        split.mkdir()
    elif case == "already-traced":
        split = traced["clean"]
    elif case == "other-models":
        split = tmp_path / "clean_other_models"
        shutil.copytree(rendered["clean"], split)
        info = split / "models" / "models_info.json"
        extra = ["--models-dir", str(info.parent)]
        models = json.loads(info.read_text())
        models["1"]["diameter"] *= 2.0
        info.write_text(json.dumps(models))
    elif case == "samples-zero":
        extra = ["--samples", "0"]
    elif case == "out-is-split":
        out = split
    elif case == "other-settings":
        out = traced["clean"]
        extra = ["--seed", "9"]
    line = _refusal(["path-trace", "--split", str(split), "--out", str(out), *SAMPLES, *extra, "--quiet"], monkeypatch)
    assert expect in line, line


def test_a_missing_renderer_says_what_to_install(rendered: dict[str, Path], tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # import mitsuba raises ImportError
    line = _refusal(["path-trace", "--split", str(rendered["clean"]), "--out", str(tmp_path / "out"), "--quiet"],
                    monkeypatch)
    assert "pip install mitsuba" in line and "'.[pathtrace]'" in line


def test_a_run_trains_on_a_share_of_path_traced_images(tmp_path: Path) -> None:
    """``traced_train_images`` renders further single parts and path traces them beside the training split;
    ``traced_share`` is their share of every epoch's crops, beside the scenes'."""
    size = PipelineSize(2, 1, small_config(epochs=1, n_axes=42, n_angles=12), ("population_code",),
                        train_scenes=1, scene_share=0.25, traced_train_images=1, traced_share=0.25)
    train_split, _ = render_splits(size, tmp_path, progress=False)
    traced = traced_split_of(train_split)
    assert len(list(traced.glob("*/gray/*.png"))) == 6
    assert json.loads((traced / "popcode_render.json").read_text())["path_traced"]["seed"] == 1  # not validation's
    config = training_config(size, "population_code", [1, 2], train_split, tmp_path / "run")
    assert config.data.splits == (str(train_split), str(traced), str(scene_split_of(train_split)))
    assert config.data.split_weights == (0.5, 0.25, 0.25)
    with pytest.raises(PopcodeError, match="traced_share must lie in"):
        PipelineSize(2, 1, size.config, traced_train_images=1, traced_share=0.0)
