"""Pose estimation from boxes: crop -> batched ONNX encoder -> regressors -> poses.

The one code path of evaluation and the live loop. Needs onnxruntime and numpy; never torch
or scikit-learn.
"""
from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass

import numpy as np

from tracker.core.bundle import Bundle, open_bundle
from tracker.core.errors import UserError
from tracker.core.geometry import crop_and_resize, square_crop
from tracker.runtime.confidence import box_agreement, code_similarity, confidence
from tracker.runtime.heads import load_bundle_codebook, load_bundle_head


@dataclass
class Detection:
    obj_id: int
    box: np.ndarray  # (x, y, w, h) in the frame's pixels
    score: float = 1.0
    exact: bool = False  # a ground-truth box, not a detector's (the head weighs its distance cues by it)
    group: int | None = None  # candidates of one object share a group: the most confident pose is kept


@dataclass
class PoseEstimate:
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    score: float  # the pose's confidence (:mod:`tracker.runtime.confidence`), BOP's score column
    box: np.ndarray
    detector_score: float = 1.0  # the box's own score (1 for ground truth)


def most_confident(pairs: list[tuple[Detection, PoseEstimate]]) -> list[PoseEstimate]:
    """The poses of (detection, pose) pairs, one per candidate group: its most confident pose
    (ties: the first, the detector's better box), at the place of the group's first pose;
    detections without a group keep their pose."""
    out: list[PoseEstimate] = []
    where: dict[int, int] = {}
    for d, p in pairs:
        if d.group is None:
            out.append(p)
        elif d.group not in where:
            where[d.group] = len(out)
            out.append(p)
        elif p.score > out[where[d.group]].score:
            out[where[d.group]] = p
    return out


def trees_weights(manifest) -> dict[str, float]:
    """The distance-from-rotation trees' share of the log distance for exact (ground-truth)
    boxes and for the detector's (``app.py lab tune-heads`` chooses the latter; default
    :data:`tracker.runtime.heads.TREES_WEIGHT` for both)."""
    from tracker.runtime.heads import TREES_WEIGHT
    tw = manifest.heads.get("trees_weight", {})
    out = {k: tw.get(k, TREES_WEIGHT) for k in ("exact", "detector")}
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 1 for v in out.values()):
        raise UserError(f"manifest: heads.trees_weight must hold numbers in [0, 1], not {tw}; rebuild the bundle")
    return {k: float(v) for k, v in out.items()}


def make_session(path, threads: int = 1):
    """onnxruntime session tuned for a small CPU: fixed threads, no spinning (spinning
    threads starve the regressors and the renderer on 2 cores)."""
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:
        raise UserError(f"{path}: cannot load the ONNX model ({str(e).splitlines()[0][:120]})") from None


