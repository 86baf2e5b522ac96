"""Geometry shared by training, evaluation and the live loop.

One implementation of each piece: rotation representations, pinhole projection,
translation from a projected centre and a depth (thesis Eq. 4.3), rescaling of
intrinsics and depth between cameras, the square crop-and-resize with its box
features and the crop <-> image pixel mapping, and the RE / TE errors.

Conventions: rotations are 3x3 matrices mapping model to camera coordinates
(BOP ``cam_R_m2c``); translations are in millimetres; quaternions are scalar-first
``(w, x, y, z)`` (the IMU log's order; scipy's is scalar-last); pixel coordinates put
the centre of pixel (0, 0) at (0, 0), so the image spans [-0.5, W - 0.5]; boxes are
``(x, y, w, h)`` in the BOP sense: the box covers pixel columns x .. x + w - 1, so in
pixel-centre coordinates it spans [x - 0.5, x + w - 0.5] and its centre is
(x + w / 2 - 0.5, y + h / 2 - 0.5).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

# --------------------------------------------------------------------------- rotations


def rot6d_from_matrix(R: np.ndarray) -> np.ndarray:
    """Continuous 6D representation of Zhou et al.: the first two columns of R.

    ``(..., 3, 3) -> (..., 6)`` laid out as ``[c0x, c0y, c0z, c1x, c1y, c1z]``.
    """
    R = np.asarray(R, dtype=np.float64)
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def matrix_from_rot6d(d6: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Gram-Schmidt from the 6D representation back to a rotation matrix.

    ``(..., 6) -> (..., 3, 3)``. Any two non-parallel vectors give a proper rotation.
    """
    d6 = np.asarray(d6, dtype=np.float64)
    a1, a2 = d6[..., 0:3], d6[..., 3:6]
    b1 = a1 / np.maximum(np.linalg.norm(a1, axis=-1, keepdims=True), eps)
    a2p = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = a2p / np.maximum(np.linalg.norm(a2p, axis=-1, keepdims=True), eps)
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Scalar-first unit quaternion ``(w, x, y, z)`` with w >= 0."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat(canonical=True)
    return np.roll(q, 1, axis=-1)


