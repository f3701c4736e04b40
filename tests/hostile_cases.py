"""The catalogue of hostile inputs (issue 19): each must end in one clear line, never a traceback or a hang.

Runtime-only on purpose (numpy and popcode_runtime): the runtime-only venv test
runs :data:`CLI_CASES` there too. The files the cases name are written by
``hostile_files.write_hostile_files`` (which needs onnx) into one folder; a
case's argv names them as ``{folder}/name``.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from symmetry_cases import CASES

from popcode_runtime import CodeLayout, ModelMetadata, PopcodeError, PoseEstimator, parse_camera_matrix, read_image
from popcode_runtime.coding.confidence import FEATURES, Calibrator
from popcode_runtime.commands.cli import main
from popcode_runtime.depth.surface_fit import read_depth
from popcode_runtime.geometry.crop import crop_square

LAYOUT = CodeLayout(n_axes=42, n_angles=12)
OBJECT = {**CASES["two_fold"], "hull_points_mm": [[x, y, z] for x in (-40, 40) for y in (-40, 40) for z in (-30, 30)]}
IMAGE_SHAPE = (120, 160)  # (H, W) of scene.png
GOOD_BOX = "20,20,60,50"
GOOD_K = "200,200,80,60"
# 16 surface points (the fewest a model may carry) and their outward normals, as an export writes them
SURFACE = [[x, y, z] for x in (-40, -10, 10, 40) for y in (-40, 40) for z in (-30, 30)]
NORMALS = (np.asarray(SURFACE) / np.linalg.norm(SURFACE, axis=1, keepdims=True)).tolist()
DEPTH_OBJECT = {**OBJECT, "surface_points_mm": SURFACE, "surface_normals": NORMALS}  # of depth_model.onnx
DEPTH_MM = 500  # every pixel of depth.png [mm at depth scale 1]


def _code(**changes: object) -> str:
    """``popcode.code`` JSON of LAYOUT with some fields changed (no digest: the form of older models)."""
    data = {k: v for k, v in LAYOUT.to_dict().items() if k != "digest"}
    data.update(changes)
    return json.dumps(data)


def _objects(**changes: object) -> str:
    return json.dumps({"7": {**OBJECT, **changes}})


def _confidence(**changes: object) -> str:
    calibrator = Calibrator(5.0, 10.0, [0.0] * len(FEATURES), 0.0)
    return json.dumps({**calibrator.to_dict(), **changes})


# name -> (metadata key, raw JSON text or None to delete the key, what the error line must say)
METADATA_CASES: dict[str, tuple[str, str | None, str]] = {
    "no_format_version": ("popcode.format_version", None, "not a popcode model"),
    "version_text": ("popcode.format_version", '"1"', "format version '1' is not supported"),
    "version_2": ("popcode.format_version", "2", "format version 2"),
    "version_true": ("popcode.format_version", "true", "format version True"),
    "no_code": ("popcode.code", None, "lacks 'popcode.code'"),
    "representation_unknown": ("popcode.representation", '"bogus"', "unknown representation"),
    "representation_number": ("popcode.representation", "5", "unknown representation"),
    "frame_unknown": ("popcode.rotation_frame", '"sideways"', "unknown rotation_frame"),
    "code_bad_json": ("popcode.code", "{", "'popcode.code' is not valid JSON"),
    "code_list": ("popcode.code", "[42, 12]", "'popcode.code' must be an object"),
    "n_axes_float": ("popcode.code", _code(n_axes=42.0), "code.n_axes must be an integer"),
    "n_axes_text": ("popcode.code", _code(n_axes="42"), "code.n_axes must be an integer"),
    "n_axes_huge": ("popcode.code", _code(n_axes=66_000_000), "code.n_axes must lie in"),
    "n_axes_negative": ("popcode.code", _code(n_axes=-1), "code.n_axes must lie in"),
    "n_axes_zero": ("popcode.code", _code(n_axes=0), "code.n_axes must lie in"),
    "n_axes_bool": ("popcode.code", _code(n_axes=True), "code.n_axes must be an integer"),
    "n_axes_null": ("popcode.code", _code(n_axes=None), "code.n_axes must be an integer"),
    "n_angles_huge": ("popcode.code", _code(n_angles=10**9), "code.n_angles must lie in"),
    "code_too_big": ("popcode.code", _code(n_axes=16384, n_angles=720), "exceeds the runtime's limit"),
    "sigma_text": ("popcode.code", _code(sigma_deg="20"), "code.sigma_deg must be a number"),
    "sigma_nan": ("popcode.code", _code(sigma_deg=20.0).replace("20.0", "NaN"), "NaN is not a JSON number"),
    "sigma_infinity": ("popcode.code", _code(sigma_deg=20.0).replace("20.0", "Infinity"), "Infinity is not a"),
    "n_axes_nan": ("popcode.code", _code(n_axes=float("nan")), "NaN is not a JSON number"),
    "n_angles_infinity": ("popcode.code", _code(n_angles=float("inf")), "Infinity is not a JSON number"),
    "sigma_zero": ("popcode.code", _code(sigma_deg=0), "sigma_deg must lie in (0, 180)"),
    "sigma_huge": ("popcode.code", _code(sigma_deg=500), "sigma_deg must lie in (0, 180)"),
    "axis_only_text": ("popcode.code", _code(axis_only="yes"), "code.axis_only must be true or false"),
    "lattice_unknown": ("popcode.code", _code(lattice="healpix"), "unknown lattice"),
    "code_unknown_key": ("popcode.code", _code(colour="red"), "unknown code layout keys"),
    "relabelled_with_digest": ("popcode.code", json.dumps({**LAYOUT.to_dict(), "n_axes": 84, "n_angles": 6}),
                               "checksum"),
    "relabelled_width": ("popcode.code", _code(n_axes=43), "values per crop"),
    "digest_wrong": ("popcode.code", json.dumps({**LAYOUT.to_dict(), "digest": "0123456789abcdef"}), "checksum"),
    "input_size_400_digits": ("popcode.input", json.dumps({"size": 10**400, "crop_padding": 0.2}),
                              "an integer of 401 digits"),
    "diameter_overflows": ("popcode.objects", _objects(diameter=1.0).replace("1.0", "1e400"), "overflows a float"),
    "object_id_30_digits": ("popcode.objects", json.dumps({"1" * 30: OBJECT}), "not a whole number of at most 18"),
    "confidence_fitted_on_text": ("popcode.confidence", _confidence(fitted_on="T-LESS"), "fitted_on must be an"),
    "confidence_fitted_on_pairs": ("popcode.confidence", _confidence(fitted_on=[["split", "x"]]),
                                   "fitted_on must be an"),
    "confidence_weight_400_digits": ("popcode.confidence", _confidence(bias=10**400), "an integer of 401 digits"),
    "objects_text": ("popcode.objects", '"abc"', "'popcode.objects' must be an object"),
    "objects_empty": ("popcode.objects", "{}", "lists no objects"),
    "object_text": ("popcode.objects", '{"7": "abc"}', "object 7 must be an object"),
    "object_list": ("popcode.objects", '{"7": [1, 2]}', "object 7 must be an object"),
    "object_id_word": ("popcode.objects", json.dumps({"x": OBJECT}), "object id 'x' is not a whole number"),
    "object_id_negative": ("popcode.objects", json.dumps({"-1": OBJECT}), "object id '-1' is not a whole number"),
    "diameter_text": ("popcode.objects", _objects(diameter="big"), "diameter must be a number"),
    "diameter_negative": ("popcode.objects", _objects(diameter=-5), "diameter must lie in"),
    "symmetries_text": ("popcode.objects", _objects(symmetries_discrete="abc"), "symmetries_discrete must be a list"),
    "symmetry_short": ("popcode.objects", _objects(symmetries_discrete=[[1, 2, 3]]), "has 3 numbers"),
    "symmetry_words": ("popcode.objects", _objects(symmetries_discrete=[["a"] * 16]), "not a list of numbers"),
    "symmetry_not_rotation": ("popcode.objects", _objects(symmetries_discrete=[[2.0] * 16]), "not a proper rotation"),
    "symmetry_huge_list": ("popcode.objects", _objects(symmetries_discrete=[[1.0] * 16] * 1001), "at most 1000"),
    "continuous_zero_axis": ("popcode.objects", _objects(symmetries_continuous=[{"axis": [0, 0, 0]}]), "zero"),
    "continuous_text": ("popcode.objects", _objects(symmetries_continuous=["abc"]), "needs 'axis' and 'offset'"),
    "continuous_not_list": ("popcode.objects", _objects(symmetries_continuous={"axis": [0, 0, 1]}), "must be a list"),
    "hull_identical": ("popcode.objects", _objects(hull_points_mm=[[1, 2, 3]] * 8), "degenerate"),
    "hull_flat": ("popcode.objects", _objects(hull_points_mm=[[x, y, 0] for x in (0, 1) for y in (0, 1)]),
                  "degenerate"),
    "hull_short": ("popcode.objects", _objects(hull_points_mm=[[0, 0, 0]]), "at least 4 finite points"),
    "hull_words": ("popcode.objects", _objects(hull_points_mm="abc"), "at least 4 finite points"),
    "extents_text": ("popcode.objects", json.dumps({"7": {**CASES["two_fold"], "size_x": "big"}}),
                     "size_x must be a number"),
    "diameter_nan": ("popcode.objects", _objects(diameter=float("nan")), "NaN is not a JSON number"),
    "input_size_nan": ("popcode.input", '{"size": NaN, "crop_padding": 1.1}', "NaN is not a JSON number"),
    "input_text": ("popcode.input", '"128"', "'popcode.input' must be an object"),
    "input_size_float": ("popcode.input", '{"size": 127.5, "crop_padding": 1.1}', "input size must be an integer"),
    "input_size_huge": ("popcode.input", '{"size": 100000, "crop_padding": 1.1}', "input size must lie in"),
    "input_size_tiny": ("popcode.input", '{"size": 4, "crop_padding": 1.1}', "input size must lie in"),
    "padding_negative": ("popcode.input", '{"size": 128, "crop_padding": -1}', "crop_padding must lie in"),
    "padding_text": ("popcode.input", '{"size": 128, "crop_padding": "1.1"}', "crop_padding must be a number"),
    "padding_huge": ("popcode.input", '{"size": 128, "crop_padding": 100}', "crop_padding must lie in"),
    "padding_nan": ("popcode.input", '{"size": 128, "crop_padding": NaN}', "NaN is not a JSON number"),
    "hypotheses_negative": ("popcode.num_hypotheses", "-3", "num_hypotheses must lie in"),
    "hypotheses_text": ("popcode.num_hypotheses", '"2"', "num_hypotheses must be an integer"),
    "hypotheses_missing": ("popcode.representation", '"multi_hypothesis"', "needs num_hypotheses >= 1"),
    "training_text": ("popcode.training", '"abc"', "training must be an object"),
    "deep_json": ("popcode.training", "[" * 100_000 + "]" * 100_000, "'popcode.training' nests JSON too deeply"),
    "axis_only_mismatch": ("popcode.code", _code(axis_only=True, symmetry_axis=[0, 0, 1]),
                           "axis_only must be true exactly when"),
    "surface_short": ("popcode.objects", _objects(surface_points_mm=SURFACE[:15], surface_normals=NORMALS[:15]),
                      "surface_points_mm must be a list of 16 to 512"),
    "surface_too_many": ("popcode.objects", _objects(surface_points_mm=SURFACE * 33, surface_normals=NORMALS * 33),
                         "surface_points_mm must be a list of 16 to 512"),
    "surface_words": ("popcode.objects", _objects(surface_points_mm="abc", surface_normals=NORMALS),
                      "surface_points_mm must be a list"),
    "surface_normals_missing": ("popcode.objects", _objects(surface_points_mm=SURFACE),
                                "surface_normals must be 16 finite vectors"),
    "surface_normals_without_points": ("popcode.objects", _objects(surface_normals=NORMALS),
                                       "surface_points_mm must be a list"),
    "surface_normals_not_unit": ("popcode.objects", _objects(surface_points_mm=SURFACE,
                                                             surface_normals=[[0, 0, 2]] * 16), "unit vectors"),
    "surface_one_point": ("popcode.objects", _objects(surface_points_mm=[[1e6, -1e6, 3.0]] * 16,
                                                      surface_normals=NORMALS), "surface_points_mm are all one point"),
    # issue 50: bounds and declarations
    "symmetry_numbers_as_text": ("popcode.objects", _objects(symmetries_discrete=[[str(v) for v in OBJECT[
        "symmetries_discrete"][0]]]), "symmetries_discrete[0] is not a list of numbers: got ['-1.0', "),
    "symmetry_true_for_one": ("popcode.objects", _objects(symmetries_discrete=[[True if v == 1 else v for v in OBJECT[
        "symmetries_discrete"][0]]]), "symmetries_discrete[0] is not a list of numbers"),
    "continuous_axis_as_text": ("popcode.objects", _objects(symmetries_discrete=[], symmetries_continuous=[
        {"axis": ["0", "0", "1"]}]), "symmetries_continuous[0] axis is not a list of numbers"),
    "continuous_four": ("popcode.objects", _objects(symmetries_discrete=[], symmetries_continuous=[
        {"axis": [0, 0, 1]}] * 4), "symmetries_continuous lists 4 symmetries; at most 3 are allowed"),
    "symmetries_counted_before_read": ("popcode.objects", _objects(symmetries_continuous=["abc"] * 4),
                                       "symmetries_continuous lists 4 symmetries; at most 3"),
    "hull_over_the_limit": ("popcode.objects", _objects(hull_points_mm=[[k % 7, k % 11, k % 13] for k in range(1025)]),
                            "hull_points_mm lists 1025 points; at most 1024 are allowed"),
}


@dataclass(frozen=True)
class CliCase:
    """``popcode`` with ``argv`` must exit 2 with one error line containing ``expect``."""

    id: str
    argv: tuple[str, ...]
    expect: str


def _predict(*extra: str, model: str = "model.onnx", image: str = "scene.png", box: str | None = GOOD_BOX) -> tuple:
    argv = ("predict", "{folder}/" + model, "{folder}/" + image)
    return argv + (("--box", box) if box is not None else ()) + extra


CLI_CASES: list[CliCase] = [
    *(CliCase(f"metadata-{name}", ("info", f"{{folder}}/meta_{name}.onnx"), expect)
      for name, (_, _, expect) in METADATA_CASES.items()),
    CliCase("model-non-utf8", ("info", "{folder}/non_utf8.onnx"), "UTF-8"),
    CliCase("model-missing", ("info", "{folder}/missing.onnx"), "model file not found"),
    CliCase("model-directory", ("info", "{folder}"), "model file not found"),
    CliCase("model-junk", ("info", "{folder}/junk.onnx"), "cannot load"),
    CliCase("model-empty", ("info", "{folder}/empty.onnx"), "cannot load"),
    CliCase("model-truncated", ("info", "{folder}/truncated.onnx"), "cannot load"),
    CliCase("model-wrong-input-name", ("info", "{folder}/wrong_input.onnx"), "exactly one input named 'image'"),
    CliCase("model-wrong-width", ("info", "{folder}/wrong_width.onnx"), "values per crop"),
    CliCase("model-fails-at-run-time", _predict(model="run_fails.onnx"), "cannot run"),
    CliCase("model-loops", _predict(model="loops.onnx"), "has a 'Loop' op, whose run time nothing bounds"),
    CliCase("model-fixes-a-huge-batch", _predict(model="batch_huge.onnx"), "fixes the batch at 100000 crops"),
    CliCase("image-missing", _predict(image="missing.png"), "image file not found"),
    CliCase("image-directory", _predict(image=""), "is not a regular file (a folder, FIFO or device)"),
    CliCase("image-text", _predict(image="text.png"), "cannot read image"),
    CliCase("image-empty", _predict(image="empty.png"), "cannot read image"),
    CliCase("image-truncated", _predict(image="truncated.png"), "cannot read image"),
    CliCase("image-huge-png-header", _predict(image="huge.png"), "more than the limit"),
    CliCase("image-huge-jpeg-header", _predict(image="huge.jpg"), "more than the limit"),
    CliCase("image-over-max-pixels", _predict("--max-pixels", "100"), "more than the limit of 100"),
    CliCase("image-over-opencv-limit", _predict(image="over_opencv_limit.png"), "more than the limit of 1073741824"),
    CliCase("image-over-opencv-limit-raised", _predict("--max-pixels", str(10**10), image="over_opencv_limit.png"),
            "cannot decode image"),
    CliCase("max-pixels-zero", _predict("--max-pixels", "0"), "--max-pixels must be positive"),
    CliCase("box-three-numbers", _predict(box="1,2,3"), "needs 4 numbers"),
    CliCase("box-words", _predict(box="a,b,c,d"), "must be comma-separated numbers"),
    CliCase("box-empty-text", _predict(box=""), "must be comma-separated numbers"),
    CliCase("box-nan", _predict(box="nan,0,10,10"), "NaN or inf"),
    CliCase("box-inf", _predict(box="0,0,inf,10"), "NaN or inf"),
    CliCase("box-zero-width", _predict(box="0,0,0,10"), "is empty"),
    CliCase("box-negative-height", _predict(box="0,0,10,-5"), "is empty"),
    CliCase("box-1e5", _predict(box="0,0,100000,100000"), "larger than 4x"),
    CliCase("box-1e9", _predict(box="-1e9,-1e9,2e9,2e9"), "larger than 4x"),
    CliCase("box-outside", _predict(box="5000,5000,10,10"), "wholly outside"),
    CliCase("box-negative-outside", _predict(box="-500,-500,10,10"), "wholly outside"),
    CliCase("box-sub-pixel", _predict(box="10,10,1e-9,1e-9"), "smaller than a pixel"),
    CliCase("box-missing", _predict(box=None), "--box"),
    CliCase("box-for-two-models", ("predict", "{folder}/model.onnx", "{folder}/depth_model.onnx", "{folder}/scene.png",
                                   "--box", GOOD_BOX), "2 models with --box"),
    CliCase("K-three-numbers", _predict("--K", "1,2,3"), "fx,fy,cx,cy, 9 numbers or 3x3"),
    CliCase("K-words", _predict("--K", "a,b,c,d"), "must be comma-separated numbers"),
    CliCase("K-1e300", _predict("--K", "1e300,1e300,0,0", "--translation"), "not physical"),
    CliCase("K-nan", _predict("--K", "nan,500,80,60"), "NaN or inf"),
    CliCase("K-negative-focal", _predict("--K", "-500,500,80,60"), "focal lengths must be positive"),
    CliCase("K-zero", _predict("--K", "0,0,0,0"), "focal lengths must be positive"),
    CliCase("K-bad-last-row", _predict("--K", "500,0,80,0,500,60,1,1,1"), "last row 0 0 1"),
    CliCase("K-far-principal-point", _predict("--K", "500,500,1e9,60"), "not physical"),
    CliCase("translation-without-K", _predict("--translation"), "pass the camera matrix K"),
    CliCase("depth-missing", _predict("--K", GOOD_K, "--depth", "{folder}/missing.png"), "depth image file not found"),
    CliCase("depth-text-file", _predict("--K", GOOD_K, "--depth", "{folder}/text.png"), "cannot read depth image"),
    CliCase("depth-colour", _predict("--K", GOOD_K, "--depth", "{folder}/depth_colour.png"), "has 3 channels"),
    CliCase("depth-8-bit-picture", _predict("--K", GOOD_K, "--depth", "{folder}/scene.png"), "depth is 8-bit"),
    CliCase("depth-wrong-size", _predict("--K", GOOD_K, "--depth", "{folder}/depth_small.png"),
            "depth is 80x60 but the image is 160x120"),
    CliCase("depth-huge", _predict("--K", GOOD_K, "--depth", "{folder}/huge.png"), "more than the limit"),
    CliCase("depth-scale-nan", _predict("--K", GOOD_K, "--depth", "{folder}/depth.png", "--depth-scale", "nan"),
            "depth_scale must be finite"),
    CliCase("depth-scale-negative", _predict("--K", GOOD_K, "--depth", "{folder}/depth.png", "--depth-scale", "-1"),
            "depth_scale must lie in"),
    CliCase("depth-scale-zero", _predict("--K", GOOD_K, "--depth", "{folder}/depth.png", "--depth-scale", "0"),
            "depth_scale must lie in"),
    CliCase("depth-scale-absurd", _predict("--K", GOOD_K, "--depth", "{folder}/depth.png", "--depth-scale", "1e6"),
            "depth_scale must lie in"),
    CliCase("depth-scale-word", _predict("--K", GOOD_K, "--depth", "{folder}/depth.png", "--depth-scale", "far"),
            "invalid float value"),
    CliCase("depth-beyond-100-m", _predict("--K", GOOD_K, "--depth", "{folder}/depth_far.png", "--depth-scale", "10"),
            "beyond 100 m"),
    CliCase("depth-without-K", _predict("--depth", "{folder}/depth.png"), "translation from depth: pass the camera"),
    CliCase("depth-model-without-surface-points", _predict("--K", GOOD_K, "--depth", "{folder}/depth.png"),
            "carries no surface points for object 7"),
    CliCase("refine-without-depth", _predict("--K", GOOD_K, "--refine"), "--refine is about the depth image"),
    CliCase("depth-scale-without-depth", _predict("--K", GOOD_K, "--depth-scale", "0.1"),
            "--depth-scale is about the depth image"),
    CliCase("run-refine-without-depth", ("run", "{folder}/model.onnx", "--split", "{folder}", "--gt-boxes",
                                         "--refine"), "--refine refines the pose against each image's depth"),
    CliCase("threads-2000", _predict("--threads", "2000"), "more than this machine's"),
    CliCase("threads-negative", _predict("--threads", "-1"), "threads must be >= 0"),
    CliCase("threads-float", _predict("--threads", "1.5"), "invalid int value"),
    CliCase("top-k-zero", _predict("--top-k", "0"), "top_k must lie in"),
    CliCase("top-k-huge", _predict("--top-k", "1000"), "top_k must lie in"),
    CliCase("obj-id-unknown", _predict("--obj-id", "99"), "not in this model"),
    CliCase("obj-id-too-many", _predict("--obj-id", "7", "--obj-id", "7"), "2 object ids for 1 boxes"),
    CliCase("obj-id-word", _predict("--obj-id", "seven"), "invalid int value"),
    CliCase("decoder-unknown", _predict("--decoder", "bogus"), "invalid choice"),
    CliCase("decoder-refined-single-variable", _predict("--decoder", "refined", model="single_variable.onnx"),
            "the refined decoder needs a population-code model"),
    CliCase("provider-unknown", _predict("--provider", "bogus"), "not available"),
    CliCase("bench-batch-100000", ("bench", "{folder}/model.onnx", "--batch", "100000"), "more than the limit"),
    CliCase("bench-batch-zero", ("bench", "{folder}/model.onnx", "--batch", "0"), "must be positive"),
    CliCase("bench-iterations-huge", ("bench", "{folder}/model.onnx", "--iterations", "100000000"),
            "iterations) must lie in [1, 10000]"),
    CliCase("bench-warmup-huge", ("bench", "{folder}/model.onnx", "--warmup", "100000000"),
            "warmup calls must lie in [0, 1000]"),
    CliCase("code-without-json", _predict("--code"), "--code prints the raw network output in the JSON; add --json"),
    CliCase("bench-iterations-zero", ("bench", "{folder}/model.onnx", "--iterations", "0"), "must be positive"),
    CliCase("bench-warmup-negative", ("bench", "{folder}/model.onnx", "--warmup", "-1"), "warmup non-negative"),
    CliCase("bench-threads-2000", ("bench", "{folder}/model.onnx", "--threads", "2000"), "more than this machine's"),
    CliCase("draw-onto-the-input-image", _predict("--draw", "{folder}/scene.png"), "is the input"),
    CliCase("draw-onto-the-input-image-overwrite", _predict("--draw", "{folder}/scene.png", "--overwrite"),
            "is the input"),
    CliCase("draw-onto-the-model", _predict("--draw", "{folder}/model.onnx"), "is the input"),
    CliCase("draw-onto-an-existing-picture", _predict("--draw", "{folder}/empty.png"),
            "exists already; pass --overwrite"),
    CliCase("run-draw-into-the-split", ("run", "{folder}/model.onnx", "--split", "{folder}", "--gt-boxes",
                                        "--out", "{folder}/../results.csv", "--draw", "{folder}"),
            "never replaces or joins"),
    CliCase("command-unknown", ("frobnicate",), "invalid choice"),
    CliCase("command-missing", (), "required"),
    # issue 50: cameras and depth
    CliCase("K-of-another-image-size", _predict("--K", "864,864,359.5,269.5"),
            "principal point at (359.5, 269.5), outside the 160x120 image"),
    CliCase("K-principal-point-5000", _predict("--K", "200,200,5000,60"), "principal point at (5000, 60), outside"),
    CliCase("K-principal-point-negative", _predict("--K", "200,200,80,-60"), "principal point at (80, -60), outside"),
    CliCase("K-field-of-view-178-deg", _predict("--K", "1,1,80,60"), "a camera sees 0.5 to 170 deg"),
    CliCase("K-field-of-view-0.1-deg", _predict("--K", "1e5,1e5,80,60"), "a camera sees 0.5 to 170 deg"),
    CliCase("K-fy-of-another-image", _predict("--K", "200,1,80,60"), "a camera sees 0.5 to 170 deg"),
    CliCase("K-another-camera-translation", _predict("--K", "864,864,359.5,269.5", "--translation"), "outside the"),
    CliCase("K-another-camera-depth", _predict("--K", "864,864,359.5,269.5", "--depth", "{folder}/depth.png",
                                               model="depth_model.onnx"), "outside the 160x120 image"),
    CliCase("crop-origin-without-K", _predict("--crop-origin", "10,10"), "--crop-origin places IMAGE in the frame"),
    CliCase("crop-origin-words", _predict("--K", GOOD_K, "--crop-origin", "a,b"), "must be comma-separated numbers"),
    CliCase("crop-origin-three-numbers", _predict("--K", GOOD_K, "--crop-origin", "1,2,3"), "needs 2 numbers"),
    CliCase("crop-origin-nan", _predict("--K", GOOD_K, "--crop-origin", "nan,0"), "contains NaN or inf"),
    CliCase("crop-origin-1e9", _predict("--K", GOOD_K, "--crop-origin", "1e9,0"), "lies beyond 1e+06 px"),
    CliCase("crop-origin-left-of-the-frame", _predict("--K", GOOD_K, "--crop-origin", "-500,0"),
            "wholly left of or above"),
    CliCase("crop-origin-off-axis", _predict("--K", GOOD_K, "--crop-origin", "5000,0"), "deg off the optical axis"),
    CliCase("crop-origin-with-the-crops-own-K", _predict("--K", "200,200,-20,60", "--crop-origin", "100,0"),
            "outside its own frame"),
    CliCase("depth-torn", _predict("--K", GOOD_K, "--depth", "{folder}/depth_torn.png", model="depth_model.onnx"),
            "ends before its IEND chunk"),
    CliCase("depth-damaged", _predict("--K", GOOD_K, "--depth", "{folder}/depth_damaged.png",
                                      model="depth_model.onnx"), "chunk 'IDAT' fails its CRC"),
    CliCase("depth-16-bit-rgba", _predict("--K", GOOD_K, "--depth", "{folder}/depth_rgba16.png",
                                          model="depth_model.onnx"), "has 4 channels"),
    CliCase("run-depth-without-depth-scale", ("run", "{folder}/depth_model.onnx", "--split", "{folder}/split_unscaled",
                                              "--gt-boxes", "--depth", "--out", "{folder}/../unscaled.csv"),
            "scene 1 image 0 has no 'depth_scale' in its scene_camera.json entry"),
    CliCase("run-cam-K-of-another-image-size", ("run", "{folder}/model.onnx", "--split", "{folder}/split_other_camera",
                                                "--gt-boxes", "--out", "{folder}/../other_camera.csv"),
            "scene 1 image 0 (000000.png), its cam_K in scene_camera.json: the camera K puts its principal point"),
    # issue 62: option clashes in one line, not argparse's usage block
    CliCase("run-detector-and-detections", ("run", "{folder}/model.onnx", "--split", "{folder}", "--detector",
                                            "{folder}/model.onnx", "--detections", "{folder}/d.json"),
            "popcode run: error: argument --detections: not allowed with argument --detector"),
    CliCase("run-detector-and-gt-boxes", ("run", "{folder}/model.onnx", "--split", "{folder}", "--detector",
                                          "{folder}/model.onnx", "--gt-boxes"),
            "popcode run: error: argument --gt-boxes: not allowed with argument --detector"),
    CliCase("run-top-k", ("run", "{folder}/model.onnx", "--split", "{folder}", "--gt-boxes", "--top-k", "3"),
            "popcode run: error: unrecognized arguments: --top-k 3 (see popcode run --help)"),
]


def cli_argv(case: CliCase, folder: Path) -> list[str]:
    return [part.replace("{folder}", str(folder)) for part in case.argv]


def run_cli(argv: list[str], entry: Callable[[list[str]], int] = main) -> tuple[int, str, str]:
    """``popcode`` (or another ``entry``) in-process: exit code, stdout, stderr (argparse's ``SystemExit``
    caught)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = entry(argv)
        except SystemExit as exit_:
            code = exit_.code if isinstance(exit_.code, int) else 1
    return code, out.getvalue(), err.getvalue()


