"""The tracker driven frame by frame (runtime.pipeline), and the run loop when the camera is
lost midway. Uses the small fixtures in tests/fixtures and the shipped bundle only (no shared data)."""
import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO
from tracker.core.bop import load_scene
from tracker.core.manifest import ObjectEntry
from tracker.core.meshes import load_models
from tracker.runtime.estimator import Detection, PoseEstimate
from tracker.runtime.pipeline import BoxSchedule, GtBoxes, Pipeline

FIX = Path(__file__).parent / "fixtures"


class _Bundle:
    objects = [ObjectEntry(1, "m/1.ply", 74.8, "box"), ObjectEntry(2, "m/2.ply", 58.3, "cylinder")]


class OracleEstimator:
    """Stands in for the pose estimator: the ground-truth pose of the object behind each box,
    so the test sees what the pipeline does around it (boxes, filtering, smoothing, overlay)."""
    bundle = _Bundle()

    def __init__(self, scene):
        self.scene, self.calls = scene, []

    def estimate(self, rgb, K, dets, timings=None):
        self.calls.append([d.obj_id for d in dets])
        if timings is not None:
            timings.update(encode=1.0, regress=0.5)
        gt = {g.obj_id: g for g in self.scene.gt[self.frame]}
        return [PoseEstimate(d.obj_id, gt[d.obj_id].R, gt[d.obj_id].t, d.score, d.box) for d in dets]


@pytest.fixture()
def scene():
    return load_scene(FIX / "scene" / "000001", require_gt=True)


def _frames(scene):
    from tracker.runtime.sources import BopSceneSource
    return list(BopSceneSource(scene.root))


def test_the_pipeline_steps_frame_by_frame_with_ground_truth_boxes(scene):
    est = OracleEstimator(scene)
    boxes_of = {i: [(np.asarray(g.info["bbox_visib"], float), g.info["visib_fract"]) for g in scene.gt[i]]
                for i in scene.gt}
    meshes = {k: m.mesh for k, m in load_models(FIX / "models").items()}
    p = Pipeline(est, GtBoxes(boxes_of, known=[1, 2]), meshes=meshes, overlay_downscale=1)
    results = []
    for f in _frames(scene):
        est.frame = f.index
        results.append(p.step(f))
    p.close()
    a, b = results
    assert (a.index, b.index) == (0, 1) and a.box_source == b.box_source == "gt"
    assert est.calls == [[1, 2], [1]]  # the cylinder of frame 1 is 4 % visible: under the 10 % floor
    assert all(d.exact for d in a.detections)
    assert set(a.ms) >= {"undistort", "detect", "encode", "regress", "render"}
    assert np.allclose(a.K, scene.K(0)) and a.rgb.shape == (120, 160, 3)
    x, y, w, h = (int(v) for v in boxes_of[0][0][0])
    inside = np.abs(a.overlay[y:y + h, x:x + w].astype(int) - a.rgb[y:y + h, x:x + w].astype(int)).mean()
    outside = np.abs(a.overlay[:10, :10].astype(int) - a.rgb[:10, :10].astype(int)).mean()
    assert inside > 10 and outside == 0  # the meshes drawn where the objects are, the rest untouched


def test_the_pipeline_with_a_detector_schedule_reuses_poses_between_detections(scene):
    est = OracleEstimator(scene)
    boxes_seen = []

    def detector(rgb):
        boxes_seen.append(rgb.shape)
        return [Detection(1, np.asarray(scene.gt[0][0].info["bbox_visib"], float), 0.9)]
    pts = {1: np.asarray(load_models(FIX / "models", [1])[1].vertices)}
    p = Pipeline(est, BoxSchedule(detector, 2, pts), meshes=None)
    f0 = _frames(scene)[0]
    est.frame = 0
    r0, r1 = p.step(f0), p.step(f0)
    assert (r0.box_source, r1.box_source) == ("detector", "pose") and len(boxes_seen) == 1
    assert r0.overlay is None and r0.poses[0].score == 0.9
    # the box predicted from the first pose covers the object's true box
    bx, by, bw, bh = r1.detections[0].box
    gx, gy, gw, gh = scene.gt[0][0].info["bbox_visib"]
    assert abs(bx - gx) <= 2 and abs(by - gy) <= 2 and abs(bw - gw) <= 3 and abs(bh - gh) <= 3
    p.reset()
    assert p.step(f0).box_source == "detector"  # a new shot runs the detector again


