"""The frame loop: capture -> undistort -> boxes -> crops -> encoder -> regressors -> overlay
-> logs. ``app.py track`` and ``app.py demo`` are thin layers over :func:`run_track`."""
from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from tracker.core.bop import Estimate, write_json
from tracker.core.camera import Undistorter, read_camera
from tracker.core.errors import UserError
from tracker.runtime.estimator import Detection, PoseEstimator
from tracker.core.geometry import scale_intrinsics
from tracker.runtime.sinks import STAGES, CsvSink, RerunSink
from tracker.core.priors import in_prior


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


class _Stopper:
    """SIGINT / SIGTERM end the loop after the frame in flight."""

    def __init__(self):
        self.stop = False
        self._old = {}

    def __enter__(self):
        for s in (signal.SIGINT, signal.SIGTERM):
            self._old[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, *_):
        self.stop = True

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)


class _Deferred(_Stopper):
    """SIGINT / SIGTERM while the run's files are being finished: the first is noted (and
    said) and the work goes on; a second one stops it (KeyboardInterrupt)."""

    def __init__(self, log, what: str):
        super().__init__()
        self.log, self.what = log, what

    @property
    def hit(self) -> bool:
        return self.stop

    def _handle(self, *_):
        if self.stop:
            raise KeyboardInterrupt
        self.stop = True
        self.log(f"{self.what}; interrupt again to skip it")


def _gt_detections(frame, boxes_of, known) -> list[Detection]:
    """Ground-truth visible boxes of the bundle's objects that are at least 10 % visible."""
    from tracker.evaluation.evaluate import gt_instances_with_boxes
    if boxes_of is not None and frame.index in boxes_of:
        return [Detection(o, b, exact=True) for o, b, _ in gt_instances_with_boxes(frame.gt, boxes_of[frame.index], 0.1)
                if o in known]
    return []


class BoxSchedule:
    """Which boxes a frame uses: the detector's, or (when ``every`` > 1) boxes predicted from
    the previous frame's poses, the model points projected at that pose. The detector runs on
    every ``every``-th frame and on any frame after one where an object was lost."""

    def __init__(self, detector, every: int, points: dict[int, np.ndarray], obj_ids=None):
        if int(every) < 1:
            raise UserError(f"--detect-every must be >= 1, got {every}")
        self.detector, self.every, self.points = detector, int(every), points
        self.obj_ids = set(obj_ids) if obj_ids else None
        self.detector_frames = 0
        self.reset()

    def reset(self):
        """Forget the previous frame (a new shot: the next frame runs the detector)."""
        self.since, self.prev, self.lost, self.n_expected = 0, [], True, 0

    def boxes(self, rgb, K) -> tuple[list[Detection], str]:
        """This frame's boxes and where they came from ('detector' or 'pose')."""
        from tracker.core.geometry import box_from_points, clip_box, project
        h, w = rgb.shape[:2]
        if self.lost or self.since + 1 >= self.every or not self.prev:
            self.since = 0
            self.detector_frames += 1
            dets = [d for d in self.detector(rgb) if self.obj_ids is None or d.obj_id in self.obj_ids]
            self.n_expected = len(dets)
            return dets, "detector"
        self.since += 1
        out = []
        for p in self.prev:
            b = clip_box(box_from_points(project(self.points[p.obj_id], K, p.R, p.t)), w, h)
            if b[2] > 4 and b[3] > 4:
                out.append(Detection(p.obj_id, b, p.score))
        return out, "pose"

    def update(self, poses):
        """The poses estimated from this frame's boxes (unsmoothed)."""
        self.lost = len(poses) < self.n_expected
        self.prev = list(poses)