def error_lines(stderr: str) -> list[str]:
    """The lines of stderr that report an error."""
    return [line for line in stderr.splitlines() if ": error: " in line]


def refused_in_one_line(code: int, stderr: str, expect: str) -> bool:
    """Whether a command exited 2 with stderr exactly one error line that contains ``expect``: no usage block, no
    progress line before it, no traceback."""
    lines = stderr.splitlines()
    return code == 2 and lines == error_lines(stderr) and len(lines) == 1 and expect.lower() in lines[0].lower()


def _estimator(folder: Path) -> PoseEstimator:
    return PoseEstimator(folder / "model.onnx", threads=1)


def _scene() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, size=IMAGE_SHAPE, dtype=np.uint8)


def _depth() -> np.ndarray:
    return np.full(IMAGE_SHAPE, DEPTH_MM, np.uint16)


GOOD_K_LIST = [float(v) for v in GOOD_K.split(",")]


def _without_small_gicp(folder: Path) -> object:
    """Refinement asked of a model that can use depth, with small_gicp not importable (the runtime alone)."""
    missing = object()
    saved = sys.modules.get("small_gicp", missing)
    sys.modules["small_gicp"] = None  # importing it raises ImportError, as where it is not installed
    try:
        return PoseEstimator(folder / "depth_model.onnx", threads=1).predict(
            _scene(), [[20, 20, 60, 50]], K=GOOD_K_LIST, depth=_depth(), refine_depth=True)
    finally:
        if saved is missing:
            del sys.modules["small_gicp"]
        else:
            sys.modules["small_gicp"] = saved


