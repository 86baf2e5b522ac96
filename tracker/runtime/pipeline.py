"""One frame through the tracker: undistort -> boxes -> crops -> encoder -> regressors ->
smoothing -> overlay. :meth:`Pipeline.step` takes a :class:`~tracker.runtime.sources.Frame`
and gives a :class:`FrameResult`; the run loop (:mod:`tracker.runtime.loop`) adds capture,
logging and the run's files around it, and a test can drive it frame by frame."""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from tracker.core.bop import gt_instances_with_boxes
from tracker.core.errors import UserError
from tracker.core.geometry import box_from_points, clip_box, project, scale_intrinsics
from tracker.runtime.confidence import UNCERTAIN_BELOW
from tracker.runtime.estimator import Detection, PoseEstimate, PoseEstimator


@dataclass
class FrameResult:
    index: int                      # the frame's id (im_id of a BOP scene, else the frame counter)
    rgb: np.ndarray                 # the undistorted frame, RGB
    K: np.ndarray                   # its intrinsics
    detections: list[Detection]     # the boxes the poses came from
    poses: list[PoseEstimate]       # smoothed when the pipeline smooths
    overlay: np.ndarray | None      # the annotated frame (None without an overlay)
    box_source: str                 # 'detector', 'pose' (boxes from the previous poses), 'gt' or 'none'
    ms: dict[str, float] = field(default_factory=dict)  # undistort, detect, encode, regress, render


class GtBoxes:
    """Ground-truth boxes as given (``boxes_of``: im_id -> [(box, visible fraction)] in the
    order of the frame's ground truth), the instances at least 10 % visible, of ``known`` objects."""

    def __init__(self, boxes_of: dict, known):
        self.boxes_of, self.known = boxes_of, set(known)

    def boxes(self, frame) -> list[Detection]:
        if frame.index not in self.boxes_of:
            return []
        return [Detection(o, b, exact=True) for o, b, _ in gt_instances_with_boxes(frame.gt, self.boxes_of[frame.index], 0.1)
                if o in self.known]


PROPAGATE = ("off", "join", "all")


class BoxSchedule:
    """Which boxes a frame uses: the detector's, or (when ``every`` > 1) boxes predicted from
    the previous frame's poses, the model points projected at that pose. The detector runs on
    every ``every``-th frame and on any frame after one where an object was lost.

    ``propagate`` (detector frames): the previous frame's pose boxes as candidates, verified by
    the pose pipeline, never trusted. 'join': an object the detector found gets its previous
    pose's box as one more candidate of its group (at the group's best detector score), and the
    most confident pose of the group is kept; 'all': also an object the detector missed, if its
    previous pose was confident (>= ``min_confidence``), with that confidence as the box's
    score, so a pose no frame confirms fades below the bar and stops; 'off': the detector's
    boxes only."""

    def __init__(self, detector, every: int, points: dict[int, np.ndarray], obj_ids=None,
                 propagate: str = "off", min_confidence: float = UNCERTAIN_BELOW):
        if int(every) < 1:
            raise UserError(f"--detect-every must be >= 1, got {every}")
        if propagate not in PROPAGATE:
            raise UserError(f"--propagate {propagate}: choose from {', '.join(PROPAGATE)}")
        self.propagate, self.min_confidence = propagate, float(min_confidence)
        self.detector, self.every, self.points = detector, int(every), points
        self.obj_ids = set(obj_ids) if obj_ids else None
        self.detector_frames = 0
        self.reset()

    def reset(self):
        """Forget the previous frame (a new shot: the next frame runs the detector)."""
        self.since, self.prev, self.lost, self.n_expected = 0, [], True, 0

    def boxes(self, rgb, K) -> tuple[list[Detection], str]:
        """This frame's boxes and where they came from ('detector' or 'pose')."""
        h, w = rgb.shape[:2]
        if self.lost or self.since + 1 >= self.every or not self.prev:
            self.since = 0
            self.detector_frames += 1
            dets = [d for d in self.detector(rgb) if self.obj_ids is None or d.obj_id in self.obj_ids]
            # objects, not candidates: one per group, one per detection without a group
            self.n_expected = len({d.group for d in dets if d.group is not None}) + sum(d.group is None for d in dets)
            if self.propagate != "off" and self.prev:
                dets = self._with_pose_boxes(dets, K, w, h)
            return dets, "detector"
        self.since += 1
        out = []
        for p in self.prev:
            b = self._pose_box(p, K, w, h)
            if b is not None:
                out.append(Detection(p.obj_id, b, p.detector_score))
        return out, "pose"

    def _pose_box(self, p, K, w, h):
        """The box the model points project to at pose ``p``, clipped; None if (nearly) empty."""
        b = clip_box(box_from_points(project(self.points[p.obj_id], K, p.R, p.t)), w, h)
        return b if b[2] > 4 and b[3] > 4 else None

    def _with_pose_boxes(self, dets: list[Detection], K, w, h) -> list[Detection]:
        """``dets`` with the previous poses' boxes added as candidates (``propagate``)."""
        out = list(dets)
        next_group = max((d.group for d in dets if d.group is not None), default=-1) + 1
        for p in self.prev:
            b = self._pose_box(p, K, w, h)
            if b is None:
                continue
            mine = [i for i, d in enumerate(dets) if d.obj_id == p.obj_id]
            groups = {out[i].group for i in mine}
            if mine and len(groups) == 1:  # one object found: the pose box joins its candidates
                g = groups.pop()
                if g is None:
                    g, next_group = next_group, next_group + 1
                    for i in mine:
                        out[i] = replace(out[i], group=g)
                out.append(Detection(p.obj_id, b, max(dets[i].score for i in mine), group=g))
            elif not mine and self.propagate == "all" and p.score >= self.min_confidence:
                out.append(Detection(p.obj_id, b, p.score))
        return out

    def update(self, poses):
        """The poses estimated from this frame's boxes (unsmoothed)."""
        self.lost = len(poses) < self.n_expected
        self.prev = list(poses)


