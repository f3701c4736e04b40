"""All per-instance errors of one method on one split: what ``popcode-train evaluate`` calls.

Rotation only, as in the paper, unless estimated translations are given: then
every error is of the full 6-D pose.
Vertex-based errors are batched per object; VSD renders each instance twice.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.symmetries import SymmetryTransforms, symmetry_transforms

from ...metrics.pose_errors import (
    RenderDepth,
    adi,
    mspd,
    mssd,
    sphere_projections_overlap,
    spheres_overlap,
    vsd_from_depths,
)
from ...metrics.recall import InstanceErrors, Thresholds

MakeRenderDepth = Callable[[int, np.ndarray, int, int], RenderDepth]
"""``make_render_depth(obj_id, K, width, height) -> render_depth``: a non-anti-aliased depth renderer."""


@dataclass(frozen=True)
class ObjectModel:
    """What the errors need of one object: every vertex of its evaluation mesh, diameter, symmetries."""

    pts_mm: np.ndarray  # (P, 3)
    diameter_mm: float
    syms: SymmetryTransforms

    @classmethod
    def from_info(cls, pts_mm: np.ndarray, info: Mapping[str, Any], max_sym_disc_step: float = 0.01) -> ObjectModel:
        """From the mesh vertices and the object's ``models_info.json`` entry."""
        if "diameter" not in info:
            raise PopcodeError("the models_info.json entry has no 'diameter'")
        syms = symmetry_transforms(info, max_sym_disc_step)
        return cls(np.asarray(pts_mm, np.float64), float(info["diameter"]), syms)


