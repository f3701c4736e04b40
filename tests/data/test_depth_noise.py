"""Sensor depth: noise that grows with distance, holes where they belong, quantisation, seeded draws, and ground
truth that the noise leaves alone."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import popcode_trainer.data.scene_render as scene_module
from popcode_runtime import PopcodeError
from popcode_runtime.base.files import write_json_atomic
from popcode_trainer.data.bop import RENDER_MARKER, is_scene_split, read_bop_split
from popcode_trainer.data.depth_noise import (
    DEPTH_NOISE_PRESETS,
    DepthNoise,
    apply_depth_noise,
    depth_noise_preset,
    incidence_angle_deg,
)
from popcode_trainer.data.objects import write_builtin_models
from popcode_trainer.data.scene_content import SceneSettings
from popcode_trainer.data.scene_render import render_scene_split
from popcode_trainer.data.sensor import SENSOR_PRESETS

SIDE = 128
NARROW_K = np.array([[4000.0, 0.0, (SIDE - 1) / 2], [0.0, 4000.0, (SIDE - 1) / 2], [0.0, 0.0, 1.0]])  # ~2 deg across
GREY = np.full((SIDE, SIDE, 3), 128, np.uint8)
SCENES = SceneSettings(scenes=3, width=96, height=72, seed=7, parts=(3, 5), sensor="phone")


def _tilted_plane(tilt_deg: float, distance_mm: float = 500.0, K: np.ndarray = NARROW_K) -> np.ndarray:
    """Depth [mm] of a plane through (0, 0, distance) whose normal is tilted by ``tilt_deg`` about the x-axis."""
    normal = np.array([0.0, np.sin(np.radians(tilt_deg)), -np.cos(np.radians(tilt_deg))])
    x = (np.arange(SIDE) - K[0, 2]) / K[0, 0]
    y = (np.arange(SIDE) - K[1, 2]) / K[1, 1]
    rays = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.ones((1, 1))), axis=-1)
    return (normal[2] * distance_mm / (rays @ normal)).astype(np.float32)


def _noisy(depth_mm: np.ndarray, noise: DepthNoise, seed: int = 0, rgb: np.ndarray = GREY) -> np.ndarray:
    return apply_depth_noise(depth_mm, NARROW_K, rgb, np.random.default_rng(seed), noise)


def test_axial_noise_follows_sigma_of_distance() -> None:
    noise = DepthNoise(axial_sigma_floor_mm=0.5, axial_sigma_per_m2_mm=2.0)
    for z_mm in (300.0, 1000.0, 2000.0):
        measured = _noisy(np.full((SIDE, SIDE), z_mm, np.float32), noise) - z_mm
        expected = 0.5 + 2.0 * (z_mm / 1000.0) ** 2
        assert measured.std() == pytest.approx(expected, rel=0.03) and abs(measured.mean()) < 0.05 * expected
    for name, preset in DEPTH_NOISE_PRESETS.items():
        if preset is not None:
            sigmas = preset.axial_sigma_mm(np.array([300.0, 1000.0, 2000.0]))
            assert (np.diff(sigmas) > 0).all(), f"{name}: sigma must grow with distance"
    z_mm = np.array([300.0, 1000.0, 2000.0])
    industrial, webcam, phone = (DEPTH_NOISE_PRESETS[name].axial_sigma_mm(z_mm)
                                 for name in ("industrial", "webcam", "phone"))
    assert (industrial < webcam).all() and (webcam < phone).all()  # structured light beats the phone's ToF


def test_incidence_angle_of_tilted_planes() -> None:
    for tilt_deg in (0.0, 30.0, 60.0, 75.0):
        angle_deg = incidence_angle_deg(_tilted_plane(tilt_deg), NARROW_K)
        assert np.abs(angle_deg - tilt_deg).max() < 2.5  # the narrow view sees the plane at about its tilt
    K = np.array([[100.0, 0.0, 63.5], [0.0, 100.0, 63.5], [0.0, 0.0, 1.0]])  # wide: the ray's angle shows
    angle_deg = incidence_angle_deg(np.full((SIDE, SIDE), 400.0, np.float32), K)
    assert angle_deg[64, 64] < 0.5 and angle_deg[64, 0] == pytest.approx(np.degrees(np.arctan(63.5 / 100)), abs=0.1)
    step = np.full((SIDE, SIDE), 500.0, np.float32)
    step[:, 64:] = 300.0  # a depth edge: each side keeps its own surface's normal
    flat = incidence_angle_deg(np.full((SIDE, SIDE), 500.0, np.float32), NARROW_K)
    assert np.allclose(incidence_angle_deg(step, NARROW_K), flat, atol=0.05)  # float32 arccos near 0 deg
    assert incidence_angle_deg(np.zeros((4, 4), np.float32), NARROW_K).min() == 90.0  # nothing seen


def test_holes_appear_on_steep_and_dark_surfaces() -> None:
    noise = DepthNoise(hole_angle_deg=(60.0, 85.0), hole_patch_px=2.0)
    for tilt_deg, share in ((20.0, 0.0), (50.0, 0.0), (70.0, 0.4), (80.0, 0.8)):
        holes = (_noisy(_tilted_plane(tilt_deg), noise) == 0).mean()
        assert holes == pytest.approx(share, abs=0.07), f"tilt {tilt_deg} deg"
    dark = GREY.copy()
    dark[:, : SIDE // 2] = 0
    plane = np.full((SIDE, SIDE), 500.0, np.float32)
    holes = _noisy(plane, DepthNoise(dark_level=0.05, dark_hole_p=0.6), rgb=dark) == 0
    assert holes[:, : SIDE // 2].mean() == pytest.approx(0.6, abs=0.03) and not holes[:, SIDE // 2:].any()
    patchy = _noisy(_tilted_plane(72.0), dataclasses.replace(noise, hole_patch_px=3.0)) == 0
    single = _noisy(_tilted_plane(72.0), dataclasses.replace(noise, hole_patch_px=0.0)) == 0
    assert _hole_neighbours(patchy) > _hole_neighbours(single) + 0.2  # patches: a hole's neighbour is a hole


def _hole_neighbours(holes: np.ndarray) -> float:
    """Share of the holes whose right-hand neighbour is a hole too."""
    return float((holes[:, :-1] & holes[:, 1:]).sum() / max(holes[:, :-1].sum(), 1))


def test_depth_edges_drop_out_or_fly_between_the_surfaces() -> None:
    depth = np.full((SIDE, SIDE), 500.0, np.float32)
    depth[40:90, 40:90] = 400.0  # a raised square
    noise = DepthNoise(edge_width_px=1, edge_dropout_p=0.5, flying_pixel_p=0.5)
    measured = _noisy(depth, noise)
    changed = measured != depth
    border = cv2.dilate((np.abs(cv2.Laplacian(depth, cv2.CV_32F)) > 0).astype(np.uint8), np.ones((3, 3))) > 0
    assert changed.any() and not (changed & ~border).any(), "only pixels next to the jump change"
    lost, flying = changed & (measured == 0), changed & (measured > 0)
    assert lost.sum() / changed.sum() == pytest.approx(0.5, abs=0.1)
    assert ((measured[flying] > 400.0) & (measured[flying] < 500.0)).all()
    wide = _noisy(depth, dataclasses.replace(noise, edge_width_px=3)) != depth
    assert wide.sum() > 2 * changed.sum()
    assert np.array_equal(_noisy(np.full((SIDE, SIDE), 500.0, np.float32), noise), np.full((SIDE, SIDE), 500.0))


def test_quantisation_to_disparity_and_output_steps() -> None:
    whole_mm = _noisy(_tilted_plane(30.0), DepthNoise(axial_sigma_floor_mm=3.0, output_step_mm=1.0))
    assert np.array_equal(whole_mm, np.round(whole_mm)) and len(np.unique(whole_mm)) > 5
    noise = DepthNoise(axial_sigma_floor_mm=20.0, disparity_step_at_1m_mm=2.9)
    for z_mm in (1000.0, 2000.0):
        step_mm = 2.9 * (z_mm / 1000.0) ** 2
        levels = np.unique(_noisy(np.full((SIDE, SIDE), z_mm, np.float32), noise))
        assert np.median(np.diff(levels[np.abs(levels - z_mm) < 3 * step_mm])) == pytest.approx(step_mm, rel=0.03)


def test_none_is_exact_and_draws_are_seeded() -> None:
    assert depth_noise_preset("none") is None and set(DEPTH_NOISE_PRESETS) == set(SENSOR_PRESETS)
    depth = _tilted_plane(70.0)
    depth[50:70, 50:70] -= 100.0
    for name in ("industrial", "webcam", "phone"):
        preset = depth_noise_preset(name)
        first, again, other = (_noisy(depth, preset, seed) for seed in (3, 3, 4))
        assert np.array_equal(first, again) and not np.array_equal(first, other)
    assert np.array_equal(_noisy(depth, DepthNoise()), depth)  # every effect off: the exact depth


def test_bad_parameters_are_one_line_errors() -> None:
    for bad in ({"axial_sigma_floor_mm": -1.0}, {"axial_sigma_per_m2_mm": float("nan")}, {"edge_dropout_p": 1.5},
                {"edge_dropout_p": 0.7, "flying_pixel_p": 0.5}, {"edge_width_px": 0}, {"edge_width_px": 1.5},
                {"edge_jump_fraction": 0.0}, {"hole_angle_deg": (80.0, 60.0)}, {"hole_angle_deg": (60.0, 95.0)},
                {"dark_level": 2.0}, {"hole_patch_px": float("inf")}, {"output_step_mm": "1"}):
        with pytest.raises(PopcodeError) as error:
            DepthNoise(**bad)
        message = str(error.value)
        assert "\n" not in message and "depth noise" in message and next(iter(bad)) in message
    with pytest.raises(PopcodeError, match="unknown sensor preset"):
        depth_noise_preset("kinect")
    with pytest.raises(PopcodeError, match="differ in size"):
        apply_depth_noise(np.ones((4, 5), np.float32), NARROW_K, GREY, np.random.default_rng(0), DepthNoise())


@pytest.fixture(scope="module")
def splits(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """The built-in parts under the phone's depth noise, the same render with exact depth, and the models."""
    folder = tmp_path_factory.mktemp("depth_noise")
    models = write_builtin_models(folder / "models")
    render_scene_split(models, folder / "noisy", SCENES, progress=False)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(scene_module, "apply_depth_noise", lambda depth_mm, *args: depth_mm)
        render_scene_split(models, folder / "exact", SCENES, progress=False)
    return folder / "noisy", folder / "exact", models


