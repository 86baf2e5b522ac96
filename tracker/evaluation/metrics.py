"""Pose errors, one function each, with the semantics of bop_toolkit's ``pose_error.py``.

Every function takes an estimated pose ``(R_e, t_e)`` and a ground-truth pose
``(R_g, t_g)`` (3x3 model-to-camera rotations, translations in mm, any shape with 3
values) and returns one float:

- :func:`add`  mean distance of corresponding model points (Hinterstoisser et al. 2012), mm
- :func:`adi`  mean distance from each GT-posed point to the nearest estimate-posed point, mm
- :func:`mssd` maximum symmetry-aware surface distance (BOP 2019), mm
- :func:`mspd` maximum symmetry-aware projection distance (BOP 2019), px
- :func:`re`   rotation error, degrees; :func:`te` translation error, mm

``syms`` is an (S, 4, 4) array of symmetry transforms of the model (identity included),
as :func:`tracker.core.bop.symmetry_transforms` returns it; symmetry ``S`` maps the GT pose to
the equivalent pose ``(R_g S_R, R_g S_t + t_g)``.

:func:`vsd` (visible surface discrepancy) works on depth images: the scene's measured depth
and the object rendered at both poses (the caller renders; this module is numpy only).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from tracker.core.geometry import rotation_error_deg, translation_error

# points x symmetries evaluated at once in mssd / mspd (bounds the temporary arrays)
_CHUNK_POINTS = 2_000_000


def _Rt(R, t) -> tuple[np.ndarray, np.ndarray]:
    return (np.asarray(R, dtype=np.float64).reshape(3, 3),
            np.asarray(t, dtype=np.float64).reshape(3))


def _pts(pts) -> np.ndarray:
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3)


def _syms(syms) -> np.ndarray:
    if syms is None:
        return np.eye(4)[None]
    s = np.asarray(syms, dtype=np.float64)
    return s.reshape(-1, 4, 4)


def _gt_sym_poses(R_g, t_g, syms) -> tuple[np.ndarray, np.ndarray]:
    """(S, 3, 3) rotations and (S, 3) translations of the GT pose composed with each symmetry."""
    S = _syms(syms)
    R = np.einsum("ij,sjk->sik", R_g, S[:, :3, :3])
    t = np.einsum("ij,sj->si", R_g, S[:, :3, 3]) + t_g
    return R, t


# --------------------------------------------------------------------------- ADD / ADI


def add(R_e, t_e, R_g, t_g, pts) -> float:
    """ADD: mean over model points x of ||(R_e x + t_e) - (R_g x + t_g)|| (mm)."""
    R_e, t_e = _Rt(R_e, t_e)
    R_g, t_g = _Rt(R_g, t_g)
    d = _pts(pts) @ (R_e - R_g).T + (t_e - t_g)
    return float(np.linalg.norm(d, axis=1).mean())


def adi(R_e, t_e, R_g, t_g, pts, tree: cKDTree | None = None) -> float:
    """ADI (ADD-S): mean over the GT-posed points of the distance to the nearest
    estimate-posed point (mm), as bop_toolkit's ``adi``.

    The nearest-neighbour search runs in the model frame (distances are invariant under
    the estimated pose), so ``tree = cKDTree(pts)`` can be built once per object and reused.
    """
    R_e, t_e = _Rt(R_e, t_e)
    R_g, t_g = _Rt(R_g, t_g)
    P = _pts(pts)
    if tree is None:
        tree = cKDTree(P)
    # GT-posed points, brought into the frame of the estimated model: R_e^T (R_g x + t_g - t_e)
    q = P @ (R_e.T @ R_g).T + R_e.T @ (t_g - t_e)
    d, _ = tree.query(q, k=1, workers=-1)  # exact; all cores (the search dominates scoring)
    return float(d.mean())


# --------------------------------------------------------------------------- MSSD / MSPD


def mssd_per_symmetry(R_e, t_e, R_g, t_g, pts, syms) -> np.ndarray:
    """Max surface distance to each symmetric equivalent of the GT pose, shape (S,)."""
    R_e, t_e = _Rt(R_e, t_e)
    R_g, t_g = _Rt(R_g, t_g)
    P = _pts(pts)
    Rs, ts = _gt_sym_poses(R_g, t_g, syms)
    A = R_e[None] - Rs             # (S, 3, 3): (R_e - R_g S_R) x + (t_e - t_gs)
    b = t_e[None] - ts             # (S, 3)
    out = np.empty(len(A))
    step = max(1, _CHUNK_POINTS // max(len(P), 1))
    for i in range(0, len(A), step):
        d = np.matmul(P[None], A[i:i + step].transpose(0, 2, 1)) + b[i:i + step, None, :]
        out[i:i + step] = np.sqrt(np.einsum("sni,sni->sn", d, d).max(axis=1))
    return out


def mssd(R_e, t_e, R_g, t_g, pts, syms) -> float:
    """MSSD: min over symmetries S of max over model points x of
    ||(R_e x + t_e) - (R_g (S_R x + S_t) + t_g)|| (mm).

    The distance is a convex function of x, so its maximum over the points equals its
    maximum over their convex hull's vertices: passing ``hull_points(pts)`` gives the same
    value, faster.
    """
    return float(mssd_per_symmetry(R_e, t_e, R_g, t_g, pts, syms).min())


def mspd_per_symmetry(R_e, t_e, R_g, t_g, K, pts, syms) -> np.ndarray:
    """Max projection distance to each symmetric equivalent of the GT pose, shape (S,)."""
    R_e, t_e = _Rt(R_e, t_e)
    R_g, t_g = _Rt(R_g, t_g)
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    P = _pts(pts)
    Rs, ts = _gt_sym_poses(R_g, t_g, syms)
    pe = (P @ R_e.T + t_e) @ K.T
    pe = pe[:, :2] / pe[:, 2:3]
    out = np.empty(len(Rs))
    step = max(1, _CHUNK_POINTS // max(len(P), 1))
    for i in range(0, len(Rs), step):
        KR = np.einsum("ij,sjk->sik", K, Rs[i:i + step])
        Kt = ts[i:i + step] @ K.T
        pg = np.matmul(P[None], KR.transpose(0, 2, 1)) + Kt[:, None, :]
        pg = pg[..., :2] / pg[..., 2:3]
        d = pg - pe[None]
        out[i:i + step] = np.sqrt(np.einsum("sni,sni->sn", d, d).max(axis=1))
    return out


def mspd(R_e, t_e, R_g, t_g, K, pts, syms) -> float:
    """MSPD: min over symmetries S of max over model points x of
    ||proj(R_e x + t_e) - proj(R_g (S_R x + S_t) + t_g)|| in pixels, with proj through K."""
    return float(mspd_per_symmetry(R_e, t_e, R_g, t_g, K, pts, syms).min())


# --------------------------------------------------------------------------- RE / TE


def re(R_e, R_g) -> float:
    """Rotation error: the angle of R_e R_g^T in degrees, in [0, 180]."""
    return float(rotation_error_deg(np.asarray(R_e, dtype=np.float64).reshape(3, 3),
                                    np.asarray(R_g, dtype=np.float64).reshape(3, 3)))


def te(t_e, t_g) -> float:
    """Translation error: ||t_e - t_g|| (mm)."""
    return float(translation_error(np.asarray(t_e).reshape(3), np.asarray(t_g).reshape(3)))


# --------------------------------------------------------------------------- VSD


def distance_image(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Depth (z, mm) -> distance from the camera centre along each pixel's ray (mm), as
    bop_toolkit's ``depth_im_to_dist_im_fast``."""
    h, w = depth.shape
    xs = (np.arange(w) - K[0, 2]) / K[0, 0]
    ys = (np.arange(h) - K[1, 2]) / K[1, 1]
    return depth * np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)


