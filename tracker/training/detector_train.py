"""``app.py train-detector``: train the CenterNet-style detector on ``synth`` scenes (torch,
CPU), export it to ONNX and add it to a model bundle (manifest re-hashed).

Images are letterboxed to the detector's input size once and cached (uint8) in
``<bundle>.work/``; every batch then gets a random zoom/shift (boxes follow exactly: no
rotation), colour, blur and noise augmentation. The learning rate follows a cosine over the
time budget; a checkpoint is written every few minutes and training resumes from it.
"""
from __future__ import annotations

import hashlib
import json
import math
import pickle
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from tracker.core.bop import load_scene
from tracker.training.crops import split_fingerprint, split_scene_dirs, train_val_split
from tracker.runtime.detector import BOX_KINDS, DetectorSpec, decode, letterbox, normalise
from tracker.core.errors import UserError
from tracker.core.files import write_whole
from tracker.core.paths import work_dir
from tracker.core.visibility import mask_box
from tracker.training.nets.schedule import budget_lr

MIN_VISIB = 0.1
CUTOUT_MAX_SIDE = 160  # px a cut-out is kept at; pastes reach 40 % of the input width (128 px at 320)
CUTOUT_SHARE = 0.5     # share of training images that get cut-outs when --cutouts is given
# recipe keys added after checkpoints were first written, at the value a run without them records
RECIPE_ADDED = {"cutouts": None, "cutout_share": 0.0, "boxes": "visible", "frozen_batchnorm": False,
                "colour": "standard", "ema": 0.0, "backbone": "plain", "pretrained": False,
                "freeze_through": None}
COLOUR_AUGS = ("standard", "strong", "mild")


def target_box(info: dict, kind: str, width: int, height: int) -> list[float]:
    """An instance's training box (x, y, w, h) from its ``scene_gt_info`` entry: the visible
    box, or (``amodal``) the whole silhouette's clipped to the image (with the visible box in
    it: the silhouette is rendered in a window of its own, a pixel or two off at times)."""
    if kind == "visible":
        return list(info["bbox_visib"])
    (x, y, w, h), (vx, vy, vw, vh) = info["bbox_obj"], info["bbox_visib"]
    x0, y0 = max(min(x, vx), 0), max(min(y, vy), 0)
    return [x0, y0, min(max(x + w, vx + vw), width) - x0, min(max(y + h, vy + vh), height) - y0]


def load_detection_set(split_dir, spec: DetectorSpec, cache: Path | None = None, max_images=None, log=print,
                       fingerprint: str | None = None):
    """Letterboxed images (N, H, W, 3) uint8 and per image an (n, 5) array [class, x, y, w, h]
    of the boxes ``spec.boxes`` names (visible or amodal; instances with visib >= 0.1) in
    network-input pixels. ``cache`` holds them with the split's fingerprint: a split rendered
    again since is cut again (a cache written before the fingerprint was kept is trusted).
    ``fingerprint``: the split's, when the caller has it already."""
    split = fingerprint or split_fingerprint(split_dir)
    if cache is not None and cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            if "split" not in z or str(z["split"]) == split:
                images, boxes = z["images"], np.split(z["boxes"], np.cumsum(z["counts"])[:-1])
                log(f"loaded {len(images)} images from {cache}")
                return images, boxes
        log(f"{cache}: cut from an earlier version of {split_dir}; cutting its images again")
    lut = {c: i for i, c in enumerate(spec.classes)}
    imgs, boxes = [], []
    scenes = split_scene_dirs(split_dir)
    total = sum(len(json.loads((s / "scene_camera.json").read_text())) for s in scenes)
    total = min(total, max_images or total)
    for sdir in scenes:
        if len(imgs) >= total:
            break
        scene = load_scene(sdir, require_gt=True)
        for im_id in tqdm(scene.im_ids, desc=f"images {sdir.name}", unit="img", leave=False):
            if len(imgs) >= total:
                break
            rgb = scene.read_rgb(im_id)
            img, lb = letterbox(rgb, spec.input_w, spec.input_h, spec.pad_value)
            b = [[lut[g.obj_id], *target_box(g.info, spec.boxes, rgb.shape[1], rgb.shape[0])] for g in scene.gt[im_id]
                 if g.obj_id in lut and g.info.get("visib_fract", 0) >= MIN_VISIB and g.info["bbox_visib"][2] > 1]
            b = np.array(b, np.float32).reshape(-1, 5)
            b[:, 1:] = lb.to_input(b[:, 1:])
            imgs.append(img)
            boxes.append(b)
    if not imgs:
        raise UserError(f"{split_dir}: no images")
    images = np.stack(imgs)
    if cache is not None:
        write_whole(cache, lambda tmp: np.savez(tmp, images=images, boxes=np.concatenate(boxes),
                                                counts=np.array([len(b) for b in boxes]), split=np.array(split)))
    return images, boxes


def draw_targets(boxes_list, n_classes: int, out_w: int, out_h: int, stride: int):
    """CenterNet targets at ``stride``: Gaussian centre heatmaps (elliptical, sigma = 0.54 x
    box size / 6, as TTFNet), and at each centre cell log size and sub-cell offset."""
    B = len(boxes_list)
    hm = np.zeros((B, n_classes, out_h, out_w), np.float32)
    reg = np.zeros((B, 4, out_h, out_w), np.float32)
    mask = np.zeros((B, 1, out_h, out_w), np.float32)
    ys, xs = np.mgrid[0:out_h, 0:out_w].astype(np.float32)
    for i, boxes in enumerate(boxes_list):
        for c, x, y, w, h in boxes:
            cx, cy = (x + w / 2) / stride, (y + h / 2) / stride
            ix, iy = int(cx), int(cy)
            if not (0 <= ix < out_w and 0 <= iy < out_h) or w < 2 or h < 2:
                continue
            sx, sy = max(0.54 * w / 6 / stride, 0.5), max(0.54 * h / 6 / stride, 0.5)
            g = np.exp(-((xs - ix) ** 2 / (2 * sx * sx) + (ys - iy) ** 2 / (2 * sy * sy)))
            hm[i, int(c)] = np.maximum(hm[i, int(c)], g)
            hm[i, int(c), iy, ix] = 1.0
            reg[i, :, iy, ix] = (math.log(w / stride), math.log(h / stride), cx - ix, cy - iy)
            mask[i, 0, iy, ix] = 1.0
    return hm, reg, mask


