"""A tiny end-to-end training per method: the code paths, export, bundle safety and the
camera independence of the pose head. Accuracy is measured by `app.py eval`, not here."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tests.conftest import REPO  # noqa: E402
from tracker.core.bop import load_scene  # noqa: E402
from tracker.core.bundle import open_bundle  # noqa: E402
from tracker.core.errors import UserError  # noqa: E402
from tracker.runtime.estimator import Detection, PoseEstimator  # noqa: E402
from tracker.core.geometry import project, ray_rotation, rotation_error_deg, scale_intrinsics  # noqa: E402
from tracker.training.synth.engine import SynthConfig, generate  # noqa: E402
from tracker.training.train import train_bundle  # noqa: E402

OBJS = [1, 9]


@pytest.fixture(scope="module")
def tiny_split(tmp_path_factory, data_dir):
    out = tmp_path_factory.mktemp("tiny_synth")
    cfg = SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                      obj_ids=OBJS, seed=2, objects_per_image=(2, 2))
    generate(cfg, out, 6, workers=1, progress=False)
    return out


def _train(split, out, method, encoder="plain"):
    return train_bundle(split, out, method=method, size=32, latent=16, max_steps=6, reg_epochs=10,
                        models_info_path=None, log=lambda *a: None, encoder=encoder)


@pytest.fixture(scope="module")
def bundles(tiny_split, tmp_path_factory):
    root = tmp_path_factory.mktemp("bundles")
    out = {m: (_train(tiny_split, root / m, m), root / m) for m in ("dalsr", "cvml", "cvam")}
    out["cvam-resnet"] = (_train(tiny_split, root / "cvam-resnet", "cvam", "resnet"), root / "cvam-resnet")
    return out


@pytest.mark.parametrize("method", ["dalsr", "cvml", "cvam", "cvam-resnet"])
def test_every_method_trains_exports_and_runs(bundles, tiny_split, method):
    manifest, path = bundles[method]
    assert manifest.method == method.split("-")[0] and manifest.pose_prior == "table"
    assert manifest.encoder == ("resnet" if method.endswith("resnet") else "plain")
    assert manifest.training["onnx_max_abs_diff"] <= 1e-4
    import onnx
    ops = {n.op_type for n in onnx.load(str(path / "encoder.onnx")).graph.node}
    assert "Conv" in ops and "BatchNormalization" not in ops  # trained with BatchNorm, folded into the convs
    import torch
    state = torch.load(path.parent / f"{path.name}.work" / "ae_best.pt", weights_only=True)
    assert any(k.endswith("norm.running_var") for k in state) and manifest.training["ae_norm"] == "batch"
    assert {o.id for o in manifest.objects} == set(OBJS)
    est = PoseEstimator(path)
    scene = load_scene(tiny_split / "000000", require_gt=True)
    img = scene.read_rgb(0)
    dets = [Detection(g.obj_id, np.array(g.info["bbox_visib"], float)) for g in scene.gt[0]
            if g.info["visib_fract"] > 0.1]
    for mode in ("regression", "aae"):
        poses = est.estimate(img, scene.K(0), dets, mode=mode)
        assert len(poses) == len(dets)
        for p in poses:
            assert np.allclose(p.R @ p.R.T, np.eye(3), atol=1e-6) and 10 < p.t[2] < 10000


def test_estimator_leaves_the_process_thread_pools_alone(bundles, tiny_split):
    """The one-thread cap on BLAS/OpenMP holds only while the regressors run, never leaking
    into the rest of the process (torch training in the same process, for one)."""
    from threadpoolctl import threadpool_info
    before = [(p["filepath"], p["num_threads"]) for p in threadpool_info()]
    est = PoseEstimator(bundles["cvam"][1])
    scene = load_scene(tiny_split / "000000", require_gt=True)
    dets = [Detection(g.obj_id, np.array(g.info["bbox_visib"], float)) for g in scene.gt[0]]
    assert est.estimate(scene.read_rgb(0), scene.K(0), dets)
    after = {p["filepath"]: p["num_threads"] for p in threadpool_info()}
    assert all(after[f] == n for f, n in before if f in after)


def test_tampered_or_missing_files_are_refused(bundles, tmp_path):
    _, src = bundles["cvam"]
    b = tmp_path / "b"
    shutil.copytree(src, b)
    with open(b / "pose_head.npz", "ab") as f:
        f.write(b"\0")
    with pytest.raises(UserError, match="SHA-256"):
        open_bundle(b)
    shutil.rmtree(b)
    shutil.copytree(src, b)
    (b / "encoder.onnx").unlink()
    with pytest.raises(UserError, match="missing"):
        PoseEstimator(b)
    shutil.rmtree(b)
    shutil.copytree(src, b)
    m = json.loads((b / "manifest.json").read_text())
    m["artefacts"]["pose_head"] = "../../evil.json"
    (b / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="not hashed"):
        PoseEstimator(b)


def test_unknown_object_is_a_clear_error(bundles, tiny_split):
    est = PoseEstimator(bundles["cvam"][1])
    img = load_scene(tiny_split / "000000").read_rgb(0)
    with pytest.raises(UserError, match="not in this bundle"):
        est.estimate(img, np.eye(3), [Detection(42, np.array([10, 10, 50, 50.0]))])
    assert est.estimate(img, np.eye(3), []) == []


def test_eval_scores_a_bundle_of_some_of_the_scenes_objects(bundles, data_dir, tmp_path, capsys):
    """A bundle of two of LM-O's eight objects (``build --objects``) is scored on LM-O frames:
    on their instances alone, the other six still hiding parts of them (meshes from BOP's
    models/ above the scene), or, with no meshes of the others to be found, left out (said)."""
    from tracker.evaluation.evaluate import evaluate
    from tracker.evaluation.scoring import score_results
    dev = data_dir / "lmo" / "dev"
    m = evaluate(bundles["cvam"][1], dev, tmp_path / "m.json", max_frames=3, progress=False)
    assert m["scored_obj_ids"] == OBJS and set(m["per_object"]) == {str(o) for o in OBJS}
    assert m["visibility_meshes"] == str((data_dir / "lmo" / "models").resolve())
    assert "scoring objects [1, 9] only" in capsys.readouterr().err
    ids = sorted(load_scene(dev).gt)[:3]  # the same instances as a bundle of all eight is scored on
    every = score_results(m["bop_csv"], dev, data_dir / "lmo" / "models", models_info=REPO / "models" / "lmo_models_info.json",
                          im_ids=ids)
    assert m["n_gt"] == sum(every["per_object"][str(o)]["n_gt"] for o in OBJS) > 0
    for o in OBJS:
        assert m["per_object"][str(o)]["ar_mspd"] == pytest.approx(every["per_object"][str(o)]["ar_mspd"])
    alone = tmp_path / "scene"  # no models/ beside or above it
    shutil.copytree(dev, alone)
    m2 = evaluate(bundles["cvam"][1], alone, tmp_path / "m2.json", max_frames=3, progress=False)
    assert "left out of the visibility" in capsys.readouterr().err
    assert m2["n_gt"] >= m["n_gt"] and m2["visibility_meshes"].endswith("meshes")
    with pytest.raises(UserError, match="--gt-models"):
        evaluate(bundles["cvam"][1], dev, tmp_path / "m3.json", max_frames=3, progress=False, gt_models=tmp_path)


def test_kl_warmup_raises_the_kl_weight_step_by_step(tiny_split, tmp_path, monkeypatch):
    from tracker.training.nets import fit
    assert fit.kl_weight(0) == fit.kl_weight(10**6) == fit.KL_ALPHA
    assert fit.kl_weight(0, 1000) == 0.0 and fit.kl_weight(250, 1000) == pytest.approx(fit.KL_ALPHA / 4)
    assert fit.kl_weight(1000, 1000) == fit.kl_weight(5000, 1000) == fit.KL_ALPHA
    seen = []
    real = fit.kl_weight
    monkeypatch.setattr(fit, "kl_weight", lambda step, warmup=0: seen.append((step, warmup)) or real(step, warmup))
    train_bundle(tiny_split, tmp_path / "w", method="cvam", size=32, latent=16, max_steps=4, reg_epochs=5,
                 models_info_path=None, log=lambda *a: None, kl_warmup=7)
    steps = [st for st, _ in seen]
    assert all(w == 7 for _, w in seen) and steps == [0, 1, 2, 3]  # one per step, from 0
    assert np.float64(5e-324) > 0  # the subnormal flush of training does not outlive it


def test_pose_does_not_depend_on_camera_or_resolution(bundles, tiny_split):
    """The same crop content seen by a camera of another resolution, or with the principal
    point elsewhere, gives the same pose: box features are normalised by the intrinsics.
    (Same latent code on purpose: resampled crops through a seconds-trained encoder would
    test the encoder's noise, not the features.)"""
    est = PoseEstimator(bundles["cvam"][1])
    scene = load_scene(tiny_split / "000000", require_gt=True)
    img, K = scene.read_rgb(1), scene.K(1)
    g = max(scene.gt[1], key=lambda g: g.info["visib_fract"])
    box = np.array(g.info["bbox_visib"], float)
    mu = est.encode(est.crops(img, [box]), [g.obj_id])
    R1, t1 = est.head.predict(mu, [g.obj_id], box[None], K)
    # 2x resolution: intrinsics and box scale together (a BOP box's left edge x - 0.5 maps to
    # 2x - 0.5, so the box simply doubles)
    K2 = scale_intrinsics(K, (640, 480), (1280, 960))
    box2 = box * 2
    R2, t2 = est.head.predict(mu, [g.obj_id], box2[None], K2)
    # another camera: focal lengths and principal point elsewhere, the box where it projects
    K3 = np.array([[900.0, 0, 300.0], [0, 910.0, 260.0], [0, 0, 1]])
    c = np.array([box[0] + box[2] / 2 - 0.5, box[1] + box[3] / 2 - 0.5])
    c3 = (c - K[:2, 2]) / np.diag(K)[:2] * np.diag(K3)[:2] + K3[:2, 2]
    s3 = np.diag(K3)[:2] / np.diag(K)[:2]
    w3, h3 = box[2] * s3[0], box[3] * s3[1]
    box3 = np.array([c3[0] - w3 / 2 + 0.5, c3[1] - h3 / 2 + 0.5, w3, h3])
    R3, t3 = est.head.predict(mu, [g.obj_id], box3[None], K3)
    for R, t, KK in ((R2, t2, K2), (R3, t3, K3)):
        # the centre offset is in units of the box's longer side, which anisotropic focal
        # lengths change slightly; the translation stays within 1 % of the distance ...
        assert np.linalg.norm(t1[0] - t[0]) < 0.01 * t1[0, 2]
        # ... and the rotation relative to the viewing ray through that centre is the same
        allo = [ray_rotation(project(np.zeros((1, 3)), k, None, tt)[0], k).T @ RR
                for RR, tt, k in ((R1[0], t1[0], K), (R[0], t[0], KK))]
        assert np.allclose(allo[0], allo[1], atol=1e-9)
    assert np.allclose(t1, t2, rtol=1e-9)
    assert np.allclose(R1, R2, atol=1e-9)


def test_training_resumes_from_its_checkpoint(tiny_split, tmp_path):
    out = tmp_path / "m"
    _train(tiny_split, out, "cvml")
    ck = tmp_path / "m.work" / "ae_checkpoint.pt"
    assert ck.is_file()
    logs = []
    m = train_bundle(tiny_split, out, method="cvml", size=32, latent=16, max_steps=9, reg_epochs=10, log=logs.append)
    assert any(str(ln).startswith("resumed from") for ln in logs)
    assert m.training["ae_epochs"] == 9 and m.training["ae_max_steps"] == 9  # one batch an epoch: 6 + 3 more
    with pytest.raises(UserError, match="checkpoint of another network"):
        _train(tiny_split, out, "dalsr")  # same --out, another network: a clear error, no traceback


def test_training_can_start_from_another_runs_weights(tiny_split, tmp_path):
    import json

    import torch
    _train(tiny_split, tmp_path / "a", "cvml")
    src = tmp_path / "a.work" / "ae_checkpoint.pt"
    logs = []
    train_bundle(tiny_split, tmp_path / "b", method="cvml", size=32, latent=16, max_steps=2, reg_epochs=5,
                 init_from=src, log=logs.append)
    assert any(str(ln).startswith("started from the weights of") for ln in logs)
    m = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert m["training"]["init_from"] == str(src)
    from tracker.training.nets.autoencoder import AutoEncoder
    a = torch.load(src, weights_only=True)
    b = torch.load(tmp_path / "b.work" / "ae_checkpoint.pt", weights_only=True)
    assert b["hist"]["epoch"][0] == 0 and len(b["hist"]["epoch"]) == b["epoch"] + 1  # a new history
    assert len(a["hist"]["epoch"]) == a["epoch"] + 1  # the source's own is left as it was
    # a tiny budget moves the weights a little: far closer to the source than a fresh network is
    torch.manual_seed(123)
    fresh = AutoEncoder("cvml", 32, 16, len(OBJS)).state_dict()

    def dist(x, y):
        keys = [k for k in x if x[k].dtype.is_floating_point]
        return float(sum((x[k] - y[k]).abs().sum() for k in keys) / sum(x[k].numel() for k in keys))
    assert dist(b["model"], a["model"]) < 0.3 * dist(fresh, a["model"])
    with pytest.raises(UserError, match="no such checkpoint"):
        _train_from(tiny_split, tmp_path / "c", "cvml", tmp_path / "missing.pt")
    with pytest.raises(UserError, match="checkpoint of another network"):
        _train_from(tiny_split, tmp_path / "d", "dalsr", src)  # another network's weights


def _train_from(split, out, method, init_from):
    return train_bundle(split, out, method=method, size=32, latent=16, max_steps=2, reg_epochs=5,
                        init_from=init_from, log=lambda *a: None)


def test_ablate_tables_on_a_tiny_bundle(tiny_bundle, tmp_path):
    import json

    from tracker.research.ablate import ablate
    res = ablate(tiny_bundle, tiny_bundle.parent / "split", tmp_path / "ablate.json", mlp_minutes=0.01,
                 log=lambda *a: None)
    assert json.loads((tmp_path / "ablate.json").read_text())["table_4_1"] == res["table_4_1"]
    names = [r["method"] for r in res["table_4_1"]]
    assert names == ["MLP + 6D", "RF + 6D", "MLP + quaternion", "RF + quaternion", "MLP + axis-angle",
                     "RF + axis-angle", "NNS (codebook, cosine)"]
    for r in res["table_4_1"]:
        assert 0 <= r["add_recall_true_t"] <= 1 and 0 <= r["re_median_deg"] <= 180
    assert [r["method"] for r in res["table_4_2a"]] == ["MLP", "RF", "KNN", "box centre"]
    assert all(r["centre_err_mean_px"] >= 0 for r in res["table_4_2a"])
    assert [r["method"] for r in res["table_4_2b"]] == ["MLP", "RF", "KNN", "trees on estimated rotation",
                                                        "MLP + trees (log average)"]
    assert all(np.isfinite(r["tz_err_mean_mm"]) for r in res["table_4_2b"])


def test_report_on_a_tiny_bundle(tiny_bundle, tmp_path):
    from tracker.evaluation.report import build_report
    from tracker.core.paths import DEMO_RECORDING
    path = build_report(tiny_bundle, DEMO_RECORDING, tmp_path / "rep", max_frames=3, log=lambda *a: None)
    md = path.read_text()
    for head in ("Table 5.6", "Table 5.7", "Figure 5.3", "Tables 4.1 and 4.2", "t-SNE"):
        assert head in md
    assert "genus 2" in md or "can 2" in md  # the can's genus, from its mesh
    for png in ("recall_vs_visibility.png", "tsne_objects.png", "tsne_genus.png"):
        assert (tmp_path / "rep" / png).stat().st_size > 1000
    assert (tmp_path / "rep" / "eval_gt_aae.json").is_file()


def test_report_reuses_evaluations_only_of_the_same_bundle(tiny_bundle, tmp_path):
    from tracker.evaluation.report import build_report
    from tracker.core.paths import DEMO_RECORDING
    out = tmp_path / "rep"
    build_report(tiny_bundle, DEMO_RECORDING, out, max_frames=1, log=lambda *a: None)
    p = out / "eval_gt_regression.json"
    m = json.loads(p.read_text())
    m["marker"] = 1
    p.write_text(json.dumps(m))
    build_report(tiny_bundle, DEMO_RECORDING, out, reuse=True, max_frames=1, log=lambda *a: None)
    assert json.loads(p.read_text())["marker"] == 1  # the same bundle: reused
    m["bundle_manifest_sha256"] = "0" * 64           # made for the bundle as it was before a change
    p.write_text(json.dumps(m))
    build_report(tiny_bundle, DEMO_RECORDING, out, reuse=True, max_frames=1, log=lambda *a: None)
    assert "marker" not in json.loads(p.read_text())  # evaluated again


def test_crop_caches_are_named_for_their_split(tmp_path, monkeypatch):
    from tracker.training.crops import crops_cache_path
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    monkeypatch.chdir(tmp_path)
    a = crops_cache_path("w", tmp_path / "a", 64, 0)
    assert crops_cache_path("w", "a", 64, 0) == a  # the same folder however it is spelt
    assert crops_cache_path("w", tmp_path / "b", 64, 0) != a  # retrained on other data: not the old crops
    assert crops_cache_path("w", "a", 64, 0, jitter=False) != a != crops_cache_path("w", "a", 64, 1)
    assert crops_cache_path("w", "a", 64, 0, jitter_scale=0.08) == a  # the default's name is unchanged
    assert crops_cache_path("w", "a", 64, 0, jitter_scale=0.12) != a  # other box noise: other crops
    scene = tmp_path / "a" / "000000"
    shutil.copytree(Path(__file__).parent / "fixtures" / "scene" / "000001", scene)
    b = crops_cache_path("w", "a", 64, 0)
    assert b != a and crops_cache_path("w", "a", 64, 0) == b  # named for what the split holds, stably
    gt = json.loads((scene / "scene_gt.json").read_text())
    gt[next(iter(gt))][0]["cam_t_m2c"][2] += 1.0  # rendered again into the same folder, other poses
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    assert crops_cache_path("w", "a", 64, 0) != b  # not the old split's crops


def test_distance_knn_equals_scikit_learns_brute_force():
    from sklearn.neighbors import KNeighborsRegressor

    from tracker.training.fit_heads import KNNRegressor as DistanceKNN
    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(2000, 12)), rng.normal(size=2000)
    m = DistanceKNN(k=6, box_weight=2.5).fit(X, y)
    Q = rng.normal(size=(700, 12))  # more than one chunk of queries
    Q[3] = X[10]  # a training point as a query
    ref = KNeighborsRegressor(6, weights="distance", algorithm="brute").fit(
        m._prep(X).astype(np.float32), y.astype(np.float32)).predict(m._prep(Q).astype(np.float32))
    np.testing.assert_allclose(m.predict(Q), ref, atol=1e-5)
    # several k from one neighbour search: each as a KNN fitted with that k predicts
    many = m.predict_ks(Q, [1, 3, 6, 20])
    for k in (1, 3, 6, 20):
        np.testing.assert_allclose(many[k], DistanceKNN(k=k, box_weight=2.5).fit(X, y).predict(Q), atol=1e-12)
    assert not np.allclose(many[1], many[20])


