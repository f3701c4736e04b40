"""The metrics agree with the BOP toolkit's own code.

``bop_reference/`` holds a small concave mesh, poses, and every error the
unmodified toolkit computed for them (``bop_reference/make_reference.py``, run
once offline; the toolkit is not part of popcode). Here popcode recomputes them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from popcode_runtime.geometry.symmetries import SymmetryTransforms, symmetry_transforms
from popcode_trainer.data.gl import DepthRenderer
from popcode_trainer.data.meshes import load_mesh
from popcode_trainer.eval.pipeline.instance_errors import ObjectModel, compute_instance_errors
from popcode_trainer.metrics.pose_errors import (
    add,
    adi,
    mspd,
    mssd,
    proj,
    rotation_error_deg,
    translation_error_mm,
    vsd_from_depths,
)
from popcode_trainer.metrics.recall import Thresholds

REFERENCE = Path(__file__).parent / "bop_reference"
REF = json.loads((REFERENCE / "reference.json").read_text())
PAIRS = REF["pairs"]
K = np.array(REF["K"])
WIDTH, HEIGHT = REF["image_size"]
DEPTHS = np.load(REFERENCE / "depths.npz")


def _value(x):
    return np.asarray([float(v) for v in x] if isinstance(x, list) else float(x))


def _pose(pair: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return tuple(np.array(pair[key], dtype=np.float64) for key in ("R_est", "t_est", "R_gt", "t_gt"))


@pytest.fixture(scope="module")
def mesh():
    return load_mesh(REFERENCE / REF["mesh"])


@pytest.fixture(scope="module")
def renderer(mesh):
    renderer = DepthRenderer(mesh.vertices, mesh.faces, WIDTH, HEIGHT)
    yield renderer
    renderer.close()


def _syms(name: str) -> SymmetryTransforms:
    return symmetry_transforms(REF["models_info"][name], REF["max_sym_disc_step"])


def test_vertices_are_read_in_float64_as_the_toolkit_reads_them(mesh) -> None:
    assert float(pdist(mesh.vertices).max()) == pytest.approx(REF["diameter_mm"], rel=1e-14)
    assert not np.array_equal(mesh.vertices, mesh.vertices.astype(np.float32))  # float32 would lose digits


@pytest.mark.parametrize("name", sorted(REF["symmetry_transforms"]))
def test_symmetry_transforms_are_the_toolkits(name: str) -> None:
    ours = _syms(name)
    theirs = REF["symmetry_transforms"][name]
    as_rows = [np.concatenate([np.ravel(R), t]) for R, t in zip(ours.R, ours.t_mm, strict=True)]
    ref_rows = [np.concatenate([np.ravel(s["R"]), s["t"]]) for s in theirs]
    ours_sorted, theirs_sorted = (np.array(sorted(rows, key=lambda r: tuple(np.round(r, 9)))) for rows in
                                  (as_rows, ref_rows))
    assert ours_sorted.shape == theirs_sorted.shape
    np.testing.assert_allclose(ours_sorted, theirs_sorted, atol=1e-12)


@pytest.mark.parametrize("pair", PAIRS, ids=[f"{i}-{p['kind']}" for i, p in enumerate(PAIRS)])
def test_vertex_errors_are_the_toolkits(pair: dict, mesh) -> None:
    R_e, t_e, R_g, t_g = _pose(pair)
    pts, syms, expected = mesh.vertices, _syms(REF["errors_use_symmetries"]), pair["errors"]
    ours = {
        "mssd": mssd(R_e, t_e, R_g, t_g, pts, syms),
        "mssd_no_sym": mssd(R_e, t_e, R_g, t_g, pts, None),
        "mspd": mspd(R_e, t_e, R_g, t_g, K, pts, syms),
        "mspd_no_sym": mspd(R_e, t_e, R_g, t_g, K, pts, None),
        "add": add(R_e, t_e, R_g, t_g, pts),
        "adi": adi(R_e, t_e, R_g, t_g, pts),
        "re": rotation_error_deg(R_e, R_g),
        "te": translation_error_mm(t_e, t_g),
        "proj": proj(R_e, t_e, R_g, t_g, K, pts),
    }
    for name, value in ours.items():
        # The toolkit's re is acos of the trace: 1e-7 deg of rounding near 0 and 180 deg, where ours is exact.
        atol = 2e-6 if name == "re" else 1e-9
        np.testing.assert_allclose(value, _value(expected[name]), rtol=1e-9, atol=atol, err_msg=name)


@pytest.mark.parametrize("pair", PAIRS, ids=[f"{i}-{p['kind']}" for i, p in enumerate(PAIRS)])
def test_vsd_and_vss_are_the_toolkits(pair: dict, renderer) -> None:
    i = PAIRS.index(pair)
    R_e, t_e, R_g, t_g = _pose(pair)
    depth_test = DEPTHS[f"gt_{i}"]
    est, gt = renderer.render(K, R_e, t_e), renderer.render(K, R_g, t_g)
    # Our renderer draws what the toolkit's draws: the same pixels, depths within float32 rounding.
    for ours, theirs in ((est, DEPTHS[f"est_{i}"]), (gt, depth_test)):
        assert np.array_equal(ours > 0, theirs > 0)
        np.testing.assert_allclose(ours, theirs, atol=0.05)
    args = (depth_test, K, REF["vsd_delta_mm"])
    for depth_est, depth_gt in ((DEPTHS[f"est_{i}"], depth_test), (est, gt)):
        vsd = vsd_from_depths(depth_est, depth_gt, *args, REF["vsd_taus"], REF["diameter_mm"])
        vss = vsd_from_depths(depth_est, depth_gt, *args, [np.inf], REF["diameter_mm"])
        np.testing.assert_allclose(vsd, _value(pair["errors"]["vsd"]), atol=1e-12)
        np.testing.assert_allclose(vss, _value(pair["errors"]["vss"]), atol=1e-12)


def test_errors_are_gated_by_the_bounding_spheres_as_the_toolkit_gates_them(mesh, renderer) -> None:
    R_e, t_e, R_g, t_g = (np.stack(arrays) for arrays in zip(*(_pose(p) for p in PAIRS), strict=True))
    info = dict(REF["models_info"][REF["errors_use_symmetries"]], diameter=REF["diameter_mm"])
    thresholds = Thresholds(vsd_taus=tuple(REF["vsd_taus"]), vsd_delta_mm=REF["vsd_delta_mm"])
    count = len(PAIRS)
    errors = compute_instance_errors(
        np.ones(count, int), R_e, R_g, t_g, np.broadcast_to(K, (count, 3, 3)), np.full(count, WIDTH),
        {1: ObjectModel.from_info(mesh.vertices, info)}, thresholds,
        depth_mm=[DEPTHS[f"gt_{i}"] for i in range(count)],
        make_render_depth=lambda _obj, _K, _w, _h: lambda R, t: renderer.render(K, R, t), t_est_mm=t_e)
    assert not all(p["spheres_overlap"] for p in PAIRS) and not all(p["sphere_projections_overlap"] for p in PAIRS)
    for i, pair in enumerate(PAIRS):
        gated = pair["gated"]
        np.testing.assert_allclose(errors.mssd_mm[i], float(gated["mssd"]), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(errors.adi_mm[i], float(gated["adi"]), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(errors.mspd_px[i], pair["errors"]["mspd"], rtol=1e-9, atol=1e-9)  # never gated
        np.testing.assert_allclose(errors.vsd[i], _value(gated["vsd"]), atol=1e-12)