def occlude(x, boxes_list, rng: np.random.Generator, p: float, max_covered: float = 0.5, objects: float = 0.0):
    """With probability ``p`` per batch item, paste 1-3 rectangles (8-30 % of the image's
    width and height each) cut from another item of the batch where it shows none of its
    objects (10 tries, else that rectangle is skipped), as clutter in front of the objects. A
    box more than ``max_covered`` hidden by them is dropped from the targets; the others keep
    their boxes. With probability ``objects`` a rectangle is instead cut around one of the
    other item's objects (its box plus a 0-30 % margin), and that object joins the targets:
    labelled objects in front of labelled objects, as the LM-O objects stand in a cluster
    (parts of the other item's objects caught in the margin are not labelled).
    ``x``: (B, 3, H, W) tensor, changed in place."""
    B, _, H, W = x.shape
    out = []
    src = x.clone()
    for i, b in enumerate(boxes_list):
        if B < 2 or rng.random() >= p:
            out.append(b)
            continue
        covered = np.zeros((H, W), bool)
        pasted = []
        for _ in range(rng.integers(1, 4)):
            if objects > 0 and rng.random() < objects:  # (no draw at 0: older runs' streams unchanged)
                j = (i + int(rng.integers(1, B))) % B
                if not len(boxes_list[j]):
                    continue
                c, bx, by, bw, bh = boxes_list[j][int(rng.integers(len(boxes_list[j])))]
                m = rng.uniform(0, 0.3)
                sx, sy = int(max(bx - m * bw, 0)), int(max(by - m * bh, 0))
                w = int(min(np.ceil(bx + bw * (1 + m)), W)) - sx
                h = int(min(np.ceil(by + bh * (1 + m)), H)) - sy
                if w < 2 or h < 2:
                    continue
                x0, y0 = int(rng.integers(0, W - w + 1)), int(rng.integers(0, H - h + 1))
                x[i, :, y0:y0 + h, x0:x0 + w] = src[j, :, sy:sy + h, sx:sx + w]
                covered[y0:y0 + h, x0:x0 + w] = True
                pasted.append([c, x0 + bx - sx, y0 + by - sy, bw, bh])
                continue
            w, h = int(rng.uniform(0.08, 0.3) * W), int(rng.uniform(0.08, 0.3) * H)
            x0, y0 = int(rng.integers(0, W - w + 1)), int(rng.integers(0, H - h + 1))
            j = (i + int(rng.integers(1, B))) % B
            for _ in range(10):  # a patch with none of the source's objects in it: no unlabelled targets
                sx, sy = int(rng.integers(0, W - w + 1)), int(rng.integers(0, H - h + 1))
                if not any(bx < sx + w and sx < bx + bw and by < sy + h and sy < by + bh
                           for _, bx, by, bw, bh in boxes_list[j]):
                    x[i, :, y0:y0 + h, x0:x0 + w] = src[j, :, sy:sy + h, sx:sx + w]
                    covered[y0:y0 + h, x0:x0 + w] = True
                    break
        kept = _uncovered(b, covered, max_covered)
        # a later rectangle may cover part of an earlier pasted object; it stays a target
        out.append(np.concatenate([kept, np.asarray(pasted, b.dtype).reshape(-1, 5)]) if pasted else kept)
    return x, out


def _uncovered(b, covered, max_covered: float):
    """The boxes of ``b`` ([class, x, y, w, h] rows) at most ``max_covered`` hidden by ``covered``."""
    H, W = covered.shape
    keep = []
    for _, bx, by, bw, bh in b:
        c0, r0 = int(max(bx, 0)), int(max(by, 0))
        c1, r1 = int(min(np.ceil(bx + bw), W)), int(min(np.ceil(by + bh), H))
        area = max(c1 - c0, 0) * max(r1 - r0, 0)
        keep.append(area > 0 and covered[r0:r1, c0:c1].sum() <= max_covered * area)
    return b[np.asarray(keep, bool)] if len(b) else b


