"""Per-instance masks and visible fractions from rendered depth (BOP ``scene_gt_info``).

Without a depth image of the real scene (the LM-O frames we have), visibility is derived
from the mutual occlusion of the known objects rendered at their poses: occluders that are
not among the known objects are missed, so the visible fraction is then an upper bound.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .render import Renderer

DEPTH_TOL_MM = 1.0  # a pixel is visible when the instance is the front surface there


@dataclass
class InstanceVisibility:
    mask_all: np.ndarray    # bool HxW: the whole silhouette (inside the image)
    mask_visib: np.ndarray  # bool HxW: the part in front of every other instance
    px_count_all: int
    px_count_visib: int
    visib_fract: float
    bbox_obj: list[int]     # box of mask_all, BOP (x, y, w, h); [-1, -1, -1, -1] if empty
    bbox_visib: list[int]


def mask_box(mask: np.ndarray) -> list[int]:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


def scene_visibility(renderer: Renderer, K: np.ndarray, instances, scene_depth: np.ndarray | None = None
                     ) -> list[InstanceVisibility]:
    """Visibility of each of ``instances`` = [(obj_id, R, t), ...] in the rendered scene.

    ``scene_depth``: the depth of the whole scene when the caller already rendered it.
    """
    if scene_depth is None:
        _, scene_depth = renderer.render(K, instances, depth_only=True)
    out = []
    for inst in instances:
        _, d = renderer.render(K, [inst], depth_only=True)
        m_all = d > 0
        m_vis = m_all & (np.abs(d - scene_depth) < DEPTH_TOL_MM)
        n_all, n_vis = int(m_all.sum()), int(m_vis.sum())
        out.append(InstanceVisibility(m_all, m_vis, n_all, n_vis, n_vis / n_all if n_all else 0.0,
                                      mask_box(m_all), mask_box(m_vis)))
    return out
