"""Translation from depth and its refinement (issue 29): on a synthetic, exactly known depth camera (depth_scene)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from depth_scene import (
    SHAPE,
    K,
    bracket_box,
    bracket_info,
    perturbed,
    pose,
    render_depth,
)
from hostile_cases import run_cli
from onnx_models import linear_model, save

from popcode_runtime import (
    CodeLayout,
    ModelMetadata,
    PopcodeError,
    PopulationCode,
    PoseEstimator,
    Representation,
)
from popcode_runtime.commands import run_loop
from popcode_runtime.depth.icp import keep_symmetry_roll
from popcode_runtime.depth.placement import pose_with_depth
from popcode_runtime.depth.surface_fit import (
    TranslationSource,
    check_depth,
    depth_fit,
    object_surface,
    translation_from_depth,
)
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, geodesic_angle
from popcode_runtime.geometry.symmetries import symmetry_transforms
from popcode_runtime.geometry.translation import object_points_mm, translation_from_box

INFO = bracket_info()
SURFACE, HULL = object_surface(INFO), object_points_mm(INFO)
LAYOUT = CodeLayout(n_axes=642, n_angles=36)
DEPTH_SCALE = 0.1  # mm per unit of the uint16 depth images, as the renderer writes them


def sensor_depth(depth_mm: np.ndarray) -> np.ndarray:
    """The exact depth as a uint16 PNG stores it (0.1 mm steps)."""
    return np.round(depth_mm / DEPTH_SCALE).astype(np.uint16)


def box_translation(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return translation_from_box(R, bracket_box(R, t), K, HULL)


def test_a_surface_s_diameter_is_its_largest_distance_between_two_points():
    """The Gram-matrix diameter against every pair's difference, on a cloud far from the origin."""
    points = np.random.default_rng(0).normal(size=(512, 3)) * [30.0, 20.0, 5.0] + 1e7
    info = {"surface_points_mm": points.tolist(), "surface_normals": np.tile([0.0, 0.0, 1.0], (512, 1)).tolist()}
    pairwise = np.linalg.norm(points[:, None] - points[None], axis=-1).max()
    assert object_surface(info).diameter_mm == pytest.approx(pairwise, rel=1e-9)
    assert SURFACE.diameter_mm == pytest.approx(np.linalg.norm(SURFACE.points_mm[:, None] - SURFACE.points_mm[None],
                                                              axis=-1).max(), rel=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_translation_from_exact_depth_is_within_a_millimetre(seed):
    """With the true rotation the depth places the bracket to well under a millimetre, the bin floor behind it."""
    R, t = pose(seed)
    depth = check_depth(sensor_depth(render_depth(R, t, floor_mm=t[2] + 60.0)[0]), SHAPE, DEPTH_SCALE)
    t_depth, problem = translation_from_depth(R, box_translation(R, t), K, depth, SURFACE)
    assert problem is None and np.linalg.norm(t_depth - t) < 1.0
    assert depth_fit(R, t_depth, K, depth, SURFACE) > 0.2


def test_an_occluder_in_front_does_not_pull_the_object_forward():
    """A part in front covering much of the bracket confirms a surface that the rest of the readings see through."""
    R, t = pose(1)
    occluder = (t + np.array([-15.0, 0.0, -40.0]), np.array([25.0, 60.0, 5.0]))
    depth_mm, visible = render_depth(R, t, floor_mm=t[2] + 60.0, occluder=occluder)
    assert 0.2 < visible.sum() / render_depth(R, t)[1].sum() < 0.7  # a real occlusion, not a total one
    t_depth, problem = translation_from_depth(R, box_translation(R, t), K, check_depth(depth_mm, SHAPE, 1.0),
                                              SURFACE)
    assert problem is None and np.linalg.norm(t_depth - t) < 1.0


def test_depth_far_from_the_box_keeps_the_box_translation_and_says_why():
    R, t = pose(2)
    wall = np.full(SHAPE, t[2] + 600.0, np.float32)  # the object is not in this depth image
    placed = pose_with_depth([R], bracket_box(R, t), K, wall, SURFACE, HULL, INFO)
    assert placed.source == TranslationSource.BOX and placed.fit is None
    assert placed.note.startswith("too little of the object's surface in the depth near the box's distance")
    assert np.allclose(placed.t_m2c_mm, box_translation(R, t))


@pytest.fixture(scope="module")
def exact_model(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """A model whose code decodes to one grid rotation, and that rotation (the true one of the tests below)."""
    pc = PopulationCode(LAYOUT)
    code = pc.encode(pose(3)[0])
    R = pc.decode(code[None]).R[0]
    meta = ModelMetadata(Representation.POPULATION_CODE, LAYOUT, {6: INFO})
    return save(linear_model(code, metadata=meta), tmp_path_factory.mktemp("depth") / "bracket.onnx"), R


def test_predict_with_depth_says_where_each_translation_came_from(exact_model):
    model, R = exact_model
    t = pose(3)[1]
    box = bracket_box(R, t)
    depth = sensor_depth(render_depth(R, t, floor_mm=t[2] + 60.0)[0])
    estimator = PoseEstimator(model, threads=1)
    image = np.zeros(SHAPE, np.uint8)
    found = estimator.predict(image, [box], K=K, depth=depth, depth_scale=DEPTH_SCALE)[0]
    assert found.t_source == TranslationSource.DEPTH and found.depth_note is None and found.depth_fit > 0.5
    assert np.linalg.norm(found.t_m2c_mm - t) < 1.0
    assert json.loads(json.dumps(found.to_dict()))["t_source"] == "depth"
    from_box = estimator.predict(image, [box], K=K, translation=True)[0]
    assert from_box.t_source == TranslationSource.BOX and from_box.depth_fit is None

    empty = estimator.predict(image, [box], K=K, depth=np.zeros(SHAPE, np.uint16))[0]  # all zeros: no reading
    assert empty.t_source == TranslationSource.BOX and empty.depth_note == "no valid depth in the box"
    assert np.allclose(empty.t_m2c_mm, from_box.t_m2c_mm)
    holes = depth.copy()
    x, y, w, h = (int(v) for v in box)
    holes[y : y + h + 1, x : x + w + 1] = 0  # readings around the box, none inside it
    assert estimator.predict(image, [box], K=K, depth=holes, depth_scale=DEPTH_SCALE)[0].t_source == "box"


def test_refinement_improves_perturbed_poses():
    """Rotations 8 degrees off come back to under a degree, the translations closer and the depth fitting better."""
    pytest.importorskip("small_gicp")
    plain_mm, refined_mm = [], []
    for seed in range(6):
        R, t = pose(seed)
        depth = check_depth(sensor_depth(render_depth(R, t, floor_mm=t[2] + 60.0)[0]), SHAPE, DEPTH_SCALE)
        start = perturbed(R, 8.0, seed=seed)
        plain = pose_with_depth([start], bracket_box(R, t), K, depth, SURFACE, HULL, INFO)
        refined = pose_with_depth([start], bracket_box(R, t), K, depth, SURFACE, HULL, INFO, refine=True)
        assert plain.source == TranslationSource.DEPTH and refined.source == TranslationSource.REFINED
        assert np.degrees(geodesic_angle(refined.R_m2c, R)) < 1.0 and refined.fit > plain.fit
        plain_mm.append(np.linalg.norm(plain.t_m2c_mm - t))
        refined_mm.append(np.linalg.norm(refined.t_m2c_mm - t))
    assert max(refined_mm) < 1.5 and np.median(refined_mm) < 0.5 < np.median(plain_mm)


def test_refinement_from_several_hypotheses_keeps_the_best_fit():
    pytest.importorskip("small_gicp")
    R, t = pose(5)
    depth = check_depth(render_depth(R, t, floor_mm=t[2] + 60.0)[0], SHAPE, 1.0)
    wrong = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.pi) @ R  # turned over: no ICP reaches R from it
    placed = pose_with_depth([wrong, perturbed(R, 6.0, seed=5)], bracket_box(R, t), K, depth, SURFACE, HULL, INFO,
                             refine=True)
    assert np.degrees(geodesic_angle(placed.R_m2c, R)) < 1.0 and np.linalg.norm(placed.t_m2c_mm - t) < 1.0
    alone = pose_with_depth([wrong], bracket_box(R, t), K, depth, SURFACE, HULL, INFO, refine=True)
    assert alone.fit < placed.fit  # the first start alone (what top_k=1 refines) fits worse


def test_a_continuous_symmetry_keeps_the_starting_roll():
    """ICP may turn a symmetric part about its axis; the result keeps the start's roll and is the same pose."""
    info = {"symmetries_continuous": [{"axis": [0.0, 0.0, 1.0], "offset": [5.0, -3.0, 0.0]}]}
    R_start = perturbed(np.eye(3), 30.0, seed=1)
    R_icp = perturbed(R_start, 4.0, seed=2) @ axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), 1.1)  # tilt + roll
    t_icp = np.array([10.0, 20.0, 500.0])
    R, t = keep_symmetry_roll(R_start, R_icp, t_icp, info)
    axis = np.array([0.0, 0.0, 1.0])
    assert np.allclose(R @ axis, R_icp @ axis)  # the axis where ICP put it
    assert np.degrees(geodesic_angle(R, R_start)) < 4.5  # the roll of the start, not ICP's 63 degrees
    symmetries = symmetry_transforms(info)  # (R, t) is (R_icp, t_icp) moved along the symmetry: a point of the
    points = np.random.default_rng(0).normal(size=(50, 3)) * 20  # model lands where some symmetric image of it does
    placed = points @ R.T + t
    images = np.einsum("kij,pj->kpi", symmetries.R, points) + symmetries.t_mm[:, None]
    distances = np.linalg.norm(images @ R_icp.T + t_icp - placed, axis=-1).mean(axis=1)
    assert distances.min() < 0.2  # the toolkit's steps are 0.01 rad apart
    assert keep_symmetry_roll(R_start, R_icp, t_icp, {}) == (R_icp, t_icp)


