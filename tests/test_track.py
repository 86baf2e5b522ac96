"""The frame loop on short replays: files written, rerun recording readable, threaded capture,
and what a run opens is closed on every way out."""
import json
import signal
import socket
import threading
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import rerun as rr

from tracker.core.bop import read_results
from tracker.core.errors import UserError
from tracker.evaluation.track import track
from tracker.runtime.loop import TrackConfig, run_track
from tracker.runtime.sinks import RERUN_GRPC_PORT, STAGES, RerunSink, port_taken
from tracker.runtime.sources import CameraSource, open_source

REPO = Path(__file__).resolve().parents[1]


def test_track_on_a_bop_replay_writes_valid_files(tiny_bundle, data_dir, tmp_path):
    out = tmp_path / "run"
    s = track(TrackConfig(str(data_dir / "lmo" / "dev"), str(tiny_bundle), out, rerun="save", max_frames=3),
                  log=lambda m: None)
    assert s.frames == 3 and s.poses > 10 and not s.interrupted
    ests = read_results(out / "poses.csv")
    assert {e.im_id for e in ests} == {3, 8, 17} and all(e.t[2] > 0 for e in ests)
    rows = (out / "timings.csv").read_text().splitlines()
    assert rows[0].split(",") == ["im_id", "t_capture", *STAGES] and len(rows) == 4
    summary = json.loads((out / "summary.json").read_text())
    assert summary["accuracy"]["n_gt"] > 20 and set(summary["stages_ms"]) == set(STAGES)
    store = rr.chunk.RrdReader(out / "recording.rrd").store()
    paths = set(store.schema().entity_paths())
    for p in ("/world/camera", "/world/camera/image", "/overlay", "/world/objects/ape", "/timings/total_ms"):
        assert p in paths, (p, sorted(paths)[:20])


def test_frames_without_ground_truth_are_not_scored(tiny_bundle, data_dir, tmp_path):
    """A scene annotated in some frames only: the run scores those and keeps its exit status."""
    import shutil
    src = tmp_path / "scene"
    shutil.copytree(data_dir / "lmo" / "dev", src)
    gt = json.loads((src / "scene_gt.json").read_text())
    (src / "scene_gt.json").write_text(json.dumps({"3": gt["3"], "17": gt["17"]}))
    s = track(TrackConfig(str(src), str(tiny_bundle), tmp_path / "run", rerun="off", max_frames=3),
              log=lambda m: None)
    assert s.frames == 3 and s.error is None
    assert s.accuracy["n_gt"] == sum(1 for i in ("3", "17") for _ in gt[i])


def test_video_and_folder_sources(tmp_path, data_dir):
    frames = [np.full((120, 160, 3), i * 20, np.uint8) for i in range(5)]
    vid = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(vid), cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 120))
    for f in frames:
        w.write(f)
    w.release()
    src = open_source(str(vid))
    got = list(src)
    src.close()
    assert len(got) == 5 and got[0].rgb.shape == (120, 160, 3)
    assert [f.t_capture for f in got] == sorted(f.t_capture for f in got)
    (tmp_path / "broken.mp4").write_bytes(b"\x00" * 1000)
    with pytest.raises(UserError, match="broken.mp4"):
        open_source(str(tmp_path / "broken.mp4"))
    with pytest.raises(UserError, match="not a camera"):
        open_source(str(tmp_path / "nothing-here"))
    assert len(list(open_source(str(data_dir / "lmo" / "dev" / "rgb"), max_frames=2))) == 2


WAIT_S = 10.0  # generous: a condition that holds within milliseconds on an idle machine


