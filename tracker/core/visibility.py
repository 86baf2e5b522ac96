"""Per-instance masks, boxes and visible fractions (BOP ``scene_gt_info``), from renders.

Visible masks come from one label render of the whole scene (which instance is in front
at each pixel). The whole silhouette (``px_count_all``, counted outside the image too, as
BOP does for truncated objects) comes from rendering the instance alone into a square
window around its projected model, the same window the reconstruction targets use.

Without a depth image of the real scene (the LM-O frames we have), occlusion is derived
from the known objects alone: occluders that are not among them are missed, so the
visible fraction is then an upper bound.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tracker.core.geometry import SquareCrop, box_from_points, project, square_crop

WINDOW_PAD = 1.2  # window side over the projected model box's longer side


@dataclass
class InstanceVisibility:
    mask_visib: np.ndarray  # bool HxW: the pixels where this instance is in front
    px_count_all: int       # whole silhouette, in image pixels (outside the image too)
    px_count_valid: int     # the silhouette's pixels inside the image
    px_count_visib: int
    visib_fract: float
    bbox_obj: list[int]     # box of the whole silhouette, BOP (x, y, w, h); may leave the image
    bbox_visib: list[int]   # box of mask_visib; [-1, -1, -1, -1] if empty
    window: SquareCrop      # where the instance was rendered alone
    alone_rgb: np.ndarray | None = None  # that render (the clean reconstruction target)


def mask_box(mask: np.ndarray) -> list[int]:
    """BOP box (x, y, w, h) of a mask's pixels; [-1, -1, -1, -1] if it has none."""
    m = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)  # (OpenCV's scan: ~5x numpy's nonzero)
    x, y, w, h = cv2.boundingRect(m)
    if w == 0:
        return [-1, -1, -1, -1]
    return [int(x), int(y), int(w), int(h)]


def instance_window(vertices: np.ndarray, K: np.ndarray, R, t, size: int, pad: float = WINDOW_PAD) -> SquareCrop:
    """The square window around the model projected at (R, t)."""
    return square_crop(box_from_points(project(vertices, K, R, t)), size, pad)


def silhouette(crop_renderer, K: np.ndarray, inst, window: SquareCrop, rgb: bool = True):
    """Render ``inst`` alone into ``window``: (rgb or None, depth) at window resolution."""
    return crop_renderer.render(window.intrinsics(K), [inst], depth_only=not rgb)


def visibility_from_render(labels: np.ndarray, index: int, alone_depth: np.ndarray,
                           window: SquareCrop, alone_rgb: np.ndarray | None = None) -> InstanceVisibility:
    """Visibility of instance ``index`` of a label image, given its depth rendered alone
    into ``window`` (as :func:`silhouette` does)."""
    h, w = labels.shape
    m_vis = labels == index
    sil = alone_depth > 0
    scale = window.side / window.size  # image pixels per window pixel
    n_all = float(sil.sum()) * scale * scale
    ys, xs = np.nonzero(sil)
    if len(xs):
        lo = window.to_image(np.array([[xs.min(), ys.min()]], dtype=np.float64))[0]
        hi = window.to_image(np.array([[xs.max(), ys.max()]], dtype=np.float64))[0]
        # window pixels cover `scale` image pixels: edges at lo - scale/2 .. hi + scale/2
        x0, y0 = (lo - scale / 2 + 0.5).round()
        bw, bh = (hi - lo + scale).round()
        bbox_obj = [int(x0), int(y0), max(int(bw), 1), max(int(bh), 1)]
        # pixels of the silhouette that fall inside the image
        u = window.to_image(np.stack([xs, ys], 1).astype(np.float64))
        inside = (u[:, 0] >= -0.5) & (u[:, 0] < w - 0.5) & (u[:, 1] >= -0.5) & (u[:, 1] < h - 0.5)
        n_valid = float(inside.sum()) * scale * scale
    else:
        bbox_obj, n_valid = [-1, -1, -1, -1], 0.0
    n_vis = int(np.count_nonzero(m_vis))
    n_all_i = max(int(round(n_all)), n_vis)  # counts at window resolution are approximate
    return InstanceVisibility(m_vis, n_all_i, int(round(n_valid)), n_vis, n_vis / n_all_i if n_all_i else 0.0,
                              bbox_obj, mask_box(m_vis), window, alone_rgb)


def scene_visibility(scene_renderer, crop_renderer, K: np.ndarray, instances, vertices: dict,
                     n_targets: int | None = None, labels: np.ndarray | None = None,
                     keep_rgb: bool = False) -> list[InstanceVisibility]:
    """Visibility of the first ``n_targets`` of ``instances`` = [(obj_id, R, t), ...]
    (the rest only occlude). ``vertices``: {obj_id: (N, 3)} model vertices. With
    ``keep_rgb`` each record carries the instance rendered alone in its window."""
    n_targets = len(instances) if n_targets is None else n_targets
    if labels is None:
        labels = scene_renderer.render_labels(K, instances)
    out = []
    for k, (oid, R, t) in enumerate(instances[:n_targets]):
        win = instance_window(vertices[oid], K, R, t, crop_renderer.width)
        rgb, d = silhouette(crop_renderer, K, (oid, R, t), win, rgb=keep_rgb)
        out.append(visibility_from_render(labels, k, d, win, rgb))
    return out