def run_track(cfg: TrackConfig, log=print) -> dict:
    from tracker.core.meshes import load_mesh
    from tracker.runtime.overlay import blend, colour, draw_axes, draw_box
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
    boxes_of = None
    if cfg.boxes in ("auto", "gt") and isinstance(src, BopSceneSource) and src.scene.gt:
        from tracker.evaluation.evaluate import gt_boxes, gt_object_ids
        from tracker.core.meshes import load_models
        ids = gt_object_ids(src.scene, src.ids, est.obj_ids, "; use --boxes detector, or a bundle trained on them")
        boxes_of, _ = gt_boxes(src.scene, load_models(est.bundle.root / "meshes", ids), src.ids)
    elif cfg.boxes == "gt":
        raise UserError("--boxes gt needs a BOP scene with scene_gt.json")
    elif cfg.boxes == "detector" and not est.bundle.manifest.has_detector:
        raise UserError(f"--boxes detector: {cfg.model} has no detector; train one with 'app.py train-detector' "
                        f"or use a BOP scene with --boxes gt")
    elif not est.bundle.manifest.has_detector:
        log("warning: this bundle has no detector and the source has no ground truth: "
            "no boxes, so no poses; frames are still logged")
    meshes = {o.id: load_mesh(est.bundle.overlay_mesh_path(o), o.id).mesh for o in est.bundle.objects}
    schedule = None
    if boxes_of is None and est.bundle.manifest.has_detector:
        from tracker.runtime.detector import Detector
        pts = {o: np.asarray(m.vertices)[:: max(1, len(m.vertices) // 500)] for o, m in meshes.items()}
        schedule = BoxSchedule(Detector(est.bundle, threads=cfg.detector_threads), cfg.detect_every, pts, cfg.obj_ids)
    smoother = None
    if cfg.smooth is not None:
        from tracker.runtime.smoothing import PoseSmoother
        smoother = PoseSmoother(cfg.smooth)
    diam = {o.id: o.diameter for o in est.bundle.objects}
    cam = read_camera(cfg.calib) if cfg.calib else None
    undist = Undistorter(cam) if cam else None
    if cam is None and not isinstance(src, BopSceneSource):  # only BOP scenes carry their intrinsics
        raise UserError("this source needs a camera file: pass --calib FILE")
    out.mkdir(parents=True, exist_ok=True)  # only now: a run that cannot start leaves no empty folder
    csv_sink = CsvSink(out)
    renderer = rr_sink = None
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
    try:
        with _Stopper() as stopper:
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
                    if schedule is not None:  # the replay starts again: no pose carries over the cut
                        schedule.reset()
                    if smoother is not None:
                        smoother.reset()
                index = n if cfg.loop else frame.index
                ms = {"capture": 1000 * (time.perf_counter() - t0)}
                t = time.perf_counter()
                h, w = frame.rgb.shape[:2]
                if frame.K is not None:
                    K, rgb = frame.K, frame.rgb
                else:  # (a source without intrinsics and no --calib was refused before the loop)
                    K, rgb = undist.camera_for(w, h).K, undist(frame.rgb)
                ms["undistort"] = 1000 * (time.perf_counter() - t)
                t = time.perf_counter()
                if schedule is not None:
                    dets, _ = schedule.boxes(rgb, K)
                else:
                    dets = _gt_detections(frame, boxes_of, set(est.obj_ids))
                if cfg.obj_ids:
                    dets = [d for d in dets if d.obj_id in cfg.obj_ids]
                ms["detect"] = 1000 * (time.perf_counter() - t)
                t = time.perf_counter()
                poses = est.estimate(rgb, K, dets, timings=ms) if dets else []
                if schedule is not None:
                    schedule.update(poses)
                if smoother is not None:  # new objects: the schedule keeps the raw poses
                    poses = [replace(p, R=r, t=tt) for p in poses for r, tt in [smoother(p.obj_id, p.R, p.t, n)]]
                ms.setdefault("encode", 0.0)  # crops + encoder
                ms.setdefault("regress", 0.0)
                t = time.perf_counter()
                vis = None
                if cfg.overlay:
                    rw, rh = max(w // cfg.overlay_downscale, 1), max(h // cfg.overlay_downscale, 1)
                    if renderer is None or (renderer.width, renderer.height) != (rw, rh):
                        from tracker.runtime.render import Renderer
                        renderer = Renderer(rw, rh, meshes)
                    col, depth = renderer.render(scale_intrinsics(K, (w, h), (rw, rh)),
                                                 [(p.obj_id, p.R, p.t) for p in poses])
                    if (rw, rh) != (w, h):
                        col = cv2.resize(col, (w, h), interpolation=cv2.INTER_LINEAR)
                        depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
                    vis = blend(rgb, col, depth, 0.6)
                    for p in poses:
                        draw_box(vis, p.box, colour(p.obj_id), names.get(p.obj_id))
                        draw_axes(vis, K, p.R, p.t, 0.3 * diam[p.obj_id])
                ms["render"] = 1000 * (time.perf_counter() - t)
                t = time.perf_counter()
                if rr_sink is None:
                    rr_sink = RerunSink(cfg.rerun, out, meshes, names, K, (w, h))
                rr_sink.log_frame(index, rgb, vis, dets, poses)
                dt_frame = time.perf_counter() - t0
                ests = [Estimate(0 if not isinstance(src, BopSceneSource) else _scene_id(cfg.source), index,
                                 p.obj_id, p.score, p.R, p.t, dt_frame) for p in poses]
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
                if n == 10:
                    rss_early = _rss_mb()["current"]
                n_poses += len(poses)
                bad = sum(not in_prior(prior, p.R, p.t) for p in poses)
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
        with _Deferred(log, "closing the run's files") as closing:
            csv_sink.close()
            src.close()
            if rr_sink is not None:
                rr_sink.close()
            if renderer is not None:
                renderer.close()
    interrupted = interrupted or closing.hit
    wall = time.perf_counter() - t_run
    summary = {
        "frames": n, "poses": n_poses, "wall_s": round(wall, 2), "fps": round(n / wall, 2) if wall > 0 else None,
        "stages_ms": {k: {"median": float(np.median(v)) if v else None,
                          "p95": float(np.percentile(v, 95)) if v else None} for k, v in stage_log.items()},
        "dropped_frames": int(getattr(src, "dropped", 0)), "pose_prior": prior, "poses_outside_prior": out_of_prior, "interrupted": interrupted,
        "camera_lost": bool(getattr(src, "lost", False)), "camera_reconnects": int(getattr(src, "reconnects", 0)), "video_truncated": bool(getattr(src, "truncated", False)),
        "source": str(cfg.source), "model": str(cfg.model), "boxes": "gt" if boxes_of is not None else ("detector" if schedule is not None else "none"),
        "detector_frames": schedule.detector_frames if schedule is not None else None,
        "detect_every": cfg.detect_every, "smoothing_alpha": cfg.smooth, "looped": cfg.loop,
        "rss_mb": dict(_rss_mb(), after_10_frames=rss_early),
        "recording": str(rr_sink.path) if rr_sink is not None and rr_sink.path else None,
        "error": None if failure is None else (str(failure) if isinstance(failure, UserError)
                                               else f"{type(failure).__name__}: {failure}"),
    }
    # written at once (an interrupted or failed run keeps it), again with the accuracy below
    save_summary = partial(write_json, out / "summary.json")  # (a file replaced whole, never half-written)
    save_summary(summary)
    if failure is not None:
        raise failure
    has_gt = isinstance(src, BopSceneSource) and bool(src.scene.gt) and not cfg.loop
    gt_objs = {g.obj_id for i in src.ids[:n] for g in src.scene.gt.get(i, [])} if has_gt else set()
    # (a subset of the objects would count the rest as missed; a run whose frames were cut short is not scored)
    if has_gt and n and gt_objs <= set(est.obj_ids) and not cfg.obj_ids and not interrupted:
        from tracker.evaluation.scoring import score_results
        with _Deferred(log, "scoring the poses against the ground truth") as scoring:
            try:
                m = score_results(out / "poses.csv", src.scene.root, est.bundle.root / "meshes",
                                  models_info=est.bundle.root / "meshes" / "models_info.json",
                                  im_ids=src.ids[:n], scene_id=_scene_id(cfg.source))
                summary["accuracy"] = {k: m[k] for k in ("n_gt", "add_recall", "ar_mssd", "ar_mspd",
                                                         "re_median_deg", "te_median_mm", "visibility_source")}
            except KeyboardInterrupt:  # the second Ctrl-C: no accuracy, the rest stands
                summary["accuracy_skipped"] = True
            except UserError as e:
                summary["error"] = f"scoring: {e}"
                save_summary(summary)
                raise
            summary["interrupted"] = scoring.hit  # a Ctrl-C came; the frames were all done (and scored, once)
            save_summary(summary)
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