HIDE_SMALL_GICP = {"small_gicp": None}  # sys.modules entry None: importing it raises ImportError


def test_the_runtime_needs_small_gicp_only_to_refine(exact_model, monkeypatch):
    model, R = exact_model
    t = pose(3)[1]
    depth = sensor_depth(render_depth(R, t)[0])
    estimator, image, box = PoseEstimator(model, threads=1), np.zeros(SHAPE, np.uint8), bracket_box(R, t)
    for name, value in HIDE_SMALL_GICP.items():
        monkeypatch.setitem(sys.modules, name, value)
    with pytest.raises(PopcodeError, match=r"needs small_gicp: pip install \./runtime\[depth\]"):
        estimator.predict(image, [box], K=K, depth=depth, depth_scale=DEPTH_SCALE, refine_depth=True)
    assert estimator.predict(image, [box], K=K, depth=depth, depth_scale=DEPTH_SCALE)[0].t_source == "depth"
    script = "import sys, popcode_runtime.commands.cli, popcode_runtime.depth.icp; print('small_gicp' in sys.modules)"
    imports = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert imports.stdout.strip() == "False"  # imported only when a refinement runs


def _write(folder: Path, R: np.ndarray, t: np.ndarray) -> tuple[Path, Path]:
    image, depth = folder / "image.png", folder / "depth.png"
    cv2.imwrite(str(image), np.zeros(SHAPE, np.uint8))
    cv2.imwrite(str(depth), sensor_depth(render_depth(R, t, floor_mm=t[2] + 60.0)[0]))
    return image, depth


