"""A montage of synthetic samples with their boxes and visible fractions, and the crops the
autoencoder will see next to their clean targets: look at the data before training on it."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tracker.core.bop import load_scene
from tracker.core.geometry import SquareCrop, crop_and_resize, square_crop
from tracker.runtime.overlay import LMO_NAMES, colour, draw_box, montage


def load_windows(scene_root: Path) -> dict[int, list[list[float]]]:
    import json
    p = Path(scene_root) / "clean_crops.json"
    return {int(k): v for k, v in json.loads(p.read_text()).items()} if p.is_file() else {}


def preview(split_dir, out_file, n_scenes: int = 8, n_crops: int = 16, crop_size: int = 96) -> Path:
    root = Path(split_dir) / "000000"
    scene = load_scene(root, require_gt=True)
    windows = load_windows(root)
    tiles, pairs = [], []
    for im_id in scene.im_ids[:n_scenes]:
        img = scene.read_rgb(im_id)
        vis = img.copy()
        for k, g in enumerate(scene.gt[im_id]):
            info = g.info
            col = colour(g.obj_id)
            if info.get("bbox_obj", [-1])[0] != -1:
                draw_box(vis, info["bbox_obj"], (128, 128, 128))
            if info.get("bbox_visib", [-1])[0] != -1:
                draw_box(vis, info["bbox_visib"], col,
                         f"{LMO_NAMES.get(g.obj_id, g.obj_id)} {info.get('visib_fract', 0):.2f}")
            if len(pairs) < n_crops and info.get("visib_fract", 0) >= 0.1:
                crop = square_crop(info["bbox_visib"], crop_size)
                x = crop_and_resize(img, crop)
                clean_p = root / "clean" / f"{im_id:06d}_{k:06d}.png"
                clean = cv2.cvtColor(cv2.imread(str(clean_p)), cv2.COLOR_BGR2RGB)
                x0, y0, side = windows[im_id][k]
                target = crop_and_resize(clean, crop.within(SquareCrop(x0, y0, side, clean.shape[0])))
                pairs.append(np.concatenate([x, target], axis=1))
        tiles.append(vis)
    sheet = montage(tiles, cols=4, scale=0.5)
    if pairs:
        while len(pairs) % 8:
            pairs.append(np.zeros_like(pairs[0]))
        rows = [np.concatenate(pairs[i:i + 8], axis=1) for i in range(0, len(pairs), 8)]
        strip = np.concatenate(rows, axis=0)
        s = sheet.shape[1] / strip.shape[1]
        strip = cv2.resize(strip, (sheet.shape[1], int(strip.shape[0] * s)), interpolation=cv2.INTER_AREA)
        sheet = np.concatenate([sheet, strip], axis=0)
    out = Path(out_file)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return out