def test_a_camera_lost_midway_ends_the_run_cleanly_with_its_files(tmp_path, monkeypatch, capsys):
    """A camera that delivers 4 frames, then is unplugged. It delivers each frame only once the
    run has logged the one before (the gated fake capture of test_track): the run handles all
    4, drops none, and ends by itself, however slow or busy the machine."""
    import threading

    from tests.test_track import WAIT_S, FakeCapture
    from tracker.cli import main
    from tracker.runtime import sinks, sources
    gate = threading.Semaphore(0)
    write = sinks.CsvSink.write

    def write_then_next_frame(self, *a, **kw):
        write(self, *a, **kw)
        gate.release()

    def fake_open(src, max_frames=None, **kw):
        return sources.CameraSource(0, capture=FakeCapture(n=4, gate=gate, shape=(480, 640, 3)), max_frames=max_frames,
                                    timeout_s=WAIT_S, reconnect_s=0)
    monkeypatch.setattr(sources, "open_source", fake_open)
    monkeypatch.setattr(sinks.CsvSink, "write", write_then_next_frame)
    out = tmp_path / "run"
    gate.release()  # the first frame
    rc = main(["track", "--source", "0", "--model", str(REPO / "models" / "lmo"), "--calib",
               str(REPO / "calib" / "lmo_kinect.yml"), "--out", str(out), "--rerun", "off", "--no-overlay"])
    err = capsys.readouterr().err
    assert rc == 0 and "camera stopped delivering frames" in err
    s = json.loads((out / "summary.json").read_text())
    assert s["camera_lost"] and not s["interrupted"] and s["error"] is None
    assert s["frames"] == 4 and s["dropped_frames"] == 0
    assert "accuracy" not in s  # a camera has no ground truth
    timings = (out / "timings.csv").read_text().splitlines()
    assert len(timings) == 1 + 4 and timings[-1].count(",") == timings[0].count(",")  # complete rows, closed
    assert (out / "poses.csv").read_text().startswith("scene_id,im_id,obj_id,score,R,t,time")


class DoubtfulEstimator(OracleEstimator):
    """The oracle's poses with a confidence of 0.1."""

    def estimate(self, rgb, K, dets, timings=None):
        return [PoseEstimate(p.obj_id, p.R, p.t, 0.1, p.box) for p in super().estimate(rgb, K, dets, timings)]


def test_a_pose_below_the_confidence_threshold_is_drawn_as_an_outline_only(scene):
    boxes_of = {i: [(np.asarray(g.info["bbox_visib"], float), g.info["visib_fract"]) for g in scene.gt[i]]
                for i in scene.gt}
    meshes = {k: m.mesh for k, m in load_models(FIX / "models").items()}
    f0 = _frames(scene)[0]
    x, y, w, h = (int(v) for v in boxes_of[0][0][0])
    changed = {}
    for name, est in (("sure", OracleEstimator(scene)), ("doubtful", DoubtfulEstimator(scene))):
        est.frame = 0
        p = Pipeline(est, GtBoxes(boxes_of, known=[1, 2]), meshes=meshes, overlay_downscale=1, min_confidence=0.3)
        r = p.step(f0)
        p.close()
        changed[name] = np.abs(r.overlay.astype(int) - r.rgb.astype(int))[y:y + h, x:x + w].mean()
    # the rendered object changes much of its box; a dimmed outline only a thin band of it
    assert changed["sure"] > 10 and 0 < changed["doubtful"] < changed["sure"] / 3, changed
