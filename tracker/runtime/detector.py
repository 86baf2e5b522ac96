"""The 2D object detector at run time: letterbox -> ONNX (CenterNet-style maps) -> peaks ->
boxes -> NMS, with the whole contract (input size, normalisation, stride, thresholds, classes)
read from the bundle's manifest. Training (torch) lives in ``nets/detector.py`` and
``detector_train.py``; both use the pre- and post-processing here, so there is one of each.

Network output: one tensor (1, C + 4, h, w) at ``stride``: C per-class centre heatmaps
(probabilities, sigmoid inside the graph), log(box width / stride), log(box height / stride),
and the sub-cell offset (x, y) of the centre in cells.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from tracker.core.errors import UserError
from tracker.runtime.estimator import Detection
from tracker.core.geometry import clip_box, iou_matrix


# the ranked list that detection AP is measured on (COCO's protocol), not what the live loop uses
CANDIDATE_SCORE = 0.01
CANDIDATE_PER_CLASS = 10
CANDIDATE_MAX = 100


BOX_KINDS = ("visible", "amodal")  # what a detector's boxes cover (DetectorSpec.boxes)


@dataclass
class DetectorSpec:
    classes: list[int]               # object id of each heatmap channel
    input_w: int = 320
    input_h: int = 240
    stride: int = 8
    mean: float = 0.5                # x = (rgb / 255 - mean) / std
    std: float = 0.25
    score_thresh: float = 0.25
    nms_iou: float = 0.5
    max_per_class: int = 1           # LM-O: one instance of each object per image
    max_dets: int = 32
    pad_value: int = 114
    file: str = "detector.onnx"
    boxes: str = "visible"           # what a box covers: the visible part, or the whole object ("amodal")
    # verified candidates (with max_per_class 1): an object whose best peak reaches score_thresh
    # comes with up to `candidates` boxes (class-wise NMS, each scoring >= candidate_floor); the
    # pose pipeline poses them all and keeps the most confident (PoseEstimator.estimate)
    candidates: int = 1
    candidate_floor: float = 0.05

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "DetectorSpec":
        known = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
        return cls(**known)


@dataclass
class Letterbox:
    sx: float  # network-input pixels per frame pixel (x, y: the resized size is rounded)
    sy: float
    pad_x: int
    pad_y: int

    def to_frame(self, boxes: np.ndarray) -> np.ndarray:
        """(N, 4) x, y, w, h in network-input pixels -> frame pixels."""
        b = np.asarray(boxes, np.float64).copy()
        b[:, 0] = (b[:, 0] - self.pad_x) / self.sx
        b[:, 1] = (b[:, 1] - self.pad_y) / self.sy
        b[:, 2] /= self.sx
        b[:, 3] /= self.sy
        return b

    def to_input(self, boxes: np.ndarray) -> np.ndarray:
        b = np.asarray(boxes, np.float64).copy()
        b[:, 0] = b[:, 0] * self.sx + self.pad_x
        b[:, 1] = b[:, 1] * self.sy + self.pad_y
        b[:, 2] *= self.sx
        b[:, 3] *= self.sy
        return b


def letterbox(image: np.ndarray, width: int, height: int, pad_value: int = 114) -> tuple[np.ndarray, Letterbox]:
    """Scale ``image`` uniformly to fit (width, height), centred, padded with ``pad_value``;
    frames of any size or aspect map to the network input and back."""
    h, w = image.shape[:2]
    s = min(width / w, height / h)
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    px, py = (width - nw) // 2, (height - nh) // 2
    out = np.full((height, width, 3), pad_value, np.uint8)
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
    out[py:py + nh, px:px + nw] = cv2.resize(image, (nw, nh), interpolation=interp) if (nw, nh) != (w, h) else image
    return out, Letterbox(nw / w, nh / h, px, py)


def normalise(images_u8: np.ndarray, spec: DetectorSpec) -> np.ndarray:
    """(N, H, W, 3) uint8 RGB -> (N, 3, H, W) float32 network input."""
    x = images_u8.astype(np.float32).transpose(0, 3, 1, 2) / 255.0
    return (x - spec.mean) / spec.std


def peaks(heat: np.ndarray, k: int, thresh: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Local maxima (3x3) of (C, h, w) heatmaps above ``thresh``, best ``k`` first:
    (class index, y, x, score)."""
    C = heat.shape[0]
    dil = np.stack([cv2.dilate(heat[c], np.ones((3, 3), np.uint8)) for c in range(C)])
    keep = (heat >= dil) & (heat >= thresh)
    c, y, x = np.nonzero(keep)
    s = heat[c, y, x]
    order = np.argsort(-s, kind="stable")[:k]
    return c[order], y[order], x[order], s[order]