def test_popcode_predict_with_depth(exact_model, tmp_path):
    model, R = exact_model
    t = pose(3)[1]
    image, depth = _write(tmp_path, R, t)
    box = ",".join(f"{v:g}" for v in bracket_box(R, t))
    camera = ",".join(f"{v:g}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    argv = ["predict", str(model), str(image), "--box", box, "--K", camera, "--depth", str(depth),
            "--depth-scale", str(DEPTH_SCALE)]
    code, out, err = run_cli([*argv, "--json"])
    found = json.loads(out)["predictions"][0]
    assert code == 0 and found["t_source"] == "depth" and np.linalg.norm(np.array(found["t_m2c_mm"]) - t) < 1.0
    code, out, err = run_cli(argv)
    assert code == 0 and "(depth: depth fit" in out
    if importlib.util.find_spec("small_gicp") is not None:
        code, out, err = run_cli([*argv, "--refine", "--json"])
        assert code == 0 and json.loads(out)["predictions"][0]["t_source"] in ("refined", "depth"), err


def _split(folder: Path, R: np.ndarray, t: np.ndarray, depth: bool = True, images: int = 1) -> tuple[Path, Path]:
    """A BOP split of ``images`` views of the bracket (all alike) and its box in each as a detection."""
    scene = folder / "split" / "000001"
    (scene / "gray").mkdir(parents=True)
    (scene / "depth").mkdir(exist_ok=True)  # empty without depth: a split whose images have none
    cameras, detections = {}, []
    for im_id in range(images):
        cv2.imwrite(str(scene / "gray" / f"{im_id:06d}.png"), np.zeros(SHAPE, np.uint8))
        if depth:
            cv2.imwrite(str(scene / "depth" / f"{im_id:06d}.png"),
                        sensor_depth(render_depth(R, t, floor_mm=t[2] + 60.0)[0]))
        cameras[str(im_id)] = {"cam_K": K.ravel().tolist(), "depth_scale": DEPTH_SCALE}
        detections.append({"scene_id": 1, "image_id": im_id, "category_id": 6, "bbox": list(bracket_box(R, t)),
                           "score": 1.0, "time": 0.0})
    (scene / "scene_camera.json").write_text(json.dumps(cameras))
    (folder / "detections.json").write_text(json.dumps(detections))
    return folder / "split", folder / "detections.json"


