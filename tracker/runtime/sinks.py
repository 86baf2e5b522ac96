"""Where a run's results go: BOP poses CSV, per-frame timings CSV (both flushed every frame,
so an interrupt loses at most the frame in flight) and rerun (a recording stream per sink;
its servers, for ``--rerun serve``, stop with it)."""
from __future__ import annotations

import csv
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from tracker.core.bop import RESULT_HEADER, Estimate, format_result_row
from tracker.core.errors import UserError

STAGES = ("capture", "undistort", "detect", "encode", "regress", "render", "log", "total")


class CsvSink:
    """poses.csv and timings.csv in ``out_dir``; a context manager (leaving it closes both)."""

    def __init__(self, out_dir: Path):
        out_dir.mkdir(parents=True, exist_ok=True)
        self._pf = open(out_dir / "poses.csv", "w", newline="")
        self._tf = open(out_dir / "timings.csv", "w", newline="")
        self._pw = csv.writer(self._pf, lineterminator="\n")
        self._tw = csv.writer(self._tf, lineterminator="\n")
        self._pw.writerow(RESULT_HEADER)
        self._tw.writerow(["im_id", "t_capture", *STAGES])
        self._pf.flush()
        self._tf.flush()

    def write(self, estimates: list[Estimate], im_id: int, t_capture: float, stages_ms: dict):
        for e in estimates:
            self._pw.writerow(format_result_row(e))
        self._tw.writerow([im_id, f"{t_capture:.6f}", *(f"{stages_ms.get(s, 0.0):.3f}" for s in STAGES)])
        self._pf.flush()
        self._tf.flush()

    def close(self):
        self._pf.close()
        self._tf.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


RERUN_GRPC_PORT, RERUN_WEB_PORT = 9876, 9090  # rerun's defaults for serve_grpc / serve_web_viewer


def port_taken(port: int) -> bool:
    """Whether a server already listens on ``port`` (a socket bound and released, as the server
    will bind it; reuse-address, so connections closing from an earlier run do not count)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return True
    return False


def _first_line(e: Exception) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0][:160]


def has_display() -> bool:
    """Whether a native window can open here: on Linux an X11 or Wayland display must be named."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


RERUN_MODES = ("save", "serve", "spawn", "off")


def check_rerun_mode(mode: str) -> None:
    """Refuse, before the run opens anything, a viewer mode that cannot start here: spawn
    without a display, serve with rerun's ports taken (rerun's servers print errors of their
    own before raising, so the ports are checked first)."""
    if mode not in RERUN_MODES:
        raise UserError(f"--rerun {mode}: use one of {', '.join(RERUN_MODES)}")
    if mode == "spawn" and not has_display():
        raise UserError("--rerun spawn: no display here (DISPLAY and WAYLAND_DISPLAY are unset); use "
                        "--rerun serve (a web viewer: open the printed URL) or --rerun save")
    if mode == "serve":
        taken = [p for p in (RERUN_GRPC_PORT, RERUN_WEB_PORT) if port_taken(p)]
        if taken:
            raise UserError(f"--rerun serve: port {' and '.join(map(str, taken))} already in use (another run "
                            f"serving?); stop it, or use --rerun save")


def blueprint(names: dict, overlay: bool = True):
    """The viewer's layout, the same every run: the annotated frame large on the left; on the
    right the 3D view (camera frustum and meshes), the per-object confidence, one timings
    panel (every stage and fps) and the tracking status (objects seen, uncertain, lost)."""
    import rerun.blueprint as rrb
    image = (rrb.Spatial2DView(origin="overlay", name="camera + poses") if overlay
             else rrb.Spatial2DView(origin="world/camera/image", name="camera + boxes"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(image, rrb.TextDocumentView(origin="status", name="status"), row_shares=[5, 1]),
            rrb.Vertical(rrb.Spatial3DView(origin="world", name="3D"),
                         rrb.TimeSeriesView(origin="confidence", name="confidence per object"),
                         rrb.TimeSeriesView(origin="timings", name="timings (ms per stage, fps)"),
                         row_shares=[2, 1, 1]),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline="frame", state="collapsed"),  # not log_time, which a viewer may pick before frames arrive
        collapse_panels=True)


