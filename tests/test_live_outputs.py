"""What a person watching the tracker sees and keeps: the annotated video and frames, the
per-pose confidence and how uncertain poses are drawn, the per-object status, the rerun
recording's panels, and the viewer modes (serve keeps the recording; spawn without a display)."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rerun as rr

from tracker.core.bop import Estimate, load_scene
from tracker.core.errors import UserError
from tracker.core.geometry import box_from_points, project
from tracker.core.meshes import load_models
from tracker.evaluation.scoring import ObjectEval, confidence_ranking, models_info_for, ranking_auc
from tracker.evaluation.track import track
from tracker.runtime.confidence import box_agreement, box_iou, code_similarity, confidence
from tracker.runtime.estimator import PoseEstimate
from tracker.runtime.loop import TrackConfig
from tracker.runtime.sinks import RerunSink, blueprint, port_taken, RERUN_GRPC_PORT, RERUN_WEB_PORT
from tracker.runtime.status import TrackStatus
from tracker.runtime.video import FrameWriter

FIX = Path(__file__).parent / "fixtures"


def test_track_writes_the_annotated_video_frames_status_and_confidences(tiny_bundle, data_dir, tmp_path):
    out, video, frames = tmp_path / "run", tmp_path / "run.mp4", tmp_path / "frames"
    track(TrackConfig(str(data_dir / "lmo" / "dev"), str(tiny_bundle), out, rerun="save", max_frames=3,
                      video_out=str(video), frames_out=str(frames)), log=lambda m: None)
    cap = cv2.VideoCapture(str(video))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 3 and (cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (640, 480)
    assert abs(cap.get(cv2.CAP_PROP_FPS) - 30.0) < 0.5  # the scene's rate
    cap.release()
    assert sorted(p.name for p in frames.iterdir()) == ["000003.png", "000008.png", "000017.png"]
    raw = cv2.imread(str(data_dir / "lmo" / "dev" / "rgb" / "000003.png"))
    drawn = cv2.imread(str(frames / "000003.png"))
    assert drawn.shape == raw.shape and np.abs(drawn.astype(int) - raw).mean() > 0.5  # annotated, not raw
    summary = json.loads((out / "summary.json").read_text())
    assert summary["video"] == str(video) and summary["frames_dir"] == str(frames)
    objs = summary["objects"]
    assert set(objs) == {"ape", "can", "cat", "driller", "duck", "eggbox", "glue", "holepuncher"}
    assert all(v["tracked"] + v["uncertain"] + v["not_found"] == 3 for v in objs.values())
    poses = (out / "poses.csv").read_text().splitlines()[1:]
    scores = [float(r.split(",")[3]) for r in poses]
    assert all(0 <= c <= 1 for c in scores) and len(set(scores)) > 1  # confidences, not a constant
    paths = set(rr.chunk.RrdReader(out / "recording.rrd").store().schema().entity_paths())
    assert "/status" in paths and any(p.startswith("/confidence/") for p in paths), sorted(paths)


def test_a_video_path_that_cannot_be_written_is_refused_before_the_run(tiny_bundle, data_dir, tmp_path):
    with pytest.raises(UserError, match=r"\.mp4, \.avi or \.mkv"):
        track(TrackConfig(str(data_dir / "lmo" / "dev"), str(tiny_bundle), tmp_path / "run", max_frames=1,
                          video_out=str(tmp_path / "run.gif")), log=lambda m: None)
    with pytest.raises(UserError, match="does not exist"):
        FrameWriter(tmp_path / "nowhere" / "run.mp4")
    assert not (tmp_path / "run").exists()


def test_frame_writer_keeps_the_first_size_and_counts_frames(tmp_path):
    w = FrameWriter(tmp_path / "v.avi", fps=12)
    w.write(0, np.zeros((60, 80, 3), np.uint8))
    w.write(1, np.full((120, 160, 3), 200, np.uint8))  # a source that changed size
    w.close()
    cap = cv2.VideoCapture(str(tmp_path / "v.avi"))
    sizes = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        sizes.append(f.shape[:2])
    assert sizes == [(60, 80), (60, 80)] and w.frames == 2 and abs(cap.get(cv2.CAP_PROP_FPS) - 12) < 0.5


def _pose(oid, score):
    return PoseEstimate(oid, np.eye(3), np.array([0, 0, 500.0]), score, np.array([0, 0, 10, 10.0]))


def test_status_tells_tracked_uncertain_lost_and_not_seen():
    st = TrackStatus({1: "ape", 5: "can", 6: "cat"}, [1, 5, 6], min_confidence=0.3)
    text = st.update(0, [_pose(1, 0.9), _pose(5, 0.1)])
    assert "tracked: ape 0.90" in text and "uncertain: can 0.10" in text and "not seen: cat" in text
    text = st.update(1, [_pose(5, 0.5)])
    assert "LOST: ape (last tracked at frame 0)" in text and "tracked: can 0.50" in text
    s = st.summary()
    assert s["ape"] == {"tracked": 1, "uncertain": 0, "not_found": 1, "state_at_end": "lost", "last_tracked_frame": 0}
    assert s["can"]["uncertain"] == 1 and s["can"]["state_at_end"] == "tracked"
    assert s["cat"] == {"tracked": 0, "uncertain": 0, "not_found": 2, "state_at_end": "not seen", "last_tracked_frame": None}


def test_the_confidence_checks():
    assert box_iou([0, 0, 10, 10], [5, 0, 10, 10]) == pytest.approx(50 / 150)
    assert box_iou([0, 0, 10, 10], [20, 20, 5, 5]) == 0.0
    pts = np.random.default_rng(0).uniform(-40, 40, (200, 3))
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    R, t = np.eye(3), np.array([10.0, -5, 600])
    box = box_from_points(project(pts, K, R, t))
    assert box_agreement(pts, K, R, t, box) == pytest.approx(1.0)
    assert box_agreement(pts, K, R, t + [60, 0, 0], box) < 0.3  # the pose's box moved off the detection
    assert box_agreement(pts, K, R, np.array([0, 0, -600.0]), box) == 0.0  # behind the camera
    codes = np.eye(4)
    assert code_similarity(np.array([[2.0, 0, 0, 0], [1.0, 1, 0, 0]]), codes) == pytest.approx([1.0, 2 ** -0.5])
    assert confidence(0.8, 0.5, 0.5) == pytest.approx(0.2) and confidence(1.2, -0.3, 1) == 0.0


def test_ranking_auc_counts_pairs():
    rng = np.random.default_rng(1)
    s, y = rng.integers(0, 5, 60).astype(float), rng.random(60) < 0.4  # many ties
    pairs = [(a > b) + 0.5 * (a == b) for a, ya in zip(s, y) if ya for b, yb in zip(s, y) if not yb]
    assert ranking_auc(s, y) == pytest.approx(np.mean(pairs))
    assert ranking_auc([1, 2], [True, True]) is None


def test_confidence_ranking_labels_each_estimate_by_its_own_error():
    scene = load_scene(FIX / "scene" / "000001", require_gt=True)
    models = load_models(FIX / "models")
    info = models_info_for(FIX / "models", FIX / "models" / "models_info.json")
    objects = {o: ObjectEval.from_info(o, np.asarray(m.mesh.vertices), info[o]) for o, m in models.items()}
    g = scene.gt[0][0]
    good = Estimate(0, 0, g.obj_id, 0.9, g.R, g.t, 0.0)
    bad = Estimate(0, 0, g.obj_id, 0.2, g.R, g.t + np.array([0, 0, 200.0]), 0.0)
    ghost = Estimate(0, 0, 99, 0.1, g.R, g.t, 0.0)  # an object that is not in the image
    by_im = {0: {g.obj_id: [good, bad], 99: [ghost]}}
    visib = {0: [1.0] * len(scene.gt[0])}
    r = confidence_ranking(by_im, scene, objects, visib, [0])
    assert r["n_estimates"] == 3 and r["n_good"] == 1 and r["auc"] == 1.0
    good.score = 0.0  # the good pose ranked last
    assert confidence_ranking(by_im, scene, objects, visib, [0])["auc"] == 0.0


def test_spawn_without_a_display_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr("sys.platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(UserError, match="no display.*--rerun serve.*--rerun save"):
        RerunSink("spawn", tmp_path, {}, {}, np.eye(3), (640, 480))


def _serve_or_skip(tmp_path, **kw):
    if port_taken(RERUN_GRPC_PORT) or port_taken(RERUN_WEB_PORT):
        pytest.skip("rerun's ports are in use on this machine")
    return RerunSink("serve", tmp_path, {}, {1: "ape"}, np.eye(3), (64, 48), **kw)


def test_serve_saves_the_recording_and_holds_until_told(tmp_path):
    sink = _serve_or_skip(tmp_path)
    try:
        assert sink.url.startswith(f"http://localhost:{RERUN_WEB_PORT}/?url=rerun+http://127.0.0.1:{RERUN_GRPC_PORT}")
        for i in range(3):
            sink.log_frame(i, np.zeros((48, 64, 3), np.uint8), None, [], [_pose(1, 0.7)], status=f"frame {i}")
            sink.log_timings({"total": 5.0}, 20.0)
        sink.close()
        assert port_taken(RERUN_GRPC_PORT) and port_taken(RERUN_WEB_PORT)  # still serving after the run
        said = []
        sink.hold(0.01, log=said.append)
        assert "still serving" in said[0] and "Ctrl-C" in said[0]
    finally:
        sink.stop()
    # both servers stopped with the hold: the gRPC server with the sink's recording, the web
    # viewer with its process
    assert not port_taken(RERUN_GRPC_PORT) and not port_taken(RERUN_WEB_PORT) and not sink.serving
    paths = set(rr.chunk.RrdReader(tmp_path / "recording.rrd").store().schema().entity_paths())
    assert {"/status", "/confidence/ape", "/timings/total_ms", "/timings/fps", "/timings/detect_ms"} <= paths


def test_a_serving_sink_left_by_an_error_stops_its_servers(tmp_path):
    with pytest.raises(RuntimeError, match="the run broke"):
        with _serve_or_skip(tmp_path) as sink:
            assert sink.serving and port_taken(RERUN_WEB_PORT)
            raise RuntimeError("the run broke")
    assert not sink.serving and not port_taken(RERUN_GRPC_PORT) and not port_taken(RERUN_WEB_PORT)


def _rows(rrd):
    """(entity path, is static, frame or None, {component: value}) for every row of a recording."""
    rows = []
    for chunk in rr.chunk.RrdReader(rrd).store().stream():
        batch = chunk.to_record_batch()
        cols = {n: batch.column(n).to_pylist() for n in batch.schema.names if ":" in n}
        frames = batch.column("frame").to_pylist() if "frame" in batch.schema.names else [None] * batch.num_rows
        for i, f in enumerate(frames):
            rows.append((str(chunk.entity_path), chunk.is_static, f, {k: v[i] for k, v in cols.items() if v[i] is not None}))
    return rows


def _meshes_drawn(rrd, frames) -> dict:
    """Which objects a viewer draws in the 3D view at each of ``frames``: the latest-at query of
    each object's mesh that rerun's viewer makes, computed from the recording's rows. A static
    mesh is drawn at every frame (a Clear cannot hide static data); a temporal one from the frame
    it is logged at until a Clear of it (or, recursive, of a parent) at a later frame."""
    rows = _rows(rrd)
    meshes = {p for p, _, _, c in rows if "Mesh3D:vertex_positions" in c}
    drawn = {f: set() for f in frames}
    for mesh in meshes:
        name = mesh.split("/")[3]  # /world/objects/<name>/mesh
        events = []
        for path, static, f, c in rows:
            if path == mesh and "Mesh3D:vertex_positions" in c:
                events.append((-1 if static else f, "mesh"))
            elif "Clear:is_recursive" in c and (path == mesh or (c["Clear:is_recursive"] and mesh.startswith(path + "/"))):
                assert not static
                events.append((f, "clear"))
        for k in frames:
            before = sorted(e for e in events if e[0] <= k)
            assert len({e[0] for e in before}) == len(before), f"a mesh and a Clear in one frame: {before}"
            if before and (before[-1][1] == "mesh" or (-1, "mesh") in before):
                drawn[k].add(name)
    return drawn


def test_rerun_draws_an_object_only_in_the_frames_it_is_tracked_in(tmp_path):
    """Lost objects used to stay where last seen (their last transform) and objects not found yet
    sat at the camera's origin (their meshes were static): now a frame draws what it tracks."""
    from trimesh.creation import box
    names = {1: "ape", 5: "can", 6: "cat"}
    meshes = {o: box((10, 10, 10)) for o in names}
    sink = RerunSink("save", tmp_path, meshes, names, np.eye(3), (64, 48), mesh_every=3)
    tracked = [[1], [], [1, 5], [5], [], [5], [5], [5], [5]]  # cat: never found
    for i, objs in enumerate(tracked):
        sink.log_frame(i, np.zeros((48, 64, 3), np.uint8), None, [], [_pose(o, 0.9) for o in objs])
    sink.close()
    rrd = tmp_path / "recording.rrd"
    drawn = _meshes_drawn(rrd, range(len(tracked)))
    assert drawn == {i: {names[o] for o in objs} for i, objs in enumerate(tracked)}
    # a long stretch in view: the mesh logged again every mesh_every frames (a late viewer of a
    # served run gets it after the server dropped the oldest data)
    can = sorted(f for p, _, f, c in _rows(rrd) if p == "/world/objects/can/mesh" and "Mesh3D:vertex_positions" in c)
    assert can == [2, 5, 8]