def wait_until(cond, what, timeout=WAIT_S):
    """Poll ``cond`` until it holds; fail after ``timeout`` seconds (no fixed sleeps that race)."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.001)


class FakeCapture:
    """A camera delivering numbered frames, unplugged after ``n``. It delivers a frame only when
    the test lets it (``gate``, a semaphore that may be shared by several plugs), so that how
    far the camera runs ahead of the pipeline is set by the test, not by the machine's load."""

    def __init__(self, n=60, gate=None, shape=(48, 64, 3), gate_timeout=WAIT_S):
        self.n, self.i, self.reads, self.released = n, 0, 0, 0
        self.gate_timeout = gate_timeout  # None: a read waits for the test however long it takes
        self.gate = gate if gate is not None else threading.Semaphore(0)
        self.shape = shape

    def isOpened(self):
        return True

    def set(self, *a):
        return True

    def get(self, prop):
        return 200.0

    def read(self):
        self.reads += 1
        if self.i >= self.n:
            return False, None  # unplugged
        if not self.gate.acquire(timeout=self.gate_timeout):
            return False, None  # the test stopped asking for frames
        f = np.full(self.shape, self.i % 256, np.uint8)
        self.i += 1
        return True, f

    def release(self):
        self.released += 1


def test_threaded_capture_hands_over_the_newest_frame_and_counts_drops():
    cap = FakeCapture(n=60)

    def camera_runs_ahead(k=4):  # k new frames, all stored by the capture thread (it asks for the next)
        target = min(cap.i + k, cap.n)
        cap.gate.release(target - cap.i)
        wait_until(lambda: cap.i == target and cap.reads > target, f"frame {target - 1} to be captured")

    cam = CameraSource(0, capture=cap, timeout_s=WAIT_S)
    seen = []
    camera_runs_ahead()
    for f in cam:
        seen.append(int(f.rgb[0, 0, 0]))
        if cap.i < cap.n:
            camera_runs_ahead()  # a slow pipeline: the camera delivers 4 frames per frame handled
    cam.close()
    assert cam.lost  # unplugged: the loop ended by itself
    # each time, the newest of the 4 new frames is handed over and the other 3 are counted as dropped
    assert seen == list(range(3, 60, 4))
    assert cam.dropped == 45 and len(seen) + cam.dropped == 60


def test_camera_unplugged_and_plugged_back_in_reconnects():
    gate = threading.Semaphore(0)  # one frame at a time, whichever plug is in
    plugs = iter([FakeCapture(n=10, gate=gate), None, FakeCapture(n=10, gate=gate)])

    class Unplugged(FakeCapture):
        def isOpened(self):
            return False

    def opener():  # the first retry finds no device, the second finds it back, later ones none
        c = next(plugs, None)
        opened.append(c is not None)
        return c if c is not None else Unplugged()
    opened = []
    # retries: the first reconnection takes 2 of its 3 tries; after the second unplug the camera is
    # given up after 3 failed tries (counted, not timed: reconnect_s is only a generous outer bound)
    cam = CameraSource(0, capture=opener(), opener=opener, reconnect_s=WAIT_S, retry_s=0.0, retries=3,
                       timeout_s=WAIT_S)
    frames, values = [], []
    gate.release()
    for f in cam:
        frames.append(f.index)
        values.append(int(f.rgb[0, 0, 0]))
        gate.release()  # the next frame only once this one is handled: none dropped
    cam.close()
    assert cam.reconnects == 1 and cam.lost  # back once; gone for good after the second unplug
    assert opened == [True, False, True, False, False, False]  # the first plug, then 2 tries, then 3
    assert frames == list(range(20)) and values == list(range(10)) * 2 and cam.dropped == 0


def test_a_digit_that_is_not_a_number_is_no_camera_index():
    from tracker.runtime.sources import is_camera
    assert is_camera("0") and is_camera("/dev/video2") and not is_camera("²") and not is_camera("٣")


def test_missing_camera_is_a_clear_error():
    class Closed(FakeCapture):
        def isOpened(self):
            return False
    with pytest.raises(UserError, match="no camera"):
        CameraSource(7, capture=Closed())


