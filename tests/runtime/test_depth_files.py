"""Issue 50: depth files as they come — torn, damaged, with alpha, or without their depth_scale — each end in one
line of popcode's own, never libpng's words beside it, and a split's missing depth_scale is not taken as 1."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hostile_cases import GOOD_K, IMAGE_SHAPE
from hostile_files import write_hostile_files

from popcode_runtime import PopcodeError, read_image
from popcode_runtime.bop.split import split_images
from popcode_runtime.commands.cli import main
from popcode_runtime.depth.surface_fit import read_depth


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_hostile_files(tmp_path_factory.mktemp("depth_files"))


def _scaled_split(folder: Path, tmp_path: Path, depth_png: str) -> Path:
    """The catalogue's one-image split with its depth_scale, and ``depth_png`` as its depth image."""
    split = tmp_path / "split"
    shutil.copytree(folder / "split_unscaled", split)
    camera = split / "000001" / "scene_camera.json"
    camera.write_text(json.dumps({"0": {**json.loads(camera.read_text())["0"], "depth_scale": 1.0}}))
    shutil.copyfile(folder / depth_png, split / "000001" / "depth" / "000000.png")
    return split


@pytest.mark.parametrize(("depth_png", "problem"), [("depth_torn.png", "ends before its IEND chunk"),
                                                    ("depth_damaged.png", "chunk 'IDAT' fails its CRC")])
def test_a_broken_depth_png_is_one_line_on_the_terminal(folder: Path, tmp_path: Path, capfd, depth_png: str,
                                                        problem: str) -> None:
    """libpng writes its own "Read Error" to file descriptor 2, which no OpenCV log level silences."""
    capfd.readouterr()
    assert main(["predict", str(folder / "depth_model.onnx"), str(folder / "scene.png"), "--box", "20,20,60,50",
                 "--K", GOOD_K, "--depth", str(folder / depth_png)]) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and err.startswith("popcode: error: cannot read depth image") and problem in err, err

    split = _scaled_split(folder, tmp_path, depth_png)
    assert main(["run", str(folder / "depth_model.onnx"), "--split", str(split), "--gt-boxes", "--depth", "--out",
                 str(tmp_path / "results.csv"), "--quiet"]) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and "cannot read depth image" in err and problem in err, err


def test_png_chunks_are_walked_to_IEND_and_no_further(folder: Path, tmp_path: Path) -> None:
    depth_png = (folder / "depth.png").read_bytes()
    end = depth_png.index(b"IEND") - 4  # where the IEND chunk begins: every chunk before it is whole
    (tmp_path / "no_iend.png").write_bytes(depth_png[:end])
    with pytest.raises(PopcodeError, match="ends before its IEND chunk"):
        read_depth(tmp_path / "no_iend.png")
    depth = np.random.default_rng(3).integers(0, 65536, size=IMAGE_SHAPE, dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "trailing.png"), depth)
    with open(tmp_path / "trailing.png", "ab") as handle:
        handle.write(b"not a chunk")  # libpng ignores what follows IEND
    found = read_depth(tmp_path / "trailing.png")
    assert found.dtype == np.uint16 and np.array_equal(found, depth)
    (tmp_path / "scene_torn.png").write_bytes((folder / "scene.png").read_bytes()[:-20])
    with pytest.raises(PopcodeError, match="cannot read image .*ends before its IEND chunk"):
        read_image(tmp_path / "scene_torn.png")


@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
def test_a_depth_image_with_alpha_is_told_its_four_channels(tmp_path: Path, dtype: type) -> None:
    """OpenCV's colour reading drops alpha: the 16-bit RGBA file was reported as 3 channels."""
    path = tmp_path / "depth.png"
    cv2.imwrite(str(path), np.full((*IMAGE_SHAPE, 4), 100, dtype))
    with pytest.raises(PopcodeError, match="has 4 channels; a depth image has one"):
        read_depth(path)


def test_a_split_tells_a_missing_depth_scale_from_one(folder: Path, tmp_path: Path) -> None:
    assert split_images(folder / "split_unscaled")[(1, 0)].depth_scale is None
    assert split_images(_scaled_split(folder, tmp_path, "depth.png"))[(1, 0)].depth_scale == 1.0
    assert split_images(folder / "split_other_camera")[(1, 0)].depth_scale == 1.0


def test_popcode_run_depth_refuses_a_missing_depth_scale_before_any_work(folder: Path, tmp_path: Path,
                                                                        capsys) -> None:
    out = tmp_path / "out" / "results.csv"
    out.parent.mkdir()
    argv = ["run", str(folder / "depth_model.onnx"), "--gt-boxes", "--out", str(out), "--quiet", "--depth"]
    assert main([*argv, "--split", str(folder / "split_unscaled")]) == 2
    err = capsys.readouterr().err
    assert "scene 1 image 0 has no 'depth_scale' in its scene_camera.json entry" in err, err
    assert list(out.parent.iterdir()) == []  # nothing written, no lock left
    assert main([*argv, "--split", str(_scaled_split(folder, tmp_path, "depth.png"))]) == 0  # with it, the run runs
    assert len(out.with_name("results.translation.csv").read_text().splitlines()) == 2
