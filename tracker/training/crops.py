"""Crop datasets: object crops from BOP scenes, with their clean targets and pose labels.

The same function cuts the crops of a training split, of an evaluation scene and of the
live loop (:func:`tracker.core.geometry.square_crop` + :func:`tracker.core.geometry.crop_and_resize`);
this module adds the bookkeeping around it for training: which instances, which boxes
(visible boxes, jittered like a detector's), and the reconstruction target cut from the
stored clean render with the very same window.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from tracker.core.bop import load_scene
from tracker.core.errors import UserError
from tracker.core.files import write_whole
from tracker.core.geometry import SquareCrop, crop_and_resize, project, ray_rotation, square_crop
from tracker.core.paths import work_dir

MIN_VISIB = 0.1  # BOP: instances less visible than this are not used


@dataclass
class CropSet:
    x: np.ndarray        # (N, S, S, 3) uint8 RGB input crops
    y: np.ndarray        # (N, S, S, 3) uint8 RGB clean targets (same window)
    obj_id: np.ndarray   # (N,)
    R: np.ndarray        # (N, 3, 3)
    t: np.ndarray        # (N, 3) mm
    box: np.ndarray      # (N, 4) the box the crop was cut from (x, y, w, h)
    K: np.ndarray        # (N, 3, 3)
    visib: np.ndarray    # (N,)

    def __len__(self):
        return len(self.obj_id)

    def centres(self) -> np.ndarray:
        """(N, 2) projected object origins in pixels."""
        return np.stack([project(np.zeros((1, 3)), k, None, t)[0] for k, t in zip(self.K, self.t)])

    def R_ray(self, centres: np.ndarray | None = None) -> np.ndarray:
        """(N, 3, 3) the rotations relative to the viewing ray through the object's centre:
        what the crop shows (:func:`tracker.core.geometry.ray_rotation`). ``centres``: the
        caller's :meth:`centres`, if it has them."""
        c = self.centres() if centres is None else centres
        return np.swapaxes(ray_rotation(c, self.K), 1, 2) @ self.R

    def labels(self) -> "CropSet":
        """The same crops without their pixels (``x``, ``y`` of width 0: no memory), for what
        needs only poses, boxes and intrinsics (the heads learn from latent codes)."""
        none = np.empty((len(self), 0, 0, 3), np.uint8)
        return CropSet(none, none, self.obj_id, self.R, self.t, self.box, self.K, self.visib)

    def subset(self, idx) -> "CropSet":
        return CropSet(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))

    def save(self, path) -> Path:
        return write_whole(path, lambda tmp: np.savez(tmp, **{f: getattr(self, f) for f in self.__dataclass_fields__}))

    @classmethod
    def concat(cls, *sets: "CropSet") -> "CropSet":
        return cls(*(np.concatenate([getattr(c, f) for c in sets]) for f in cls.__dataclass_fields__))

    @classmethod
    def load(cls, path) -> "CropSet":
        with np.load(path) as z:
            return cls(**{f: z[f] for f in cls.__dataclass_fields__})


