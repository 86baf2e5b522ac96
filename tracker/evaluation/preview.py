"""Ground-truth overlay of a BOP scene: every object rendered at its annotated pose.

The most real end-to-end job the foundation can run: it reads the scene and its models,
renders with the scene's intrinsics and checks that each rendered silhouette agrees with
the model's vertices projected through the same pose (box IoU).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, asdict
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from tracker.core.bop import load_scene
from tracker.core.errors import UserError
from tracker.core.geometry import box_from_points, clip_box, iou_matrix, project
from tracker.core.meshes import load_models
from tracker.runtime.overlay import LMO_NAMES, blend, colour, draw_axes, draw_box, draw_contour, montage
from tracker.runtime.render import Renderer


@dataclass
class PreviewSummary:
    frames: int
    instances: int
    box_iou_median: float
    box_iou_min: float
    instances_in_view: int
    centres_in_image: int
    ms_per_frame_render: float
    montage: str
    frames_dir: str


def render_gt_overlays(scene_dir, models_dir, out_dir, max_frames: int | None = None,
                       progress: bool = True) -> PreviewSummary:
    scene = load_scene(scene_dir, require_gt=True)
    im_ids = scene.im_ids[:max_frames] if max_frames else scene.im_ids
    obj_ids = sorted({g.obj_id for i in im_ids for g in scene.gt.get(i, [])})
    if not obj_ids:
        raise UserError(f"{scene_dir}: its ground truth lists no object instances; nothing to overlay")
    models = load_models(models_dir, obj_ids)
    out = Path(out_dir)
    frames_dir = out / "overlay"
    frames_dir.mkdir(parents=True, exist_ok=True)
    first = scene.read_rgb(im_ids[0])
    h, w = first.shape[:2]
    ious, in_image, sheet, t_render = [], 0, [], 0.0
    with Renderer(w, h, {k: m.mesh for k, m in models.items()}) as renderer:
        for im_id in tqdm(im_ids, desc="overlay", unit="frame", disable=not progress):
            img = scene.read_rgb(im_id)
            if img.shape[:2] != (h, w):
                raise UserError(f"{scene.images[im_id]}: {img.shape[1]}x{img.shape[0]}, the scene's "
                                f"first image is {w}x{h}")
            K = scene.K(im_id)
            gts = scene.gt.get(im_id, [])
            t0 = time.perf_counter()
            rgb, depth = renderer.render(K, [(g.obj_id, g.R, g.t) for g in gts])
            t_render += time.perf_counter() - t0
            vis = blend(img, rgb, depth, 0.55)
            for g in gts:
                m = models[g.obj_id]
                pbox = box_from_points(project(m.vertices, K, g.R, g.t))
                _, d1 = renderer.render(K, [(g.obj_id, g.R, g.t)], depth_only=True)
                ys, xs = np.nonzero(d1 > 0)
                vbox = clip_box(pbox, w, h)
                if vbox[2] * vbox[3] > 0:  # some of it is in view: compare the visible parts
                    rbox = ((xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
                            if len(xs) else (0, 0, 0, 0))
                    ious.append(float(iou_matrix(vbox, rbox)[0, 0]))
                c = project(np.zeros((1, 3)), K, g.R, g.t)[0]
                in_image += int(0 <= c[0] < w and 0 <= c[1] < h)
                col = colour(g.obj_id)
                draw_contour(vis, d1, col)
                draw_box(vis, pbox, col, LMO_NAMES.get(g.obj_id, str(g.obj_id)))
                draw_axes(vis, K, g.R, g.t, 0.3 * float(np.ptp(m.vertices, axis=0).max()))
            cv2.imwrite(str(frames_dir / f"{im_id:06d}.png"), cv2.cvtColor(vis, cv2.COLOR_RGB2BGR))
            if len(sheet) < 12:
                sheet.append(vis)
    mpath = out / "overlay_montage.png"
    cv2.imwrite(str(mpath), cv2.cvtColor(montage(sheet, cols=4, scale=0.5), cv2.COLOR_RGB2BGR))
    summary = PreviewSummary(len(im_ids), sum(len(scene.gt.get(i, [])) for i in im_ids), float(np.median(ious)) if ious else 0.0,
                             float(np.min(ious)) if ious else 0.0, len(ious), in_image,
                             1000 * t_render / max(len(im_ids), 1), str(mpath), str(frames_dir))
    (out / "summary.json").write_text(json.dumps(asdict(summary), indent=1))
    return summary
