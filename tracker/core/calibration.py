"""Checkerboard calibration (OpenCV) from image files or a video / camera source."""
from __future__ import annotations

import glob as globmod
from dataclasses import dataclass, field

import cv2
import numpy as np

from tracker.core.camera import Camera
from tracker.core.errors import UserError

MIN_VIEWS = 3
# two views whose corners all lie within this many pixels are one view (a copy, a board held still)
SAME_VIEW_PX = 1.0
# the focal length's standard deviation (OpenCV's estimate) above this share of it: a warning
LOOSE_FOCAL = 0.02


@dataclass
class CalibrationResult:
    camera: Camera
    rms_px: float
    per_view_px: list[float]
    used: list[str]
    skipped: list[str] = field(default_factory=list)


def parse_board(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6): inner corners per row and per column."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"--board must look like COLSxROWS of inner corners, e.g. 9x6; got '{text}'") from None
    if not (3 <= cols <= 100 and 3 <= rows <= 100):  # OpenCV's finder needs more than 2 each way
        raise UserError(f"--board needs 3 to 100 inner corners each way (e.g. 9x6), got {text}")
    return cols, rows


def board_points(board: tuple[int, int], square_mm: float) -> np.ndarray:
    cols, rows = board
    obj = np.zeros((rows * cols, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_mm
    return obj


def find_corners(gray: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners of the board, or None where the board is not found."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    ok, corners = cv2.findChessboardCorners(gray, board, flags)
    if not ok:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    return cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), crit)


def _frames_from_glob(pattern: str):
    paths = sorted(globmod.glob(pattern))
    if not paths:
        raise UserError(f"no image matches '{pattern}'")
    for p in paths:
        img = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
        yield p, img


def _frames_from_video(source: str, every: int, max_views: int):
    src = int(source) if source.isdigit() else source
    cap = cv2.VideoCapture(src)
    if not cap.isOpened():
        raise UserError(f"cannot open video source '{source}'")
    i = taken = 0
    try:
        while taken < max_views:
            ok, frame = cap.read()
            if not ok:
                break
            if i % every == 0:
                taken += 1
                yield f"{source}#frame{i}", cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            i += 1
    finally:
        cap.release()


def calibrate(board: tuple[int, int], square_mm: float, images: str | None = None,
              source: str | None = None, every: int = 15, max_views: int = 60,
              log=print) -> CalibrationResult:
    """Calibrate from the views of ``images`` (a glob) or ``source`` (video / camera)."""
    if square_mm <= 0:
        raise UserError(f"--square must be positive (mm), got {square_mm}")
    frames = _frames_from_glob(images) if images else _frames_from_video(source, every, max_views)
    obj = board_points(board, square_mm)
    obj_pts, img_pts, used, skipped = [], [], [], []
    size = None
    for name, gray in frames:
        if gray is None:
            skipped.append(f"{name} (unreadable)")
            continue
        if size is None:
            size = gray.shape[::-1]
        elif gray.shape[::-1] != size:
            skipped.append(f"{name} (size {gray.shape[1]}x{gray.shape[0]} differs from {size[0]}x{size[1]})")
            continue
        corners = find_corners(gray, board)
        if corners is None:
            skipped.append(f"{name} (board not found)")
            continue
        same = next((u for u, c in zip(used, img_pts) if np.abs(c - corners).max() < SAME_VIEW_PX), None)
        if same is not None:  # a copy, or the board held still: it adds nothing but weight
            skipped.append(f"{name} (the same view as {same})")
            continue
        obj_pts.append(obj)
        img_pts.append(corners)
        used.append(name)
    for s in skipped:
        log(f"skipped {s}")
    if len(used) < MIN_VIEWS:
        raise UserError(f"only {len(used)} distinct view(s) show the {board[0]}x{board[1]} board; "
                        f"need at least {MIN_VIEWS} (check --board, lighting and focus; move the board between views)")
    rms, K, dist, rvecs, tvecs, std, _, _ = cv2.calibrateCameraExtended(obj_pts, img_pts, size, None, None)
    loose = std.ravel()[:2] / np.array([K[0, 0], K[1, 1]])
    if np.max(loose) > LOOSE_FOCAL:
        log(f"warning: the views pin the focal length down only to +-{100 * np.max(loose):.0f} % "
            f"(fx {K[0, 0]:.0f} +- {std.ravel()[0]:.0f} px); add views with the board tilted and near the corners")
    per_view = []
    for o, i, r, t in zip(obj_pts, img_pts, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj - i) ** 2, axis=-1)))))
    return CalibrationResult(Camera(K, size[0], size[1], dist.ravel()), float(rms), per_view, used, skipped)
