"""Reference values of the BOP metrics, computed by the unmodified BOP toolkit (run once, offline).

    EGL_PLATFORM=surfaceless PYOPENGL_PLATFORM=egl python make_reference.py --toolkit /path/to/bop_toolkit

needs numpy, scipy, imageio, pypng, vispy and PyOpenGL beside a checkout of
github.com/thodan/bop_toolkit (not part of popcode). It writes, next to itself:
``mesh.ply`` (a small concave part made here), ``reference.json`` (poses,
camera, symmetries and every error the toolkit computes) and ``depths.npz``
(the toolkit renderer's depth of every pose). ``tests/eval/test_bop_toolkit.py``
recomputes everything with popcode and compares.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
WIDTH, HEIGHT = 160, 120
K = np.array([[200.0, 0.0, 79.3], [0.0, 201.5, 61.7], [0.0, 0.0, 1.0]])
VSD_DELTA_MM = 15.0
VSD_TAUS = np.arange(0.05, 0.51, 0.05)  # fractions of the diameter, as eval_bop19_pose.py
OBJ_ID = 1


def l_shaped_part() -> tuple[np.ndarray, np.ndarray]:
    """An L-shaped prism (concave, so it hides parts of itself) whose coordinates float32 cannot hold exactly.

    The top face is wound the wrong way on purpose: a renderer that culls back
    faces loses it, the toolkit's does not.
    """
    outline = np.array([[0.0, 0.0], [60.0, 0.0], [60.0, 20.0], [20.0, 20.0], [20.0, 50.0], [0.0, 50.0]])
    outline = (outline - [21.3, 17.9]) * 1.000000123 + 0.00000037
    half_height = 12.345678912
    vertices = np.concatenate([np.c_[outline, np.full(6, -half_height)], np.c_[outline, np.full(6, half_height)]])
    fan = [(0, i, i + 1) for i in range(1, 5)]
    bottom = [(a, c, b) for a, b, c in fan]  # seen from -z: counter-clockwise
    top_wrong = [(a + 6, c + 6, b + 6) for a, b, c in fan]  # should be (a, b, c): reversed on purpose
    sides = []
    for i in range(6):
        j = (i + 1) % 6
        sides += [(i, j, j + 6), (i, j + 6, i + 6)]
    return vertices, np.array(bottom + top_wrong + sides)


def write_ascii_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
             "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(f"{v:.9f}" for v in vertex) for vertex in vertices]
    lines += ["3 " + " ".join(str(i) for i in face) for face in faces]
    path.write_text("\n".join(lines) + "\n")


def rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * skew + (1 - np.cos(angle_rad)) * skew @ skew


def pose_pairs(rng: np.random.Generator, symmetry_R: np.ndarray) -> list[dict[str, list]]:
    """Ground truth and estimate pairs from identical to far apart; one estimate too far for the spheres to meet."""
    pairs = []
    kinds = ["same", "close", "close", "medium", "medium", "far", "far", "symmetric", "random", "random",
             "beside", "deeper", "behind-spheres-apart"]
    for kind in kinds:
        R_gt = rotation(rng.normal(size=3), rng.uniform(0, np.pi))
        t_gt = np.array([rng.uniform(-20, 20), rng.uniform(-15, 15), rng.uniform(280, 340)])
        R_est, t_est = R_gt.copy(), t_gt.copy()
        if kind in ("close", "medium", "far"):
            degrees, mm = {"close": (2.0, 2.0), "medium": (8.0, 8.0), "far": (35.0, 20.0)}[kind]
            R_est = rotation(rng.normal(size=3), np.radians(degrees)) @ R_gt
            t_est = t_gt + rng.normal(size=3) / np.sqrt(3) * mm
        elif kind == "symmetric":
            R_est = R_gt @ symmetry_R
        elif kind == "random":
            R_est = rotation(rng.normal(size=3), rng.uniform(0, np.pi))
        elif kind == "beside":
            t_est = t_gt + [45.0, -10.0, 5.0]
        elif kind == "deeper":
            t_est = t_gt + [0.0, 0.0, 30.0]
        elif kind == "behind-spheres-apart":
            t_est = t_gt + [150.0, 0.0, 0.0]
        pairs.append({"kind": kind, "R_est": R_est.tolist(), "t_est": t_est.tolist(),
                      "R_gt": R_gt.tolist(), "t_gt": t_gt.tolist()})
    return pairs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--toolkit", required=True, type=Path, help="a checkout of thodan/bop_toolkit")
    parser.add_argument("--commit", help="the toolkit's commit, when --toolkit is an export without .git")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(args.toolkit))
    from bop_toolkit_lib import inout, misc, pose_error
    from bop_toolkit_lib.rendering import renderer_vispy

    vertices, faces = l_shaped_part()
    mesh_path = HERE / "mesh.ply"
    write_ascii_ply(mesh_path, vertices, faces)
    pts = inout.load_ply(str(mesh_path))["pts"]
    diameter = float(misc.calc_pts_diameter(pts))

    symmetry_R = rotation(np.array([0.0, 0.0, 1.0]), np.pi)
    symmetric_T = np.eye(4)
    symmetric_T[:3, :3], symmetric_T[:3, 3] = symmetry_R, [1.5, -2.25, 0.0]
    models_info = {
        "discrete_2fold": {"diameter": diameter, "symmetries_discrete": [symmetric_T.reshape(-1).tolist()]},
        "continuous": {"diameter": diameter, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},
        "continuous_flip": {"diameter": diameter,
                            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
                            "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]]},
    }
    transforms = {name: [{"R": s["R"].tolist(), "t": s["t"].reshape(-1).tolist()}
                         for s in misc.get_symmetry_transformations(info, 0.01)]
                  for name, info in models_info.items()}
    syms_2fold = misc.get_symmetry_transformations(models_info["discrete_2fold"], 0.01)
    no_syms = [{"R": np.eye(3), "t": np.zeros((3, 1))}]

    renderer = renderer_vispy.RendererVispy(WIDTH, HEIGHT, mode="depth")
    renderer.add_object(OBJ_ID, str(mesh_path))

    def depth(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        return renderer.render_object(OBJ_ID, R, t, K[0, 0], K[1, 1], K[0, 2], K[1, 2])["depth"].astype(np.float32)

    pairs = pose_pairs(np.random.default_rng(2024), symmetry_R)
    depths = {}
    for i, pair in enumerate(pairs):
        R_e, R_g = np.array(pair["R_est"]), np.array(pair["R_gt"])
        t_e, t_g = np.array(pair["t_est"]).reshape(3, 1), np.array(pair["t_gt"]).reshape(3, 1)
        depth_test = depth(R_g, t_g)
        depths[f"gt_{i}"], depths[f"est_{i}"] = depth_test, depth(R_e, t_e)
        vsd_args = (depth_test, K, VSD_DELTA_MM)
        errors = {
            "mssd": pose_error.mssd(R_e, t_e, R_g, t_g, pts, syms_2fold),
            "mssd_no_sym": pose_error.mssd(R_e, t_e, R_g, t_g, pts, no_syms),
            "mspd": pose_error.mspd(R_e, t_e, R_g, t_g, K, pts, syms_2fold),
            "mspd_no_sym": pose_error.mspd(R_e, t_e, R_g, t_g, K, pts, no_syms),
            "add": pose_error.add(R_e, t_e, R_g, t_g, pts),
            "adi": pose_error.adi(R_e, t_e, R_g, t_g, pts),
            "re": pose_error.re(R_e, R_g),
            "te": pose_error.te(t_e, t_g),
            "proj": pose_error.proj(R_e, t_e, R_g, t_g, K, pts),
            "vsd": pose_error.vsd(R_e, t_e, R_g, t_g, *vsd_args, VSD_TAUS, True, diameter, renderer, OBJ_ID, "step"),
            "vss": pose_error.vsd(R_e, t_e, R_g, t_g, *vsd_args, [np.inf], True, diameter, renderer, OBJ_ID, "step"),
        }
        # scripts/eval_calc_errors.py: errors of poses whose bounding spheres (or their projections) cannot overlap.
        spheres_overlap = bool(np.linalg.norm(t_e - t_g) < diameter)
        projections_overlap = bool(misc.overlapping_sphere_projections(0.5 * diameter, t_e.squeeze(), t_g.squeeze()))
        pair["errors"] = {name: np.asarray(value, np.float64).tolist() for name, value in errors.items()}
        pair["spheres_overlap"], pair["sphere_projections_overlap"] = spheres_overlap, projections_overlap
        pair["gated"] = {
            "mssd": errors["mssd"] if spheres_overlap else float("inf"),
            "add": errors["add"] if spheres_overlap else float("inf"),
            "adi": errors["adi"] if spheres_overlap else float("inf"),
            "vsd": list(errors["vsd"]) if projections_overlap else [1.0] * len(VSD_TAUS),
        }
    np.savez_compressed(HERE / "depths.npz", **depths)
    commit = args.commit or subprocess.run(["git", "-C", str(args.toolkit), "rev-parse", "HEAD"],
                                           capture_output=True, text=True).stdout.strip()
    reference = {
        "toolkit_commit": commit or "unknown (not a git checkout)",
        "versions": {name: importlib.metadata.version(name) for name in ("numpy", "scipy", "vispy", "PyOpenGL")},
        "mesh": mesh_path.name, "obj_id": OBJ_ID, "diameter_mm": diameter,
        "image_size": [WIDTH, HEIGHT], "K": K.tolist(),
        "vsd_delta_mm": VSD_DELTA_MM, "vsd_taus": VSD_TAUS.tolist(), "vsd_normalized_by_diameter": True,
        "max_sym_disc_step": 0.01, "models_info": models_info, "symmetry_transforms": transforms,
        "errors_use_symmetries": "discrete_2fold",
        "gating": "mssd/add/adi: inf unless |t_est - t_gt| < diameter; vsd: 1 unless the bounding spheres' "
                  "projections overlap (misc.overlapping_sphere_projections, radius diameter/2); others ungated",
        "pairs": pairs,
    }
    text = json.dumps(reference, indent=1).replace("Infinity", '"inf"')
    (HERE / "reference.json").write_text(text + "\n")
    print(f"{len(pairs)} pose pairs, diameter {diameter:.6f} mm -> {HERE}")


if __name__ == "__main__":
    main()