def decode(maps: np.ndarray, spec: DetectorSpec, lb: Letterbox | None = None,
           frame_size: tuple[int, int] | None = None) -> list[Detection]:
    """(C + 4, h, w) network output -> detections in frame pixels (x, y, w, h), best first:
    peaks, box sizes and offsets, class-wise NMS, at most ``max_per_class`` per object."""
    C = len(spec.classes)
    if maps.ndim != 3 or maps.shape[0] != C + 4:
        raise UserError(f"detector output has shape {maps.shape}; expected ({C + 4}, h, w)")
    verify = spec.max_per_class == 1 and spec.candidates > 1
    floor = min(spec.score_thresh, spec.candidate_floor) if verify else spec.score_thresh
    ci, yi, xi, sc = peaks(maps[:C], 4 * spec.max_dets * (spec.candidates if verify else 1), floor)
    if len(sc) == 0:
        return []
    lw, lh, ox, oy = (maps[C + j, yi, xi] for j in range(4))
    cx = (xi + ox) * spec.stride
    cy = (yi + oy) * spec.stride
    bw = np.exp(np.clip(lw, -8, 8)) * spec.stride
    bh = np.exp(np.clip(lh, -8, 8)) * spec.stride
    boxes = np.stack([cx - bw / 2, cy - bh / 2, bw, bh], 1)
    if lb is not None:
        boxes = lb.to_frame(boxes)
    if frame_size is not None:
        boxes = clip_box(boxes, *frame_size)
    ok = (boxes[:, 2] > 1) & (boxes[:, 3] > 1)  # boxes clipped to nothing never take a slot
    boxes, ci, sc = boxes[ok], ci[ok], sc[ok]
    out: list[Detection] = []
    if verify:
        return _candidates(boxes, ci, sc, spec)
    for c in np.unique(ci):
        m = np.nonzero(ci == c)[0]
        # one per object: the best peak, which NMS would keep first (ties: the first, as NMS)
        keep = [int(np.argmax(sc[m]))] if spec.max_per_class == 1 else nms(boxes[m], sc[m], spec.nms_iou)[:spec.max_per_class]
        out += [Detection(int(spec.classes[c]), boxes[m[j]], float(sc[m[j]])) for j in keep]
    out.sort(key=lambda d: -d.score)
    return out[:spec.max_dets]


def _candidates(boxes: np.ndarray, ci: np.ndarray, sc: np.ndarray, spec: DetectorSpec) -> list[Detection]:
    """Each object whose best peak reaches ``score_thresh`` (at most ``max_dets`` objects, best
    first): its best box and the next ones that NMS keeps, up to ``candidates``, all in one
    ``group`` (the object's id) that the pose pipeline reduces to its most confident pose."""
    groups = []
    for c in np.unique(ci):
        m = np.nonzero(ci == c)[0]
        if sc[m].max() < spec.score_thresh:
            continue
        keep = nms(boxes[m], sc[m], spec.nms_iou)[:spec.candidates]
        obj = int(spec.classes[c])
        groups.append([Detection(obj, boxes[m[j]], float(sc[m[j]]), group=obj) for j in keep])
    groups.sort(key=lambda g: -g[0].score)
    return [d for g in groups[:spec.max_dets] for d in g]


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float) -> list[int]:
    """Greedy non-maximum suppression; indices kept, best score first."""
    order = list(np.argsort(-np.asarray(scores), kind="stable"))
    keep = []
    ious = iou_matrix(boxes, boxes)
    while order:
        i = order.pop(0)
        keep.append(int(i))
        order = [j for j in order if ious[i, j] <= iou]
    return keep