def _distance_case(X, y):
    """Validation arguments of choose_distance for crops at the image centre with log(Tz size) = y."""
    from tracker.core.geometry import translation_from_centre
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    size = np.full(len(y), 0.1)
    centre = np.tile([320.0, 240.0], (len(y), 1))
    t = np.stack([translation_from_centre(c, z, K) for c, z in zip(centre, np.exp(y) / size)])
    return size, centre, t, np.repeat(K[None], len(y), 0)


def test_choose_distance_keeps_the_head_with_the_lower_validation_error(monkeypatch):
    import tracker.training.train
    from tracker.training.fit_heads import KNNRegressor as DistanceKNN, NumpyMLP
    from tracker.training.train import choose_distance
    rng = np.random.default_rng(0)
    X = rng.normal(size=(1500, 20)).astype(np.float32)
    w = rng.normal(size=20) * 0.05
    y = 6.0 + X @ w  # smooth in 20 dimensions: an MLP generalises, nearest neighbours do not
    tr, va = np.arange(1200), np.arange(1200, 1500)
    # epochs, not minutes (reg_epochs: no time budget), so that a busy machine fits the same MLP:
    # 150 epochs give about 37 mm against the KNN's 442 (50 epochs are still worse than the KNN)
    m, info = choose_distance(X[tr], y[tr], X[va], y[va], *_distance_case(X[va], y[va]), reg_minutes=float("inf"),
                              reg_epochs=150, log=lambda *a: None)
    assert isinstance(m, NumpyMLP) and info["head"] == "mlp"
    assert info["val_te_median_mm"] < 0.5 * info["knn"]["val_te_median_mm"]
    # arbitrary targets asked again at the training points: only the neighbours remember them
    y2 = 6.0 + rng.normal(size=1500) * 0.3
    m, info = choose_distance(X[tr], y2[tr], X[tr[:300]], y2[tr[:300]], *_distance_case(X[tr[:300]], y2[tr[:300]]),
                              reg_minutes=float("inf"), reg_epochs=20, log=lambda *a: None)
    assert isinstance(m, DistanceKNN) and info["head"] == "knn" and info["val_te_median_mm"] < 1e-3
    assert info["knn"]["rows"] == 1200 and len(m.X_) == 1200
    # a large training set: the KNN keeps a random subset, so the bundle stays small
    monkeypatch.setattr(tracker.training.train, "KNN_MAX_ROWS", 500)
    m, info = choose_distance(X[tr], y2[tr], X[tr[:300]], y2[tr[:300]], *_distance_case(X[tr[:300]], y2[tr[:300]]),
                              reg_minutes=float("inf"), reg_epochs=20, log=lambda *a: None)
    assert info["knn"]["rows"] == 500 and info["knn"]["val_te_median_mm"] > 1e-3