def test_looping_replay_numbers_frames_and_reports_memory(tiny_bundle, data_dir, tmp_path):
    import shutil
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in (3, 8):
        shutil.copy(data_dir / "lmo" / "dev" / "rgb" / f"{i:06d}.png", folder)
    out = tmp_path / "run"
    s = track(TrackConfig(str(folder), str(tiny_bundle), out, calib=str(Path(__file__).resolve().parents[1] / "calib" / "lmo_kinect.yml"), rerun="off",
                              max_frames=5, loop=True), log=lambda m: None)
    assert s.frames == 5 and s.looped and s.rss_mb["current"] > 0
    rows = (out / "timings.csv").read_text().splitlines()[1:]
    assert [int(r.split(",")[0]) for r in rows] == [0, 1, 2, 3, 4]
    with pytest.raises(UserError, match="camera cannot be looped"):
        track(TrackConfig("0", str(tiny_bundle), tmp_path / "cam", loop=True), log=lambda m: None)


def _two_frames_and_a_corrupt_one(data_dir, folder):
    import shutil
    folder.mkdir()
    for i in (3, 8):
        shutil.copy(data_dir / "lmo" / "dev" / "rgb" / f"{i:06d}.png", folder)
    (folder / "000009.png").write_bytes(b"not a png at all")
    return str(Path(__file__).resolve().parents[1] / "calib" / "lmo_kinect.yml")


def test_a_run_that_fails_midway_keeps_its_summary(tiny_bundle, data_dir, tmp_path):
    calib = _two_frames_and_a_corrupt_one(data_dir, tmp_path / "imgs")
    out = tmp_path / "run"
    with pytest.raises(UserError, match="unreadable image"):
        track(TrackConfig(str(tmp_path / "imgs"), str(tiny_bundle), out, calib=calib, rerun="off"),
                  log=lambda m: None)
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 2 and "unreadable image" in s["error"] and not s["interrupted"]
    assert len((out / "timings.csv").read_text().splitlines()) == 3
    assert {e.im_id for e in read_results(out / "poses.csv")} <= {0, 1}


def test_an_interrupted_run_writes_its_summary_without_scoring(tiny_bundle, data_dir, tmp_path, monkeypatch):
    from tracker.runtime import sinks
    write = sinks.CsvSink.write

    def write_then_interrupt(self, *a, **kw):  # Ctrl-C while the second frame is being logged
        write(self, *a, **kw)
        if a[1] == 8:
            signal.raise_signal(signal.SIGINT)  # handled before it returns
    monkeypatch.setattr(sinks.CsvSink, "write", write_then_interrupt)
    out = tmp_path / "run"
    s = track(TrackConfig(str(data_dir / "lmo" / "dev"), str(tiny_bundle), out, rerun="off", max_frames=4),
                  log=lambda m: None)
    assert s.interrupted and s.frames == 2 and s.accuracy is None and s.error is None
    assert json.loads((out / "summary.json").read_text())["frames"] == 2


def test_finishing_a_run_defers_the_first_interrupt():
    from tracker.runtime.signals import Deferred as _Deferred
    said = []
    before = signal.getsignal(signal.SIGINT)  # SIG_IGN in a job started in the background
    # signal.raise_signal: the signal is raised in this thread and its Python handler has run when
    # the call returns (no waiting for a delivery)
    with _Deferred(said.append, "scoring") as d:
        signal.raise_signal(signal.SIGINT)  # the first: noted, not raised
        assert d.hit and said == ["scoring; interrupt again to skip it"]
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is before  # put back


def test_unknown_object_ids_are_refused(tiny_bundle, data_dir, tmp_path):
    with pytest.raises(UserError, match="--obj-ids 99: not objects of"):
        track(TrackConfig(str(data_dir / "lmo" / "dev"), str(tiny_bundle), tmp_path / "run", obj_ids=[1, 99]),
                  log=lambda m: None)
    assert not (tmp_path / "run").exists()


