"""Drawing on RGB frames: rendered objects blended in, boxes, axes and labels."""
from __future__ import annotations

import cv2
import numpy as np

from tracker.core.geometry import project

# distinct RGB colours per object id (tab10-like)
PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                    [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]],
                   dtype=np.uint8)

LMO_NAMES = {1: "ape", 5: "can", 6: "cat", 8: "driller", 9: "duck", 10: "eggbox", 11: "glue",
             12: "holepuncher"}


def colour(obj_id: int) -> tuple[int, int, int]:
    return tuple(int(c) for c in PALETTE[int(obj_id) % len(PALETTE)])


def blend(frame_rgb: np.ndarray, render_rgb: np.ndarray, depth: np.ndarray, alpha: float = 0.6) -> np.ndarray:
    """Render pasted over the frame where depth > 0, with opacity ``alpha``."""
    out = frame_rgb.copy()
    m = depth > 0
    out[m] = (alpha * render_rgb[m].astype(np.float32) + (1 - alpha) * frame_rgb[m]).astype(np.uint8)
    return out


def draw_box(img: np.ndarray, box_xywh, rgb, label: str | None = None) -> None:
    x, y, w, h = (int(round(v)) for v in box_xywh)
    cv2.rectangle(img, (x, y), (x + w - 1, y + h - 1), rgb, 1, cv2.LINE_AA)
    if label:
        cv2.putText(img, label, (x, max(y - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, rgb, 1, cv2.LINE_AA)


def draw_axes(img: np.ndarray, K, R, t, length_mm: float) -> None:
    """Model axes at the pose: x red, y green, z blue (RGB image)."""
    pts = np.array([[0, 0, 0], [length_mm, 0, 0], [0, length_mm, 0], [0, 0, length_mm]], dtype=np.float64)
    if (np.asarray(R) @ pts.T + np.asarray(t).reshape(3, 1))[2].min() <= 1.0:
        return  # behind the camera
    uv = project(pts, K, R, t)
    if not np.all(np.isfinite(uv)) or np.abs(uv).max() > 1e5:
        return
    o = tuple(int(round(v)) for v in uv[0])
    for i, c in zip(range(1, 4), [(255, 0, 0), (0, 255, 0), (0, 0, 255)]):
        cv2.line(img, o, tuple(int(round(v)) for v in uv[i]), c, 2, cv2.LINE_AA)


def draw_uncertain(img: np.ndarray, points: np.ndarray, K, R, t, rgb, label: str | None = None) -> None:
    """A pose not trusted: only the outline (convex hull) of the object's points projected at
    it, thin and dimmed, and its label with a question mark; no rendered object, no axes."""
    if (np.asarray(R) @ np.asarray(points).T + np.asarray(t).reshape(3, 1))[2].min() <= 1.0:
        return
    uv = project(points, K, R, t)
    if not np.all(np.isfinite(uv)) or np.abs(uv).max() > 1e5:
        return
    dim = tuple(int(0.5 * c + 0.5 * 128) for c in rgb)
    hull = cv2.convexHull(np.round(uv).astype(np.int32))
    cv2.polylines(img, [hull], True, dim, 1, cv2.LINE_AA)
    if label:
        x, y = hull[:, 0, 0].min(), hull[:, 0, 1].min()
        cv2.putText(img, label, (int(x), int(max(y - 4, 10))), cv2.FONT_HERSHEY_SIMPLEX, 0.4, dim, 1, cv2.LINE_AA)


def draw_contour(img: np.ndarray, depth: np.ndarray, rgb) -> None:
    m = (depth > 0).astype(np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, contours, -1, rgb, 1, cv2.LINE_AA)


def montage(images: list[np.ndarray], cols: int, scale: float = 0.5) -> np.ndarray:
    """Tile equally sized RGB images into one sheet (scaled by ``scale``)."""
    small = [cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) for im in images]
    h, w = small[0].shape[:2]
    rows = (len(small) + cols - 1) // cols
    sheet = np.zeros((rows * h, cols * w, 3), np.uint8)
    for i, im in enumerate(small):
        r, c = divmod(i, cols)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = im
    return sheet