class _Const:
    def __init__(self, value):
        self.value = np.asarray(value, dtype=float)

    def predict(self, X):
        return np.repeat(self.value[None], len(X), 0)


def test_pose_head_turns_ray_frame_rotations_into_the_camera_frame():
    from scipy.spatial.transform import Rotation

    from tracker.core.geometry import box_offset_of_centre, ray_rotation
    from tracker.runtime.heads import PoseHead
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    R_a = Rotation.from_euler("xyz", [20, -35, 110], degrees=True).as_matrix()
    boxes = np.array([[300.0, 220, 50, 45], [10, 15, 60, 60], [560, 400, 70, 70]])
    off = np.array([0.05, -0.1])
    head = PoseHead([1], _Const(R_a), _Const(off), _Const(np.log(500.0)), rotation_frame="ray")
    R, t = head.predict(np.zeros((3, 4)), [1, 1, 1], boxes, K)
    centres = np.stack([c for c in (boxes[:, :2] + boxes[:, 2:] / 2 - 0.5)]) + off * boxes[:, 2:].max(1)[:, None]
    assert np.allclose(box_offset_of_centre(boxes, centres), off)
    assert np.allclose(R, ray_rotation(centres, K) @ R_a)
    # the object lies on the ray through its estimated centre, as the rotation assumed
    assert np.allclose(np.swapaxes(ray_rotation(centres, K), 1, 2) @ t[..., None],
                       np.c_[np.zeros((3, 2)), np.linalg.norm(t, axis=1)][..., None], atol=1e-6)
    assert rotation_error_deg(R[2], R_a) > 20  # a corner object is seen turned
    # an MLP distance head predicts (N, 1): the same translations
    head_mlp = PoseHead([1], _Const(R_a), _Const(off), _Const([np.log(500.0)]), rotation_frame="ray")
    assert np.allclose(head_mlp.predict(np.zeros((3, 4)), [1, 1, 1], boxes, K)[1], t)
    # a head pickled before the option existed predicts camera-frame rotations, as trained
    del head.__dict__["rotation_frame"]
    R_old, t_old = head.predict(np.zeros((3, 4)), [1, 1, 1], boxes, K)
    assert np.allclose(R_old, R_a) and np.allclose(t_old, t)