class Pipeline:
    """The tracker on one frame at a time. ``boxes``: a :class:`BoxSchedule` (the bundle's
    detector), a :class:`GtBoxes` or None (no boxes, no poses). ``undistorter``: for frames
    without their own intrinsics (cameras, videos, image folders). ``meshes``: {obj_id: trimesh}
    for the overlay (None: no overlay), rendered at 1/``overlay_downscale`` of the frame size
    and scaled up (on the CPU rasteriser the full-size render of 8 objects cost ~110 ms of a
    ~150 ms frame). Poses whose confidence is below ``min_confidence`` are drawn as uncertain:
    an outline only, dimmed, never as a rendered object."""

    def __init__(self, estimator: PoseEstimator, boxes=None, undistorter=None, meshes: dict | None = None,
                 overlay_downscale: int = 2, smoother=None, obj_ids=None, min_confidence: float = UNCERTAIN_BELOW):
        self.est, self.box_source, self.undistorter = estimator, boxes, undistorter
        self.min_confidence = float(min_confidence)
        self.meshes, self.overlay_downscale, self.smoother = meshes, overlay_downscale, smoother
        self.obj_ids = obj_ids
        self.names = {o.id: o.name for o in estimator.bundle.objects}
        self.diameters = {o.id: o.diameter for o in estimator.bundle.objects}
        self.renderer = None
        self._pts: dict[int, np.ndarray] = {}
        self.n = 0

    def reset(self):
        """A new shot (a replay starts again): no pose carries over the cut."""
        if isinstance(self.box_source, BoxSchedule):
            self.box_source.reset()
        if self.smoother is not None:
            self.smoother.reset()

    def step(self, frame) -> FrameResult:
        ms = {}
        t = time.perf_counter()
        h, w = frame.rgb.shape[:2]
        if frame.K is not None:
            K, rgb = frame.K, frame.rgb
        elif self.undistorter is not None:
            K, rgb = self.undistorter.camera_for(w, h).K, self.undistorter(frame.rgb)
        else:
            raise UserError("this source needs a camera file: pass --calib FILE")
        ms["undistort"] = 1000 * (time.perf_counter() - t)
        t = time.perf_counter()
        if isinstance(self.box_source, BoxSchedule):
            dets, source = self.box_source.boxes(rgb, K)
        elif self.box_source is not None:
            dets, source = self.box_source.boxes(frame), "gt"
        else:
            dets, source = [], "none"
        if self.obj_ids:
            dets = [d for d in dets if d.obj_id in self.obj_ids]
        ms["detect"] = 1000 * (time.perf_counter() - t)
        poses = self.est.estimate(rgb, K, dets, timings=ms) if dets else []
        if isinstance(self.box_source, BoxSchedule):
            self.box_source.update(poses)
        if self.smoother is not None:  # new objects: the schedule keeps the raw poses
            poses = [replace(p, R=r, t=tt) for p in poses for r, tt in [self.smoother(p.obj_id, p.R, p.t, self.n)]]
        ms.setdefault("encode", 0.0)  # crops + encoder
        ms.setdefault("regress", 0.0)
        t = time.perf_counter()
        vis = self._overlay(rgb, K, poses) if self.meshes is not None else None
        ms["render"] = 1000 * (time.perf_counter() - t)
        self.n += 1
        return FrameResult(frame.index, rgb, K, dets, poses, vis, source, ms)

    def _overlay(self, rgb, K, poses):
        from tracker.runtime.overlay import blend, colour, draw_axes, draw_box, draw_uncertain
        sure = [p for p in poses if p.score >= self.min_confidence]
        h, w = rgb.shape[:2]
        rw, rh = max(w // self.overlay_downscale, 1), max(h // self.overlay_downscale, 1)
        if self.renderer is None or (self.renderer.width, self.renderer.height) != (rw, rh):
            from tracker.runtime.render import Renderer
            if self.renderer is not None:
                self.renderer.close()
            self.renderer = Renderer(rw, rh, self.meshes)
        col, depth = self.renderer.render(scale_intrinsics(K, (w, h), (rw, rh)), [(p.obj_id, p.R, p.t) for p in sure])
        if (rw, rh) != (w, h):
            col = cv2.resize(col, (w, h), interpolation=cv2.INTER_LINEAR)
            depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
        vis = blend(rgb, col, depth, 0.6)
        for p in poses:
            name = self.names.get(p.obj_id, str(p.obj_id))
            if p.score >= self.min_confidence:
                draw_box(vis, p.box, colour(p.obj_id), f"{name} {p.score:.2f}")
                draw_axes(vis, K, p.R, p.t, 0.3 * self.diameters[p.obj_id])
            else:
                draw_uncertain(vis, self._points(p.obj_id), K, p.R, p.t, colour(p.obj_id), f"{name}? {p.score:.2f}")
        return vis

    def _points(self, obj_id: int) -> np.ndarray:
        """About 2,000 of the overlay mesh's vertices (the outline of an uncertain pose)."""
        if obj_id not in self._pts:
            v = np.asarray(self.meshes[obj_id].vertices)
            self._pts[obj_id] = v[:: max(1, len(v) // 2000)]
        return self._pts[obj_id]

    def close(self):
        """Release the overlay's renderer (its GL context); the pipeline can still step (a new
        renderer is made when needed)."""
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