def _predict_with(**kwargs: object) -> Callable[[Path], object]:
    def call(folder: Path) -> object:
        arguments = {"image": _scene(), "boxes": [[20, 20, 60, 50]], **kwargs}
        return _estimator(folder).predict(**arguments)
    return call


# (id, call with the files' folder, what the PopcodeError must say)
API_CASES: list[tuple[str, Callable[[Path], object], str]] = [
    ("boxes-none", _predict_with(boxes=None), "boxes must be a list"),
    ("boxes-text", _predict_with(boxes="0,0,10,10"), "boxes must be a list"),
    ("boxes-int", _predict_with(boxes=5), "boxes must be a list"),
    ("boxes-generator", _predict_with(boxes=([20, 20, 60, 50] for _ in range(2))), "boxes must be a list"),
    ("boxes-empty", _predict_with(boxes=[]), "no boxes given"),
    ("box-three-numbers", _predict_with(boxes=[[1, 2, 3]]), "a box is 4 numbers"),
    ("box-words", _predict_with(boxes=[["a", "b", "c", "d"]]), "a box is 4 numbers"),
    ("box-number-strings", _predict_with(boxes=[["1", "2", "30", "40"]]), "a box is 4 numbers"),
    ("box-none", _predict_with(boxes=[None]), "a box is 4 numbers"),
    ("box-dict", _predict_with(boxes=[{"x": 1}]), "a box is 4 numbers"),
    ("box-huge", _predict_with(boxes=[[0, 0, 1e5, 1e5]]), "larger than 4x"),
    ("box-sub-pixel", _predict_with(boxes=[[10, 10, 1e-9, 1e-9]]), "smaller than a pixel"),
    ("boxes-10001", _predict_with(boxes=[[20, 20, 60, 50]] * 10_001), "the limit is 10000"),
    ("image-none", _predict_with(image=None), "image must be a numpy array"),
    ("image-list", _predict_with(image=[[0, 1], [1, 0]]), "image must be a numpy array"),
    ("image-4d", _predict_with(image=np.zeros((1, 10, 10, 3), np.uint8)), "must have shape"),
    ("image-rgba", _predict_with(image=np.zeros((100, 100, 4), np.uint8)), "must have shape"),
    ("image-bool", _predict_with(image=np.zeros((100, 100), bool)), "unsupported image dtype"),
    ("image-int32", _predict_with(image=np.zeros((100, 100), np.int32)), "unsupported image dtype"),
    ("image-complex", _predict_with(image=np.zeros((100, 100), np.complex64)), "unsupported image dtype"),
    ("image-float-range", _predict_with(image=np.full((100, 100), 2.0, np.float32)), "must lie in [0, 1]"),
    ("image-nan", _predict_with(image=np.full((100, 100), np.nan, np.float32)), "NaN or inf"),
    ("image-empty", _predict_with(image=np.zeros((0, 10), np.uint8)), "image is empty"),
    ("K-text", _predict_with(K="500,500,80,60"), "not the text"),
    ("K-ragged", _predict_with(K=[[1, 2], [3]]), "a camera matrix is"),
    ("K-dict", _predict_with(K={"fx": 1}), "a camera matrix is"),
    ("K-1e300", _predict_with(K=[1e300, 1e300, 0, 0], translation=True), "not physical"),
    ("K-2x2", _predict_with(K=np.eye(2)), "got shape (2, 2)"),
    ("top-k-text", _predict_with(top_k="2"), "top_k must be an integer"),
    ("top-k-none", _predict_with(top_k=None), "top_k must be an integer"),
    ("top-k-float", _predict_with(top_k=2.5), "top_k must be an integer"),
    ("top-k-bool", _predict_with(top_k=True), "top_k must be an integer"),
    ("top-k-zero", _predict_with(top_k=0), "top_k must lie in"),
    ("obj-ids-float", _predict_with(obj_ids=[3.7]), "an object id must be an integer"),
    ("obj-ids-text", _predict_with(obj_ids="7"), "obj_ids must be a list"),
    ("obj-ids-int", _predict_with(obj_ids=7), "obj_ids must be a list"),
    ("obj-ids-none-entry", _predict_with(obj_ids=[None]), "an object id must be an integer"),
    ("obj-ids-empty", _predict_with(obj_ids=[]), "0 object ids for 1 boxes"),
    ("obj-ids-unknown", _predict_with(obj_ids=[99]), "not in this model"),
    ("return-code-text", _predict_with(return_code="yes"), "return_code must be true or false"),
    ("translation-int", _predict_with(translation=1), "translation must be true or false"),
    ("depth-list", _predict_with(K=GOOD_K_LIST, depth=[[500]]), "depth must be a numpy array"),
    ("depth-3d", _predict_with(K=GOOD_K_LIST, depth=np.zeros((*IMAGE_SHAPE, 3), np.uint16)), "must be a 2-D array"),
    ("depth-bool", _predict_with(K=GOOD_K_LIST, depth=np.ones(IMAGE_SHAPE, bool)), "must hold integers or floats"),
    ("depth-complex", _predict_with(K=GOOD_K_LIST, depth=np.ones(IMAGE_SHAPE, np.complex64)),
     "must hold integers or floats"),
    ("depth-wrong-size", _predict_with(K=GOOD_K_LIST, depth=np.ones((60, 80), np.uint16)),
     "depth is 80x60 but the image is 160x120"),
    ("depth-transposed", _predict_with(K=GOOD_K_LIST, depth=np.ones(IMAGE_SHAPE[::-1], np.uint16)),
     "depth is 120x160 but the image is 160x120"),
    ("depth-nan", _predict_with(K=GOOD_K_LIST, depth=np.full(IMAGE_SHAPE, np.nan, np.float32)), "NaN or inf"),
    ("depth-inf", _predict_with(K=GOOD_K_LIST, depth=np.full(IMAGE_SHAPE, np.inf)), "NaN or inf"),
    ("depth-negative", _predict_with(K=GOOD_K_LIST, depth=np.full(IMAGE_SHAPE, -1.0, np.float32)),
     "negative values"),
    ("depth-scale-zero", _predict_with(K=GOOD_K_LIST, depth=_depth(), depth_scale=0.0), "depth_scale must lie in"),
    ("depth-scale-negative", _predict_with(K=GOOD_K_LIST, depth=_depth(), depth_scale=-0.1), "depth_scale must lie in"),
    ("depth-scale-nan", _predict_with(K=GOOD_K_LIST, depth=_depth(), depth_scale=float("nan")),
     "depth_scale must be finite"),
    ("depth-scale-text", _predict_with(K=GOOD_K_LIST, depth=_depth(), depth_scale="0.1"), "must be a number"),
    ("depth-scale-none", _predict_with(K=GOOD_K_LIST, depth=_depth(), depth_scale=None), "must be a number"),
    ("depth-scale-huge", _predict_with(K=GOOD_K_LIST, depth=_depth(), depth_scale=1e9), "depth_scale must lie in"),
    ("depth-beyond-100-m", _predict_with(K=GOOD_K_LIST, depth=np.full(IMAGE_SHAPE, 65535, np.uint16),
                                         depth_scale=10.0), "beyond 100 m"),
    ("depth-without-K", _predict_with(depth=_depth()), "translation from depth: pass the camera matrix K"),
    ("depth-model-without-surface-points", _predict_with(K=GOOD_K_LIST, depth=_depth()),
     "carries no surface points for object 7"),
    ("refine-without-depth", _predict_with(K=GOOD_K_LIST, refine_depth=True), "refine_depth refines the pose"),
    ("refine-int", _predict_with(K=GOOD_K_LIST, depth=_depth(), refine_depth=1), "refine_depth must be true or false"),
    ("refine-without-small-gicp", _without_small_gicp, "pip install ./runtime[depth]"),
    ("read-depth-colour", lambda folder: read_depth(folder / "depth_colour.png"), "has 3 channels"),
    ("read-depth-missing", lambda folder: read_depth(folder / "missing.png"), "depth image file not found"),
    ("threads-float", lambda folder: PoseEstimator(folder / "model.onnx", threads=1.5), "threads must be an integer"),
    ("threads-text", lambda folder: PoseEstimator(folder / "model.onnx", threads="2"), "threads must be an integer"),
    ("threads-2000", lambda folder: PoseEstimator(folder / "model.onnx", threads=2000), "more than this machine's"),
    ("providers-string", lambda folder: PoseEstimator(folder / "model.onnx", providers="cpu"), "list of names"),
    ("providers-number", lambda folder: PoseEstimator(folder / "model.onnx", providers=[1]), "a provider is a name"),
    ("decoder-number", lambda folder: PoseEstimator(folder / "model.onnx", decoder=5), "unknown decoder"),
    ("decoder-refined-single-variable", lambda folder: PoseEstimator(folder / "single_variable.onnx",
                                                                     decoder="refined"), "needs a population-code"),
    ("model-path-none", lambda folder: PoseEstimator(None), "model path must be a file path"),
    ("model-path-number", lambda folder: PoseEstimator(5), "model path must be a file path"),
    ("run-wrong-crops", lambda folder: _estimator(folder).run(np.zeros((1, 1, 64, 64), np.float32)), "crops must"),
    ("run-list", lambda folder: _estimator(folder).run([[0.0]]), "crops must"),
    ("read-image-none", lambda folder: read_image(None), "image path must be a file path"),
    ("read-image-max-pixels-text", lambda folder: read_image(folder / "scene.png", max_pixels="100"),
     "max_pixels must be an integer"),
    ("read-image-max-pixels-zero", lambda folder: read_image(folder / "scene.png", max_pixels=0),
     "max_pixels must lie in"),
    ("read-image-huge", lambda folder: read_image(folder / "huge.png"), "more than the limit"),
    ("crop-padding-negative", lambda folder: crop_square(np.zeros((10, 10), np.float32), [1, 1, 5, 5], 16, -1.0),
     "crop padding must lie in"),
    ("crop-padding-nan", lambda folder: crop_square(np.zeros((10, 10), np.float32), [1, 1, 5, 5], 16, np.nan),
     "crop padding must lie in"),
    ("camera-text", lambda folder: parse_camera_matrix("abc"), "not the text"),
    ("layout-float", lambda folder: CodeLayout(n_axes=642.0), "code.n_axes must be an integer"),
    ("layout-sigma-text", lambda folder: CodeLayout(sigma_deg="20"), "code.sigma_deg must be a number"),
    ("metadata-props-nan", lambda folder: ModelMetadata.from_props({"popcode.format_version": "NaN"}),
     "not valid JSON"),
    ("metadata-code-type", lambda folder: ModelMetadata(representation="population_code", code={"n_axes": 4},
                                                        objects={1: CASES["none"]}), "must be a CodeLayout"),
    ("metadata-padding", lambda folder: ModelMetadata(representation="population_code", code=LAYOUT,
                                                      objects={1: CASES["none"]}, crop_padding=-1),
     "crop_padding must lie in"),
    # issue 50: cameras and depth
    ("K-of-another-image-size", _predict_with(K=[864, 864, 359.5, 269.5]), "outside the 160x120 image"),
    ("K-principal-point-5000", _predict_with(K=[200, 200, 5000, 60]), "principal point at (5000, 60), outside"),
    ("K-3x3-of-another-image-size", _predict_with(K=np.array([[864, 0, 359.5], [0, 864, 269.5], [0, 0, 1]])),
     "outside the 160x120 image"),
    ("K-field-of-view-178-deg", _predict_with(K=[1, 1, 80, 60]), "a camera sees 0.5 to 170 deg"),
    ("K-field-of-view-0.1-deg", _predict_with(K=[1e5, 1e5, 80, 60], translation=True), "a camera sees 0.5 to 170"),
    ("K-another-camera-depth", lambda folder: PoseEstimator(folder / "depth_model.onnx", threads=1).predict(
        _scene(), [[20, 20, 60, 50]], K=[864, 864, 359.5, 269.5], depth=_depth()), "outside the 160x120 image"),
    ("crop-origin-without-K", _predict_with(crop_origin=(10, 10)), "crop_origin moves K's principal point"),
    ("crop-origin-text", _predict_with(K=GOOD_K_LIST, crop_origin="10,10"), "must be numbers, got the text"),
    ("crop-origin-three-numbers", _predict_with(K=GOOD_K_LIST, crop_origin=[1, 2, 3]), "must have shape"),
    ("crop-origin-none-entry", _predict_with(K=GOOD_K_LIST, crop_origin=[None, 1]), "contains NaN or inf"),
    ("crop-origin-inf", _predict_with(K=GOOD_K_LIST, crop_origin=[np.inf, 0]), "contains NaN or inf"),
    ("crop-origin-off-axis", _predict_with(K=GOOD_K_LIST, crop_origin=(0, 5000)), "deg off the optical axis"),
    ("crop-origin-left-of-the-frame", _predict_with(K=GOOD_K_LIST, crop_origin=(-500, 0)), "wholly left of"),
    ("read-depth-torn", lambda folder: read_depth(folder / "depth_torn.png"), "ends before its IEND chunk"),
    ("read-depth-damaged", lambda folder: read_depth(folder / "depth_damaged.png"), "fails its CRC"),
    ("read-depth-16-bit-rgba", lambda folder: read_depth(folder / "depth_rgba16.png"), "has 4 channels"),
    ("read-image-torn-depth-png", lambda folder: read_image(folder / "depth_torn.png"), "ends before its IEND"),
]