class _Recording(_Const):
    def predict(self, X):
        self.X = np.array(X)
        return super().predict(X)[:, 0]


def test_distance_from_rotation_is_averaged_with_the_latent_distance_in_log_space():
    from scipy.spatial.transform import Rotation

    from tracker.core.geometry import rot6d_from_matrix
    from tracker.runtime.heads import PoseHead, apparent_size
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    R_a = Rotation.from_euler("xyz", [20, -35, 110], degrees=True).as_matrix()
    boxes = np.array([[300.0, 220, 50, 45], [10, 15, 60, 60]])
    latent, by_rotation = 50.0, 200.0  # Tz * sqrt(w' h') from each head (mm)
    by_r = _Recording([np.log(by_rotation)])
    head = PoseHead([3, 7], _Const(R_a), _Const([0.0, 0.0]), _Const([np.log(latent)]), rotation_frame="ray",
                    distance_by_rotation=by_r)
    _, t = head.predict(np.zeros((2, 4)), [7, 3], boxes, K)
    assert np.allclose(t[:, 2], np.sqrt(latent * by_rotation) / apparent_size(boxes, K))  # geometric mean
    # the second head sees the estimated ray-frame rotation (6D), the object one-hot and the log box size
    assert np.allclose(by_r.X[:, :6], rot6d_from_matrix(R_a)[None].repeat(2, 0), atol=1e-6)
    assert np.array_equal(by_r.X[:, 6:8], [[0, 1], [1, 0]])
    assert by_r.X.shape == (2, 10)
    # without it (and in heads pickled before they existed) the latent head alone gives Tz
    del head.__dict__["distance_by_rotation"]
    assert np.allclose(head.predict(np.zeros((2, 4)), [7, 3], boxes, K)[1][:, 2], latent / apparent_size(boxes, K))
    with pytest.raises(ValueError, match="ray-frame"):
        PoseHead([1], None, None, None, rotation_frame="camera", distance_by_rotation=by_r)


