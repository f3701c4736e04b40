"""Pose error functions with the BOP benchmark's definitions, vectorised over poses.

Poses map model to camera (``x_c = R x_m + t``), rotations ``(..., 3, 3)``,
translations ``(..., 3)`` in mm; estimate and ground truth broadcast against each
other, and every vertex-based error returns an array of the broadcast batch shape
(a 0-d array for a single pose). ``pts_mm`` are *all* vertices of the evaluation
mesh ``(P, 3)`` [mm]: the toolkit uses every vertex, and subsampling changes MSSD.
Symmetries are a :class:`popcode_runtime.geometry.symmetries.SymmetryTransforms` (identity
first); symmetric errors are the minimum over them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.camera import project_camera_points
from popcode_runtime.geometry.rotations import geodesic_angle
from popcode_runtime.geometry.symmetries import SymmetryTransforms

from .visibility import depth_to_distance, visible_mask_est, visible_mask_gt

RenderDepth = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``render_depth(R_m2c, t_m2c_mm) -> depth (H, W) float [mm], 0 where empty``, without anti-aliasing."""

# Vertex x pose x symmetry triples per chunk: each (poses, symmetries, vertices, 3) temporary stays ~24 MB.
_CHUNK_ELEMENTS = 1_000_000


def _batch(R_est, t_est, R_gt, t_gt) -> tuple[tuple[int, ...], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Broadcast the four pose arrays and flatten them to ``(N, 3, 3)`` / ``(N, 3)``."""
    R_est, R_gt = np.asarray(R_est, np.float64), np.asarray(R_gt, np.float64)
    t_est, t_gt = np.asarray(t_est, np.float64), np.asarray(t_gt, np.float64)
    for name, R, t in (("estimate", R_est, t_est), ("ground truth", R_gt, t_gt)):
        if R.shape[-2:] != (3, 3) or t.shape[-1:] != (3,):
            raise PopcodeError(
                f"{name}: rotations must be (..., 3, 3) and translations (..., 3); got {R.shape} and {t.shape}"
            )
    shape = np.broadcast_shapes(R_est.shape[:-2], t_est.shape[:-1], R_gt.shape[:-2], t_gt.shape[:-1])

    def flat(a: np.ndarray, tail: tuple[int, ...]) -> np.ndarray:
        return np.broadcast_to(a, shape + tail).reshape((-1,) + tail)
    return shape, flat(R_est, (3, 3)), flat(t_est, (3,)), flat(R_gt, (3, 3)), flat(t_gt, (3,))


def _points(pts_mm: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise PopcodeError(f"model points must be a non-empty (P, 3) array, got shape {pts.shape}")
    return pts


def _max_symmetric_distance(
    R_est, t_est, R_gt, t_gt, pts_mm, syms: SymmetryTransforms | None, K: np.ndarray | None
) -> np.ndarray:
    """``min_k max_x |f(R_est x + t_est) - f(R_gt (S_k x + s_k) + t_gt)|`` over symmetries ``k``.

    ``f`` is the identity (MSSD, [mm]) or the projection with ``K`` (MSPD, [px]).
    Chunked over poses and symmetries so that memory stays bounded.
    """
    shape, R_e, t_e, R_g, t_g = _batch(R_est, t_est, R_gt, t_gt)
    pts = _points(pts_mm)
    sym_R = np.eye(3)[None] if syms is None else np.asarray(syms.R, np.float64)
    sym_t = np.zeros((1, 3)) if syms is None else np.asarray(syms.t_mm, np.float64)
    sym_chunk = max(1, min(len(sym_R), _CHUNK_ELEMENTS // len(pts)))
    pose_chunk = max(1, _CHUNK_ELEMENTS // (len(pts) * sym_chunk))
    errors = np.empty(len(R_e))
    for p0 in range(0, len(R_e), pose_chunk):
        sl = slice(p0, p0 + pose_chunk)
        pts_est = pts @ np.swapaxes(R_e[sl], -1, -2) + t_e[sl, None]  # (n, P, 3); matmul: BLAS, not einsum's loop
        if K is not None:
            pts_est = project_camera_points(pts_est, K)
        best = np.full(len(pts_est), np.inf)
        for k0 in range(0, len(sym_R), sym_chunk):
            R_sym = np.einsum("nij,kjl->nkil", R_g[sl], sym_R[k0 : k0 + sym_chunk])
            t_sym = np.einsum("nij,kj->nki", R_g[sl], sym_t[k0 : k0 + sym_chunk]) + t_g[sl, None]
            pts_gt = pts @ np.swapaxes(R_sym, -1, -2) + t_sym[:, :, None]  # (n, k, P, 3)
            if K is not None:
                pts_gt = project_camera_points(pts_gt, K)
            offsets = pts_est[:, None] - pts_gt
            dist = np.sqrt(np.einsum("nkpi,nkpi->nkp", offsets, offsets).max(axis=-1))  # one root per (n, k)
            best = np.minimum(best, dist.min(axis=-1))
        errors[sl] = best
    return errors.reshape(shape)


def mssd(
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts_mm: np.ndarray,
    syms: SymmetryTransforms | None,
) -> np.ndarray:
    """Maximum Symmetry-aware Surface Distance [mm] (BOP19).

    Minimum over the symmetry transformations of the largest 3-D distance between a
    vertex in the estimated pose and the same vertex in the symmetric ground truth.
    ``syms=None`` means the object has no symmetry.
    Rotations ``(..., 3, 3)``, translations ``(..., 3)`` [mm], ``pts_mm (P, 3)`` [mm]; the result has the
    broadcast batch shape ``(...)`` [mm].
    """
    return _max_symmetric_distance(R_est, t_est, R_gt, t_gt, pts_mm, syms, None)


def mspd(
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, K: np.ndarray, pts_mm: np.ndarray,
    syms: SymmetryTransforms | None,
) -> np.ndarray:
    """Maximum Symmetry-aware Projection Distance [px] (BOP19).

    As :func:`mssd` but with the vertices projected with the 3x3 intrinsics ``K``
    (:func:`popcode_runtime.geometry.camera.project_camera_points`). The BOP thresholds
    scale with the image width / 640.
    Rotations ``(..., 3, 3)``, translations ``(..., 3)`` [mm], ``pts_mm (P, 3)`` [mm]; the result has the
    broadcast batch shape ``(...)`` [px].
    """
    return _max_symmetric_distance(R_est, t_est, R_gt, t_gt, pts_mm, syms, np.asarray(K, np.float64))


def add(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts_mm: np.ndarray) -> np.ndarray:
    """Average Distance of model points, ADD [mm] (Hinterstoisser et al., ACCV 2012).

    Mean over vertices of the distance between the vertex in the two poses;
    blind to symmetry.
    Rotations ``(..., 3, 3)``, translations ``(..., 3)`` [mm], ``pts_mm (P, 3)`` [mm]; the result has the
    broadcast batch shape ``(...)`` [mm].
    """
    shape, R_e, t_e, R_g, t_g = _batch(R_est, t_est, R_gt, t_gt)
    pts = _points(pts_mm)
    errors = np.empty(len(R_e))
    chunk = max(1, _CHUNK_ELEMENTS // len(pts))
    for n0 in range(0, len(R_e), chunk):
        sl = slice(n0, n0 + chunk)
        diff = np.einsum("nij,pj->npi", R_e[sl] - R_g[sl], pts) + (t_e[sl] - t_g[sl])[:, None]
        errors[sl] = np.linalg.norm(diff, axis=-1).mean(axis=-1)
    return errors.reshape(shape)


def adi(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts_mm: np.ndarray) -> np.ndarray:
    """Average Distance for Indistinguishable views, ADI [mm] (Hinterstoisser et al., ACCV 2012).

    Mean over the vertices in the ground-truth pose of the distance to the nearest
    vertex in the estimated pose. Distances are invariant under a rigid motion, so
    the ground-truth vertices are mapped into the estimate's model frame and one
    k-d tree over the model serves every pose. Always ``adi <= add``.
    Rotations ``(..., 3, 3)``, translations ``(..., 3)`` [mm], ``pts_mm (P, 3)`` [mm]; the result has the
    broadcast batch shape ``(...)`` [mm].
    """
    shape, R_e, t_e, R_g, t_g = _batch(R_est, t_est, R_gt, t_gt)
    pts = _points(pts_mm)
    tree = cKDTree(pts)
    errors = np.empty(len(R_e))
    chunk = max(1, _CHUNK_ELEMENTS // len(pts))
    for n0 in range(0, len(R_e), chunk):
        sl = slice(n0, n0 + chunk)
        # R_e^T (R_g x + t_g - t_e): the ground-truth vertices in the estimate's model frame.
        R_rel = np.einsum("nji,njk->nik", R_e[sl], R_g[sl])
        t_rel = np.einsum("nji,nj->ni", R_e[sl], t_g[sl] - t_e[sl])
        query = np.einsum("nij,pj->npi", R_rel, pts) + t_rel[:, None]
        errors[sl] = tree.query(query.reshape(-1, 3), k=1)[0].reshape(len(query), -1).mean(axis=-1)
    return errors.reshape(shape)


def proj(
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, K: np.ndarray, pts_mm: np.ndarray
) -> np.ndarray:
    """Average projection distance, PROJ [px] (Brachmann et al., CVPR 2016; the toolkit's ``proj``).

    Mean over vertices of the distance between their projections with the 3x3
    intrinsics ``K`` in the two poses; blind to symmetry.
    Rotations ``(..., 3, 3)``, translations ``(..., 3)`` [mm], ``pts_mm (P, 3)`` [mm]; the result has the
    broadcast batch shape ``(...)`` [px].
    """
    shape, R_e, t_e, R_g, t_g = _batch(R_est, t_est, R_gt, t_gt)
    pts, K = _points(pts_mm), np.asarray(K, np.float64)
    errors = np.empty(len(R_e))
    chunk = max(1, _CHUNK_ELEMENTS // len(pts))
    for n0 in range(0, len(R_e), chunk):
        sl = slice(n0, n0 + chunk)
        uv_est = project_camera_points(np.einsum("nij,pj->npi", R_e[sl], pts) + t_e[sl, None], K)
        uv_gt = project_camera_points(np.einsum("nij,pj->npi", R_g[sl], pts) + t_g[sl, None], K)
        errors[sl] = np.linalg.norm(uv_est - uv_gt, axis=-1).mean(axis=-1)
    return errors.reshape(shape)


def spheres_overlap(t_est_mm: np.ndarray, t_gt_mm: np.ndarray, diameter_mm: float) -> np.ndarray:
    """Whether the object's bounding spheres in the two poses can overlap ``(...,)`` bool.

    The toolkit's ``eval_calc_errors.py`` sets MSSD, ADD and ADI to infinity
    where they cannot (centre distance ``>= diameter``), without computing them.
    """
    distance = np.linalg.norm(np.asarray(t_est_mm, np.float64) - np.asarray(t_gt_mm, np.float64), axis=-1)
    return distance < diameter_mm


def sphere_projections_overlap(t_est_mm: np.ndarray, t_gt_mm: np.ndarray, diameter_mm: float) -> np.ndarray:
    """Whether the image silhouettes of the bounding spheres in the two poses can overlap ``(...,)`` bool.

    The toolkit's approximation (``misc.overlapping_sphere_projections``): the
    centres' normalised image points ``(x/z, y/z)`` lie closer than
    ``r (1/z_est + 1/z_gt)`` with ``r = diameter / 2``; a centre at ``z = 0``
    never overlaps. Where they cannot, the toolkit sets VSD to 1.
    """
    t_e, t_g = np.asarray(t_est_mm, np.float64), np.asarray(t_gt_mm, np.float64)
    z_e, z_g = t_e[..., 2], t_g[..., 2]
    valid = (z_e != 0) & (z_g != 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = np.linalg.norm(t_e[..., :2] / z_e[..., None] - t_g[..., :2] / z_g[..., None], axis=-1)
        overlap = distance < 0.5 * diameter_mm * (1.0 / z_e + 1.0 / z_g)
    return valid & overlap


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Rotation error re [deg] (BOP): angle of ``R_est R_gt^T``, in [0, 180], for rotations ``(..., 3, 3)``.

    Computed with the chord formula, which equals the toolkit's ``acos`` of the
    trace but stays accurate near 0.
    """
    return np.degrees(geodesic_angle(R_gt, R_est))


def translation_error_mm(t_est: np.ndarray, t_gt: np.ndarray) -> np.ndarray:
    """Translation error te [mm] (BOP): Euclidean distance between translations ``(..., 3)`` [mm], shape ``(...)``."""
    return np.linalg.norm(np.asarray(t_est, np.float64) - np.asarray(t_gt, np.float64), axis=-1)


def vsd_from_depths(
    depth_est_mm: np.ndarray,
    depth_gt_mm: np.ndarray,
    depth_test_mm: np.ndarray,
    K: np.ndarray,
    delta_mm: float,
    taus: Sequence[float] | np.ndarray,
    diameter_mm: float | None = None,
) -> np.ndarray:
    """Visible Surface Discrepancy with the ``step`` cost (BOP18/19), one error per tau.

    ``depth_est_mm`` / ``depth_gt_mm`` are the model rendered in the estimated and
    ground-truth pose and ``depth_test_mm`` the scene, all ``(H, W)`` [mm] with 0 for
    no depth; ``delta_mm`` is the visibility tolerance [mm] (15 for T-LESS). With
    ``diameter_mm`` the misalignment tolerances ``taus`` are fractions of the
    diameter (the BOP19 setting), otherwise they are in mm; ``inf`` gives VSS.
    A pixel of the union of the visible surfaces costs 1 unless it is in both and
    the distances differ by less than tau. Returns ``(len(taus),)`` errors in [0, 1];
    1 when neither pose shows any visible surface.
    """
    dist_test = depth_to_distance(depth_test_mm, K)
    dist_gt = depth_to_distance(depth_gt_mm, K)
    dist_est = depth_to_distance(depth_est_mm, K)
    visible_gt = visible_mask_gt(dist_test, dist_gt, delta_mm)
    visible_est = visible_mask_est(dist_test, dist_est, visible_gt, delta_mm)
    both = visible_gt & visible_est
    union_count = int(np.count_nonzero(visible_gt | visible_est))
    taus = np.asarray(taus, dtype=np.float64).reshape(-1)
    if union_count == 0:
        return np.ones(len(taus))
    dists = np.abs(dist_gt[both] - dist_est[both])
    if diameter_mm is not None:
        dists = dists / diameter_mm
    mismatched = union_count - len(dists)
    costs = (dists[None, :] >= taus[:, None]).sum(axis=1)
    return (costs + mismatched) / union_count


def vsd(
    R_est: np.ndarray,
    t_est_mm: np.ndarray,
    R_gt: np.ndarray,
    t_gt_mm: np.ndarray,
    depth_test_mm: np.ndarray,
    K: np.ndarray,
    render_depth: RenderDepth,
    delta_mm: float,
    taus: Sequence[float] | np.ndarray,
    diameter_mm: float | None = None,
) -> np.ndarray:
    """VSD of one estimate (see :func:`vsd_from_depths`), rendering both poses with ``render_depth``.

    ``render_depth`` must render as the toolkit's renderer does: with the
    intrinsics of the test image as given (pixel ``i`` samples ``x = i + 0.5``),
    both faces of every triangle, and without anti-aliasing, which moves
    silhouette pixels (``popcode_trainer.data.gl.DepthRenderer(...).render``
    with ``K`` bound does).
    """
    depth_est = render_depth(np.asarray(R_est, np.float64), np.asarray(t_est_mm, np.float64))
    depth_gt = render_depth(np.asarray(R_gt, np.float64), np.asarray(t_gt_mm, np.float64))
    return vsd_from_depths(depth_est, depth_gt, depth_test_mm, K, delta_mm, taus, diameter_mm)


def vss(
    R_est: np.ndarray,
    t_est_mm: np.ndarray,
    R_gt: np.ndarray,
    t_gt_mm: np.ndarray,
    depth_test_mm: np.ndarray,
    K: np.ndarray,
    render_depth: RenderDepth,
    delta_mm: float,
) -> float:
    """Visible Surface Similarity error: VSD with tau = inf, i.e. the mismatch of the visible silhouettes, in [0, 1].

    The toolkit has no function of this name: it is its ``vsd`` with ``taus=[inf]``.
    """
    return float(vsd(R_est, t_est_mm, R_gt, t_gt_mm, depth_test_mm, K, render_depth, delta_mm, [np.inf])[0])
