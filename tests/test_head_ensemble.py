"""The averaged pose head: symmetric estimates are aligned before they are averaged; bundles
with another encoder are refused."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tracker.core.geometry import mean_pose, rotation_error_deg
from tracker.runtime.heads import HeadEnsemble


class FixedHead:
    """A stand-in pose head that answers the same pose for every crop."""
    rotation_frame = "ray"

    def __init__(self, R, t, obj_ids=(10,)):
        self.R, self.t, self.obj_ids = np.asarray(R, float), np.asarray(t, float), list(obj_ids)

    def predict(self, mu, obj_ids, boxes, K, mode="regression", trees_weight=0.5):
        n = len(obj_ids)
        return np.repeat(self.R[None], n, 0), np.repeat(self.t[None], n, 0)


def test_symmetric_estimates_are_aligned_before_averaging():
    R0 = Rotation.from_euler("xyz", [20, 40, -30], degrees=True).as_matrix()
    flip = Rotation.from_euler("z", 180, degrees=True).as_matrix()  # the object's symmetry (model frame)
    near = Rotation.from_rotvec([0.0, 0.1, 0.0]).as_matrix()
    t = np.array([0.0, 0.0, 900.0])
    heads = [FixedHead(R0, t), FixedHead(R0 @ near @ flip, t)]  # the second: R0 turned a little, then flipped
    ens = HeadEnsemble(heads, {10: np.stack([np.eye(3), flip])})
    R, tt = ens.predict(np.zeros((1, 4)), [10], np.array([[0, 0, 10, 10]]), np.eye(3))
    expected, _ = mean_pose(np.stack([R0, R0 @ near])[:, None], np.stack([t, t])[:, None])
    assert rotation_error_deg(R[0], expected[0]) < 1e-4
    assert rotation_error_deg(R[0], R0) == pytest.approx(np.degrees(0.05), abs=1e-3)  # half of the small turn
    assert np.allclose(tt, t)
    plain = HeadEnsemble(heads, {})  # without the symmetry the flipped estimate drags the mean far off
    assert rotation_error_deg(plain.predict(np.zeros((1, 4)), [10], np.zeros((1, 4)), np.eye(3))[0][0], R0) > 45


def test_ensembles_flatten_and_refuse_heads_of_other_objects():
    a, b = FixedHead(np.eye(3), [0, 0, 500]), FixedHead(np.eye(3), [0, 0, 2000])
    ens = HeadEnsemble([HeadEnsemble([a, b], {}), a], {})
    assert len(ens.members) == 3
    from tracker.core.errors import UserError
    with pytest.raises(UserError, match="cannot be averaged"):
        HeadEnsemble([a, FixedHead(np.eye(3), [0, 0, 1], obj_ids=(1,))], {})


def test_stacked_trees_and_mlps_give_each_members_prediction():
    from tracker.training.fit_heads import BoostedTrees, NumpyMLP
    from tracker.runtime.heads import StackedMLP, StackedTrees
    rng = np.random.default_rng(1)
    X = rng.normal(size=(800, 5))
    forests = [BoostedTrees(max_iter=n, max_leaf_nodes=leaves, seed=s).fit(X, np.sin(X[:, 0] * s) + X[:, s])
               for n, leaves, s in ((30, 63, 1), (12, 7, 2), (45, 31, 3))]  # unequal counts and depths
    Xt = rng.normal(size=(3, 9, 5)) * 1.5
    Xt[1, :3, 2] = np.nan
    got = StackedTrees(forests).predict(Xt)
    assert got.shape == (3, 9)
    for m, f in enumerate(forests):
        assert np.allclose(got[m], f.predict(Xt[m]), atol=1e-12)
    mlps = []
    for s in range(3):
        m = NumpyMLP(hidden=(16, 16))
        r = np.random.default_rng(s)
        m.mean_, m.scale_ = r.normal(size=5).astype(np.float32), r.uniform(0.5, 2, 5).astype(np.float32)
        m.layers_ = [(r.normal(size=(a, b)).astype(np.float32), r.normal(size=b).astype(np.float32))
                     for a, b in ((5, 16), (16, 16), (16, 6))]
        mlps.append(m)
    assert StackedMLP.stackable(mlps)
    out = StackedMLP(mlps).forward(Xt[0])
    for m, mlp in enumerate(mlps):
        assert np.allclose(out[m], mlp._forward(Xt[0]), rtol=1e-5, atol=1e-5)
    mlps[2].layers_ = mlps[2].layers_[:2] + [(np.zeros((16, 3), np.float32), np.zeros(3, np.float32))]
    assert not StackedMLP.stackable(mlps)


def test_the_bundled_averaged_head_stacked_equals_member_by_member():
    from tests.conftest import REPO
    from tracker.runtime.heads import HeadEnsemble
    from tracker.runtime.estimator import PoseEstimator
    est = PoseEstimator(REPO / "models" / "lmo")
    head = est.head
    assert isinstance(head, HeadEnsemble) and head.stacked() is not None
    rng = np.random.default_rng(0)
    ids = est.obj_ids * 2
    mu = rng.normal(size=(len(ids), est.bundle.manifest.latent_size)).astype(np.float32)
    boxes = np.column_stack([rng.uniform(0, 500, len(ids)), rng.uniform(0, 350, len(ids)),
                             rng.uniform(30, 140, len(ids)), rng.uniform(30, 140, len(ids))])
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    for k in (K, np.repeat(K[None], len(ids), 0)):  # one camera, or one per crop
        Rs, ts = head.member_poses(mu, ids, boxes, k)
        for m, h in enumerate(head.members):
            R, t = h.predict(mu, ids, boxes, k)
            assert np.allclose(Rs[m], R, atol=1e-6) and np.allclose(ts[m], t, rtol=1e-6)

    # the trees' share of the distance, one per crop: stacked as member by member; 0 leaves the
    # latent MLP's distance alone and the rotation untouched
    w = np.tile([0.0, 0.5], len(ids) // 2)
    Rw, tw = head.member_poses(mu, ids, boxes, K, trees_weight=w)
    R0, t0 = head.member_poses(mu, ids, boxes, K, trees_weight=0.0)
    R5, t5 = head.member_poses(mu, ids, boxes, K)
    for m, h in enumerate(head.members):
        R, t = h.predict(mu, ids, boxes, K, trees_weight=w)
        assert np.allclose(Rw[m], R, atol=1e-6) and np.allclose(tw[m], t, rtol=1e-6)
    assert np.allclose(R0, R5) and np.allclose(tw[:, w == 0], t0[:, w == 0]) and np.allclose(tw[:, w > 0], t5[:, w > 0])
    assert not np.allclose(t0[..., 2], t5[..., 2], rtol=1e-3)  # the trees do move the distance



def test_mlp_weights_are_stored_in_half_precision_and_evaluated_in_float32(tmp_path):
    from tracker.training.fit_heads import NumpyMLP
    from tracker.runtime.heads import MLP, PoseHead, load_head, save_head
    r = np.random.default_rng(0)

    def mlp(shapes):
        m = NumpyMLP(hidden=(32,))
        m.mean_, m.scale_ = np.zeros(shapes[0][0], np.float32), np.ones(shapes[0][0], np.float32)
        m.layers_ = [(r.normal(size=s).astype(np.float32), r.normal(size=s[1]).astype(np.float32)) for s in shapes]
        return m
    m = mlp([(5, 32), (32, 6)])
    head = PoseHead([1], m, mlp([(5, 8), (8, 2)]), mlp([(5, 8), (8, 1)]))
    save_head(head, tmp_path / "h.json", tmp_path / "h.npz")
    assert all(W.dtype == np.float32 for W, _ in m.layers_)  # storing leaves the fitted object as it was
    small = load_head(tmp_path / "h.json", tmp_path / "h.npz").rotation
    assert type(small) is MLP and small.layers_[0][0].dtype == np.float32
    assert np.array_equal(small.layers_[0][0], m.layers_[0][0].astype(np.float16).astype(np.float32))
    X = r.normal(size=(20, 5)).astype(np.float32)
    assert np.allclose(small._forward(X), m._forward(X), rtol=1e-2, atol=1e-2)
    big = mlp([(5, 600), (600, 3)])
    big.layers_[0] = (np.zeros((5, 600), np.float32), np.zeros(600, np.float32))
    spec, arrays = big.to_arrays()
    assert arrays["W0"].nbytes + arrays["b0"].nbytes == (5 * 600 + 600) * 2  # half the bytes of float32


def test_every_regressor_kind_survives_storage_exactly(tmp_path):
    """Each kind the bundle stores (MLP, KNN, trees, codebook) predicts the same after a round trip
    through JSON + npz, in an ensemble with symmetries."""
    from tracker.training.fit_heads import BoostedTrees, KNNRegressor
    from tracker.runtime.heads import Codebook, PoseHead, load_codebook, load_head, save_codebook, save_head
    r = np.random.default_rng(1)
    mu, ids = r.normal(size=(40, 8)).astype(np.float32), r.choice([3, 7], 40)
    boxes = np.c_[r.uniform(50, 300, (40, 2)), r.uniform(20, 90, (40, 2))]
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    n_in = 8 + 2

    def mlp(out):
        from tracker.training.fit_heads import NumpyMLP
        m = NumpyMLP(loss="l1_rotation" if out == 6 else "l1")
        m.mean_, m.scale_ = r.normal(size=n_in).astype(np.float32), np.ones(n_in, np.float32)
        m.layers_ = [(r.normal(size=(n_in, 16)).astype(np.float16).astype(np.float32), np.zeros(16, np.float32)),
                     (r.normal(size=(16, out)).astype(np.float16).astype(np.float32), np.zeros(out, np.float32))]
        return m
    cen = mlp(2)
    cen.mean_, cen.scale_ = np.zeros(n_in + 4, np.float32), np.ones(n_in + 4, np.float32)
    cen.layers_[0] = (r.normal(size=(n_in + 4, 16)).astype(np.float16).astype(np.float32), np.zeros(16, np.float32))
    knn = KNNRegressor(k=3).fit(r.normal(size=(50, n_in + 2)), r.normal(size=50))
    trees = BoostedTrees(max_iter=5, seed=0).fit(r.normal(size=(60, 6 + 2 + 2)), r.normal(size=60))
    heads = [PoseHead([3, 7], mlp(6), cen, knn, distance_by_rotation=trees) for _ in range(2)]
    flip = np.diag([-1.0, -1.0, 1.0])
    ens = HeadEnsemble(heads, {7: np.stack([np.eye(3), flip])})
    save_head(ens, tmp_path / "h.json", tmp_path / "h.npz")
    back = load_head(tmp_path / "h.json", tmp_path / "h.npz")
    for w in (0.0, 0.5):
        for a, b in zip(ens.predict(mu, ids, boxes, K, trees_weight=w), back.predict(mu, ids, boxes, K, trees_weight=w)):
            assert np.array_equal(a, b)
    cb = Codebook().fit(mu, ids, r.normal(size=(40, 3, 3)), r.uniform(1, 2, 40))
    save_codebook(cb, tmp_path / "cb.npz")
    for a, b in zip(cb.predict(mu[:5], ids[:5]), load_codebook(tmp_path / "cb.npz").predict(mu[:5], ids[:5])):
        assert np.array_equal(a, b)


def test_malformed_pose_heads_are_refused_not_run(tmp_path):
    """Every way a stored head can be wrong ends in ValueError (a one-line error at load), never
    in another exception or an endless tree walk."""
    import json

    import pytest

    from tracker.training.fit_heads import BoostedTrees, NumpyMLP
    from tracker.runtime.heads import PoseHead, load_head, save_head
    r = np.random.default_rng(2)

    def mlp(n_in, out):
        m = NumpyMLP()
        m.mean_, m.scale_ = np.zeros(n_in, np.float32), np.ones(n_in, np.float32)
        m.layers_ = [(r.normal(size=(n_in, 4)).astype(np.float32), np.zeros(4, np.float32)),
                     (r.normal(size=(4, out)).astype(np.float32), np.zeros(out, np.float32))]
        return m
    trees = BoostedTrees(max_iter=3, seed=0).fit(r.normal(size=(40, 10)), r.normal(size=40))
    save_head(PoseHead([1], mlp(9, 6), mlp(13, 2), mlp(11, 1), distance_by_rotation=trees),
              tmp_path / "h.json", tmp_path / "h.npz")
    good_spec = json.loads((tmp_path / "h.json").read_text())
    with np.load(tmp_path / "h.npz") as z:
        good = dict(z)

    def broken(spec_change=None, arrays_change=None):
        spec, arrays = json.loads(json.dumps(good_spec)), dict(good)
        if spec_change:
            spec_change(spec)
        if arrays_change:
            arrays_change(arrays)
        (tmp_path / "b.json").write_text(json.dumps(spec))
        np.savez(tmp_path / "b.npz", **arrays)
        with pytest.raises(ValueError):
            load_head(tmp_path / "b.json", tmp_path / "b.npz")
    broken(lambda s: s.update(members=["not a mapping"]))
    broken(lambda s: s["members"][0].update(rotation=[1, 2]))
    broken(lambda s: s["members"][0]["distance"].update(kind="forest"))
    broken(lambda s: s["members"][0].update(centre=s["members"][0]["rotation"]))  # 6 outputs for the centre
    broken(arrays_change=lambda a: a.update({"m0.rotation.W1": np.zeros((5, 6), np.float32)}))  # shapes do not chain
    broken(arrays_change=lambda a: a.update({"m0.distance_by_rotation.left": np.zeros_like(a["m0.distance_by_rotation.left"])}))
    broken(lambda s: s.update(kind="ensemble", symmetries=[1]))
    assert load_head(tmp_path / "h.json", tmp_path / "h.npz").distance_by_rotation is not None