def test_boosted_trees_predict_as_scikit_learn_does():
    from sklearn.ensemble import HistGradientBoostingRegressor

    from tracker.training.fit_heads import BoostedTrees
    rng = np.random.default_rng(0)
    X = rng.normal(size=(2000, 6))
    y = np.sin(2 * X[:, 0]) + X[:, 1] * X[:, 2] + 0.1 * rng.normal(size=2000)
    ours = BoostedTrees(max_iter=60, seed=3).fit(X, y)
    ref = HistGradientBoostingRegressor(loss="absolute_error", max_iter=60, learning_rate=0.1, max_leaf_nodes=63,
                                        early_stopping=False, random_state=3).fit(X, y)
    Xt = rng.normal(size=(300, 6)) * 2
    Xt[:5, 1] = np.nan  # missing values take the side the trees learnt
    assert np.allclose(ours.predict(Xt), ref.predict(Xt), atol=1e-9)
    assert np.abs(ours.predict(Xt) - y.mean()).max() > 0.5  # it learnt something
    assert ours.predict(Xt[:1]).shape == (1,)


def test_distance_from_rotation_is_always_kept_with_its_validation_recorded():
    from tracker.core.geometry import project
    from tracker.runtime.heads import apparent_size
    from tracker.training.train import choose_distance_by_rotation
    from tracker.runtime.heads import distance_by_rotation_inputs
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(0)
    n = 600
    R = Rotation.random(n, random_state=1).as_matrix()
    K = np.broadcast_to(np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]), (n, 3, 3))
    t = np.c_[rng.uniform(-50, 50, (n, 2)), rng.uniform(600, 1200, n)]
    centres = np.stack([project(np.zeros((1, 3)), k, None, tt)[0] for k, tt in zip(K, t)])
    # a box whose size depends on the rotation: Tz * size is a function of R (what the trees learn)
    s = 80 * (1 + 0.3 * R[:, 2, 0]) * 900 / t[:, 2]
    boxes = np.c_[centres - s[:, None] / 2, s, s]
    y = np.log(t[:, 2] * apparent_size(boxes, K))
    idx = np.zeros(n, int)
    tr, va = np.arange(500), np.arange(500, n)
    args = (R[tr], idx[tr], 1, boxes[tr], K[tr], y[tr], R[va], idx[va], boxes[va], K[va])
    rest = (apparent_size(boxes[va], K[va]), centres[va], t[va])
    noisy = y[va] + rng.normal(0, 0.3, len(va))  # a poor latent head: the average helps
    trees, info = choose_distance_by_rotation(*args, noisy, *rest, log=lambda *a: None)
    assert trees is not None and info["used"] and info["val_te_median_mm_averaged"] < info["val_te_median_mm_latent"], info
    # a perfect latent head: the average is worse on the renders, and the trees are kept all the
    # same (they help on real frames, which the renders' validation does not see)
    trees, info = choose_distance_by_rotation(*args, y[va], *rest, log=lambda *a: None)
    assert trees is not None and info["used"] and info["val_te_median_mm_averaged"] > info["val_te_median_mm_latent"]
    assert np.allclose(np.exp(trees.predict(distance_by_rotation_inputs(R[va], idx[va], 1, boxes[va], K[va]))),
                       np.exp(y[va]), rtol=0.2)  # the kept trees predict the distance


def test_refit_heads_can_keep_the_regressors_and_add_the_distance_from_rotation(tiny_bundle, tmp_path):
    import pickle

    from tracker.training.train import refit_heads
    m = refit_heads(tiny_bundle, tiny_bundle.parent / "split", out_dir=tmp_path / "kept", keep_regressors=True,
                    log=lambda *a: None)
    assert m.heads["kept_regressors"] and set(m.heads["distance_by_rotation"]) >= {"used"}
    src, kept = PoseEstimator(tiny_bundle), PoseEstimator(tmp_path / "kept")
    for name in ("rotation", "centre", "distance"):  # the very same regressors
        a, b = getattr(src.head, name), getattr(kept.head, name)
        assert type(a) is type(b) and pickle.dumps(a, protocol=4) == pickle.dumps(b, protocol=4)
    assert (kept.head.distance_by_rotation is not None) == m.heads["distance_by_rotation"]["used"]
    assert len(list((tiny_bundle.parent / "lmo.work").glob("codes_*.npy"))) == 2  # cached for the next refit