def load_cutouts(folder, log=print) -> tuple[list[np.ndarray], str]:
    """The ``.png .webp .tif .tiff`` images under ``folder`` (recursively) whose alpha channel
    has clear pixels and at least 64 opaque ones (alpha > 127): photos or drawings of things
    cut out of their background. Each is cropped to its non-clear pixels, shrunk to at most
    ``CUTOUT_MAX_SIDE`` px and kept as premultiplied RGBA uint8 (colour x alpha: resizing then
    blends no colour of the clear pixels into the edges). Also returns the set's identity (count
    and a hash of the files' relative names and sizes) for the checkpoint's recipe."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"--cutouts {folder}: no such folder")
    files = sorted(f for f in folder.rglob("*") if f.suffix.lower() in (".png", ".webp", ".tif", ".tiff"))
    out, used, skipped = [], hashlib.sha1(), 0
    for f in files:
        im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if im is not None and im.dtype == np.uint16:
            im = (im >> 8).astype(np.uint8)
        if im is None or im.ndim != 3 or im.shape[2] != 4 or im.dtype != np.uint8:
            skipped += 1
            continue
        a = im[..., 3]
        if (a > 127).sum() < 64 or (a > 0).all():
            skipped += 1
            continue
        x0, y0, w, h = mask_box(a)
        im = im[y0:y0 + h, x0:x0 + w]
        im = np.dstack([(im[..., [2, 1, 0]].astype(np.uint16) * im[..., 3:] + 127) // 255, im[..., 3]]).astype(np.uint8)
        s = CUTOUT_MAX_SIDE / max(im.shape[:2])
        if s < 1:
            im = cv2.resize(im, (max(round(im.shape[1] * s), 1), max(round(im.shape[0] * s), 1)),
                            interpolation=cv2.INTER_AREA)
        out.append(np.ascontiguousarray(im))
        used.update(f"{f.relative_to(folder).as_posix()}:{f.stat().st_size}\n".encode())
    if not out:
        raise UserError(f"--cutouts {folder}: no images with transparency (RGBA PNG) found")
    log(f"cut-outs: {len(out)} images from {folder}"
        + (f" ({skipped} skipped: unreadable, no alpha, or no clear or too few opaque pixels)" if skipped else ""))
    return out, f"{len(out)} images, id {used.hexdigest()[:10]}"


def paste_cutouts(x, boxes_list, rng: np.random.Generator, cutouts: list[np.ndarray], p: float,
                  max_covered: float = 0.5):
    """With probability ``p`` per batch item, alpha-blend 1-3 cut-outs (premultiplied RGBA, as
    ``load_cutouts``; longer side 6-40 % of the image's width, mirrored at random, brightness
    x0.7-1.3) at random places, part of them possibly outside the image: real things that are
    not targets, in front of the scene. Boxes more than ``max_covered`` hidden by their opaque
    pixels (alpha > 127) leave the targets. ``x``: (B, 3, H, W) float tensor in [0, 1], changed
    in place."""
    import torch
    _, _, H, W = x.shape
    out = []
    for i, b in enumerate(boxes_list):
        if rng.random() >= p:
            out.append(b)
            continue
        covered = np.zeros((H, W), bool)
        for _ in range(rng.integers(1, 4)):
            im = cutouts[int(rng.integers(len(cutouts)))]
            s = rng.uniform(0.06, 0.4) * W / max(im.shape[:2])
            w, h = max(round(im.shape[1] * s), 2), max(round(im.shape[0] * s), 2)
            im = cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
            if rng.random() < 0.5:
                im = im[:, ::-1]
            x0, y0 = int(rng.integers(-w // 2, W - w // 2)), int(rng.integers(-h // 2, H - h // 2))
            c0, r0, c1, r1 = max(x0, 0), max(y0, 0), min(x0 + w, W), min(y0 + h, H)
            part = im[r0 - y0:r1 - y0, c0 - x0:c1 - x0]
            rgb = torch.from_numpy(np.ascontiguousarray(part[..., :3].transpose(2, 0, 1))).float()
            rgb = rgb * float(rng.uniform(0.7, 1.3) / 255)
            a = torch.from_numpy(np.ascontiguousarray(part[..., 3])).float()[None] / 255
            x[i, :, r0:r1, c0:c1] = (rgb + x[i, :, r0:r1, c0:c1] * (1 - a)).clamp(0, 1)
            covered[r0:r1, c0:c1] |= part[..., 3] > 127
        out.append(_uncovered(b, covered, max_covered))
    return x, out


def hue_turns(angles) -> np.ndarray:
    """(B, 3, 3) float32: RGB turned about the grey axis by each angle (radians); grey stays
    grey, a third of a turn takes red to green."""
    from scipy.spatial.transform import Rotation
    axis = np.ones(3) / np.sqrt(3)
    return Rotation.from_rotvec(np.asarray(angles, float)[:, None] * axis).as_matrix().astype(np.float32)


def strong_colour(x, rng: np.random.Generator, torch):
    """The heavier photometric changes that detectors trained on renders for BOP use (GDR-Net's
    and CosyPose's imgaug pipelines, in spirit): each with its own chance per image, a
    grey-scale blend, a per-channel gain and offset, a stronger contrast, the hue turned
    by up to 30 degrees, channels inverted, a wider blur. They leave the geometry alone, so
    the boxes stand. ``x``: (B, 3, H, W) float in [0, 1]."""
    from torch.nn import functional as F
    B = x.shape[0]

    def per_image(p, lo, hi, shape=(1, 1, 1), neutral=1.0):
        v = rng.uniform(lo, hi, (B,) + shape).astype(np.float32)
        v[rng.random(B) >= p] = neutral
        return torch.from_numpy(v)

    grey = x.mean(dim=1, keepdim=True)
    a = per_image(0.5, 0.0, 1.0, neutral=0.0)
    x = x * (1 - a) + grey * a                                               # towards grey
    x = x * per_image(0.5, 0.6, 1.4, (3, 1, 1)) + per_image(0.5, -0.1, 0.1, (3, 1, 1), 0.0)  # per-channel gain, offset
    m = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - m) * per_image(0.5, 0.5, 2.2) + m                                # contrast
    ang = rng.uniform(-np.pi / 6, np.pi / 6, B) * (rng.random(B) < 0.3)  # shades, not other objects' colours
    x = torch.einsum("bij,bjhw->bihw", torch.from_numpy(hue_turns(ang)), x)  # hue turned
    inv = torch.from_numpy(((rng.random((B, 3)) < 0.2) & (rng.random((B, 1)) < 0.3)).astype(np.float32))[:, :, None, None]
    x = x.clamp(0, 1)
    x = x * (1 - inv) + (1 - x) * inv                                         # channels inverted
    sig = rng.uniform(0.5, 2.0, B)
    for i in np.nonzero(rng.random(B) < 0.2)[0]:                               # a wider blur
        r = int(np.ceil(2.5 * sig[i]))
        k = torch.from_numpy(np.exp(-0.5 * (np.arange(-r, r + 1) / sig[i]) ** 2).astype(np.float32))
        k = k / k.sum()
        xi = F.pad(x[i:i + 1], (r, r, r, r), mode="replicate")
        xi = F.conv2d(xi, k.view(1, 1, 1, -1).repeat(3, 1, 1, 1), groups=3)
        x[i:i + 1] = F.conv2d(xi, k.view(1, 1, -1, 1).repeat(3, 1, 1, 1), groups=3)
    return x.clamp(0, 1)


def augment_batch(x, boxes_list, rng: np.random.Generator, torch, occlusion: float = 0.0,
                  paste_objects: float = 0.0, cutouts: list[np.ndarray] | None = None, cutout_share: float = 0.0,
                  colour: str = "standard"):
    """Random zoom (0.6-1.6, log-uniform) and shift on the whole batch item (boxes follow),
    then (with ``occlusion`` > 0) clutter pasted over it (``occlude``; ``paste_objects`` is its
    ``objects``), then (with ``cutouts`` and ``cutout_share`` > 0) real cut-outs over a share of
    the items (``paste_cutouts``), then colour
    (brightness, contrast, saturation, per-channel gain), blur and noise; with ``colour``
    'strong', ``strong_colour`` before the noise; with 'mild', no saturation or per-channel
    gain (the objects' colours kept).
    ``x``: (B, 3, H, W) float in [0, 1]."""
    from torch.nn import functional as F
    B, _, H, W = x.shape
    s = np.exp(rng.uniform(np.log(0.6), np.log(1.6), B))
    tx = rng.uniform(-0.3, 0.3, B) * W
    ty = rng.uniform(-0.3, 0.3, B) * H
    theta = np.zeros((B, 2, 3), np.float32)  # output -> input, normalised coordinates
    theta[:, 0, 0] = 1 / s
    theta[:, 1, 1] = 1 / s
    # a pixel u_in maps to u_out = s * (u_in - c) + c + t  (c = image centre)
    theta[:, 0, 2] = -tx / s / (W / 2)
    theta[:, 1, 2] = -ty / s / (H / 2)
    grid = F.affine_grid(torch.from_numpy(theta), list(x.shape), align_corners=False)
    x = F.grid_sample(x - 0.45, grid, mode="bilinear", padding_mode="zeros", align_corners=False) + 0.45
    out_boxes = []
    for i, b in enumerate(boxes_list):
        b = b.copy()
        x0 = s[i] * (b[:, 1] - W / 2) + W / 2 + tx[i]
        y0 = s[i] * (b[:, 2] - H / 2) + H / 2 + ty[i]
        x1, y1 = x0 + s[i] * b[:, 3], y0 + s[i] * b[:, 4]
        cx0, cy0, cx1, cy1 = np.clip(x0, 0, W), np.clip(y0, 0, H), np.clip(x1, 0, W), np.clip(y1, 0, H)
        area = np.maximum(cx1 - cx0, 0) * np.maximum(cy1 - cy0, 0)
        keep = area >= 0.35 * np.maximum((x1 - x0) * (y1 - y0), 1e-6)
        b[:, 1:] = np.stack([cx0, cy0, cx1 - cx0, cy1 - cy0], 1)
        out_boxes.append(b[keep])
    if occlusion > 0:
        x, out_boxes = occlude(x, out_boxes, rng, occlusion, objects=paste_objects)
    if cutouts and cutout_share > 0:  # (no draw without: older runs' streams unchanged)
        x, out_boxes = paste_cutouts(x, out_boxes, rng, cutouts, cutout_share)
    g = torch.from_numpy(rng.uniform(0.5, 1.5, (B, 1, 1, 1)).astype(np.float32))
    x = x * g                                                   # brightness
    m = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - m) * torch.from_numpy(rng.uniform(0.6, 1.4, (B, 1, 1, 1)).astype(np.float32)) + m  # contrast
    sat = torch.from_numpy(rng.uniform(0.5, 1.5, (B, 1, 1, 1)).astype(np.float32))
    wb = torch.from_numpy(rng.uniform(0.85, 1.15, (B, 3, 1, 1)).astype(np.float32))
    if colour != "mild":  # ('mild' keeps the objects' colours: drawn all the same, so the rest is as standard)
        grey = x.mean(dim=1, keepdim=True)
        x = (x - grey) * sat + grey                             # saturation
        x = x * wb                                              # white balance
    blur = rng.random(B) < 0.3
    if blur.any():
        k = torch.tensor([1, 4, 6, 4, 1], dtype=torch.float32)
        k = (k[:, None] * k[None]) / 256
        idx = torch.from_numpy(np.nonzero(blur)[0])
        xb = F.conv2d(F.pad(x[idx], (2, 2, 2, 2), mode="replicate"), k[None, None].repeat(3, 1, 1, 1), groups=3)
        x = x.clone()
        x[idx] = xb
    if colour == "strong":  # (no draw without: older runs' streams unchanged)
        x = strong_colour(x.clamp(0, 1), rng, torch)
    x = x + torch.randn_like(x) * torch.from_numpy(rng.uniform(0, 0.04, (B, 1, 1, 1)).astype(np.float32))
    return x.clamp(0, 1), out_boxes


def _init_weights(torch, path, width: int, classes: list[int], backbone: str = "plain") -> tuple[dict, bool]:
    """The network weights to start from, checked against this run's width and classes, and
    whether the BatchNorms must stay frozen: another run's checkpoint (tensors and plain
    containers only are read: no code runs), or a bundle whose detector is a single float
    network (its manifest verified; the weights read back from its ONNX graph, where the
    export folded the BatchNorms: ``nets.detector.state_from_export``)."""
    if Path(path).is_dir():
        return _weights_from_bundle(torch, path, width, classes), True
    try:
        z = torch.load(path, weights_only=True)
        ok = isinstance(z, dict) and z.get("width") == width and z.get("classes") == classes
        theirs = z.get("recipe", {}).get("backbone", "plain") if isinstance(z, dict) else "?"
        if ok and theirs != backbone:
            raise UserError(f"--init-from {path}: a detector on the '{theirs}' backbone, this run has --backbone {backbone}")
        if not ok:
            raise UserError(f"--init-from {path}: a detector of width {z.get('width') if isinstance(z, dict) else '?'} "
                            f"and classes {z.get('classes') if isinstance(z, dict) else '?'}, this run has width "
                            f"{width} and classes {classes}")
        return z["model"], bool(z.get("recipe", {}).get("frozen_batchnorm", False))
    except FileNotFoundError:
        raise UserError(f"--init-from {path}: no such file or bundle (it takes a detector_ckpt_*.pt from a bundle's "
                        f".work folder, or a bundle folder)") from None
    except (RuntimeError, KeyError, ValueError, TypeError, EOFError, pickle.UnpicklingError) as e:
        raise UserError(f"--init-from {path}: not a detector checkpoint ({type(e).__name__})") from None


def _weights_from_bundle(torch, path, width: int, classes: list[int]) -> dict:
    import onnx
    from onnx import numpy_helper
    from tracker.runtime.detector import float_detector, run_graph
    from tracker.training.nets.detector import CenterNetLite, state_from_export
    # verified; joined or int8 detectors refused
    _, spec, _, onnx_path = float_detector(path, "start from the bundle of one of the networks it was made from")
    if spec.classes != classes:
        raise UserError(f"--init-from {path}: its detector has classes {spec.classes}, this run has {classes}")
    g = onnx.load(str(onnx_path)).graph
    init = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    convs = [n for n in g.node if n.op_type == "Conv"]
    weights = [(init.get(n.input[1]), init.get(n.input[2]) if len(n.input) > 2 else None) for n in convs]
    model = CenterNetLite(len(classes), width)
    try:
        if any(w is None for w, _ in weights):
            raise ValueError("a convolution whose weights are not stored in the graph")
        sd = state_from_export(model, weights)
    except ValueError as e:
        raise UserError(f"--init-from {path}: its detector is not a width-{width} network of this kind ({e})") from None
    model.load_state_dict(sd)
    x = np.random.default_rng(0).normal(0, 1, (1, 3, spec.input_h, spec.input_w)).astype(np.float32)
    with torch.no_grad():
        y = model.eval()(torch.from_numpy(x)).numpy()
    diff = float(np.abs(run_graph(onnx_path, x) - y).max())
    if diff > 1e-4:
        raise UserError(f"--init-from {path}: the weights read back differ from its detector by {diff:.1e}")
    return sd


def ema_update(ema: dict, model, decay: float, step: int) -> None:
    """One step of the weights' exponential moving average (``ema``: name -> float tensor, every
    floating-point entry of the model's state, BatchNorm statistics too). The decay ramps up as
    (1 + step) / (10 + step) until it reaches ``decay``, so the early, random weights fade fast."""
    import torch
    d = min(decay, (1 + step) / (10 + step))
    with torch.no_grad():
        for k, v in model.state_dict().items():
            if k in ema:
                ema[k].mul_(d).add_(v.float(), alpha=1 - d)


def _recipe_options(old: dict, new: dict) -> str:
    """The options of recipe ``old`` that differ from ``new``, as a user would pass them (the
    share of cut-outs goes unsaid where the old run had none)."""
    out = []
    for k, v in old.items():
        if new.get(k) == v or (k == "cutout_share" and not old["cutouts"]):
            continue
        if k == "cutouts":
            out.append("no --cutouts" if v is None else f"--cutouts (a folder of {v})")
        elif k == "frozen_batchnorm":
            out.append("--init-from a bundle (its BatchNorms frozen)" if v else "no --init-from a bundle")
        elif v is None:
            out.append(f"no --{k.replace('_', '-')}")
        else:
            out.append(f"--{k.replace('_', '-')} {v}")
    return ", ".join(out)


# validation on the held-out renders and the ONNX export, at the end of a run (a two-object
# build's 433 validation images: well under this; build's detector stage ran 1.3 min over its
# share, loading the images and these, before stage_minutes)
AFTER_MINUTES = 0.5


def train_detector(data_dir, bundle_dir, minutes: float = 60.0, width: int = 32, input_w: int = 320,
                   input_h: int = 240, batch: int = 32, lr: float = 2e-3, seed: int = 0, max_images=None,
                   val_parts: int = 20, threads: int = 2, init_from=None, occlusion: float = 0.0,
                   paste_objects: float = 0.0, cutouts=None, cutout_share: float | None = None, log=print,
                   command: str | None = None, precision: str = "auto", box_kind: str = "visible",
                   colour: str = "standard", ema: float = 0.0, backbone: str = "plain",
                   pretrained: bool = True, device: str = "cpu", stage_minutes: float | None = None,
                   max_steps: int | None = None, freeze_through: str | None = None) -> dict:
    """``stage_minutes``: the whole call's budget (``build``): training gets ``minutes`` or what
    is left of it after loading the images, less :data:`AFTER_MINUTES` for validation and
    export. ``backbone``: ``plain`` (:class:`CenterNetLite` from random weights) or an
    EfficientNet-Lite trunk (``lite0``..``lite2``, ImageNet weights unless ``pretrained`` is
    False; BatchNorm frozen; the spec's normalisation becomes the weights'). ``box_kind``: the targets are the objects' visible boxes, or their whole silhouettes'
    (``amodal``, clipped to the image: a box's size and centre then follow the object's
    distance and position behind whatever hides part of it). ``ema`` > 0: validate and export
    the exponential moving average of the weights with this decay (``ema_update``), not the
    last weights. ``max_steps``: a budget of training steps (the resumed run's included) instead
    of time: training ends after that many, however long they take (``minutes`` and
    ``stage_minutes`` then end nothing, and the step size's cosine runs over the steps), so a
    seed gives the same network on any machine. ``freeze_through`` (``nanodet`` only): the
    COCO backbone from its stem through this stage (``stage2``: stride 8, ``stage3``: 16) keeps
    its weights: no gradients, no backward pass through it; the later stages, the neck and the
    heads train.

    Under ``torchrun --nproc_per_node N`` (DistributedDataParallel: gloo on CPUs, NCCL on GPUs)
    the N processes share every batch; the first one validates, exports and writes the bundle
    and returns the manifest's detector entry, the others return None."""
    if box_kind not in BOX_KINDS:
        raise UserError(f"--boxes must be one of {', '.join(BOX_KINDS)}, not '{box_kind}'")
    if colour not in COLOUR_AUGS:
        raise UserError(f"--colour must be one of {', '.join(COLOUR_AUGS)}, not '{colour}'")
    from tracker.training.nets.detector import BACKBONES, COCO_MEAN_STD, IMAGENET_MEAN_STD
    if backbone not in BACKBONES:
        raise UserError(f"--backbone must be one of {', '.join(BACKBONES)}, not '{backbone}'")
    if backbone != "plain" and init_from and Path(init_from).is_dir():
        raise UserError("--init-from BUNDLE reads back a plain detector; with --backbone "
                        f"{backbone} start from a checkpoint (detector_ckpt_*.pt) instead")
    if freeze_through is not None:
        from tracker.training.nets.nanodet import Backbone
        if backbone != "nanodet" or not pretrained:
            raise UserError("--freeze-through keeps part of NanoDet's COCO weights: it needs --backbone nanodet "
                            "(and its weights, not --no-pretrained)")
        if freeze_through not in Backbone.STAGES:
            raise UserError(f"--freeze-through must be one of {', '.join(Backbone.STAGES)}, not '{freeze_through}'")
    if max_steps is not None and not (isinstance(max_steps, int) and max_steps >= 1):
        raise UserError(f"the step budget must be a whole number of at least 1, not {max_steps}")
    if not 0.0 <= ema < 1.0:
        raise UserError(f"--ema is a decay in [0, 1) (0: off; 0.999 averages about the last 1,000 steps), not {ema}")
    if paste_objects > 0 and occlusion <= 0:  # before torch is imported: nothing to wait for
        raise UserError("--paste-objects cuts some of the occlusion rectangles around objects: "
                        "it needs --occlusion above 0 as well")
    if cutout_share is not None and not cutouts:
        raise UserError("--cutout-share is the share of images that get cut-outs: it needs --cutouts DIR as well")
    cutout_images, cutout_set = load_cutouts(cutouts, log) if cutouts else (None, None)
    from tracker.training.train import require_torch
    torch = require_torch()
    from tracker.core.bundle import open_bundle, update_manifest
    from tracker.evaluation.detection_metrics import detection_ap
    from tracker.training.nets import precision as prec
    from tracker.training.nets.detector import Logits, focal_loss, freeze_batchnorm, make_detector
    from tracker.training.nets import distributed as dd
    from tracker.evaluation.report import fmt_num
    bundle = open_bundle(bundle_dir)  # verified before anything is changed
    device = prec.resolve_device(device)
    rank, n_proc = dd.init_from_env(device)  # under torchrun: several processes share each batch
    from tracker.training.nets.memory import keep_freed_memory
    torch.set_num_threads(threads if n_proc == 1 else max(1, threads // n_proc))
    keep_freed_memory()  # no page faults for every step's buffers (nets/memory.py)
    if rank != 0:
        log = lambda *a, **k: None  # noqa: E731  (the first process reports)
    torch.manual_seed(seed)
    precision = prec.resolve(precision, device)
    spec = DetectorSpec(classes=bundle.manifest.obj_ids, input_w=input_w, input_h=input_h, boxes=box_kind)
    if backbone != "plain":
        spec.mean, spec.std = COCO_MEAN_STD if backbone == "nanodet" else IMAGENET_MEAN_STD
    root = Path(bundle_dir)
    work = work_dir(root)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    # caches and checkpoints are keyed by the data, the classes and the network's shape
    key = hashlib.sha1(json.dumps([str(Path(data_dir).resolve()), spec.classes, input_w, input_h, max_images,
                                   width] + ([box_kind] if box_kind != "visible" else [])
                                  + ([backbone, pretrained] if backbone != "plain" else [])).encode()).hexdigest()[:10]
    cache = work / f"det_images_{key}.npz"
    data_print = split_fingerprint(data_dir)  # the key has the split's folder; this, what it holds
    # the first process cuts and caches the set, the others read it
    images, boxes = dd.first_then_rest(lambda: load_detection_set(data_dir, spec, cache, max_images, log,
                                                                     fingerprint=data_print))
    n = len(images)
    if stage_minutes is not None:
        minutes = min(minutes, max(0.05, stage_minutes - (time.perf_counter() - t0) / 60 - AFTER_MINUTES))
    tr, va = train_val_split(n, seed, parts=val_parts)
    if len(tr) < batch:
        raise UserError(f"{data_dir}: {len(tr)} training images, fewer than a batch of {batch}; "
                        f"make more with 'app.py synth' or pass a smaller --batch")
    C, S = len(spec.classes), spec.stride
    oh, ow = math.ceil(input_h / S), math.ceil(input_w / S)
    model = make_detector(C, width, backbone, pretrained)
    if freeze_through is not None:
        model.trunk.freeze(freeze_through)
    n_params = sum(p.numel() for p in model.parameters())
    n_trained = sum(p.numel() for p in model.parameters() if p.requires_grad)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    ckpt = work / f"detector_ckpt_{key}.pt"
    state = {"step": 0, "seconds": 0.0, "history": []}
    averaged = None  # the weights' moving average (--ema)
    # weights to start from, and whether its BatchNorms stay frozen (a bundle's exported network)
    init_weights, frozen = _init_weights(torch, init_from, width, spec.classes, backbone) if init_from else (None, False)
    # what a resumed run must share with the run that wrote the checkpoint (the data and the
    # network are in the key): otherwise one run silently mixes two augmentations or optimisers.
    # Not --minutes: a larger budget trains a finished run on (docs/experiments/)
    recipe = {"batch": batch, "lr": lr, "seed": seed, "occlusion": occlusion, "paste_objects": paste_objects,
              **RECIPE_ADDED, "boxes": box_kind, "frozen_batchnorm": frozen, "colour": colour, "ema": ema,
              "backbone": backbone, "pretrained": pretrained if backbone != "plain" else False,
              "freeze_through": freeze_through}
    if cutouts:
        recipe.update(cutouts=cutout_set, cutout_share=CUTOUT_SHARE if cutout_share is None else cutout_share)
    if ckpt.is_file():
        z = torch.load(ckpt, weights_only=True, map_location="cpu")  # tensors and plain containers only: no code runs
        # checkpoints written before the recipe was kept are trusted; keys added since have their off value
        old = {**RECIPE_ADDED, **z.get("recipe", recipe)}
        if z.get("data", data_print) != data_print:  # (checkpoints written before it was kept are trusted)
            raise UserError(f"{ckpt} was trained on an earlier version of {data_dir} (rendered again since): "
                            f"delete it to start afresh")
        if old != recipe:
            raise UserError(f"{ckpt} was written by a run with {_recipe_options(old, recipe)}: rerun with those "
                            f"options to resume it, or delete it to start afresh")
        if z.get("width") == width and z.get("classes") == spec.classes:
            model.load_state_dict(z["model"])
            opt.load_state_dict(z["opt"])
            state = z["state"]
            averaged = z.get("ema")
            log(f"resumed from {ckpt}: step {state['step']}, {state['seconds'] / 60:.1f} min done")
        else:
            raise UserError(f"{ckpt} is the checkpoint of another network (width or classes differ): "
                            f"delete it to start afresh")
        if init_from:
            log("--init-from ignored: resuming this run's own checkpoint")
    elif init_from:
        model.load_state_dict(init_weights)
        state["init_from"] = str(init_from)
        log(f"started from the weights of {init_from}; new optimiser, schedule and budget")
    if ema and averaged is None:  # a new run (a resumed one shares its recipe, so its checkpoint holds the average)
        averaged = {k: v.detach().float().clone() for k, v in model.state_dict().items() if v.is_floating_point()}
    # one budget on every process: each cut its own from what its loading took, and one that
    # stops a step before another leaves that one waiting in DDP's gradient exchange for ever
    # (seen under build --ray: two workers idle at the budget's last step)
    minutes = dd.max_over_ranks(minutes)
    budget = 60.0 * minutes
    weights = {"plain": "", "nanodet": ", COCO weights"}.get(backbone, ", ImageNet weights") if pretrained else ""
    log(f"detector ({backbone}{weights}): "
        f"{n_params / 1e6:.2f} M parameters"
        f"{f' ({n_trained / 1e6:.2f} M trained, frozen through {freeze_through})' if freeze_through else ''}, {len(tr)} train / {len(va)} validation images, "
        f"{input_w}x{input_h} input, budget {f'{max_steps} steps' if max_steps is not None else f'{minutes:.0f} min'}, "
        f"{precision} training passes on {device}")
    if max_steps is not None:
        bar = tqdm(total=max_steps, initial=min(state["step"], max_steps), unit="step", desc="detector",
                   disable=rank != 0)
    else:
        bar = tqdm(total=int(budget), initial=int(min(state["seconds"], budget)), unit="s", desc="detector",
                   disable=rank != 0)
    last_ckpt = time.perf_counter()
    run_start = time.perf_counter() - state["seconds"]
    losses = []

    def save():
        if rank != 0:  # one checkpoint, the first process's (the weights are the same in all)
            return
        z = {"model": model.state_dict(), "opt": opt.state_dict(), "state": state, "width": width,
             "classes": spec.classes, "recipe": recipe, "data": data_print, **({"ema": averaged} if averaged else {})}
        write_whole(ckpt, lambda tmp: torch.save(z, tmp))

    try:
        model.train()
        if frozen:
            freeze_batchnorm(model)
        model.to(device)
        opt.load_state_dict(opt.state_dict())  # moves a resumed optimiser's state to the device
        if averaged:
            averaged = {k: v.to(device) for k, v in averaged.items()}
        prec.channels_last(model)
        net = Logits(model)
        if n_proc > 1:
            from torch.nn.parallel import DistributedDataParallel
            net = DistributedDataParallel(net, device_ids=[torch.cuda.current_device()] if device == "cuda" else None)
        while True:
            if max_steps is not None:  # the same on every process
                if state["step"] >= max_steps:
                    break
                frac = state["step"] / max_steps
            else:
                spent = dd.max_over_ranks(state["seconds"])  # one clock: the same step size and last step everywhere
                if spent >= budget:
                    break
                frac = spent / budget
            for gr in opt.param_groups:
                gr["lr"] = budget_lr(lr, frac, state["step"], warmup=200)
            b_rng = np.random.default_rng([seed, state["step"]])
            idx = b_rng.choice(tr, batch, replace=False)
            if n_proc > 1:  # this process's share of the batch, augmented from its own stream
                idx = idx[rank::n_proc]
                b_rng = np.random.default_rng([seed, state["step"], rank])
            x = torch.from_numpy(images[idx]).permute(0, 3, 1, 2).float().div_(255)
            x, bl = augment_batch(x, [boxes[i] for i in idx], b_rng, torch, occlusion, paste_objects,
                                  cutout_images, recipe["cutout_share"], colour)
            hm_t, reg_t, mask_t = (torch.from_numpy(a).to(device) for a in draw_targets(bl, C, ow, oh, S))
            with prec.autocast(precision, device):
                hm, reg = net(prec.channels_last(((x - spec.mean) / spec.std).to(device)))
            hm, reg = hm.float(), reg.float()
            l_hm = focal_loss(hm, hm_t)
            npos = mask_t.sum().clamp(min=1)
            l_size = (torch.abs(reg[:, :2] - reg_t[:, :2]) * mask_t).sum() / npos
            l_off = (torch.abs(reg[:, 2:] - reg_t[:, 2:]) * mask_t).sum() / npos
            loss = l_hm + l_size + l_off
            opt.zero_grad()
            loss.backward()
            opt.step()
            if averaged:
                ema_update(averaged, model, ema, state["step"])
            losses.append(float(loss.detach()))
            state["step"] += 1
            now = time.perf_counter()
            state["seconds"] = now - run_start
            bar.n = state["step"] if max_steps is not None else int(min(state["seconds"], budget))
            bar.set_postfix(step=state["step"], loss=f"{np.mean(losses[-50:]):.3f}")
            if now - last_ckpt > 300:
                state["history"].append({"step": state["step"], "minutes": round(state["seconds"] / 60, 2),
                                         "loss": float(np.mean(losses[-100:]))})
                save()
                last_ckpt = now
    except KeyboardInterrupt:
        save()
        bar.close()
        raise UserError(f"interrupted; checkpoint saved in {ckpt}, rerun the same command to resume") from None
    bar.close()
    save()
    if rank != 0:  # validation, export and the bundle are the first process's
        dd.finish()
        return None
    dd.finish()
    model.to("cpu")  # validated and exported on the CPU
    if averaged:
        model.load_state_dict({**model.state_dict(), **{k: v.cpu() for k, v in averaged.items()}})
        log(f"validated and exported: the weights' moving average (decay {ema})")
    model.eval()
    model.to(memory_format=torch.contiguous_format)

    # validation on held-out synthetic images, through the run-time decoder
    dets, gts = [], []
    with torch.no_grad():
        for i in range(0, len(va), 32):
            j = va[i:i + 32]
            maps = model(torch.from_numpy(normalise(images[j], spec))).numpy()
            for k, m in zip(j, maps):
                dets.append(decode(m, spec))
                gts.append([(spec.classes[int(c)], b) for c, *b in boxes[k]])
    ap = detection_ap(dets, gts, spec.classes)
    log(f"synthetic validation: AP {fmt_num(ap['ap'])}, AP50 {fmt_num(ap['ap50'])}, recall50 {fmt_num(ap['recall50'])}")

    path = root / spec.file
    staged = work / spec.file  # moved into the bundle only once the manifest is verified below
    diff = export_detector(model, spec, staged, normalise(images[va[:4]], spec))
    log(f"{spec.file}: max |onnx - torch| = {diff:.2e}")
    if diff > 1e-4:
        raise UserError(f"exported detector differs from torch by {diff:.2e} (> 1e-4)")
    d = spec.to_dict()
    d["training"] = {"data": str(data_dir), "images": len(tr), "validation": len(va), "parameters": n_params,
                     "width": width, "steps": state["step"], **recipe,
                     **({"max_steps": max_steps} if max_steps is not None else {}),
                     **({"cutouts_dir": str(cutouts)} if cutouts else {}),
                     "minutes": round(state["seconds"] / 60, 1), "precision": precision, "device": device,
                     "processes": n_proc,
                     "onnx_max_abs_diff": diff,
                     "validation_synthetic": ap, "command": command or "app.py " + " ".join(sys.argv[1:]),
                     "loss_history": state["history"][-20:],
                     **({"init_from": state["init_from"]} if "init_from" in state else {})}

    def change(manifest, folder):  # the bundle as it was is verified; now replace its detector
        from tracker.runtime.fusion import drop_members
        drop_members(manifest, folder)  # a fused detector's other networks go with it
        shutil.move(staged, folder / spec.file)
        manifest.artefacts["detector"] = spec.file
        manifest.detector = d
    update_manifest(root, change)
    log(f"added {spec.file} to {root} ({path.stat().st_size / 1e6:.1f} MB); {(time.perf_counter() - t0) / 60:.1f} min")
    return d


def export_detector(model, spec: DetectorSpec, path: Path, x_check: np.ndarray) -> float:
    """ONNX (dynamic batch); returns max |onnx - torch| on ``x_check``."""
    import torch
    from tracker.runtime.estimator import make_session
    model.eval()
    torch.onnx.export(model, (torch.from_numpy(x_check[:1]),), str(path), input_names=["image"],
                      output_names=["maps"], dynamic_axes={"image": {0: "batch"}, "maps": {0: "batch"}},
                      opset_version=17, dynamo=False)
    got = make_session(path).run(None, {"image": x_check})[0]
    with torch.no_grad():
        ref = model(torch.from_numpy(x_check)).numpy()
    return float(np.abs(got - ref).max())
