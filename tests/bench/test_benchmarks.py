"""Smoke tests of the benchmarks and the budget curve, run as a user runs them at tiny sizes: the JSON contract and
the table rows; never timings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from onnx_models import linear_model, save
from user_commands import run_module

from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.geometry.rotations import random_rotations
from popcode_runtime.geometry.symmetries import symmetry_rotations
from popcode_runtime.model.metadata import ModelMetadata, Representation
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.hull import HULL_POINTS
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from tools.toy_task import BORDER, IMAGE_SIZE, PAPER, PERIOD_DEG, shape_polygons, square_symmetry

LATENCY_FIELDS = {"variant", "network", "batch", "threads", "stage", "median_ms", "p90_ms", "p99_ms", "floor_ms",
                  "compute_floor_ms"}
QUANTISED = {"int8-static", "nbits4", "nbits8"}  # the quantised variants bench.latency measures beside fp32
LATENCY_BATCHES = {1, 8, 32}
HULL, CORNERS = f"{HULL_POINTS} hull points", "3-D box corners"  # the points bench.translation fits
TRANSLATION_ROWS = (f"{HULL}, rendered box", f"{CORNERS}, rendered box", f"{HULL}, exact box")


def test_latency_writes_the_contract(tmp_path: Path) -> None:
    run_module("bench.latency", "--quick", "--networks", "tiny", "--out", tmp_path)
    payload = json.loads((tmp_path / "latency.json").read_text(encoding="utf-8"))
    assert {"cpu", "cores", "onnxruntime", "torch"} <= set(payload["machine"])
    records = payload["records"]
    for record in records:
        assert set(record) >= LATENCY_FIELDS
        assert record["stage"] in ("end-to-end", "inference")
        assert ("argmax_agreement" in record) == (record["variant"] in QUANTISED)
        assert ("pose_agreement" in record) == (record["variant"] in QUANTISED)
        if "pose_agreement" in record:  # the same argmax is the same pose
            assert 0.0 <= record["argmax_agreement"] <= record["pose_agreement"] <= 1.0
    variants = {r["variant"] for r in records}
    assert variants == {"fp32", "torch-eager", *QUANTISED}
    assert {r["batch"] for r in records} == LATENCY_BATCHES
    assert any(r["threads"] == 1 for r in records)
    # Every runtime variant has both stages at every batch; torch eager has inference only.
    runtime_rows = [r for r in records if r["variant"] != "torch-eager"]
    assert len(runtime_rows) == 4 * len(LATENCY_BATCHES) * 2 * len({r["threads"] for r in records})
    assert all({"output_layer_share", "conv_share"} <= set(r) for r in runtime_rows
               if r["batch"] == 1 and r["stage"] == "inference")
    assert set(payload["gemm_peak_gmac_s"]) == {f"{t} {kind}" for t in {r["threads"] for r in records}
                                               for kind in ("fp32", "int8")}
    assert set(payload["networks"][0]["decode_ms"]) == {"argmax", "refined"}
    table = (tmp_path / "latency.md").read_text(encoding="utf-8")
    summary_rows = len(QUANTISED) + 2  # batch 1, 1 thread: fp32, the quantised variants, torch eager
    assert sum(line.startswith("| tiny |") for line in table.splitlines()) == summary_rows + len(records) + 1


def test_toy_orientation_has_every_row_of_table_one(tmp_path: Path) -> None:
    run_module("bench.toy_orientation", "--quick", "--jobs", "2", "--out", tmp_path)  # also the process pool
    payload = json.loads((tmp_path / "toy_orientation.json").read_text(encoding="utf-8"))
    records = payload["records"]
    for record in records:
        assert {"dataset", "method", "mean", "std", "runs"} <= set(record)
        assert record["runs"] == 1
    rows = {(r["dataset"], r["method"]) for r in records}
    assert set(PAPER) <= rows  # every row the paper reports
    assert {("arrows", "Population Code refined"), ("bars", "Population Code (Sym) refined")} <= rows
    assert ("arrows", "Population Code (Sym)") not in rows  # the paper's N/A
    table = (tmp_path / "toy_orientation.md").read_text(encoding="utf-8")
    for method in {m for _, m in rows}:
        assert f"| {method} |" in table


def test_toy_shapes_lie_inside_the_image_pointing_at_their_angle() -> None:
    # An arrow whose head leaves the image is a bar: no network can tell its direction.
    rng = np.random.default_rng(0)
    size, border = IMAGE_SIZE, BORDER
    for kind in PERIOD_DEG:
        for angle in rng.uniform(0.0, 2.0 * np.pi, size=300):
            polygons = shape_polygons(kind, angle, rng)
            points = np.concatenate(polygons)
            assert points.min() >= border and points.max() <= size - border
            if kind == "arrows":  # the head's tip lies along the angle (y up) from the shaft's centre
                direction = polygons[1][0] - polygons[0].mean(axis=0)
                assert np.isclose(np.arctan2(-direction[1], direction[0]) % (2 * np.pi), angle, atol=1e-9)


def test_square_symmetries_move_the_angle_with_the_image() -> None:
    # One lit pixel: its direction from the image centre (y up) is its angle, before and after every symmetry.
    size = IMAGE_SIZE
    image = np.zeros((1, 1, size, size), np.float32)
    image[0, 0, 10, 50] = 1.0

    def pixel_angle(picture: np.ndarray) -> float:
        row, column = np.argwhere(picture[0, 0])[0]
        centre = (size - 1) / 2.0
        return float(np.arctan2(centre - row, column - centre) % (2 * np.pi))

    angle, seen = np.array([pixel_angle(image)]), set()
    for quarter_turns in range(4):
        for mirror in (False, True):
            moved, angles = square_symmetry(image, angle, quarter_turns, mirror)
            assert moved.flags.c_contiguous and moved.shape == image.shape
            assert np.isclose(np.angle(np.exp(1j * (pixel_angle(moved) - angles[0]))), 0.0, atol=1e-12)
            seen.add(round(float(angles[0]), 9))
    assert len(seen) == 8  # eight different views


def test_translation_compares_hull_points_with_box_corners(tmp_path: Path) -> None:
    run_module("bench.translation", "--quick", "--out", tmp_path)
    payload = json.loads((tmp_path / "translation-quick.json").read_text(encoding="utf-8"))
    assert {"cpu", "cores", "onnxruntime", "torch"} <= set(payload["machine"])
    rows = payload["translation"]
    assert list(rows) == list(TRANSLATION_ROWS) and payload["settings"]["instances"] == 18
    hull, corners, exact = (rows[row] for row in TRANSLATION_ROWS)
    assert hull["median_te_percent"] < corners["median_te_percent"]  # corners lie outside the silhouette
    assert exact["median_te_percent"] < hull["median_te_percent"]  # pixel rounding is the larger error
    assert sorted(payload["per_object"][TRANSLATION_ROWS[0]]) == ["1", "2", "3", "4", "5", "6"]
    assert list(payload["full_pose_groups"]) == [HULL, CORNERS]
    table = (tmp_path / "translation-quick.md").read_text(encoding="utf-8")
    assert all(f"| {row} |" in table for row in TRANSLATION_ROWS)


def test_agreement_counts_symmetric_swaps_as_the_same_pose_per_object(tmp_path: Path) -> None:
    # Constant-output models: the reference encodes R0, the other R0 S with S a symmetry of object 3 but
    # not of object 6, so crops of 3 agree on the pose (not the argmax) and crops of 6 agree on neither.
    split = render_builtin_split(tmp_path / "split", 2, obj_ids=[3, 6], random_position=True)
    models_info = load_models_info(split / BUILTIN_MODELS_FOLDER)
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE, code=CodeLayout(n_axes=162, n_angles=12),
                             objects={3: models_info[3], 6: models_info[6]}, input_size=128)
    code = PopulationCode(metadata.code)
    R0 = random_rotations(1, np.random.default_rng(0))[0]
    S = symmetry_rotations(models_info[3])[1]
    reference = save(linear_model(code.encode(R0), metadata=metadata), tmp_path / "float.onnx")
    swapped = save(linear_model(code.encode(R0 @ S), metadata=metadata), tmp_path / "swapped.onnx")
    run_module("bench.agreement", reference, reference, swapped, "--split", split, "--out", tmp_path)
    records = json.loads((tmp_path / "agreement.json").read_text(encoding="utf-8"))["records"]
    by_row = {(r["model"], r["obj_id"]): r for r in records}
    assert {key[1] for key in by_row} == {"all", 3, 6} and by_row["float.onnx", "all"]["crops"] == 4
    assert all(by_row["float.onnx", obj][name] == 1.0 for obj in ("all", 3, 6)
               for name in ("argmax_agreement", "pose_agreement"))
    assert by_row["swapped.onnx", 3]["argmax_agreement"] == 0.0 and by_row["swapped.onnx", 3]["pose_agreement"] == 1.0
    assert by_row["swapped.onnx", 6]["pose_agreement"] == 0.0 and by_row["swapped.onnx", "all"]["pose_agreement"] == 0.5
    assert (tmp_path / "agreement.md").read_text(encoding="utf-8").count("| swapped.onnx |") == 3


@pytest.mark.parametrize(("flags", "chosen"), [(frozenset(), "eager-nchw-fp32"),
                                               (frozenset({"avx512_bf16"}), "eager-nchw-bf16")])
def test_training_throughput_smoke(flags: frozenset[str], chosen: str, tmp_path: Path) -> None:
    # 30 images a part leave 108 training crops of parts 3-6, the 96 that --quick's batches need; the bench's 2000
    # would render 12000 images for rows this test only checks the shape of. The path is chosen as on a CPU
    # without / with native bf16; a process of its own starts with the C library's allocator defaults.
    run_module("bench.training", "--quick", "--images", "30", "--networks", "tiny", "--threads", "1", "--workers",
               "0", "1", "--paths", "eager-nchw-fp32", "eager-cl-bf16", "--out", tmp_path, cpu_flags=flags)
    payload = json.loads((tmp_path / "training.json").read_text(encoding="utf-8"))
    rows = payload["rows"]
    assert payload["arguments"].startswith("--quick --images 30 ")
    parts = [(r["part"], r["workers"]) for r in rows]
    assert parts == [("data", 0), ("data", 1), ("forward_backward", None), ("optimizer", None),
                     ("path: eager-nchw-fp32", None), ("path: eager-cl-bf16", None),
                     (f"path: {chosen}", None), ("step", 0), ("step", 1), ("loop", 0)]
    # the chosen path again once freed memory is kept, as training runs; the plain rows before it with the defaults
    assert [r["memory_kept"] for r in rows] == [False] * 6 + [True] * 4
    loop = rows[-1]  # the training loop itself; --quick: two epochs, the second beside a plain eager step
    assert len(loop["epoch_crops_per_s"]) == len(loop["plain_crops_per_s"]) == 1
    assert loop["vs_plain_eager"] == pytest.approx(loop["epoch_crops_per_s"][0] / loop["plain_crops_per_s"][0])
    assert loop["crops_per_s"] == pytest.approx(loop["epoch_crops_per_s"][0])
    assert all(not r["fell_back"] and r["first_s"] > 0 for r in rows if r["part"].startswith("path"))
    assert all("NCHW" in r["path"] for r in rows if r["part"] == "step")  # tiny widths of 4: NCHW (fast_path)
    assert all(r["network"] == "tiny" and r["threads"] == 1 and r["crops_per_s"] > 0 for r in rows)
    table = (tmp_path / "training.md").read_text(encoding="utf-8")
    assert sum(line.startswith("| tiny |") for line in table.splitlines()) == len(rows)
    assert "cpu_flags" in payload["machine"]


TINY_RECIPE = ["--set", "network.conv_channels=[4, 4, 4]", "--set", "network.squeeze_channels=2",
               "--set", "network.hidden=[16, 16, 16]", "--set", "code.n_axes=42", "--set", "code.n_angles=12",
               "--set", "code.sigma_from_symmetries=false", "--set", "train.batch_size=8"]


def test_budget_curve_extends_one_run_and_resumes_from_its_scored_points(tmp_path: Path) -> None:
    args = ["--config", "trainer/configs/quick.toml", *TINY_RECIPE, "--images", "10", "--obj-ids", "3", "6",
            "--work", str(tmp_path / "work"), "--out", str(tmp_path), "--name", "tiny"]

    def curve(*epochs: str) -> list[dict]:
        """The points of ``python -m experiments.budget_curve ... --epochs EPOCHS``, as its results file holds them."""
        run_module("experiments.budget_curve", *args, "--epochs", *epochs)
        return json.loads((tmp_path / "budget-tiny.json").read_text(encoding="utf-8"))["points"]

    first = curve("1", "2")
    assert [p["epochs"] for p in first] == [1, 2]
    # The second point continued the first run: twice the crops, more seconds.
    assert first[1]["crop_updates"] == 2 * first[0]["crop_updates"] > 0
    assert first[1]["training_s"] > first[0]["training_s"]
    for point in first:
        assert set(point["mssd_per_object"]) == {"3", "6"}
        assert 0.0 <= point["mssd"] <= 1.0
        assert point["mssd_without_ambiguity"] == point["mssd_per_object"]["6"]  # part 6 has no symmetry
    again = curve("1", "2", "3")
    assert again[:2] == first  # scored points are kept, not retrained
    assert again[2]["crop_updates"] == 3 * first[0]["crop_updates"]
    assert "cpu_flags" in json.loads((tmp_path / "budget-tiny.json").read_text(encoding="utf-8"))["machine"]
    table = (tmp_path / "budget-tiny.md").read_text(encoding="utf-8").splitlines()
    assert [line.split("|")[1].strip() for line in table if line.startswith("| ") and line[2].isdigit()] == \
        ["1", "2", "3"]
    assert curve("2") == [first[1]]  # a scored budget alone: no training


def test_scene_render_prints_speed_and_visibility_and_writes_the_picture(tmp_path: Path) -> None:
    picture = tmp_path / "scene.jpg"
    printed = run_module("bench.scene_render", "--scenes", "2", "--size", "64", "48", "--picture", picture).stdout
    payload = json.loads(printed)
    assert payload["scenes"] == 2 and payload["instances"] > 0 and payload["scenes_per_s"] > 0
    assert sum(payload["instances_per_visibility_bin"].values()) == payload["instances"]
    assert picture.is_file() and picture.stat().st_size > 0
