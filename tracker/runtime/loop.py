"""The run loop: a source's frames through :class:`~tracker.runtime.pipeline.Pipeline`, with
the run's files (poses.csv, timings.csv, summary.json, recording.rrd), Ctrl-C handling and a
typed :class:`RunSummary`. ``app.py track`` and ``app.py demo`` call it through
:func:`tracker.evaluation.track.track`, which adds the ground truth's boxes and the accuracy
where a recording has them; the runtime itself knows nothing of evaluation."""
from __future__ import annotations

import contextlib
import copy
import os
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from tracker.core.bop import Estimate, write_json
from tracker.core.camera import Undistorter, read_camera
from tracker.core.errors import UserError
from tracker.core.priors import in_prior
from tracker.runtime.estimator import PoseEstimator
from tracker.runtime.confidence import UNCERTAIN_BELOW
from tracker.runtime.pipeline import BoxSchedule, GtBoxes, Pipeline
from tracker.runtime.signals import Deferred, Stopper
from tracker.runtime.sinks import STAGES, CsvSink, RerunSink
from tracker.runtime.sources import BopSceneSource


@dataclass
class TrackConfig:
    source: str
    model: str
    out: Path
    calib: str | None = None
    rerun: str = "off"
    max_frames: int | None = None
    realtime: bool = False
    overlay: bool = True
    boxes: str = "auto"  # auto: ground truth on BOP scenes with it, else the bundle's detector
    # the overlay is rendered at 1/overlay_downscale of the frame size and scaled up: on the
    # CPU rasteriser the full-size render of 8 objects cost ~110 ms of a ~150 ms frame
    overlay_downscale: int = 2
    # detector on every Nth frame; in between (and while every object is still found) boxes
    # come from the previous frame's poses projected into the frame
    detect_every: int = 1
    detector_threads: int = 2
    # the encoder's onnxruntime threads: the stages run one after another, so both cores help
    # (stop 61: 8 crops 5.2 -> 3.3 ms at 64 px, 12.3 -> 7.1 ms at 96 px; the same codes)
    encoder_threads: int = 2
    smooth: float | None = None  # PoseSmoother alpha (None: off)
    obj_ids: list[int] | None = None  # track only these objects (None: all of the bundle's)
    # replay a recorded source again and again until max_frames (a soak test); frames are then
    # numbered 0, 1, 2, ... in the logs, and no accuracy is computed
    loop: bool = False
    video_out: str | None = None  # the annotated frames as a video (.mp4, .avi, .mkv)
    frames_out: str | None = None  # ... and/or as numbered PNGs in this folder
    min_confidence: float = UNCERTAIN_BELOW  # poses below it are drawn and counted as uncertain
    # the previous frame's pose boxes as verified candidates on detector frames (pipeline.BoxSchedule)
    propagate: str = "off"


@dataclass
class RunSummary:
    """What ``summary.json`` holds (docs/formats.md)."""
    frames: int
    poses: int
    wall_s: float
    fps: float | None
    stages_ms: dict
    dropped_frames: int
    pose_prior: str
    poses_outside_prior: int
    interrupted: bool
    camera_lost: bool
    camera_reconnects: int
    video_truncated: bool
    source: str
    model: str
    boxes: str  # gt | detector | none
    detector_frames: int | None
    detect_every: int
    smoothing_alpha: float | None
    looped: bool
    rss_mb: dict
    recording: str | None
    error: str | None
    objects: dict = field(default_factory=dict)  # per object: frames tracked / uncertain / not found
    video: str | None = None  # the annotated video written (--video-out)
    frames_dir: str | None = None  # the annotated PNGs written (--frames-out)
    accuracy: dict | None = None  # set by tracker.evaluation.track where the source has ground truth
    accuracy_skipped: bool = False
    # not written: what scoring the run needs
    scene_id: int = 0
    im_ids: list = field(default_factory=list)  # the frames done, in order
    scene_root: str | None = None  # the BOP scene the frames came from (None: another source)
    bundle_obj_ids: list = field(default_factory=list)
    # the rerun sink, for a serving viewer to outlive the run (RerunSink.hold); not written
    viewer: object = None

    def to_dict(self) -> dict:
        hidden = ("im_ids", "scene_id", "scene_root", "bundle_obj_ids", "viewer")
        d = copy.deepcopy({f.name: getattr(self, f.name) for f in fields(self) if f.name not in hidden})
        if d["accuracy"] is None:
            d.pop("accuracy")
        if not d["accuracy_skipped"]:
            d.pop("accuracy_skipped")
        return d

    def save(self, out) -> None:
        """``summary.json``, replaced whole (never half-written)."""
        write_json(Path(out) / "summary.json", self.to_dict())