def test_popcode_run_reads_each_images_depth(exact_model, tmp_path, monkeypatch):
    model, R = exact_model
    t = pose(3)[1]
    split, detections = _split(tmp_path, R, t, images=2)
    out = tmp_path / "results.csv"
    argv = ["run", str(model), "--split", str(split), "--detections", str(detections), "--out", str(out), "--depth",
            "--quiet"]

    def stop(self):  # a run stopped after its first image, resumed by the same command
        raise KeyboardInterrupt
    with monkeypatch.context() as patch:
        patch.setattr(run_loop.Progress, "step", stop)
        assert run_cli(argv)[0] == 130 and not out.exists()
    code, stdout, err = run_cli(argv)
    assert code == 0, err
    lines = out.read_text().splitlines()
    assert len(lines) == 3 and all(np.linalg.norm(np.array(line.split(",")[5].split(), float) - t) < 1.0
                                   for line in lines[1:])
    sources = (tmp_path / "results.translation.csv").read_text().splitlines()
    assert sources[0] == "scene_id,im_id,obj_id,source,depth_fit,note"
    assert [line.split(",")[:4] for line in sources[1:]] == [["1", "0", "6", "depth"], ["1", "1", "6", "depth"]]
    assert "depth 1" in stdout  # this call did the second image; the first came from the stopped one

    # the translation sources are an output of the results file like itself: refused when they exist, replaced
    # with --overwrite, removed when a run without depth replaces the results they described
    out.unlink()
    code, _, err = run_cli(argv)
    assert code == 2 and "--out's translation sources" in err and "exists already" in err
    assert run_cli([*argv, "--overwrite"])[0] == 0
    code, _, err = run_cli([*argv[:-2], "--quiet", "--overwrite"])
    assert code == 0, err
    assert not (tmp_path / "results.translation.csv").exists()
    other = tmp_path / "results.txt"  # another results file of the same stem has its own sources
    code, _, err = run_cli([*argv[:-3], str(other), "--depth", "--quiet"])
    assert code == 0, err
    assert (tmp_path / "results.translation.txt").is_file() and not (tmp_path / "results.translation.csv").exists()

    no_depth, detections = _split(tmp_path / "plain", R, t, depth=False)
    code, _, err = run_cli(["run", str(model), "--split", str(no_depth), "--detections", str(detections),
                            "--out", str(tmp_path / "plain.csv"), "--depth", "--quiet"])
    assert code == 2 and "has no depth image" in err


def test_refine_starts_from_the_codes_strongest_poses_without_listing_them(tmp_path):
    """A code whose strongest peak is the part turned over and whose second is the true pose: refining with the
    default top_k tries the code's REFINE_STARTS strongest poses and keeps the one the depth confirms."""
    pytest.importorskip("small_gicp")
    R_true, t = pose(5)
    wrong = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.pi) @ R_true  # no ICP reaches R_true from it
    pc = PopulationCode(LAYOUT)
    code = np.maximum(pc.encode(wrong), 0.9 * pc.encode(R_true))
    meta = ModelMetadata(Representation.POPULATION_CODE, LAYOUT, {6: INFO})
    estimator = PoseEstimator(save(linear_model(code, metadata=meta), tmp_path / "two-peaks.onnx"), threads=1)
    depth = sensor_depth(render_depth(R_true, t, floor_mm=t[2] + 60.0)[0])
    image, box = np.zeros(SHAPE, np.uint8), bracket_box(R_true, t)
    plain = estimator.predict(image, [box], K=K, depth=depth, depth_scale=DEPTH_SCALE)[0]
    assert np.degrees(geodesic_angle(plain.R_m2c, wrong)) < 10.0  # the argmax is the turned-over pose
    refined = estimator.predict(image, [box], K=K, depth=depth, depth_scale=DEPTH_SCALE, refine_depth=True)[0]
    assert refined.t_source == TranslationSource.REFINED and refined.hypotheses is None
    assert np.degrees(geodesic_angle(refined.R_m2c, R_true)) < 1.0 and np.linalg.norm(refined.t_m2c_mm - t) < 1.0
