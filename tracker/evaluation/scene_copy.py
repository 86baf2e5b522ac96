"""A BOP scene read out at another resolution: its frames resized, its intrinsics scaled
(:func:`tracker.core.geometry.scale_intrinsics`), its poses unchanged and its boxes scaled, so
``eval`` on the copy measures what a lower-resolution camera of the same scene would give
(issue 58's 320x240 copies)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2

from tracker.core.bop import load_scene, save_scene_camera, write_json
from tracker.core.errors import UserError
from tracker.core.geometry import scale_intrinsics

# what a copy leaves out (eval and score need none of it; visibility is derived from the models)
NOT_COPIED = ("depth", "mask", "mask_visib")


def resize_scene(scene_dir, out_dir, width: int, height: int) -> dict:
    """Writes ``out_dir`` (``rgb/NNNNNN.png``, ``scene_camera.json``, ``scene_gt.json`` and
    ``scene_gt_info.json`` where the scene has them) and returns what was written. Frames are
    resized with pixel-area averaging when they shrink, bilinearly when they grow."""
    if not (isinstance(width, int) and isinstance(height, int) and width >= 16 and height >= 16):
        raise UserError(f"the copy's size must be whole numbers of at least 16 pixels, not {width}x{height}")
    scene = load_scene(scene_dir)
    out = Path(out_dir)
    if out.exists() and out.resolve() == scene.root.resolve():
        raise UserError(f"--out {out_dir} is the scene itself: the copy goes into another folder")
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    cameras, scales = {}, {}
    try:
        for im_id in scene.im_ids:
            rgb = scene.read_rgb(im_id)
            h, w = rgb.shape[:2]
            shrink = width * height < w * h
            small = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
            if not cv2.imwrite(str(out / "rgb" / f"{im_id:06d}.png"), cv2.cvtColor(small, cv2.COLOR_RGB2BGR)):
                raise UserError(f"{out / 'rgb'}: cannot write images here")
            cameras[im_id] = dict(scene.cameras[im_id], K=scale_intrinsics(scene.cameras[im_id]["K"], (w, h),
                                                                           (width, height)))
            scales[im_id] = (width / w, height / h)
    finally:
        scene.close()
    save_scene_camera(out / "scene_camera.json", cameras)
    gt_path = scene.root / "scene_gt.json"
    if gt_path.is_file():  # poses do not depend on the resolution
        d = json.loads(gt_path.read_text())
        write_json(out / "scene_gt.json", {k: v for k, v in d.items() if int(k) in scales})
    info_path = scene.root / "scene_gt_info.json"
    if info_path.is_file():
        d = json.loads(info_path.read_text())
        write_json(out / "scene_gt_info.json",
                   {k: [_scaled_info(e, *scales[int(k)]) for e in v] for k, v in d.items() if int(k) in scales})
    return {"frames": len(scales), "size": (width, height), "out": str(out),
            "left_out": [n for n in NOT_COPIED if (scene.root / n).is_dir()]}


def _scaled_info(entry: dict, sx: float, sy: float) -> dict:
    """A ``scene_gt_info`` entry at the copy's resolution: boxes and pixel counts scaled, the
    visible fraction kept."""
    e = dict(entry)
    for key in ("bbox_obj", "bbox_visib"):
        if key in e:
            x, y, w, h = (float(v) for v in e[key])
            # a box as pixel ranges [x, x + w): its edges scale like pixel boundaries
            e[key] = [int(round(x * sx)), int(round(y * sy)), int(round(w * sx)), int(round(h * sy))]
    for key in ("px_count_all", "px_count_valid", "px_count_visib"):
        if key in e:
            e[key] = int(round(float(e[key]) * sx * sy))
    return e