class WebViewer:
    """rerun's web viewer (its pages only: the data comes from the run's gRPC server) served
    on ``port`` by a child process, so that it stops when told: rerun 0.41 has no call that
    stops a web viewer started in this process. The child also ends when this process does
    (its stdin closes)."""

    _CHILD = ("import sys, rerun\n"
              "try:\n"
              "    rerun.serve_web_viewer(web_port=int(sys.argv[1]), open_browser=False)\n"
              "except Exception as e:\n"
              "    print('error', str(e).splitlines()[0] if str(e) else type(e).__name__, flush=True)\n"
              "    sys.exit(1)\n"
              "print('ready', flush=True)\n"
              "sys.stdin.read()\n")

    def __init__(self, port: int):
        self.port = port
        # its own session: a Ctrl-C in the terminal reaches the run, which decides when the viewer
        # stops (it keeps serving through --serve-for or the next Ctrl-C), not the child itself
        self._proc = subprocess.Popen([sys.executable, "-c", self._CHILD, str(port)], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, text=True, start_new_session=True)
        said = self._proc.stdout.readline().strip()  # once the server listens (or failed)
        if said != "ready":
            self.stop()
            raise RuntimeError(said.removeprefix("error ") or "the web viewer's process ended")

    @property
    def running(self) -> bool:
        return self._proc.poll() is None

    def stop(self) -> None:
        if self._proc.poll() is None:
            try:
                self._proc.stdin.close()  # its stdin.read() returns: it exits
                self._proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
        for f in (self._proc.stdin, self._proc.stdout):
            if f is not None and not f.closed:
                f.close()