def test_rerun_serve_on_a_taken_port_is_one_clear_error(tmp_path):
    """rerun's own servers print errors of their own before raising; the port is checked first."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        assert port_taken(s.getsockname()[1])
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("0.0.0.0", RERUN_GRPC_PORT))
        except OSError:
            pytest.skip(f"port {RERUN_GRPC_PORT} is in use on this machine")
        s.listen()
        # (and 9090 where something else on this machine listens there)
        with pytest.raises(UserError, match=f"port {RERUN_GRPC_PORT}( and 9090)? already in use"):
            RerunSink("serve", tmp_path, {}, {}, np.eye(3), (640, 480))


SHIPPED, CALIB = REPO / "models" / "lmo", REPO / "calib" / "lmo_kinect.yml"


def _fake_cameras(monkeypatch, gate=None):
    """Camera sources open as gated fake captures (the test delivers their frames); returns the
    list of the sources opened. close_timeout_s=0: close() does not wait for the read in flight
    (the test lets it return, and then sees the thread end)."""
    from tracker.runtime import sources
    opened = []

    def fake_open(src, max_frames=None, **kw):
        cap = FakeCapture(n=10 ** 6, gate=gate, shape=(480, 640, 3), gate_timeout=None)  # (a daemon thread reads)
        cam = CameraSource(0, capture=cap, max_frames=max_frames,
                           timeout_s=WAIT_S, reconnect_s=0, close_timeout_s=0)
        opened.append(cam)
        return cam
    monkeypatch.setattr(sources, "open_source", fake_open)
    return opened


@pytest.mark.parametrize("bad", ["no --calib", "--video-out .gif", "--frames-out a file", "--rerun spawn, no display"])
def test_a_camera_run_that_fails_its_checks_never_opens_the_camera(bad, tmp_path, monkeypatch):
    """Every check the arguments allow comes before the source opens: a camera's capture thread
    is never started for a run that cannot run (it was left running before)."""
    opened = _fake_cameras(monkeypatch)
    (tmp_path / "a-file").write_text("")
    cfg = TrackConfig("0", str(SHIPPED), tmp_path / "run", calib=str(CALIB), rerun="off", overlay=False)
    cfg = {"no --calib": replace(cfg, calib=None), "--video-out .gif": replace(cfg, video_out=str(tmp_path / "r.gif")),
           "--frames-out a file": replace(cfg, frames_out=str(tmp_path / "a-file")),
           "--rerun spawn, no display": replace(cfg, rerun="spawn")}[bad]
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.raises(UserError):
        run_track(cfg, log=lambda m: None)
    # (before, a camera opened ahead of a failing check was left capturing)
    left_running = [c for c in opened if c._thread.is_alive() and not c._stop]
    assert not left_running and opened == [] and not (tmp_path / "run").exists()


def test_a_camera_run_that_fails_after_opening_closes_the_camera(tmp_path, monkeypatch):
    """A failure once the camera is open (here the pipeline, on the first frame): the run's summary
    says so, the camera is closed and its capture thread ends with the read in flight."""
    from tracker.runtime.pipeline import Pipeline
    gate = threading.Semaphore(0)
    opened = _fake_cameras(monkeypatch, gate)

    def broken(self, frame):
        raise RuntimeError("the pipeline broke")
    monkeypatch.setattr(Pipeline, "step", broken)
    out = tmp_path / "run"
    gate.release()  # the camera delivers one frame
    with pytest.raises(RuntimeError, match="the pipeline broke"):
        run_track(TrackConfig("0", str(SHIPPED), out, calib=str(CALIB), rerun="save", overlay=False),
                  log=lambda m: None)
    (cam,) = opened
    assert cam._stop  # closed ...
    assert cam.cap.released == 0  # ... but not released under the read in flight: the thread does it as it ends
    gate.release()  # the read in flight returns a frame; the thread, told to stop, ends
    cam._thread.join(WAIT_S)
    assert not cam.capturing and cam.cap.released == 1
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 0 and s["error"] == "RuntimeError: the pipeline broke" and not s["interrupted"]
    assert len((out / "timings.csv").read_text().splitlines()) == 1  # the header, complete and closed