def cli_problem(case: CliCase, folder: Path) -> str | None:
    """What is wrong with how ``popcode`` handled ``case`` (None: exit 2 and one line naming the problem)."""
    code, _, stderr = run_cli(cli_argv(case, folder))
    return None if refused_in_one_line(code, stderr, case.expect) else f"exit {code}, stderr {stderr!r}"


def api_problem(call: Callable[[Path], object], expect: str, folder: Path) -> str | None:
    """What is wrong with how the API handled a case (None: one ``PopcodeError`` line naming the problem)."""
    try:
        call(folder)
    except PopcodeError as error:
        message = str(error)
        if "\n" in message or expect.lower() not in message.lower():
            return f"PopcodeError {message!r}"
        return None
    except Exception as error:  # the catalogue's point: report, do not crash the run
        return f"{type(error).__name__}: {error}"
    return "no PopcodeError raised"


def catalogue_problems(folder: Path) -> dict[str, str]:
    """Every case of the catalogue run once; case id -> problem, for the cases that have one."""
    problems = {case.id: cli_problem(case, folder) for case in CLI_CASES}
    problems.update({f"api-{case_id}": api_problem(call, expect, folder) for case_id, call, expect in API_CASES})
    return {case_id: problem for case_id, problem in problems.items() if problem is not None}