def _files(split: Path, folder: str) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(split.glob(f"*/{folder}/*"))}


def test_noise_leaves_the_ground_truth_alone(splits: tuple[Path, Path, Path]) -> None:
    noisy, exact, _ = splits
    for folder in ("mask", "mask_visib"):
        assert _files(noisy, folder) == _files(exact, folder) and _files(noisy, folder)
    scene = "000000"
    assert (noisy / scene / "scene_gt.json").read_bytes() == (exact / scene / "scene_gt.json").read_bytes()
    infos = {name: json.loads((split / scene / "scene_gt_info.json").read_text()) for name, split in
             (("noisy", noisy), ("exact", exact))}
    measured_fewer = 0
    for im_id, instances in infos["noisy"].items():
        depth = cv2.imread(str(noisy / scene / "depth" / f"{int(im_id):06d}.png"), cv2.IMREAD_UNCHANGED)
        truth = cv2.imread(str(exact / scene / "depth" / f"{int(im_id):06d}.png"), cv2.IMREAD_UNCHANGED)
        assert (depth == 0).any() and not (truth == 0).any() and not np.array_equal(depth, truth)
        both = (depth > 0) & (truth > 0)
        assert np.median(np.abs(depth[both].astype(float) - truth[both])) * 0.1 < 5.0  # mm: noise, not garbage
        for index, (info, exact_info) in enumerate(zip(instances, infos["exact"][im_id], strict=True)):
            valid = exact_info.pop("px_count_valid")
            mask = cv2.imread(str(noisy / scene / "mask" / f"{int(im_id):06d}_{index:06d}.png"), 0) > 0
            assert info.pop("px_count_valid") == (depth[mask] > 0).sum() <= valid == mask.sum()
            measured_fewer += int((depth[mask] > 0).sum() < valid)
            assert info == exact_info  # visib_fract, boxes and counts: the exact depth's
    assert measured_fewer > 0