def _vsd_errors(
    obj_id: np.ndarray,
    R_est: np.ndarray,
    t_est_mm: np.ndarray,
    R_gt: np.ndarray,
    t_gt_mm: np.ndarray,
    K: np.ndarray,
    depth_mm: Sequence[np.ndarray],
    models: Mapping[int, ObjectModel],
    make_render_depth: MakeRenderDepth,
    th: Thresholds,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """VSD over ``th.vsd_taus`` ``(N, T)``, at ``th.vsd_single_tau_mm`` ``(N,)`` and VSS ``(N,)``.

    As the toolkit's ``eval_calc_errors.py``, a pose whose bounding sphere's
    silhouette cannot meet the ground truth's gets error 1 without rendering.
    """
    vsd_bop, vsd_single, vss = [], [], []
    for i, depth_test in enumerate(depth_mm):
        model = models[int(obj_id[i])]
        if not sphere_projections_overlap(t_est_mm[i], t_gt_mm[i], model.diameter_mm):
            vsd_bop.append(np.ones(len(th.vsd_taus)))
            vsd_single.append(1.0)
            vss.append(1.0)
            continue
        height, width = np.shape(depth_test)
        render = make_render_depth(int(obj_id[i]), K[i], width, height)
        depth_est, depth_gt = render(R_est[i], t_est_mm[i]), render(R_gt[i], t_gt_mm[i])
        vsd_bop.append(vsd_from_depths(depth_est, depth_gt, depth_test, K[i], th.vsd_delta_mm, th.vsd_taus,
                                       model.diameter_mm))
        single, inf = vsd_from_depths(depth_est, depth_gt, depth_test, K[i], th.vsd_delta_mm,
                                      [th.vsd_single_tau_mm, np.inf])
        vsd_single.append(single)
        vss.append(inf)
    return np.array(vsd_bop).reshape(len(obj_id), len(th.vsd_taus)), np.array(vsd_single), np.array(vss)


def compute_instance_errors(
    obj_id: np.ndarray,
    R_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt_mm: np.ndarray,
    K: np.ndarray,
    image_width_px: np.ndarray,
    models: Mapping[int, ObjectModel],
    thresholds: Thresholds | None = None,
    depth_mm: Sequence[np.ndarray] | None = None,
    make_render_depth: MakeRenderDepth | None = None,
    t_est_mm: np.ndarray | None = None,
) -> InstanceErrors:
    """Errors of ``N`` rotation estimates against the ground truth, with the ground-truth translation.

    ``obj_id (N,)``, rotations ``(N, 3, 3)`` model-to-camera, ``t_gt_mm (N, 3)``,
    intrinsics ``K (N, 3, 3)``, ``image_width_px (N,)``; ``depth_mm`` the N test
    depth images [mm] (0 = no depth). Without depth images VSD, e_VSD<0.3 and VSS
    are skipped with a warning. ``t_est_mm (N, 3)`` replaces the ground-truth
    translation of the estimates: the errors of full 6-D poses, gated as the
    toolkit gates them (MSSD and ADI infinite, VSD 1 where the bounding spheres,
    or their silhouettes, cannot overlap).
    """
    th = thresholds or Thresholds()
    obj_id = np.asarray(obj_id).astype(int)
    R_est, R_gt = np.asarray(R_est, np.float64), np.asarray(R_gt, np.float64)
    t_gt_mm, K = np.asarray(t_gt_mm, np.float64), np.asarray(K, np.float64)
    t_est_mm = t_gt_mm if t_est_mm is None else np.asarray(t_est_mm, np.float64)
    count = len(obj_id)
    if not (len(R_est) == len(R_gt) == len(t_gt_mm) == len(t_est_mm) == len(K) == len(image_width_px) == count):
        raise PopcodeError(
            f"per-instance inputs differ in length: {count} object ids, {len(R_est)} estimates, "
            f"{len(R_gt)} ground-truth rotations, {len(t_gt_mm)} translations, {len(K)} intrinsics"
        )
    missing = sorted(set(obj_id.tolist()) - set(models))
    if missing:
        raise PopcodeError(f"no object model for object ids {missing}")
    mssd_mm, mspd_px, adi_mm = np.empty(count), np.empty(count), np.empty(count)
    for obj in np.unique(obj_id):
        model, rows = models[int(obj)], np.flatnonzero(obj_id == obj)
        args = (R_est[rows], t_est_mm[rows], R_gt[rows], t_gt_mm[rows])
        # As the toolkit's eval_calc_errors.py: infinite where the bounding spheres cannot overlap.
        near = spheres_overlap(t_est_mm[rows], t_gt_mm[rows], model.diameter_mm)
        mssd_mm[rows], adi_mm[rows] = np.inf, np.inf
        if near.any():
            near_args = tuple(a[near] for a in args)
            mssd_mm[rows[near]] = mssd(*near_args, model.pts_mm, model.syms)
            adi_mm[rows[near]] = adi(*near_args, model.pts_mm)
        # MSPD takes one camera: batch the instances that share intrinsics.
        cameras, camera_of_row = np.unique(K[rows].reshape(len(rows), 9), axis=0, return_inverse=True)
        for c, camera in enumerate(cameras):
            sub = rows[camera_of_row.reshape(-1) == c]
            mspd_px[sub] = mspd(R_est[sub], t_est_mm[sub], R_gt[sub], t_gt_mm[sub], camera.reshape(3, 3),
                                model.pts_mm, model.syms)
    vsd = vsd_single = vss = None
    if depth_mm is None:
        warnings.warn("no depth images: VSD, e_VSD<0.3 and VSS are skipped", stacklevel=2)
    elif make_render_depth is None:
        raise PopcodeError("VSD needs a depth renderer (make_render_depth) besides the depth images")
    elif len(depth_mm) != count:
        raise PopcodeError(f"{len(depth_mm)} depth images for {count} instances")
    else:
        vsd, vsd_single, vss = _vsd_errors(obj_id, R_est, t_est_mm, R_gt, t_gt_mm, K, depth_mm, models,
                                           make_render_depth, th)
    return InstanceErrors(obj_id, np.asarray(image_width_px, np.float64), mssd_mm, mspd_px, adi_mm,
                          vsd, vsd_single, vss)