def run_track(cfg: TrackConfig, log=print, gt_boxes=None) -> RunSummary:
    """Run the tracker over ``cfg.source``. ``gt_boxes(scene, im_ids, bundle)``: the visible
    ground-truth boxes of a BOP scene ({im_id: [(box, visible fraction)]}), for ``--boxes gt``
    and ``auto`` on scenes with ground truth (:func:`tracker.evaluation.ground_truth.scene_gt_boxes`);
    None: ground truth is not used.

    Every check the arguments allow comes first, before anything is opened; then the source,
    the run's files, the rerun sink and the renderer are opened in one ExitStack, so every way
    out (the end, Ctrl-C, an error) closes them all. A run stopped by Ctrl-C or an error once its
    frames have started still writes its summary.json (``interrupted`` / ``error``); the error
    is raised again after it."""
    from tracker.core.meshes import load_mesh
    est = PoseEstimator(cfg.model, threads=cfg.encoder_threads)
    cam = _check(cfg, est, gt_boxes)
    names = {o.id: o.name for o in est.bundle.objects}
    meshes = {o.id: load_mesh(est.bundle.overlay_mesh_path(o), o.id).mesh for o in est.bundle.objects}
    smoother = None
    if cfg.smooth is not None:
        from tracker.runtime.smoothing import PoseSmoother
        smoother = PoseSmoother(cfg.smooth)
    out = Path(cfg.out)
    with contextlib.ExitStack() as stack:
        feed = stack.enter_context(_Feed(cfg))
        boxes = _boxes(cfg, est, feed.source, meshes, gt_boxes, log)
        out.mkdir(parents=True, exist_ok=True)  # only now: a run that cannot start leaves no empty folder
        outputs = _Outputs(cfg, out, stack, meshes, names, getattr(feed.source, "fps", None))
        pipeline = stack.enter_context(
            Pipeline(est, boxes, Undistorter(cam) if cam else None, meshes if cfg.overlay else None,
                     cfg.overlay_downscale, smoother, cfg.obj_ids, cfg.min_confidence))
        from tracker.runtime.status import TrackStatus
        status = TrackStatus(names, cfg.obj_ids or est.obj_ids, cfg.min_confidence)
        stats = _Stats(est.bundle.manifest.pose_prior, log)
        scene_id = _scene_id(cfg.source) if isinstance(feed.source, BopSceneSource) else 0
        interrupted, failure = _frames(feed, pipeline, outputs, stats, status, scene_id)
        with Deferred(log, "closing the run's files") as closing:
            _close(stack, failure)
    summary = _summary(cfg, stats, feed.source, boxes, outputs, status, est, scene_id, failure,
                       interrupted=interrupted or closing.hit)
    summary.save(out)  # at once: an interrupted or failed run keeps it
    if failure is not None:
        raise failure
    return summary


def _check(cfg: TrackConfig, est: PoseEstimator, gt_boxes):
    """Every check the run's arguments allow, before anything is opened; returns the camera
    (--calib) or None."""
    from tracker.runtime.sinks import check_rerun_mode
    from tracker.runtime.sources import source_kind
    from tracker.runtime.video import check_frames_dir, check_video_path
    unknown = [o for o in cfg.obj_ids or [] if o not in est.obj_ids]
    if unknown:
        raise UserError(f"--obj-ids {','.join(map(str, unknown))}: not objects of {cfg.model} "
                        f"(it knows {','.join(map(str, est.obj_ids))})")
    kind = source_kind(cfg.source)
    if cfg.loop and kind == "camera":
        raise UserError("--loop replays recordings; a camera cannot be looped")
    if cfg.boxes == "gt" and kind != "bop":
        raise UserError("--boxes gt needs a BOP scene with scene_gt.json")
    if cfg.boxes == "gt" and gt_boxes is None:
        raise UserError("--boxes gt: this run was given no source of ground-truth boxes (run it through "
                        "tracker.evaluation.track.track, as 'app.py track' does)")
    if cfg.boxes == "detector" and not est.bundle.manifest.has_detector:
        raise UserError(f"--boxes detector: {cfg.model} has no detector; train one with 'app.py train-detector' "
                        f"or use a BOP scene with --boxes gt")
    if int(cfg.detect_every) < 1:
        raise UserError(f"--detect-every must be >= 1, got {cfg.detect_every}")
    cam = read_camera(cfg.calib) if cfg.calib else None
    if cam is None and kind != "bop":  # only BOP scenes carry their intrinsics
        raise UserError("this source needs a camera file: pass --calib FILE")
    if cfg.video_out:
        check_video_path(cfg.video_out)
    if cfg.frames_out:
        check_frames_dir(cfg.frames_out)
    if Path(cfg.out).exists() and not Path(cfg.out).is_dir():
        raise UserError(f"--out {cfg.out} is a file; give a folder")
    check_rerun_mode(cfg.rerun)
    return cam