def test_the_split_records_its_depth_noise_and_old_splits_still_read(splits: tuple[Path, Path, Path],
                                                                     tmp_path: Path) -> None:
    noisy, _, models = splits
    settings = json.loads((noisy / RENDER_MARKER).read_text())
    assert settings["depth_noise"] == json.loads(json.dumps(dataclasses.asdict(DEPTH_NOISE_PRESETS["phone"])))
    exact_settings = dataclasses.replace(SCENES, scenes=1, sensor="none")
    render_scene_split(models, tmp_path / "none", exact_settings, progress=False)
    assert "depth_noise" not in json.loads((tmp_path / "none" / RENDER_MARKER).read_text())

    del settings["depth_noise"]  # as written before depth noise existed
    write_json_atomic(noisy / RENDER_MARKER, settings)
    try:
        assert is_scene_split(noisy) and read_bop_split(noisy, models, min_visib_fract=0.0).instances
        with pytest.raises(PopcodeError, match="other settings"):  # its depth is exact: noisy images must not join
            render_scene_split(models, noisy, SCENES, progress=False)
    finally:
        settings["depth_noise"] = json.loads(json.dumps(dataclasses.asdict(DEPTH_NOISE_PRESETS["phone"])))
        write_json_atomic(noisy / RENDER_MARKER, settings)


def test_shards_render_the_same_noisy_depth(splits: tuple[Path, Path, Path], tmp_path: Path) -> None:
    noisy, _, models = splits
    for index in range(2):
        render_scene_split(models, tmp_path / "merged", SCENES, shard=(index, 2), progress=False)
    assert _files(tmp_path / "merged", "depth") == _files(noisy, "depth")
