"""Pack a BOP scene into a recording: its frames as one MJPEG video (``rgb.avi``, im_ids in
order) beside its ``scene_camera.json`` / ``scene_gt.json``. ``load_scene`` reads such a
folder like any BOP scene, so the demo, ``eval`` and ``score`` all run on it."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from tracker.core.bop import SCENE_VIDEOS, load_scene
from tracker.core.errors import UserError


def write_scene_video(scene_dir, out_dir, quality: int = 95, fps: float = 10.0) -> dict:
    """Returns the video size and the PSNR of its frames against the originals."""
    if not 1 <= quality <= 100 or not 0 < fps <= 1000:
        raise UserError(f"quality must be 1-100 and fps in (0, 1000], got {quality} and {fps}")
    scene = load_scene(scene_dir)
    out = Path(out_dir)
    if out.exists() and out.resolve() == scene.root.resolve():
        raise UserError(f"--out {out_dir} is the scene itself: the recording goes into another folder")
    out.mkdir(parents=True, exist_ok=True)
    path = out / SCENE_VIDEOS[0]
    h, w = scene.read_rgb(scene.im_ids[0]).shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.CAP_OPENCV_MJPEG, cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    if not writer.isOpened():
        raise UserError(f"{path}: OpenCV cannot write an MJPEG video here")
    # set after opening: OpenCV's MJPEG writer ignores the quality passed as an open parameter
    # (measured: the same bytes for 20 and 95)
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, quality)
    try:
        for im_id in scene.im_ids:
            rgb = scene.read_rgb(im_id)
            if rgb.shape[:2] != (h, w):
                raise UserError(f"{scene.root}: image {im_id} is {rgb.shape[1]}x{rgb.shape[0]}, not {w}x{h}")
            writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    keep = set(scene.im_ids)  # the video holds exactly these frames (keys may be zero-padded: "000003")
    for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
        if (scene.root / name).is_file():
            d = json.loads((scene.root / name).read_text())
            (out / name).write_text(json.dumps({k: v for k, v in d.items() if int(k) in keep}))
    packed = load_scene(out)
    psnr = [cv2.PSNR(scene.read_rgb(i), packed.read_rgb(i)) for i in scene.im_ids]
    packed.close()
    scene.close()
    return {"video": str(path), "frames": len(psnr), "bytes": path.stat().st_size,
            "psnr_min": float(np.min(psnr)), "psnr_median": float(np.median(psnr))}