class _Network:
    """One detector graph with its spec: a frame in, its output maps and letterbox out."""

    def __init__(self, bundle, spec: DetectorSpec, path, threads: int):
        from tracker.runtime.estimator import make_session
        self.spec = spec
        self.session = make_session(path, threads)
        out = self.session.get_outputs()[0].shape
        if len(out) != 4 or out[1] != len(spec.classes) + 4:
            raise UserError(f"{bundle.root}: {Path(path).name} has {out[1] if len(out) > 1 else '?'} output channels, "
                            f"its manifest lists {len(spec.classes)} classes (+4 box channels)")
        self.input_name = self.session.get_inputs()[0].name

    def maps(self, image_rgb: np.ndarray) -> tuple[np.ndarray, Letterbox]:
        img, lb = letterbox(image_rgb, self.spec.input_w, self.spec.input_h, self.spec.pad_value)
        return self.session.run(None, {self.input_name: normalise(img[None], self.spec)})[0][0], lb


class Detector:
    """The bundle's detector: one network, or several whose detections are fused
    (:mod:`tracker.runtime.fusion`, the manifest's ``detector.fusion``). Refuses, at load time, a
    detector whose classes are not objects of the bundle or whose output channels do not match
    its classes."""

    def __init__(self, bundle, threads: int = 1):
        m = bundle.manifest
        if not m.has_detector:
            raise UserError(f"{bundle.root}: this bundle has no detector; train one with 'app.py train-detector'")
        self.spec = DetectorSpec.from_dict(m.detector)
        self.fusion = None
        specs = [(self.spec, bundle.path("detector"))]
        if "fusion" in m.detector:
            from tracker.runtime.fusion import Fusion, member_problem, role_of
            self.fusion = Fusion.from_dict(m.detector["fusion"], f"{bundle.root}/manifest.json")
            for d in self.fusion.members:
                spec = DetectorSpec.from_dict(d)
                if problem := member_problem(self.spec, spec):
                    raise UserError(f"{bundle.root}: the fused network {spec.file}: {problem}")
                role = role_of(spec.file)
                if role is None or m.artefacts.get(role) != spec.file:
                    raise UserError(f"{bundle.root}: the fused network's file {spec.file!r} is not one of the "
                                    f"bundle's fused-network artefacts; rebuild it with 'app.py lab fuse-detectors'")
                specs.append((spec, bundle.path(role)))  # hashed in the manifest, or refused
        known = set(m.obj_ids)
        bad = [c for c in self.spec.classes if c not in known]
        if bad:
            raise UserError(f"{bundle.root}: the detector's classes {bad} are not objects of this bundle "
                            f"({sorted(known)}); retrain the detector for these objects")
        # several networks run side by side, the threads shared out (onnxruntime lets go of the GIL)
        each = max(1, threads // len(specs))
        self.networks = [_Network(bundle, spec, path, each) for spec, path in specs]
        self.session, self.input_name = self.networks[0].session, self.networks[0].input_name
        self._pool = None
        if len(self.networks) > 1 and threads > 1:
            from concurrent.futures import ThreadPoolExecutor
            self._pool = ThreadPoolExecutor(len(self.networks) - 1, thread_name_prefix="detector")

    def __call__(self, image_rgb: np.ndarray) -> list[Detection]:
        """The run-time detections: the manifest's threshold, at most ``max_per_class`` each."""
        return self.detect(image_rgb)[0]

    def detect(self, image_rgb: np.ndarray, candidates: bool = False) -> tuple[list[Detection], list[Detection]]:
        """The run-time detections and (with ``candidates``) the ranked list that COCO's AP
        is defined on: every peak scoring at least ``CANDIDATE_SCORE``, up to
        ``CANDIDATE_PER_CLASS`` per object and ``CANDIDATE_MAX`` per image (pycocotools keeps
        100 per image), from the same network pass. A fused detector's: the clusters."""
        if self.fusion is not None:
            return self._fused(image_rgb, candidates)
        h, w = image_rgb.shape[:2]
        maps, lb = self.networks[0].maps(image_rgb)
        if not np.all(np.isfinite(maps)):
            return [], []  # NaN output: no detections rather than garbage boxes
        dets = decode(maps, self.spec, lb, (w, h))
        if not candidates:
            return dets, []
        return dets, decode(maps, self._wide(self.spec, CANDIDATE_SCORE), lb, (w, h))

    @staticmethod
    def _wide(spec: DetectorSpec, floor: float) -> DetectorSpec:
        """``spec`` decoding every peak from ``floor``, the candidates' counts (not the run time's)."""
        return replace(spec, score_thresh=min(floor, spec.score_thresh), max_per_class=max(CANDIDATE_PER_CLASS,
                       spec.max_per_class), max_dets=max(CANDIDATE_MAX, spec.max_dets), candidates=1)

    def _fused(self, image_rgb: np.ndarray, candidates: bool) -> tuple[list[Detection], list[Detection]]:
        from tracker.runtime.fusion import fuse, per_object
        h, w = image_rgb.shape[:2]
        f = self.fusion
        if self._pool is not None:
            rest = [self._pool.submit(net.maps, image_rgb) for net in self.networks[1:]]
            outs = [self.networks[0].maps(image_rgb)] + [r.result() for r in rest]
        else:
            outs = [net.maps(image_rgb) for net in self.networks]
        if not all(np.all(np.isfinite(maps)) for maps, _ in outs):
            return [], []  # a network gave NaN: no detections rather than garbage boxes

        def clusters(floor: float) -> list[Detection]:
            return fuse([decode(maps, replace(self._wide(net.spec, floor), score_thresh=floor), lb, (w, h))
                         for net, (maps, lb) in zip(self.networks, outs)], f.iou)
        verify = self.spec.candidates > 1  # one instance per object (member_problem)
        best = per_object(clusters(f.floor), self.spec.candidates if verify else 1)
        groups = [g for g in best.values() if g[0].score >= f.score_thresh][:self.spec.max_dets]
        if verify:  # the best cluster and the next ones of its object, posed and the most confident kept
            dets = [replace(d, group=d.obj_id) for g in groups
                    for i, d in enumerate(g) if i == 0 or d.score >= self.spec.candidate_floor]
        else:
            dets = [g[0] for g in groups]
        dets.sort(key=lambda d: -d.score)
        if not candidates:
            return dets, []
        # AP's ranked list as for one network: every network's peaks from CANDIDATE_SCORE, fused
        ranked = [d for g in per_object(clusters(CANDIDATE_SCORE), CANDIDATE_PER_CLASS).values() for d in g]
        ranked.sort(key=lambda d: -d.score)
        return dets, ranked[:CANDIDATE_MAX]


def bundle_with_detector(path):
    """The bundle at ``path``, refused (one line) when it has no detector."""
    from tracker.core.bundle import open_bundle
    b = open_bundle(path)
    if not b.manifest.has_detector:
        raise UserError(f"{path}: this bundle has no detector; train one with 'app.py train-detector'")
    return b


def float_detector(path, use: str):
    """(bundle, its detector's spec, its manifest entry, its ONNX file) of a bundle whose
    detector is a single float network (one that can join others, or be fine-tuned from);
    ``use``: what to do instead, said when it is joined or quantised."""
    b = bundle_with_detector(path)
    d = b.manifest.detector
    if "fusion" in d:
        raise UserError(f"{path}: its detector fuses several networks; {use}")
    if "ensemble" in d or "int8" in d:
        raise UserError(f"{path}: its detector is joined or quantised already; {use}")
    return b, DetectorSpec.from_dict(d), d, b.path("detector")


def run_graph(path, x: np.ndarray) -> np.ndarray:
    """A detector graph's raw outputs for a batch of network inputs, one image at a time."""
    from tracker.runtime.estimator import make_session
    s = make_session(path, threads=2)
    name = s.get_inputs()[0].name
    return np.concatenate([s.run(None, {name: x[i:i + 1]})[0] for i in range(len(x))])
