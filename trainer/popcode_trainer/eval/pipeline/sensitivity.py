"""Metric sensitivity to rotation error (the paper's Fig. 4): how each BOP error grows as a ground-truth pose is
rotated away from itself.

The ground-truth pose of an object is rotated by growing angles about one random
axis (in the camera frame, about the object's centre) and every metric's error is
computed at each angle, normalised to be dimensionless; reporting draws them
(:func:`popcode_trainer.eval.reporting.figures.plot_sensitivity`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_runtime.geometry.symmetries import SymmetryTransforms

from ...metrics.pose_errors import RenderDepth, add, adi, mspd, mssd, vsd_from_depths


@dataclass(frozen=True)
class SensitivityCurves:
    """Normalised errors ``(A,)`` per metric for rotation errors ``angles_deg (A,)``.

    MSSD, ADD and ADI are divided by the diameter; MSPD by the diameter's
    projected length ``f_x diameter / t_z`` [px]; VSD (tau given in mm) and VSS
    are in [0, 1] already.
    """

    angles_deg: np.ndarray
    axis: np.ndarray  # (3,) unit axis of the perturbation, camera frame
    errors: dict[str, np.ndarray]


def sensitivity_curves(
    pts_mm: np.ndarray,
    syms: SymmetryTransforms | None,
    diameter_mm: float,
    K: np.ndarray,
    R_gt: np.ndarray,
    t_gt_mm: np.ndarray,
    angles_deg: np.ndarray,
    rng: np.random.Generator,
    render_depth: RenderDepth | None = None,
    vsd_delta_mm: float = 15.0,
    vsd_tau_mm: float = 20.0,
) -> SensitivityCurves:
    """Errors of the ground truth rotated by ``angles_deg`` about a random axis drawn from ``rng``.

    The translation stays the ground truth's, as in the paper's evaluation. With
    ``render_depth`` (see :data:`popcode_trainer.metrics.pose_errors.RenderDepth`) the
    VSD and VSS curves are added; the test image is then the object alone in its
    ground-truth pose.
    """
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angles_deg = np.asarray(angles_deg, dtype=np.float64)
    R_est = axis_angle_to_matrix(np.broadcast_to(axis, angles_deg.shape + (3,)), np.radians(angles_deg)) @ R_gt
    t = np.asarray(t_gt_mm, dtype=np.float64)
    projected_diameter_px = K[0, 0] * diameter_mm / t[2]
    errors = {
        "MSSD": mssd(R_est, t, R_gt, t, pts_mm, syms) / diameter_mm,
        "MSPD": mspd(R_est, t, R_gt, t, K, pts_mm, syms) / projected_diameter_px,
        "ADD": add(R_est, t, R_gt, t, pts_mm) / diameter_mm,
        "ADI": adi(R_est, t, R_gt, t, pts_mm) / diameter_mm,
    }
    if render_depth is not None:
        depth_gt = render_depth(np.asarray(R_gt, np.float64), t)
        vsd_vss = np.array([
            vsd_from_depths(render_depth(R, t), depth_gt, depth_gt, K, vsd_delta_mm, [vsd_tau_mm, np.inf])
            for R in R_est
        ])
        errors["VSD"], errors["VSS"] = vsd_vss[:, 0], vsd_vss[:, 1]
    return SensitivityCurves(angles_deg, axis, errors)