def matrix_from_quat(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix from a scalar-first quaternion (normalised here)."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return Rotation.from_quat(np.roll(q, -1, axis=-1)).as_matrix()


def axis_angle_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation vector: unit axis times angle in radians, angle in [0, pi]."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


def matrix_from_axis_angle(rotvec: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()


def is_rotation(R: np.ndarray, tol: float = 1e-4) -> bool:
    """True for a proper 3x3 rotation (orthonormal, determinant +1) within tol."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return False
    return bool(np.abs(R @ R.T - np.eye(3)).max() < tol and abs(np.linalg.det(R) - 1) < tol)


def chordal_mean(R: np.ndarray) -> np.ndarray:
    """The chordal L2 mean of M estimates of N rotations, ``(M, N, 3, 3) -> (N, 3, 3)``:
    scipy's ``Rotation.mean`` (the quaternions' principal eigenvector, Markley et al. 2007)
    for all N at once: one quaternion conversion and one batched ``eigh`` instead of N scipy
    calls (measured, 3 members x 8 objects: 0.17 against 1.16 ms)."""
    M, N = R.shape[:2]
    if not N:
        return np.zeros((0, 3, 3))
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(M, N, 4)
    _, vecs = np.linalg.eigh(np.einsum("mni,mnj->nij", q, q))  # eigenvalues ascending
    return Rotation.from_quat(vecs[:, :, -1]).as_matrix()


def mean_pose(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean of M estimates of N poses: ``R (M, N, 3, 3)``, ``t (M, N, 3)`` mm ->
    ``(N, 3, 3), (N, 3)``. Rotations: the chordal L2 mean (:func:`chordal_mean`);
    translations: the mean viewing ray (x / z, y / z) at the geometric mean of the distances z,
    so that a far and a near estimate of the same ray average along it."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.ndim != 4 or R.shape[2:] != (3, 3) or t.shape != R.shape[:2] + (3,):
        raise ValueError(f"expected R (M, N, 3, 3) and t (M, N, 3), got {R.shape} and {t.shape}")
    R_mean = chordal_mean(R)
    z = np.exp(np.mean(np.log(t[..., 2]), axis=0))
    ray = np.mean(t[..., :2] / t[..., 2:3], axis=0)
    return R_mean, np.concatenate([ray * z[:, None], z[:, None]], axis=1)


# --------------------------------------------------------------------------- errors


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """RE: angle of R_est R_gt^-1 in degrees (broadcasts over leading axes).

    The inverse, not the transpose, as bop_toolkit does: stored ground truth (LM-O's, with
    6 decimals) is orthonormal only to ~2e-3, and with the transpose small errors then read
    up to 1 degree off the official figures.
    """
    R_est = np.asarray(R_est, dtype=np.float64)
    R_gt = np.asarray(R_gt, dtype=np.float64)
    tr = np.trace(R_est @ np.linalg.inv(R_gt), axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def translation_error(t_est: np.ndarray, t_gt: np.ndarray) -> np.ndarray:
    """TE: Euclidean distance of the translations (mm in, mm out)."""
    d = np.asarray(t_est, dtype=np.float64).reshape(-1, 3) - np.asarray(t_gt, dtype=np.float64).reshape(-1, 3)
    e = np.linalg.norm(d, axis=-1)
    return e if e.size > 1 else e[0]


# --------------------------------------------------------------------------- pinhole


def project(points: np.ndarray, K: np.ndarray, R: np.ndarray | None = None,
            t: np.ndarray | None = None) -> np.ndarray:
    """Project model points (N, 3) with pose [R|t] (mm) through K to pixels (N, 2)."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if R is not None:
        P = P @ np.asarray(R, dtype=np.float64).T
    if t is not None:
        P = P + np.asarray(t, dtype=np.float64).reshape(1, 3)
    uvw = P @ np.asarray(K, dtype=np.float64).T
    return uvw[:, :2] / uvw[:, 2:3]


def translation_from_centre(centre_px: np.ndarray, tz: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Thesis Eq. 4.3: T_x = (x_c - c_x) T_z / f_x, T_y = (y_c - c_y) T_z / f_y.

    ``centre_px`` (..., 2) is the projected object origin, ``tz`` (...) the depth in mm, ``K``
    one (3, 3) or one per centre (..., 3, 3).
    """
    K = np.asarray(K, dtype=np.float64)
    c = np.asarray(centre_px, dtype=np.float64)
    tz = np.asarray(tz, dtype=np.float64)
    tx = (c[..., 0] - K[..., 0, 2]) * tz / K[..., 0, 0]
    ty = (c[..., 1] - K[..., 1, 2]) * tz / K[..., 1, 1]
    return np.stack([tx, ty, tz], axis=-1)


def ray_rotation(centre_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the optical axis onto the viewing ray through ``centre_px``.

    ``(..., 2) -> (..., 3, 3)``. A crop shows the object as a camera looking straight at it
    would: its appearance fixes the pose relative to the ray (allocentric), ``R_ray.T @ R``,
    and the pose in the camera (egocentric) is ``R_ray @ R_allo``. Off-axis objects look turned
    by the ray's angle (up to ~25 deg at the corners of a 640x480 frame with f = 570 px).
    """
    c = np.asarray(centre_px, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    x = (c[..., 0] - K[..., 0, 2]) / K[..., 0, 0]
    y = (c[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    d = np.stack([x, y, np.ones_like(x)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    axis = np.stack([-d[..., 1], d[..., 0], np.zeros_like(x)], axis=-1)  # z x d
    s = np.linalg.norm(axis, axis=-1, keepdims=True)  # sin of the angle
    angle = np.arctan2(s, d[..., 2:3])
    rotvec = np.where(s > 1e-12, axis / np.maximum(s, 1e-12) * angle, 0.0)
    return Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(*c.shape[:-1], 3, 3)


def intrinsics_problem(K) -> str | None:
    """What is wrong with a 3x3 camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (None: nothing)."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        return "the camera matrix is not 3x3 finite numbers"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return f"focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}"
    if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        return f"the camera matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.ravel().tolist()}"
    return None


def scale_intrinsics(K: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """Intrinsics of the same camera read out at another resolution.

    Sizes are ``(width, height)``. With pixel centres at integer coordinates the
    principal point maps as ``c' = (c + 0.5) * s - 0.5``.
    """
    K = np.asarray(K, dtype=np.float64)
    sx = to_size[0] / from_size[0]
    sy = to_size[1] / from_size[1]
    K2 = K.copy()
    K2[0, 0] *= sx
    K2[0, 1] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2


def rescale_depth(tz: np.ndarray, f_from: float, f_to: float) -> np.ndarray:
    """Depth regressed from apparent size on a camera with focal f_from, read on f_to.

    An object of a given pixel size is f_to / f_from times as far on the second camera.
    """
    return np.asarray(tz, dtype=np.float64) * (f_to / f_from)


def focal_mean(K: np.ndarray) -> float:
    K = np.asarray(K, dtype=np.float64)
    return float(np.sqrt(K[0, 0] * K[1, 1]))


# --------------------------------------------------------------------------- crops


@dataclass(frozen=True)
class SquareCrop:
    """A square window of the image, resized to ``size`` x ``size`` pixels.

    ``x0, y0`` is the top-left corner in the BOP box sense (the window's left edge lies at
    x0 - 0.5 in pixel-centre coordinates) and ``side`` the side in image pixels. The
    window may extend past the image; those pixels are filled with ``fill``.
    """

    x0: float
    y0: float
    side: float
    size: int

    @property
    def scale(self) -> float:
        """Crop pixels per image pixel."""
        return self.size / self.side

    def affine(self) -> np.ndarray:
        """2x3 affine map from image pixels to crop pixels (pixel-centre convention)."""
        s = self.scale
        return np.array([[s, 0.0, s * (0.5 - self.x0) - 0.5],
                         [0.0, s, s * (0.5 - self.y0) - 0.5]])

    def intrinsics(self, K: np.ndarray) -> np.ndarray:
        """Intrinsics of a virtual camera that sees exactly this crop (render crops directly)."""
        A = np.vstack([self.affine(), [0.0, 0.0, 1.0]])
        return A @ np.asarray(K, dtype=np.float64)

    def within(self, outer: "SquareCrop") -> "SquareCrop":
        """This window expressed in the pixel frame of the image that ``outer`` produced:
        cropping outer's output with the result equals cropping the original with self."""
        s = outer.scale
        return SquareCrop((self.x0 - outer.x0) * s, (self.y0 - outer.y0) * s, self.side * s, self.size)

    def to_crop(self, pts_img: np.ndarray) -> np.ndarray:
        p = np.asarray(pts_img, dtype=np.float64)
        A = self.affine()
        return p @ A[:, :2].T + A[:, 2]

    def to_image(self, pts_crop: np.ndarray) -> np.ndarray:
        p = np.asarray(pts_crop, dtype=np.float64)
        s = self.scale
        return (p + 0.5) / s + np.array([self.x0, self.y0]) - 0.5


def square_crop(box_xywh, size: int, pad: float = 1.0) -> SquareCrop:
    """Thesis 3.2.6: a square centred on the box, side = the box's longer side (x pad)."""
    x, y, w, h = (float(v) for v in box_xywh)
    if not (w > 0 and h > 0):
        raise ValueError(f"box must have positive width and height, got {box_xywh}")
    side = max(w, h) * pad
    cx, cy = x + w / 2.0, y + h / 2.0
    return SquareCrop(cx - side / 2.0, cy - side / 2.0, side, int(size))


def crop_and_resize(image: np.ndarray, crop: SquareCrop, fill: int = 0,
                    interpolation: int = cv2.INTER_CUBIC) -> np.ndarray:
    """Cut the square window out of ``image`` and resize it (bicubic by default)."""
    border = (fill,) * (image.shape[2] if image.ndim == 3 else 1)
    return cv2.warpAffine(image, crop.affine(), (crop.size, crop.size), flags=interpolation,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=border)


def box_features(box_xywh: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-independent box descriptor ``[u, v, w', h']``.

    ``u, v``: the box centre as a viewing-ray direction ((x - c_x) / f_x, (y - c_y) / f_y);
    ``w', h'``: the box size over the focal length. The same object at the same pose gives
    the same features on any pinhole camera, at any resolution. Boxes (N, 4); K (3, 3) or
    one per box (N, 3, 3). Returns (N, 4).
    """
    b = np.asarray(box_xywh, dtype=np.float64).reshape(-1, 4)
    K = np.asarray(K, dtype=np.float64)
    K = np.broadcast_to(K, (len(b), 3, 3)) if K.ndim == 2 else K.reshape(-1, 3, 3)
    cx = b[:, 0] + b[:, 2] / 2.0 - 0.5  # box centre in pixel-centre coordinates
    cy = b[:, 1] + b[:, 3] / 2.0 - 0.5
    return np.stack([(cx - K[:, 0, 2]) / K[:, 0, 0], (cy - K[:, 1, 2]) / K[:, 1, 1],
                     b[:, 2] / K[:, 0, 0], b[:, 3] / K[:, 1, 1]], axis=1)


def centre_from_box_offset(box_xywh: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Projected object centre from a box and an offset in units of the box's longer side.

    The inverse of :func:`box_offset_of_centre`; offsets are what a centre regressor
    predicts, so the prediction does not depend on image resolution.
    """
    b = np.asarray(box_xywh, dtype=np.float64).reshape(-1, 4)
    o = np.asarray(offset, dtype=np.float64).reshape(-1, 2)
    side = np.maximum(b[:, 2], b[:, 3])
    cx = b[:, 0] + b[:, 2] / 2.0 - 0.5
    cy = b[:, 1] + b[:, 3] / 2.0 - 0.5
    return np.stack([cx + o[:, 0] * side, cy + o[:, 1] * side], axis=1)


def box_offset_of_centre(box_xywh: np.ndarray, centre_px: np.ndarray) -> np.ndarray:
    b = np.asarray(box_xywh, dtype=np.float64).reshape(-1, 4)
    c = np.asarray(centre_px, dtype=np.float64).reshape(-1, 2)
    side = np.maximum(b[:, 2], b[:, 3])
    cx = b[:, 0] + b[:, 2] / 2.0 - 0.5
    cy = b[:, 1] + b[:, 3] / 2.0 - 0.5
    return np.stack([(c[:, 0] - cx) / side, (c[:, 1] - cy) / side], axis=1)


def box_from_points(pts: np.ndarray) -> np.ndarray:
    """Tight BOP box around projected points (N, 2).

    Like a box read off a mask (``x = min column, w = max - min + 1``), so its centre is
    the centre of the points' extent.
    """
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    lo = p.min(axis=0)
    hi = p.max(axis=0)
    return np.array([lo[0], lo[1], hi[0] - lo[0] + 1.0, hi[1] - lo[1] + 1.0])


def clip_box(box_xywh, width: int, height: int) -> np.ndarray:
    """Boxes (x, y, w, h), one (4,) or many (N, 4), cut to the image."""
    b = np.asarray(box_xywh, dtype=np.float64)
    one = b.ndim == 1
    b = b.reshape(-1, 4)
    x0, y0 = np.clip(b[:, 0], 0, width), np.clip(b[:, 1], 0, height)
    x1, y1 = np.clip(b[:, 0] + b[:, 2], 0, width), np.clip(b[:, 1] + b[:, 3], 0, height)
    out = np.stack([x0, y0, np.maximum(x1 - x0, 0.0), np.maximum(y1 - y0, 0.0)], 1)
    return out[0] if one else out


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of (N, 4) and (M, 4) x, y, w, h boxes."""
    a, b = np.asarray(a, np.float64).reshape(-1, 4), np.asarray(b, np.float64).reshape(-1, 4)
    ax1, ay1 = a[:, 0] + a[:, 2], a[:, 1] + a[:, 3]
    bx1, by1 = b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]
    iw = np.clip(np.minimum(ax1[:, None], bx1[None]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    ih = np.clip(np.minimum(ay1[:, None], by1[None]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = iw * ih
    union = (a[:, 2] * a[:, 3])[:, None] + (b[:, 2] * b[:, 3])[None] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