class RerunSink:
    """rerun logging into a recording stream of its own (never rerun's global one, so two sinks
    in one process stay apart). ``mode``: spawn (a local viewer), serve (web viewer, URL
    printed; the recording is saved to OUT/recording.rrd as well), save (OUT/recording.rrd) or
    off. A blueprint (:func:`blueprint`) is sent first. ``plane_mm``: the frustum's depth in the
    3D view until the first poses, then 0.8 x the nearest object's distance.

    An object is drawn in the 3D view only in the frames it has a pose in: its mesh is logged
    (on the frame's timeline, beside its transform) when it appears, and its entity is cleared
    in the first frame without it; an object never found is never drawn. ``mesh_every``: the
    mesh is logged again after that many frames in view, so a viewer that joins a long served
    run late still gets it after rerun's server dropped the oldest data.

    A context manager: leaving it closes the sink (:meth:`close`) or, on an exception, stops
    it (:meth:`stop`)."""

    def __init__(self, mode: str, out_dir: Path, meshes: dict, names: dict, K: np.ndarray, size,
                 overlay: bool = True, plane_mm: float = 300.0, mesh_every: int = 300):
        self.mode = mode
        self.rr = None   # the rerun module while this sink logs
        self.rec = None  # this sink's recording stream (None: off or stopped)
        self.path = None
        self.url = None
        self.web = None  # the web viewer's process (serve)
        self.names = names
        self.plane_mm = float(plane_mm)
        self.mesh_every = int(mesh_every)
        self._fitted = False
        self._camera = (np.asarray(K), list(size))
        self._shown: dict = {}  # obj_id -> frames logged since its mesh was, for objects drawn now
        self._meshes: dict = {}  # obj_id -> its rr.Mesh3D
        if mode == "off":
            return
        check_rerun_mode(mode)
        import rerun as rr
        bp = blueprint(names, overlay)
        self.rr = rr
        import uuid
        self.rec = rr.RecordingStream("autopose", recording_id=uuid.uuid4())  # rerun's default id is per process
        try:
            self._connect(out_dir, bp)
        except BaseException:
            self.stop()
            raise
        for oid, mesh in meshes.items():
            cols = getattr(mesh.visual, "vertex_colors", None)
            self._meshes[oid] = rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices, np.float32),
                                          triangle_indices=np.asarray(mesh.faces, np.uint32),
                                          vertex_colors=None if cols is None else np.asarray(cols)[:, :3])
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)  # OpenCV camera: x right, y down, z forward
        self.set_camera(K, size)

    def _connect(self, out_dir, bp) -> None:
        rr, rec, mode = self.rr, self.rec, self.mode
        if mode == "save":
            self.path = Path(out_dir) / "recording.rrd"
            rec.save(self.path, default_blueprint=bp)
        elif mode == "spawn":
            # the viewer installed beside this Python (.venv/bin/rerun), which need not be on PATH
            viewer = Path(sys.executable).parent / "rerun"
            try:
                rr.spawn(executable_path=str(viewer) if viewer.is_file() else None, default_blueprint=bp,
                         recording=rec)
            except Exception as e:
                raise UserError(f"--rerun spawn: cannot start the rerun viewer ({_first_line(e)}); without a "
                                f"display use --rerun serve (web viewer) or --rerun save") from None
        elif mode == "serve":
            self.path = Path(out_dir) / "recording.rrd"
            try:
                server = rr.GrpcServerSink(port=RERUN_GRPC_PORT)  # stops when the stream disconnects
                rec.set_sinks(server, rr.FileSink(self.path), default_blueprint=bp)
                uri = server.uri.replace("0.0.0.0", "127.0.0.1")  # bound on every interface; a browser here
                self.web = WebViewer(RERUN_WEB_PORT)
            except Exception as e:
                raise UserError(f"--rerun serve: cannot start rerun's servers ({_first_line(e)}); is another run "
                                f"serving on ports {RERUN_GRPC_PORT} / {RERUN_WEB_PORT}? Stop it, or use --rerun save") from None
            self.url = f"http://localhost:{RERUN_WEB_PORT}/?url={uri}"
            print(f"rerun web viewer: {self.url}", file=sys.stderr)

    def set_camera(self, K, size):
        self._camera = (np.asarray(K), list(size))
        if self.rec is not None:
            self.rec.log("world/camera", self.rr.Pinhole(image_from_camera=np.asarray(K), resolution=list(size),
                                                         image_plane_distance=self.plane_mm), static=True)

    def log_frame(self, index, frame_rgb, overlay_rgb, detections, poses, status: str | None = None):
        """One frame: the images, boxes, the poses (their transforms and confidences) and
        ``status`` (a line or two of text: what is tracked, uncertain, lost)."""
        rr, rec = self.rr, self.rec
        if rec is None:
            return
        rec.set_time("frame", sequence=int(index))
        rec.log("world/camera/image", self._jpeg(frame_rgb))
        if overlay_rgb is not None:
            rec.log("overlay", self._jpeg(overlay_rgb))
        if detections:
            rec.log("world/camera/image/boxes", rr.Boxes2D(array=np.array([d.box for d in detections]),
                                                           array_format=rr.Box2DFormat.XYWH,
                                                           labels=[self._name(d.obj_id) for d in detections]))
        else:
            rec.log("world/camera/image/boxes", rr.Clear(recursive=False))
        if poses and not self._fitted:  # the frustum reaches to just before the nearest object
            self._fitted = True
            self.plane_mm = max(50.0, 0.8 * min(float(p.t[2]) for p in poses))
            self.set_camera(*self._camera)
        shown = {}
        for p in poses:
            path = f"world/objects/{self._name(p.obj_id)}"
            rec.log(path, rr.Transform3D(translation=p.t, mat3x3=p.R))
            since = shown.get(p.obj_id, self._shown.get(p.obj_id))
            if since is None or since >= self.mesh_every:  # (re)appears: drawn from this frame on
                if p.obj_id in self._meshes:
                    rec.log(f"{path}/mesh", self._meshes[p.obj_id])
                since = 0
            shown[p.obj_id] = since
            rec.log(f"confidence/{self._name(p.obj_id)}", rr.Scalars(float(p.score)))
        for oid in self._shown.keys() - shown.keys():  # gone: not drawn from this frame on
            rec.log(f"world/objects/{self._name(oid)}", rr.Clear(recursive=True))
        self._shown = {o: n + 1 for o, n in shown.items()}
        if status is not None:
            rec.log("status", rr.TextDocument(status))

    def _name(self, obj_id) -> str:
        return self.names.get(obj_id, str(obj_id))

    def _jpeg(self, rgb, quality: int = 75):
        """JPEG through OpenCV (libjpeg-turbo): 1.2 ms per 640x480 frame vs 2.5 ms for
        ``rr.Image(...).compress`` (measured)."""
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
        return self.rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")

    def log_timings(self, stages_ms: dict, fps):
        """Per-stage milliseconds of the frame last logged (every stage, 0 where it did not
        run, so the panel's series are the same every run) and the running fps."""
        rr, rec = self.rr, self.rec
        if rec is None:
            return
        for k in STAGES:
            rec.log(f"timings/{k}_ms", rr.Scalars(float(stages_ms.get(k, 0.0))))
        rec.log("timings/fps", rr.Scalars(float(fps or 0.0)))

    @property
    def serving(self) -> bool:
        """Whether this sink's servers are up (serve, until :meth:`hold` or :meth:`stop`)."""
        return self.rec is not None and self.mode == "serve"

    def close(self):
        """The run is over: a saved recording is complete on disk. A serving sink keeps its
        servers up (and the recording open) until :meth:`hold` ends."""
        if self.serving:
            try:
                self.rec.flush(timeout_sec=10.0)
            except Exception as e:  # a viewer that stopped reading: the run's own files are written anyway
                print(f"warning: the rerun recording could not be flushed to its viewers ({e})", file=sys.stderr)
        else:
            self.stop()

    def stop(self):
        """Disconnect the recording (its file complete, its gRPC server down) and stop the web
        viewer. Idempotent."""
        rec, self.rec, self.rr = self.rec, None, None
        try:
            if rec is not None:
                rec.disconnect()
        finally:
            if self.web is not None:
                self.web.stop()
                self.web = None

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        if exc_type is None:
            self.close()
        else:  # the run failed: nobody will hold a viewer on it
            self.stop()

    def hold(self, seconds: float | None = None, log=print) -> None:
        """``--rerun serve``: keep serving the finished run until Ctrl-C (or ``seconds``), so
        a viewer opened late still gets all of it; then stop the servers. No-op otherwise."""
        if not self.serving:
            return
        try:
            if seconds is None or seconds > 0:
                log(f"rerun: the run is over; still serving it at {self.url} "
                    + (f"for {seconds:g} s " if seconds is not None else "") + "(Ctrl-C to stop)"
                    + (f"; saved in {self.path}" if self.path else ""))
                end = None if seconds is None else time.monotonic() + seconds
                while end is None or time.monotonic() < end:
                    time.sleep(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic())))
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()