def test_refit_heads_with_wider_box_noise_cuts_crops_on_wider_boxes(tiny_bundle, tmp_path):
    from tracker.core.bundle import read_verified_manifest
    from tracker.training.crops import JITTER_SCALE, bundle_training_crops
    from tracker.training.train import refit_heads
    split = tiny_bundle.parent / "split"
    m = read_verified_manifest(tiny_bundle)
    exact = bundle_training_crops(tiny_bundle, m, split, jitter=False, log=lambda *a: None)
    spread = {}
    for scale in (JITTER_SCALE, 0.3):
        cs = bundle_training_crops(tiny_bundle, m, split, jitter_scale=scale, log=lambda *a: None)
        spread[scale] = np.std(np.log(cs.box[:, 2:] / exact.box[:, 2:]))
    assert spread[0.3] > 2 * spread[JITTER_SCALE], spread
    m = refit_heads(tiny_bundle, split, out_dir=tmp_path / "wide", reg_epochs=5, jitter_scale=0.3,
                    log=lambda *a: None)
    assert m.heads["jitter_scale"] == 0.3
    assert any("scale0.3" in p.name for p in (tiny_bundle.parent / "lmo.work").glob("codes_*.npy"))


def test_refit_heads_keeps_the_encoder_and_writes_a_verified_bundle(tiny_bundle, tmp_path):
    from tracker.core.bundle import sha256
    from tracker.training.train import refit_heads
    before = {p.name: sha256(p) for p in tiny_bundle.iterdir() if p.is_file()}
    m = refit_heads(tiny_bundle, tiny_bundle.parent / "split", out_dir=tmp_path / "refit", reg_epochs=5,
                    log=lambda *a: None)
    assert {p.name: sha256(p) for p in tiny_bundle.iterdir() if p.is_file()} == before  # the source is untouched
    assert m.heads["rotation_frame"] == "ray" and m.name == "refit"
    assert m.files["encoder.onnx"]["sha256"] == before["encoder.onnx"]
    est = PoseEstimator(tmp_path / "refit")  # hashes verified on load
    assert est.head.rotation_frame == "ray" and m.heads["jitter_scale"] == 0.08
    with pytest.raises(UserError, match="synth_config"):
        refit_heads(tiny_bundle, tmp_path, out_dir=tmp_path / "x", log=lambda *a: None)


def test_refit_heads_with_an_epoch_budget_is_reproducible(tiny_bundle, tmp_path):
    from tracker.training.train import refit_heads
    split = tiny_bundle.parent / "split"
    poses = []
    for run in ("a", "b", "c"):
        m = refit_heads(tiny_bundle, split, out_dir=tmp_path / run, reg_epochs=3, seed=0 if run != "c" else 1,
                        log=lambda *a: None)
        assert m.heads["reg_epochs"] == 3 and m.heads["reg_minutes"] is None
        est = PoseEstimator(tmp_path / run)
        scene = load_scene(split / "000000")
        im_id = sorted(scene.gt)[0]
        dets = [Detection(g.obj_id, np.asarray(g.info["bbox_visib"], float)) for g in scene.gt[im_id]
                if g.info["bbox_visib"][2] > 1 and g.info["bbox_visib"][3] > 1]
        poses.append(np.stack([p.t for p in est.estimate(scene.read_rgb(im_id), scene.K(im_id), dets)]))
    assert np.array_equal(poses[0], poses[1])  # the same seed and epochs: the same heads, whatever the time
    assert not np.allclose(poses[0], poses[2])  # another seed: other heads


def test_join_heads_averages_refitted_heads_and_refuses_another_encoder(tiny_bundle, tmp_path):
    from tracker.core.bundle import write_manifest
    from tracker.core.manifest import Manifest
    from tracker.core.geometry import mean_pose
    from tracker.research.head_ensemble import join_heads
    from tracker.runtime.heads import HeadEnsemble
    from tracker.training.train import refit_heads
    split = tiny_bundle.parent / "split"
    refit_heads(tiny_bundle, split, out_dir=tmp_path / "second", reg_epochs=5, seed=1, log=lambda *a: None)
    m = join_heads(tiny_bundle, [tmp_path / "second"], out_dir=tmp_path / "joined", log=lambda *a: None)
    assert m.heads["ensemble"]["members"] == 2
    joined = PoseEstimator(tmp_path / "joined")  # hashes verified on load
    assert isinstance(joined.head, HeadEnsemble)
    members = [PoseEstimator(p).head for p in (tiny_bundle, tmp_path / "second")]
    scene = load_scene(split / "000000")
    im_id = sorted(scene.gt)[0]
    dets = [Detection(g.obj_id, np.asarray(g.info["bbox_visib"], float)) for g in scene.gt[im_id]
            if g.info["bbox_visib"][2] > 1 and g.info["bbox_visib"][3] > 1]
    img, K = scene.read_rgb(im_id), scene.K(im_id)
    poses = joined.estimate(img, K, dets)
    mu = joined.encode(joined.crops(img, np.array([d.box for d in dets])), [d.obj_id for d in dets])
    preds = [h.predict(mu, [d.obj_id for d in dets], np.array([d.box for d in dets]), K) for h in members]
    _, t_mean = mean_pose(np.stack([p[0] for p in preds]), np.stack([p[1] for p in preds]))
    assert np.allclose(np.stack([p.t for p in poses]), t_mean, rtol=1e-5)
    assert joined.estimate(img, K, dets, mode="aae")  # the codebook still answers
    other = tmp_path / "other"
    shutil.copytree(tmp_path / "second", other)
    with open(other / "encoder.onnx", "ab") as f:
        f.write(b"\0")  # another encoder, hashed anew: a consistent bundle, but not the same network
    write_manifest(other, Manifest.from_dict(json.loads((other / "manifest.json").read_text()), other))
    with pytest.raises(UserError, match="encoder"):
        join_heads(tiny_bundle, [other], out_dir=tmp_path / "bad", log=lambda *a: None)
    with pytest.raises(UserError, match="averages 2 head sets"):
        refit_heads(tmp_path / "joined", split, out_dir=tmp_path / "kept", keep_regressors=True, log=lambda *a: None)