def _visib_mask(d_test, d_model, delta):
    """BOP19 visibility: rendered, and in front of the measured surface within ``delta``
    (or where the sensor has no reading)."""
    return ((d_model - d_test <= delta) | (d_test == 0)) & (d_model > 0)


def vsd(depth_est: np.ndarray, depth_gt: np.ndarray, depth_test: np.ndarray, K: np.ndarray,
        delta: float, taus, diameter: float | None = None) -> np.ndarray:
    """Visible surface discrepancy (Hodan et al.; BOP19 variant with the step cost), one
    value per misalignment tolerance in ``taus`` (mm, or fractions of ``diameter`` when it
    is given). ``depth_est`` / ``depth_gt``: the object rendered alone at the estimated / GT
    pose; ``depth_test``: the scene's depth image (all mm, 0 = no value)."""
    d_test, d_gt, d_est = (distance_image(np.asarray(d, np.float64), K) for d in (depth_test, depth_gt, depth_est))
    visib_gt = _visib_mask(d_test, d_gt, delta)
    visib_est = _visib_mask(d_test, d_est, delta) | (visib_gt & (d_est > 0))
    inter = visib_gt & visib_est
    union_count = int((visib_gt | visib_est).sum())
    taus = np.asarray(taus, np.float64).reshape(-1)
    if union_count == 0:
        return np.ones(len(taus))
    dists = np.abs(d_gt[inter] - d_est[inter])
    if diameter is not None:
        dists = dists / diameter
    comp = union_count - int(inter.sum())
    return np.array([((dists >= tau).sum() + comp) / union_count for tau in taus])


# --------------------------------------------------------------------------- helpers


def hull_points(pts) -> np.ndarray:
    """The convex hull's vertices of ``pts`` (all points for a flat or tiny model)."""
    P = _pts(pts)
    try:
        return P[ConvexHull(P).vertices]
    except Exception:  # degenerate (flat, collinear) point sets
        return P