def _boxes(cfg: TrackConfig, est: PoseEstimator, src, meshes: dict, gt_boxes, log):
    """Where the frames' boxes come from: the ground truth (a BOP scene that has it, --boxes
    auto or gt), the bundle's detector, or nowhere (None)."""
    has_gt = isinstance(src, BopSceneSource) and bool(src.scene.gt)
    if cfg.boxes == "gt" and not has_gt:
        raise UserError("--boxes gt needs a BOP scene with scene_gt.json")
    if cfg.boxes in ("auto", "gt") and has_gt and gt_boxes is not None:
        return GtBoxes(gt_boxes(src.scene, src.ids, est.bundle), est.obj_ids)
    if not est.bundle.manifest.has_detector:
        log("warning: this bundle has no detector and the source has no ground truth: "
            "no boxes, so no poses; frames are still logged")
        return None
    from tracker.runtime.detector import Detector
    pts = {o: np.asarray(m.vertices)[:: max(1, len(m.vertices) // 500)] for o, m in meshes.items()}
    return BoxSchedule(Detector(est.bundle, threads=cfg.detector_threads), cfg.detect_every, pts, cfg.obj_ids,
                       propagate=cfg.propagate, min_confidence=cfg.min_confidence)


def _close(stack: contextlib.ExitStack, failure: Exception | None) -> None:
    """Close what the run opened; a failure is passed on (a serving rerun sink then stops
    instead of waiting to be held)."""
    if failure is None:
        stack.close()
    else:
        stack.__exit__(type(failure), failure, failure.__traceback__)


class _Feed:
    """The source's frames, with ``--loop`` replayed from the start again and again until
    ``max_frames`` (frames then numbered 0, 1, 2, ... in the logs). Owns the open source: a
    context manager that closes it."""

    def __init__(self, cfg: TrackConfig):
        from tracker.runtime.sources import open_source
        self.cfg = cfg
        self.source = open_source(cfg.source, max_frames=None if cfg.loop else cfg.max_frames, realtime=cfg.realtime)
        self._it = iter(self.source)
        self.n = 0  # frames handed out

    def next(self):
        """(index in the logs, frame, whether the replay started again), or None at the end."""
        cfg = self.cfg
        if cfg.loop and cfg.max_frames is not None and self.n >= cfg.max_frames:
            return None
        frame = next(self._it, None)
        restarted = False
        if frame is None:
            if not (cfg.loop and self.n):
                return None
            from tracker.runtime.sources import open_source
            self.source.close()
            self.source = open_source(cfg.source, realtime=cfg.realtime)
            self._it = iter(self.source)
            frame, restarted = next(self._it, None), True
            if frame is None:
                return None
        index = self.n if cfg.loop else frame.index
        self.n += 1
        return index, frame, restarted

    def close(self):
        self.source.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _Outputs:
    """Where each frame goes: poses.csv and timings.csv, the annotated video / PNGs and rerun
    (opened at the first frame, when the frame's size and intrinsics are known), all entered
    into the run's ``stack``."""

    def __init__(self, cfg: TrackConfig, out: Path, stack: contextlib.ExitStack, meshes: dict, names: dict, fps):
        from tracker.runtime.video import FrameWriter
        self.cfg, self.out, self.stack, self.meshes, self.names = cfg, out, stack, meshes, names
        self.csv = stack.enter_context(CsvSink(out))
        self.writer = stack.enter_context(FrameWriter(cfg.video_out, cfg.frames_out, fps))
        self.rerun = None

    def write(self, index: int, frame, r, ms: dict, status_text: str, t0: float, fps, scene_id: int) -> None:
        """The frame's results (``r``, a FrameResult) and its stage times (``ms``, completed with
        log and total here; ``t0``: when the frame was asked for)."""
        t = time.perf_counter()
        if self.rerun is None:
            h, w = r.rgb.shape[:2]
            self.rerun = self.stack.enter_context(
                RerunSink(self.cfg.rerun, self.out, self.meshes, self.names, r.K, (w, h), overlay=r.overlay is not None))
        self.rerun.log_frame(index, r.rgb, r.overlay, r.detections, r.poses, status_text)
        if self.writer.active:
            self.writer.write(index, r.overlay if r.overlay is not None else r.rgb)
        dt_frame = time.perf_counter() - t0
        ests = [Estimate(scene_id, index, p.obj_id, p.score, p.R, p.t, dt_frame) for p in r.poses]
        ms["log"] = 1000 * (time.perf_counter() - t)
        ms["total"] = 1000 * (time.perf_counter() - t0)
        self.csv.write(ests, index, frame.t_capture, ms)
        self.rerun.log_timings(ms, fps)


class _Stats:
    """The run's running figures: frames and poses done, per-stage times, fps, memory, poses
    outside the bundle's pose prior (warned about once)."""

    def __init__(self, prior: str, log):
        self.prior, self.log = prior, log
        self.t_start = self.last = time.perf_counter()
        self.stage_ms = {s: [] for s in STAGES}
        self.n = self.n_poses = self.out_of_prior = 0
        self.fps = None
        self.rss_early = None
        self.done_ids = []

    def add(self, index: int, poses, ms: dict) -> None:
        for k in STAGES:
            self.stage_ms[k].append(ms.get(k, 0.0))
        now = time.perf_counter()
        self.fps = 1.0 / max(now - self.last, 1e-6)
        self.last = now
        self.n += 1
        self.done_ids.append(index)
        if self.n == 10:
            self.rss_early = _rss_mb()["current"]
        self.n_poses += len(poses)
        bad = sum(not in_prior(self.prior, p.R, p.t) for p in poses)
        if bad and not self.out_of_prior:
            self.log(f"warning: estimated poses leave the bundle's '{self.prior}' pose prior (camera elevation "
                     f"outside what it was trained on); expect larger errors there")
        self.out_of_prior += bad

    def stages(self) -> dict:
        return {k: {"median": float(np.median(v)) if v else None, "p95": float(np.percentile(v, 95)) if v else None}
                for k, v in self.stage_ms.items()}


def _frames(feed: _Feed, pipeline: Pipeline, outputs: _Outputs, stats: _Stats, status, scene_id: int):
    """The frames through the pipeline to the outputs until the source ends, Ctrl-C or an
    error: returns (interrupted, the error or None)."""
    try:
        with Stopper() as stopper:
            while not stopper.stop:
                t0 = time.perf_counter()
                got = feed.next()
                if got is None:
                    break
                index, frame, restarted = got
                if restarted:
                    pipeline.reset()
                ms = {"capture": 1000 * (time.perf_counter() - t0)}
                r = pipeline.step(frame)
                ms.update(r.ms)
                outputs.write(index, frame, r, ms, status.update(index, r.poses), t0, stats.fps, scene_id)
                stats.add(index, r.poses, ms)
            return stopper.stop, None
    except KeyboardInterrupt:  # a signal in the instants around the loop's own handler
        return True, None
    except Exception as e:  # a fatal error mid-run: the frames done so far keep their summary
        return False, e


def _summary(cfg: TrackConfig, stats: _Stats, src, boxes, outputs: _Outputs, status, est: PoseEstimator,
             scene_id: int, failure, interrupted: bool) -> RunSummary:
    wall = time.perf_counter() - stats.t_start
    n, rr_sink, writer = stats.n, outputs.rerun, outputs.writer
    return RunSummary(
        frames=n, poses=stats.n_poses, wall_s=round(wall, 2), fps=round(n / wall, 2) if wall > 0 else None,
        stages_ms=stats.stages(), dropped_frames=int(getattr(src, "dropped", 0)), pose_prior=stats.prior,
        poses_outside_prior=stats.out_of_prior, interrupted=interrupted,
        camera_lost=bool(getattr(src, "lost", False)), camera_reconnects=int(getattr(src, "reconnects", 0)),
        video_truncated=bool(getattr(src, "truncated", False)), source=str(cfg.source), model=str(cfg.model),
        boxes="gt" if isinstance(boxes, GtBoxes) else ("detector" if boxes is not None else "none"),
        detector_frames=boxes.detector_frames if isinstance(boxes, BoxSchedule) else None,
        detect_every=cfg.detect_every, smoothing_alpha=cfg.smooth, looped=cfg.loop,
        rss_mb=dict(_rss_mb(), after_10_frames=stats.rss_early),
        recording=str(rr_sink.path) if rr_sink is not None and rr_sink.path else None,
        error=None if failure is None else (str(failure) if isinstance(failure, UserError)
                                            else f"{type(failure).__name__}: {failure}"),
        objects=status.summary(),
        video=str(cfg.video_out) if cfg.video_out and writer.frames else None,
        frames_dir=str(cfg.frames_out) if cfg.frames_out and writer.frames else None,
        scene_id=scene_id, im_ids=stats.done_ids, viewer=rr_sink if rr_sink is not None and rr_sink.serving else None,
        scene_root=str(src.scene.root) if isinstance(src, BopSceneSource) else None, bundle_obj_ids=list(est.obj_ids))


def _rss_mb() -> dict:
    """Peak and current resident memory of this process (MB)."""
    import resource
    cur = None
    try:
        with open("/proc/self/statm") as f:
            cur = int(f.read().split()[1]) * (os.sysconf("SC_PAGE_SIZE") / 1e6)
    except OSError:
        pass
    return {"current": None if cur is None else round(cur, 1),
            "peak": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6, 1)}  # KiB on Linux


def _scene_id(source) -> int:
    name = Path(str(source)).name
    return int(name) if name.isdigit() else 0