def test_head_sets_are_fitted_with_successive_seeds_and_averaged(tiny_split, monkeypatch):
    """train/build --head-sets N: N head sets (seeds s, s+1, ...) on one encoder's codes, their
    poses averaged; the codebook is the single set's, the validation the average's."""
    from tracker.training.crops import build_training_crops, train_val_split
    from tracker.training.train import fit_head_sets, fit_heads
    from tracker.core.bop import load_models_info
    from tracker.core.geometry import mean_pose
    from tracker.runtime.heads import HeadEnsemble
    cs = build_training_crops(tiny_split, 32, seed=0, jitter=True)
    mu = np.random.default_rng(0).normal(size=(len(cs), 16)).astype(np.float32)  # any encoder's codes
    info = load_models_info(REPO / "models" / "lmo_models_info.json")
    tr, va = train_val_split(len(cs), 0)
    opts = dict(reg_epochs=3, codebook_per_object=20, log=lambda *a: None)
    ens, cb, _, val = fit_head_sets(mu, cs, OBJS, info, tr, va, np.random.default_rng(5), n_sets=2, seed=3, **opts)
    singles = [fit_heads(mu, cs, OBJS, info, tr, va, np.random.default_rng(5), seed=s, **opts) for s in (3, 4)]
    assert len(tr) < 100  # so the distance KNNs keep every code, with one set or two
    assert isinstance(ens, HeadEnsemble) and len(ens.members) == 2
    assert all(np.array_equal(cb.codes_[o][0], singles[0][1].codes_[o][0]) for o in OBJS)  # the first set's views
    box, K = cs.box[va], cs.K[va]
    preds = [h.predict(mu[va], cs.obj_id[va], box, K) for h, *_ in singles]
    assert not np.allclose(preds[0][0], preds[1][0])  # two seeds, two fits
    for member, p in zip(ens.members, preds):
        assert np.allclose(member.predict(mu[va], cs.obj_id[va], box, K)[1], p[1])
    R, t = ens.predict(mu[va], cs.obj_id[va], box, K)
    assert np.allclose(t, mean_pose(np.stack([p[0] for p in preds]), np.stack([p[1] for p in preds]))[1])
    assert set(val) == {"regression", "aae"} and val["regression"] != singles[0][3]["regression"]
    one = fit_head_sets(mu, cs, OBJS, info, tr, va, np.random.default_rng(5), n_sets=1, seed=3, **opts)
    assert not isinstance(one[0], HeadEnsemble) and one[3] == singles[0][3]
    from tracker.training import train as tr_mod
    monkeypatch.setattr(tr_mod, "KNN_MAX_ROWS", 6)  # the sets' KNNs share the bundle's room for codes
    assert fit_head_sets(mu, cs, OBJS, info, tr, va, np.random.default_rng(5), n_sets=2, seed=3, **opts)[2]["knn"]["rows"] == 3
    assert fit_head_sets(mu, cs, OBJS, info, tr, va, np.random.default_rng(5), n_sets=1, seed=3, **opts)[2]["knn"]["rows"] == 6


def _failure(stderr: str) -> str:
    """What a failed torchrun job said: its processes' own errors (an abort's message comes
    before the launcher's long report) and the end."""
    own = [ln for ln in stderr.splitlines() if any(w in ln for w in ("terminate", "what()", "Error", "error:"))]
    return "\n".join(own[:20]) + "\n...\n" + stderr[-1500:]


def test_training_runs_under_torchrun_with_two_processes(tiny_bundle, tmp_path):
    """DistributedDataParallel with gloo on this CPU: two processes train the autoencoder
    together; the first writes the bundle, which records both."""
    import os
    import subprocess
    import sys
    torchrun = Path(sys.executable).parent / "torchrun"
    out = tmp_path / "ddp"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([str(torchrun), "--standalone", "--nproc_per_node", "2", str(REPO / "app.py"), "train",
                        "--data", str(tiny_bundle.parent / "split"), "--out", str(out), "--size", "32", "--latent", "16",
                        "--minutes", "0.05", "--reg-epochs", "1", "--batch", "8",
                        "--models-info", str(REPO / "models" / "lmo_models_info.json"), "--device", "cpu"],
                       capture_output=True, text=True, timeout=240, env=env, cwd=REPO)
    assert r.returncode == 0, _failure(r.stderr)
    from tracker.core.bundle import open_bundle
    m = open_bundle(out).manifest
    assert m.training["processes"] == 2 and m.training["ae_epochs"] >= 1
    assert r.stdout.count("wrote ") == 1  # one report, from the first process


def test_the_detector_trains_under_torchrun_with_two_processes(tiny_bundle, tmp_path):
    """DistributedDataParallel with gloo: two processes train the detector on shared batches;
    the first validates, exports and writes it into the bundle, which records both, and the
    exported detector runs."""
    import os
    import shutil
    import subprocess
    import sys
    torchrun = Path(sys.executable).parent / "torchrun"
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([str(torchrun), "--standalone", "--nproc_per_node", "2", str(REPO / "app.py"),
                        "train-detector", "--data", str(tiny_bundle.parent / "split"), "--model", str(root),
                        "--minutes", "0.05", "--batch", "2", "--width", "8", "--input", "128", "96", "--device", "cpu"],
                       capture_output=True, text=True, timeout=240, env=env, cwd=REPO)
    assert r.returncode == 0, _failure(r.stderr)
    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import Detector
    b = open_bundle(root)
    t = b.manifest.detector["training"]
    assert t["processes"] == 2 and t["steps"] >= 1 and t["onnx_max_abs_diff"] <= 1e-4
    assert r.stdout.count("detector added to") == 1  # one report, from the first process
    assert isinstance(Detector(b)(np.full((480, 640, 3), 120, np.uint8)), list)