class PoseEstimator:
    """``threads``: onnxruntime intra-op threads. ``single_thread_math``: cap numpy's BLAS
    and the OpenMP pools at one thread while the regressors run (only then: a process-wide cap
    would leak into everything else the process runs, torch training included); their pools
    cost more than they give on a handful of crops (measured: the regressors for 8 objects
    took 30 ms with the default pools, 4.6 ms with one thread, while a renderer shared the
    2 cores)."""

    def __init__(self, bundle: Bundle | str | os.PathLike, threads: int = 1, single_thread_math: bool = True):
        self.bundle = bundle if isinstance(bundle, Bundle) else open_bundle(bundle)
        m = self.bundle.manifest
        self.size = m.input_size
        self.method = m.method
        self.obj_ids = m.obj_ids
        self.session = make_session(self.bundle.path("encoder"), threads)
        self.head = load_bundle_head(self.bundle)
        self.trees_weight = trees_weights(m)
        self.conditional = len(self.session.get_inputs()) > 1
        self._pools = None
        if single_thread_math:  # after the libraries are loaded: threadpoolctl sees only those
            from threadpoolctl import ThreadpoolController
            self._pools = ThreadpoolController()
        shape = self.session.get_inputs()[0].shape
        self._codes = None  # {obj_id: L2-normalised codebook codes}, loaded on first use
        self._points: dict[int, np.ndarray] = {}  # model points for the box agreement, loaded on first use
        if shape[1:] != [3, self.size, self.size]:
            raise UserError(f"encoder input is {shape[1:]}, the manifest says 3x{self.size}x{self.size}")
        n = self.session.get_outputs()[0].shape[-1]
        if isinstance(n, int) and n != m.latent_size:
            raise UserError(f"{self.bundle.root}: the encoder gives {n} latent values, the manifest says "
                            f"{m.latent_size}; rebuild the bundle")

    def crops(self, image_rgb: np.ndarray, boxes) -> np.ndarray:
        """(N, 3, S, S) float32 in [0, 1], RGB, as the encoder takes them."""
        out = np.empty((len(boxes), self.size, self.size, 3), np.uint8)
        for i, b in enumerate(boxes):
            out[i] = crop_and_resize(image_rgb, square_crop(b, self.size))
        return out.transpose(0, 3, 1, 2).astype(np.float32) / 255.0

    def encode(self, x: np.ndarray, obj_ids) -> np.ndarray:
        feeds = {self.session.get_inputs()[0].name: x}
        if self.conditional:
            oh = np.eye(len(self.obj_ids), dtype=np.float32)[self.head.index(obj_ids)]
            feeds[self.session.get_inputs()[1].name] = oh
        return self.session.run(None, feeds)[0]

    def encode_crops(self, crops_rgb: np.ndarray, obj_ids, batch: int = 256) -> np.ndarray:
        """Latent codes of (N, S, S, 3) uint8 RGB crops, in batches."""
        if len(crops_rgb) == 0:
            return np.zeros((0, self.session.get_outputs()[0].shape[1]), np.float32)
        return np.concatenate([self.encode(crops_rgb[i:i + batch].transpose(0, 3, 1, 2).astype(np.float32) / 255.0,
                                           obj_ids[i:i + batch]) for i in range(0, len(crops_rgb), batch)])

    def estimate(self, image_rgb: np.ndarray, K: np.ndarray, detections: list[Detection],
                 mode: str = "regression", timings: dict | None = None) -> list[PoseEstimate]:
        """Poses for ``detections``; ``timings`` (if given) gets 'encode' (crops + encoder)
        and 'regress' in milliseconds."""
        dets = [d for d in detections if d.box[2] > 1 and d.box[3] > 1]
        if not dets:
            return []
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
            raise UserError(f"expected an RGB image (H, W, 3), got shape {image_rgb.shape}")
        boxes = np.array([d.box for d in dets], dtype=np.float64)
        ids = [d.obj_id for d in dets]
        self.head.index(ids)  # unknown objects fail here, before any work
        t0 = time.perf_counter()
        mu = self.encode(self.crops(image_rgb, boxes), ids)
        t1 = time.perf_counter()
        if mode == "aae" and self.head.codebook is None:
            self.head.codebook = load_bundle_codebook(self.bundle)
        w = np.array([self.trees_weight["exact" if d.exact else "detector"] for d in dets])
        with self._pools.limit(limits=1) if self._pools is not None else contextlib.nullcontext():
            R, t = self.head.predict(mu, ids, boxes, K, mode=mode, trees_weight=w)
            pairs = []
            sim = self.code_similarity(mu, ids)
            for d, r, tt, s in zip(dets, R, t, sim):
                if not (np.all(np.isfinite(r)) and np.all(np.isfinite(tt))):
                    continue  # NaN from a degenerate crop: no estimate rather than garbage
                agree = box_agreement(self.points(d.obj_id), K, r, tt, d.box)
                pairs.append((d, PoseEstimate(d.obj_id, r, tt, confidence(d.score, s, agree), d.box, float(d.score))))
            out = most_confident(pairs)
        if timings is not None:
            timings["encode"] = 1000 * (t1 - t0)
            timings["regress"] = 1000 * (time.perf_counter() - t1)
        return out

    def code_similarity(self, mu: np.ndarray, ids) -> np.ndarray:
        """Each code's cosine similarity to the nearest codebook view of its object (1 where
        the bundle has no codebook)."""
        if self._codes is None:
            has = "codebook" in self.bundle.manifest.artefacts
            self._codes = {o: c[0] for o, c in load_bundle_codebook(self.bundle).codes_.items()} if has else {}
        out = np.ones(len(mu))
        for k, o in enumerate(ids):
            if o in self._codes:
                out[k] = code_similarity(mu[k:k + 1], self._codes[o])[0]
        return out

    def points(self, obj_id: int) -> np.ndarray:
        """About 500 of the object's mesh vertices (its overlay mesh where the bundle has one)."""
        if obj_id not in self._points:
            from tracker.core.meshes import load_mesh
            obj = next(o for o in self.bundle.objects if o.id == obj_id)
            v = np.asarray(load_mesh(self.bundle.overlay_mesh_path(obj), obj_id).mesh.vertices)
            self._points[obj_id] = v[:: max(1, len(v) // 500)]
        return self._points[obj_id]