def train_val_split(n: int, seed: int = 0, parts: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """(train, validation) indices of ``n`` samples, one of ``parts`` for validation: the one
    split that training (autoencoder, detector) and the ablations use."""
    perm = np.random.default_rng(seed).permutation(n)
    n_va = max(1, n // parts)
    return np.sort(perm[n_va:]), np.sort(perm[:n_va])


# Detector-like box noise for training crops: centre shift and log-size change, standard
# deviations relative to the box's size.
JITTER_SHIFT = 0.06
JITTER_SCALE = 0.08


def jitter_box(box, rng: np.random.Generator, shift: float = JITTER_SHIFT, scale: float = JITTER_SCALE) -> np.ndarray:
    """A detector-like box: centre moved and size changed by a few percent."""
    x, y, w, h = (float(v) for v in box)
    cx = x + w / 2 + rng.normal(0, shift) * w
    cy = y + h / 2 + rng.normal(0, shift) * h
    w2 = w * np.exp(rng.normal(0, scale))
    h2 = h * np.exp(rng.normal(0, scale))
    return np.array([cx - w2 / 2, cy - h2 / 2, w2, h2])


def split_scene_dirs(split_dir) -> list[Path]:
    d = Path(split_dir)
    scenes = sorted(p for p in d.iterdir() if p.is_dir() and p.name.isdigit() and (p / "scene_gt.json").is_file())
    if not scenes:
        raise UserError(f"{d}: no BOP scene folders (NNNNNN/ with scene_gt.json); make one with 'app.py synth'")
    return scenes


def build_training_crops(split_dir, size: int, seed: int = 0, jitter: bool = True,
                         max_images: int | None = None, progress: bool = True,
                         jitter_scale: float = JITTER_SCALE) -> CropSet:
    """Crops of every instance with visib >= 0.1 of a ``synth`` split; with ``jitter``, on
    boxes jittered by :func:`jitter_box` (log-size noise ``jitter_scale``)."""
    rng = np.random.default_rng(seed)
    cols = {k: [] for k in CropSet.__dataclass_fields__}
    n_img = 0
    scenes = split_scene_dirs(split_dir)
    total = sum(len(json.loads((s / "scene_camera.json").read_text())) for s in scenes)
    bar = tqdm(total=min(total, max_images or total), unit="img", desc="crops", disable=not progress)
    for sdir in scenes:
        scene = load_scene(sdir, require_gt=True)
        wpath = sdir / "clean_crops.json"
        if not wpath.is_file():
            raise UserError(f"{sdir}: no clean_crops.json (not a 'synth' split?)")
        windows = {int(k): v for k, v in json.loads(wpath.read_text()).items()}
        for im_id in scene.im_ids:
            if max_images and n_img >= max_images:
                break
            img = scene.read_rgb(im_id)
            K = scene.K(im_id)
            for k, g in enumerate(scene.gt[im_id]):
                vf = g.info.get("visib_fract", 0.0)
                if vf < MIN_VISIB or g.info["bbox_visib"][2] <= 1 or g.info["bbox_visib"][3] <= 1:
                    continue
                box = np.asarray(g.info["bbox_visib"], float)
                if jitter:
                    box = jitter_box(box, rng, scale=jitter_scale)
                crop = square_crop(box, size)
                clean = cv2.imread(str(sdir / "clean" / f"{im_id:06d}_{k:06d}.png"))
                if clean is None:
                    raise UserError(f"{sdir}/clean/{im_id:06d}_{k:06d}.png missing or unreadable")
                clean = cv2.cvtColor(clean, cv2.COLOR_BGR2RGB)
                x0, y0, side = windows[im_id][k]
                cols["x"].append(crop_and_resize(img, crop))
                cols["y"].append(crop_and_resize(clean, crop.within(SquareCrop(x0, y0, side, clean.shape[0]))))
                cols["obj_id"].append(g.obj_id)
                cols["R"].append(g.R)
                cols["t"].append(g.t)
                cols["box"].append(box)
                cols["K"].append(K)
                cols["visib"].append(vf)
            n_img += 1
            bar.update(1)
    bar.close()
    if not cols["x"]:
        raise UserError(f"{split_dir}: no instance with visible fraction >= {MIN_VISIB}")
    # each column stacked, then its list dropped: the crops are held twice for one column at most
    return CropSet(*(np.stack(cols.pop(f)) for f in CropSet.__dataclass_fields__))


def split_fingerprint(data_dir) -> str:
    """A split as the caches cut from it know it: its folder and what its scenes hold (their
    poses and cameras), so that a split rendered again into the same folder is another split."""
    h = hashlib.sha1(str(Path(data_dir).resolve()).encode())
    for scene in sorted(p for p in Path(data_dir).glob("*") if (p / "scene_gt.json").is_file()):
        for f in ("scene_gt.json", "scene_camera.json"):
            h.update(f"{scene.name}/{f}".encode())
            h.update((scene / f).read_bytes() if (scene / f).is_file() else b"")
    return h.hexdigest()[:10]


def crops_cache_path(work_dir, data_dir, size: int, seed: int, max_images: int | None = None,
                     jitter: bool = True, jitter_scale: float = JITTER_SCALE) -> Path:
    """Where training caches the crops of its split (``<bundle>.work/``), named for the split
    (:func:`split_fingerprint`), so that a bundle retrained on other data, or on a split rendered
    again into the same folder, never loads the old crops; and for a jitter other than the default."""
    key = split_fingerprint(data_dir)
    boxes = "_exact" if not jitter else ("" if jitter_scale == JITTER_SCALE else f"_scale{jitter_scale:g}")
    return Path(work_dir) / f"crops_{size}_seed{seed}_{max_images or 'all'}{boxes}_{key}.npz"


def bundle_training_crops(model_dir, manifest, data_dir, seed: int = 0, jitter: bool = True,
                          log=print, jitter_scale: float = JITTER_SCALE) -> CropSet:
    """The crops of ``data_dir`` at a bundle's input size: training's cached crops when the
    bundle was trained on this very split, else cut now (same seed, same boxes). Objects the
    bundle does not know are an error. ``jitter=False``: on the exact visible boxes."""
    size = manifest.input_size
    cache = crops_cache_path(work_dir(model_dir), data_dir, size, seed, jitter=jitter, jitter_scale=jitter_scale)
    trained_on = manifest.training.get("data")
    kind = "jittered" if jitter else "exact"
    if trained_on is not None and Path(trained_on).resolve() == Path(data_dir).resolve() and cache.is_file():
        cs = CropSet.load(cache)
        log(f"{len(cs)} crops on {kind} boxes (cached by training)")
    else:
        cs = build_training_crops(data_dir, size, seed=seed, jitter=jitter, jitter_scale=jitter_scale)
        log(f"{len(cs)} crops on {kind} boxes (cut now)")
    unknown = sorted(set(np.unique(cs.obj_id).tolist()) - set(manifest.obj_ids))
    if unknown:
        raise UserError(f"{data_dir}: objects {unknown} are not in the bundle {model_dir}")
    return cs
