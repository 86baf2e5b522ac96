"""The run loop: a source's frames through :class:`~tracker.runtime.pipeline.Pipeline`, with
the run's files (poses.csv, timings.csv, summary.json, recording.rrd), Ctrl-C handling and a
typed :class:`RunSummary`. ``app.py track`` and ``app.py demo`` call it through
:func:`tracker.evaluation.track.track`, which adds the ground truth's boxes and the accuracy
where a recording has them; the runtime itself knows nothing of evaluation."""
from __future__ import annotations

import os
import time
import copy
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
    smooth: float | None = None  # PoseSmoother alpha (None: off)
    obj_ids: list[int] | None = None  # track only these objects (None: all of the bundle's)
    # replay a recorded source again and again until max_frames (a soak test); frames are then
    # numbered 0, 1, 2, ... in the logs, and no accuracy is computed
    loop: bool = False
    video_out: str | None = None  # the annotated frames as a video (.mp4, .avi, .mkv)
    frames_out: str | None = None  # ... and/or as numbered PNGs in this folder
    min_confidence: float = UNCERTAIN_BELOW  # poses below it are drawn and counted as uncertain


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
    None: ground truth is not used."""
    from tracker.core.meshes import load_mesh
    from tracker.runtime.sources import BopSceneSource, is_camera, open_source
    est = PoseEstimator(cfg.model)
    names = {o.id: o.name for o in est.bundle.objects}
    unknown = [o for o in cfg.obj_ids or [] if o not in est.obj_ids]
    if unknown:
        raise UserError(f"--obj-ids {','.join(map(str, unknown))}: not objects of {cfg.model} "
                        f"(it knows {','.join(map(str, est.obj_ids))})")
    if cfg.loop and is_camera(cfg.source):
        raise UserError("--loop replays recordings; a camera cannot be looped")
    src = open_source(cfg.source, max_frames=None if cfg.loop else cfg.max_frames, realtime=cfg.realtime)
    out = Path(cfg.out)
    has_detector = est.bundle.manifest.has_detector
    boxes = None
    scene_gt = cfg.boxes in ("auto", "gt") and isinstance(src, BopSceneSource) and bool(src.scene.gt)
    if scene_gt and gt_boxes is None and cfg.boxes == "gt":
        raise UserError("--boxes gt: this run was given no source of ground-truth boxes (run it through "
                        "tracker.evaluation.track.track, as 'app.py track' does)")
    if scene_gt and gt_boxes is not None:
        boxes = GtBoxes(gt_boxes(src.scene, src.ids, est.bundle), est.obj_ids)
    elif cfg.boxes == "gt":
        raise UserError("--boxes gt needs a BOP scene with scene_gt.json")
    elif cfg.boxes == "detector" and not has_detector:
        raise UserError(f"--boxes detector: {cfg.model} has no detector; train one with 'app.py train-detector' "
                        f"or use a BOP scene with --boxes gt")
    elif not has_detector:
        log("warning: this bundle has no detector and the source has no ground truth: "
            "no boxes, so no poses; frames are still logged")
    meshes = {o.id: load_mesh(est.bundle.overlay_mesh_path(o), o.id).mesh for o in est.bundle.objects}
    if boxes is None and has_detector:
        from tracker.runtime.detector import Detector
        pts = {o: np.asarray(m.vertices)[:: max(1, len(m.vertices) // 500)] for o, m in meshes.items()}
        boxes = BoxSchedule(Detector(est.bundle, threads=cfg.detector_threads), cfg.detect_every, pts, cfg.obj_ids)
    smoother = None
    if cfg.smooth is not None:
        from tracker.runtime.smoothing import PoseSmoother
        smoother = PoseSmoother(cfg.smooth)
    cam = read_camera(cfg.calib) if cfg.calib else None
    if cam is None and not isinstance(src, BopSceneSource):  # only BOP scenes carry their intrinsics
        raise UserError("this source needs a camera file: pass --calib FILE")
    from tracker.runtime.status import TrackStatus
    from tracker.runtime.video import FrameWriter, check_video_path
    if cfg.video_out:
        check_video_path(cfg.video_out)
    pipeline = Pipeline(est, boxes, Undistorter(cam) if cam else None, meshes if cfg.overlay else None,
                        cfg.overlay_downscale, smoother, cfg.obj_ids, cfg.min_confidence)
    status = TrackStatus(names, cfg.obj_ids or est.obj_ids, cfg.min_confidence)
    out.mkdir(parents=True, exist_ok=True)  # only now: a run that cannot start leaves no empty folder
    writer = FrameWriter(cfg.video_out, cfg.frames_out, getattr(src, "fps", None))
    csv_sink = CsvSink(out)
    rr_sink = None
    scene_id = _scene_id(cfg.source) if isinstance(src, BopSceneSource) else 0
    n = 0
    t_run = time.perf_counter()
    stage_log = {s: [] for s in STAGES}
    n_poses = 0
    prior = est.bundle.manifest.pose_prior
    out_of_prior = 0
    last = time.perf_counter()
    fps = None
    rss_early = None
    interrupted = False
    failure = None
    done_ids = []
    try:
        with Stopper() as stopper:
            it = iter(src)
            while not stopper.stop:
                t0 = time.perf_counter()
                if cfg.loop and cfg.max_frames is not None and n >= cfg.max_frames:
                    break
                try:
                    frame = next(it)
                except StopIteration:
                    if not (cfg.loop and n):
                        break
                    src.close()
                    src = open_source(cfg.source, realtime=cfg.realtime)
                    it = iter(src)
                    frame = next(it)
                    pipeline.reset()
                index = n if cfg.loop else frame.index
                ms = {"capture": 1000 * (time.perf_counter() - t0)}
                r = pipeline.step(frame)
                ms.update(r.ms)
                t = time.perf_counter()
                if rr_sink is None:
                    h, w = r.rgb.shape[:2]
                    rr_sink = RerunSink(cfg.rerun, out, meshes, names, r.K, (w, h), overlay=r.overlay is not None)
                rr_sink.log_frame(index, r.rgb, r.overlay, r.detections, r.poses, status.update(index, r.poses))
                if writer.active:
                    writer.write(index, r.overlay if r.overlay is not None else r.rgb)
                dt_frame = time.perf_counter() - t0
                ests = [Estimate(scene_id, index, p.obj_id, p.score, p.R, p.t, dt_frame) for p in r.poses]
                ms["log"] = 1000 * (time.perf_counter() - t)
                ms["total"] = 1000 * (time.perf_counter() - t0)
                csv_sink.write(ests, index, frame.t_capture, ms)
                rr_sink.log_timings(ms, fps)
                for k in STAGES:
                    stage_log[k].append(ms.get(k, 0.0))
                now = time.perf_counter()
                fps = 1.0 / max(now - last, 1e-6)
                last = now
                n += 1
                done_ids.append(index)
                if n == 10:
                    rss_early = _rss_mb()["current"]
                n_poses += len(r.poses)
                bad = sum(not in_prior(prior, p.R, p.t) for p in r.poses)
                if bad and not out_of_prior:
                    log(f"warning: estimated poses leave the bundle's '{prior}' pose prior (camera elevation "
                        f"outside what it was trained on); expect larger errors there")
                out_of_prior += bad
            interrupted = stopper.stop
    except KeyboardInterrupt:  # a signal in the instants around the loop's own handler
        interrupted = True
    except Exception as e:  # a fatal error mid-run: the frames done so far keep their summary
        failure = e
    finally:
        with Deferred(log, "closing the run's files") as closing:
            csv_sink.close()
            writer.close()
            src.close()
            if rr_sink is not None:
                rr_sink.close()
            pipeline.close()
    interrupted = interrupted or closing.hit
    wall = time.perf_counter() - t_run
    summary = RunSummary(
        frames=n, poses=n_poses, wall_s=round(wall, 2), fps=round(n / wall, 2) if wall > 0 else None,
        stages_ms={k: {"median": float(np.median(v)) if v else None,
                       "p95": float(np.percentile(v, 95)) if v else None} for k, v in stage_log.items()},
        dropped_frames=int(getattr(src, "dropped", 0)), pose_prior=prior, poses_outside_prior=out_of_prior,
        interrupted=interrupted, camera_lost=bool(getattr(src, "lost", False)),
        camera_reconnects=int(getattr(src, "reconnects", 0)), video_truncated=bool(getattr(src, "truncated", False)),
        source=str(cfg.source), model=str(cfg.model),
        boxes="gt" if isinstance(boxes, GtBoxes) else ("detector" if boxes is not None else "none"),
        detector_frames=boxes.detector_frames if isinstance(boxes, BoxSchedule) else None,
        detect_every=cfg.detect_every, smoothing_alpha=cfg.smooth, looped=cfg.loop,
        rss_mb=dict(_rss_mb(), after_10_frames=rss_early),
        recording=str(rr_sink.path) if rr_sink is not None and rr_sink.path else None,
        error=None if failure is None else (str(failure) if isinstance(failure, UserError)
                                            else f"{type(failure).__name__}: {failure}"),
        objects=status.summary(),
        video=str(cfg.video_out) if cfg.video_out and writer.frames else None,
        frames_dir=str(cfg.frames_out) if cfg.frames_out and writer.frames else None,
        scene_id=scene_id, im_ids=done_ids, viewer=rr_sink,
        scene_root=str(src.scene.root) if isinstance(src, BopSceneSource) else None, bundle_obj_ids=list(est.obj_ids))
    summary.save(out)  # at once: an interrupted or failed run keeps it
    if failure is not None:
        raise failure
    return summary


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