def test_two_sinks_in_one_process_write_their_own_recordings(tmp_path):
    """Each sink logs to a recording stream of its own: with rerun's global recording, the
    second sink took over the first one's logging."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = RerunSink("save", tmp_path / "a", {}, {1: "ape"}, np.eye(3), (64, 48))
    b = RerunSink("save", tmp_path / "b", {}, {1: "ape"}, np.eye(3), (64, 48))
    for i in range(3):  # interleaved
        a.log_frame(i, np.zeros((48, 64, 3), np.uint8), None, [], [], status=f"a {i}")
        b.log_frame(10 + i, np.zeros((48, 64, 3), np.uint8), None, [], [], status=f"b {i}")
    a.close()
    b.log_frame(13, np.zeros((48, 64, 3), np.uint8), None, [], [], status="b 3")  # a closed, b goes on
    b.close()
    texts = {k: sorted((f, c["TextDocument:text"]) for p, _, f, c in _rows(tmp_path / k / "recording.rrd")
                       if p == "/status") for k in "ab"}
    assert texts == {"a": [(i, [f"a {i}"]) for i in range(3)], "b": [(10 + i, [f"b {i}"]) for i in range(4)]}


def _views(container):
    out = []
    for x in container.contents:
        out += _views(x) if hasattr(x, "column_shares") else [(type(x).__name__, str(x.origin))]
    return out


def test_the_blueprint_puts_the_overlay_first_and_the_3d_view_under_world():
    """The 3D view's origin is /world: the 2D overlay outside it raised 'requires a pinhole ancestor'."""
    assert _views(blueprint({1: "ape"}).root_container) == [
        ("Spatial2DView", "overlay"), ("TextDocumentView", "status"), ("Spatial3DView", "world"),
        ("TimeSeriesView", "confidence"), ("TimeSeriesView", "timings")]
    assert _views(blueprint({}, overlay=False).root_container)[0] == ("Spatial2DView", "world/camera/image")