def test_processes_whose_time_budgets_differ_stop_together(tiny_bundle, tmp_path):
    """Each process cuts its budget from its own clock (build's stage budget less what its
    loading took), so under DDP they differ; all must stop at the same step, or the one that
    goes on waits in the gradient exchange for ever (build --ray hung so). Here the second
    process is given a budget 2.5 times the first's."""
    import os
    import shutil
    import subprocess
    import sys
    script = tmp_path / "ranks.py"
    script.write_text("import os, sys\n"
                      "from tracker.training.detector_train import train_detector\n"
                      "rank = int(os.environ['RANK'])\n"
                      "train_detector(sys.argv[1], sys.argv[2], minutes=0.02 + 0.03 * rank, batch=2, width=8,\n"
                      "               input_w=128, input_h=96, device='cpu', threads=1, log=print)\n")
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    torchrun = Path(sys.executable).parent / "torchrun"
    r = subprocess.run([str(torchrun), "--standalone", "--nproc_per_node", "2", str(script),
                        str(tiny_bundle.parent / "split"), str(root)], capture_output=True, text=True, timeout=150,
                       env=dict(os.environ, OMP_NUM_THREADS="1"), cwd=REPO)
    assert r.returncode == 0, _failure(r.stderr)
    from tracker.core.bundle import open_bundle
    t = open_bundle(root).manifest.detector["training"]
    assert t["processes"] == 2 and t["steps"] >= 1


def test_a_split_whose_meshes_are_gone_is_refused_before_training(tiny_split, tmp_path):
    split = tmp_path / "split"
    shutil.copytree(tiny_split, split)
    cfg = json.loads((split / "synth_config.json").read_text())
    cfg["config"]["models_dir"] = str(tmp_path / "moved_away")
    (split / "synth_config.json").write_text(json.dumps(cfg))
    logs = []
    with pytest.raises(UserError, match="meshes it was rendered from .* are gone"):
        train_bundle(split, tmp_path / "b", method="cvml", size=32, latent=16, minutes=5, log=logs.append)
    assert not logs and not (tmp_path / "b.work").exists()  # nothing trained, nothing cut


def test_head_sets_are_kept_one_by_one_and_a_rerun_fits_only_the_missing(tiny_split, tmp_path, monkeypatch):
    """An interruption while the head sets fit (Ctrl-C, a session's end) loses at most the set in
    flight: the rerun on the same codes loads the sets fitted before; other codes fit anew."""
    from tracker.training import train as tr_mod
    from tracker.training.crops import build_training_crops, train_val_split
    from tracker.core.bop import load_models_info
    cs = build_training_crops(tiny_split, 32, seed=0, jitter=True)
    mu = np.random.default_rng(0).normal(size=(len(cs), 16)).astype(np.float32)
    info = load_models_info(REPO / "models" / "lmo_models_info.json")
    tr, va = train_val_split(len(cs), 0)
    opts = dict(reg_epochs=3, codebook_per_object=20, log=lambda *a: None, cache_dir=tmp_path / "sets")
    real, fitted = tr_mod.fit_heads, []

    def counting(*a, **k):
        fitted.append(k["seed"])
        return real(*a, **k)

    def second_interrupted(*a, **k):
        fitted.append(k["seed"])
        if k["seed"] == 4:
            raise KeyboardInterrupt
        return real(*a, **k)
    monkeypatch.setattr(tr_mod, "fit_heads", second_interrupted)
    with pytest.raises(KeyboardInterrupt):
        tr_mod.fit_head_sets(mu, cs, OBJS, info, tr, va, np.random.default_rng(5), n_sets=3, seed=3, **opts)
    assert fitted == [3, 4]
    monkeypatch.setattr(tr_mod, "fit_heads", counting)
    fitted.clear()
    ens, cb, dist_info, val = tr_mod.fit_head_sets(mu, cs, OBJS, info, tr, va, np.random.default_rng(5),
                                                   n_sets=3, seed=3, **opts)
    assert fitted == [4, 5]  # the first set was loaded, the interrupted one fitted again
    fitted.clear()
    again = tr_mod.fit_head_sets(mu, cs, OBJS, info, tr, va, np.random.default_rng(5), n_sets=3, seed=3, **opts)
    assert fitted == []  # all three kept
    box, K = cs.box[va], cs.K[va]
    for a, b in zip(ens.predict(mu[va], cs.obj_id[va], box, K), again[0].predict(mu[va], cs.obj_id[va], box, K)):
        assert np.allclose(a, b, rtol=1e-4, atol=1e-3)  # as a bundle stores them (float16 weights)
    assert again[2] == json.loads(json.dumps(dist_info)) and set(again[3]) == set(val)
    assert all(np.array_equal(cb.codes_[o][0], again[1].codes_[o][0]) for o in OBJS)
    tr_mod.fit_head_sets(mu + 1, cs, OBJS, info, tr, va, np.random.default_rng(5), n_sets=3, seed=3, **opts)
    assert fitted == [3, 4, 5]  # other codes (another encoder): fitted anew


def test_train_with_step_and_epoch_budgets_makes_the_same_encoder_twice(tiny_bundle, tmp_path):
    """The autoencoder's starting weights come from the seed too: two runs of one command with step
    and epoch budgets export the same encoder (its first weights were drawn unseeded, so no two
    runs were alike)."""
    import onnx
    from onnx import numpy_helper
    from tracker.training.train import train_bundle
    split = tiny_bundle.parent / "split"
    weights = []
    for run in ("a", "b"):
        torch.manual_seed(1 if run == "a" else 2)  # what came before in the process must not matter
        train_bundle(split, tmp_path / run, method="cvam", size=32, latent=16, max_steps=3, reg_epochs=2,
                     models_info_path=REPO / "models" / "lmo_models_info.json", log=lambda *a: None)
        g = onnx.load(str(tmp_path / run / "encoder.onnx")).graph
        weights.append({i.name: numpy_helper.to_array(i) for i in g.initializer})
    assert weights[0].keys() == weights[1].keys() and len(weights[0]) > 4
    assert all(np.array_equal(weights[0][k], weights[1][k]) for k in weights[0])
