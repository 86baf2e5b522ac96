"""Pose errors (tracker.evaluation.metrics) and BOP-style scoring (tracker.evaluation.scoring): hand-computed pins."""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tracker.evaluation import metrics
from tracker.core.bop import Estimate, load_models_info, symmetry_transforms, write_results
from tracker.core.errors import UserError
from tracker.core.paths import REPO
from tracker.evaluation.scoring import (ObjectEval, VISIB_FROM_GT_INFO, match_greedy, score_estimates, score_results,
                             write_metrics_json)

K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
LMO_INFO = REPO / "models" / "lmo_models_info.json"
FRAMES = 3  # dev frames used by the scene-level tests


def rot(axis, deg):
    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(deg)).as_matrix()


def box_points(a=40.0, b=20.0, c=10.0):
    """The 8 corners of a box: symmetric under 180 degrees about each model axis."""
    return np.array([[x, y, z] for x in (-a, a) for y in (-b, b) for z in (-c, c)])


def T(R, t=(0.0, 0.0, 0.0)):
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


R_G = rot([1, 2, 3], 40)
T_G = np.array([30.0, -20.0, 800.0])


# --------------------------------------------------------------------------- pose errors


def test_pure_translation_gives_add_and_te_equal_to_the_offset():
    pts = box_points()
    d = np.array([3.0, -4.0, 12.0])  # |d| = 13 mm
    assert metrics.add(R_G, T_G + d, R_G, T_G, pts) == pytest.approx(13.0)
    assert metrics.te(T_G + d, T_G) == pytest.approx(13.0)
    assert metrics.re(R_G, R_G) == pytest.approx(0.0, abs=1e-4)
    # every point moves by d: the maximum surface distance is |d| too
    assert metrics.mssd(R_G, T_G + d, R_G, T_G, pts, None) == pytest.approx(13.0)


def test_rotation_error_of_a_known_rotation():
    assert metrics.re(rot([0.3, -1, 2], 30) @ R_G, R_G) == pytest.approx(30.0)
    assert metrics.re(R_G @ rot([1, 0, 0], 180), R_G) == pytest.approx(180.0)


def test_symmetric_pose_has_zero_mssd_mspd_adi_but_not_add():
    pts = box_points()
    S = T(rot([0, 0, 1], 180))
    syms = np.stack([np.eye(4), S])
    R_e, t_e = R_G @ S[:3, :3], T_G + R_G @ S[:3, 3]  # the GT pose seen through the symmetry
    assert metrics.mssd(R_e, t_e, R_G, T_G, pts, syms) == pytest.approx(0.0, abs=1e-9)
    assert metrics.mspd(R_e, t_e, R_G, T_G, K, pts, syms) == pytest.approx(0.0, abs=1e-9)
    assert metrics.adi(R_e, t_e, R_G, T_G, pts) == pytest.approx(0.0, abs=1e-9)
    # ADD pairs x with its turned self: distance 2 * |(x, y)| for every corner
    assert metrics.add(R_e, t_e, R_G, T_G, pts) == pytest.approx(2 * np.hypot(40, 20))
    # without the symmetry MSSD is the farthest such pair
    assert metrics.mssd(R_e, t_e, R_G, T_G, pts, None) == pytest.approx(2 * np.hypot(40, 20))
    assert metrics.re(R_e, R_G) == pytest.approx(180.0)


def test_symmetry_with_an_offset():
    # a box whose centre is at (5, 0, 0) in the model frame: the 180-degree turn about the
    # parallel axis through its centre is R x + (10, 0, 0)
    pts = box_points() + [5.0, 0.0, 0.0]
    Rz = rot([0, 0, 1], 180)
    S = T(Rz, [10.0, 0.0, 0.0])
    assert np.allclose(np.sort(pts @ Rz.T + S[:3, 3], axis=0), np.sort(pts, axis=0))
    R_e, t_e = R_G @ Rz, T_G + R_G @ S[:3, 3]
    assert metrics.mssd(R_e, t_e, R_G, T_G, pts, np.stack([np.eye(4), S])) == pytest.approx(0.0, abs=1e-9)
    assert metrics.mssd(R_e, t_e, R_G, T_G, pts, None) > 80


def test_one_pixel_shift_gives_mspd_of_one():
    # a flat point set facing the camera: a sideways move of Z / fx mm shifts every projection by 1 px
    pts = np.array([[x, y, 0.0] for x in (-50, 0, 50) for y in (-30, 30)])
    t = np.array([10.0, 5.0, 1000.0])
    t_e = t + [1000.0 / K[0, 0], 0.0, 0.0]
    assert metrics.mspd(np.eye(3), t_e, np.eye(3), t, K, pts, None) == pytest.approx(1.0, abs=1e-9)
    # a 3D box: a point at depth z moves by fx * dx / z px, the nearest corner the most
    z_min = (box_points() @ R_G.T + t)[:, 2].min()
    assert metrics.mspd(R_G, t_e, R_G, t, K, box_points(), None) == pytest.approx(1000.0 / z_min)


def test_adi_matches_brute_force_and_never_exceeds_add():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3)) * [40, 20, 10]
    R_e, t_e = rot([1, 1, 0], 7) @ R_G, T_G + [2.0, 1.0, -3.0]
    pe, pg = pts @ R_e.T + t_e, pts @ R_G.T + T_G
    brute = np.linalg.norm(pg[:, None] - pe[None], axis=2).min(axis=1).mean()
    assert metrics.adi(R_e, t_e, R_G, T_G, pts) == pytest.approx(brute)
    assert metrics.adi(R_e, t_e, R_G, T_G, pts) <= metrics.add(R_e, t_e, R_G, T_G, pts)


def test_mssd_on_hull_equals_mssd_on_all_points_and_the_naive_loop():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(2000, 3)) * [40, 20, 10]
    syms = np.stack([np.eye(4), T(rot([0, 0, 1], 180), [1.0, 0, 0]), T(rot([1, 0, 0], 180))])
    R_e, t_e = rot([0, 1, 1], 20) @ R_G, T_G + [5.0, -3.0, 9.0]
    naive = min(np.linalg.norm(pts @ R_e.T + t_e - ((pts @ S[:3, :3].T + S[:3, 3]) @ R_G.T + T_G), axis=1).max()
                for S in syms)
    assert metrics.mssd(R_e, t_e, R_G, T_G, pts, syms) == pytest.approx(naive)
    assert metrics.mssd(R_e, t_e, R_G, T_G, metrics.hull_points(pts), syms) == pytest.approx(naive)


def test_errors_with_lmo_symmetries(lmo_models):
    info = load_models_info(LMO_INFO)
    eggbox = lmo_models[10].vertices
    syms = symmetry_transforms(info[10])
    assert len(syms) == 2
    S = syms[1]
    R_e, t_e = R_G @ S[:3, :3], T_G + R_G @ S[:3, 3]
    assert metrics.mssd(R_e, t_e, R_G, T_G, eggbox, syms) == pytest.approx(0.0, abs=1e-6)
    assert metrics.add(R_e, t_e, R_G, T_G, eggbox) > 0.3 * info[10]["diameter"]
    # the detected symmetry is approximate: the turned model lies within a few mm of itself
    assert metrics.adi(R_e, t_e, R_G, T_G, eggbox) < 0.02 * info[10]["diameter"]


# --------------------------------------------------------------------------- matching


def test_greedy_matching_follows_score_order():
    # 2 estimates (by decreasing score) x 2 GT instances
    err = np.array([[[0.3], [0.2]],
                    [[0.1], [0.25]]])
    order = np.array([0, 1])
    valid = np.array([True, True])
    # est 0 takes its best GT (1); est 1 gets GT 0
    assert match_greedy(err, order, valid, [0.5]).tolist() == [1, 0]
    # at 0.22 est 0 still takes GT 1; est 1 takes GT 0 (0.1 < 0.22)
    assert match_greedy(err, order, valid, [0.22]).tolist() == [1, 0]
    # at 0.15 est 0 matches nothing; est 1 takes GT 0
    assert match_greedy(err, order, valid, [0.15]).tolist() == [1, -1]
    # an invalid (barely visible) GT cannot be matched
    assert match_greedy(err, order, np.array([True, False]), [0.5]).tolist() == [0, -1]
    # two-element errors (RE, TE): every element must be below and lowest so far
    e2 = np.array([[[4.0, 60.0], [4.5, 30.0]]])
    assert match_greedy(e2, np.array([0]), valid, [5.0, 50.0]).tolist() == [-1, 0]


# --------------------------------------------------------------------------- scenes


@pytest.fixture(scope="module")
def dev(lmo_dev, lmo_models):
    info = load_models_info(LMO_INFO)
    im_ids = lmo_dev.im_ids[:FRAMES]
    objs = {g.obj_id for i in im_ids for g in lmo_dev.gt[i]}
    objects = {k: ObjectEval.from_info(k, lmo_models[k].vertices, info[k]) for k in objs}
    visib = {i: [1.0] * len(lmo_dev.gt[i]) for i in im_ids}
    return lmo_dev, objects, visib, im_ids


def gt_estimates(scene, im_ids, skip_obj=None):
    return [Estimate(2, i, g.obj_id, 1.0, g.R.copy(), g.t.copy(), 0.04)
            for i in im_ids for g in scene.gt[i] if g.obj_id != skip_obj]


def score(dev, ests, visib=None):
    scene, objects, vis, im_ids = dev
    return score_estimates(ests, scene, objects, visib or vis, 640, im_ids)


def test_gt_as_estimates_scores_one_and_no_estimates_zero(dev):
    scene, _, _, im_ids = dev
    n = sum(len(scene.gt[i]) for i in im_ids)
    m = score(dev, gt_estimates(scene, im_ids))
    assert m["n_gt"] == n and m["n_est"] == n
    for k in ("ar_mssd", "ar_mspd", "add_recall", "ar", "recall_5deg5cm"):
        assert m[k] == 1.0, k
    assert m["ar_vsd"] is None and m["detection"] is None and m["ms_per_image"] is None
    assert m["re_median_deg"] == pytest.approx(0.0, abs=1e-3) and m["te_median_mm"] == pytest.approx(0.0, abs=1e-6)
    assert all(o["ar"] == 1.0 for o in m["per_object"].values())
    z = score(dev, [])
    assert z["n_gt"] == n and z["n_est"] == 0
    for k in ("ar_mssd", "ar_mspd", "add_recall", "ar", "recall_5deg5cm"):
        assert z[k] == 0.0, k
    assert z["re_median_deg"] is None and z["n_matched"] == 0


def test_a_missing_object_lowers_its_recall_only(dev):
    scene, _, _, im_ids = dev
    n = sum(len(scene.gt[i]) for i in im_ids)
    k = sum(g.obj_id == 9 for i in im_ids for g in scene.gt[i])
    m = score(dev, gt_estimates(scene, im_ids, skip_obj=9))
    assert m["per_object"]["9"]["ar_mssd"] == 0.0 and m["per_object"]["9"]["n_est"] == 0
    assert m["per_object"]["1"]["ar_mssd"] == 1.0
    assert m["ar_mssd"] == pytest.approx((n - k) / n) and m["add_recall"] == pytest.approx((n - k) / n)


def test_partial_error_gives_fraction_of_thresholds(dev):
    scene, objects, _, im_ids = dev
    d = objects[1].diameter
    ests = gt_estimates(scene, im_ids)
    for e in ests:
        if e.obj_id == 1:
            e.t = e.t + [0.0, 0.0, 0.12 * d]  # MSSD = 0.12 d: correct from 0.15 on (8 of 10 thresholds)
    o = score(dev, ests)["per_object"]["1"]
    assert o["ar_mssd"] == pytest.approx(0.8)
    assert o["recall_mssd"][:2] == [0.0, 0.0] and o["add_recall"] == 0.0  # ADD = 0.12 d > 0.1 d
    assert o["te_median_mm"] == pytest.approx(0.12 * d)


def test_best_scoring_estimate_is_the_one_evaluated(dev):
    # one instance per object: only the top-scoring estimate counts, even if a lower one is right
    scene, _, _, im_ids = dev
    ests = gt_estimates(scene, im_ids)
    wrong = [Estimate(e.scene_id, e.im_id, e.obj_id, 2.0, e.R, e.t + [300.0, 0.0, 0.0], e.time)
             for e in ests if e.obj_id == 5]
    o = score(dev, ests + wrong)["per_object"]["5"]
    assert o["ar"] == 0.0 and o["n_est"] == 2 * len(wrong)
    o = score(dev, ests + [Estimate(w.scene_id, w.im_id, w.obj_id, 0.5, w.R, w.t, w.time) for w in wrong])
    assert o["per_object"]["5"]["ar"] == 1.0


def test_barely_visible_instances_do_not_count(dev):
    scene, _, vis, im_ids = dev
    i0 = im_ids[0]
    j = next(j for j, g in enumerate(scene.gt[i0]) if g.obj_id == 6)
    visib = {i: list(v) for i, v in vis.items()}
    visib[i0][j] = 0.05
    ests = [e for e in gt_estimates(scene, im_ids) if not (e.im_id == i0 and e.obj_id == 6)]
    m = score(dev, ests, visib)
    n = sum(len(scene.gt[i]) for i in im_ids)
    assert m["n_gt"] == n - 1 and m["n_gt_all"] == n and m["ar"] == 1.0
    assert sum(b["n_gt"] for b in m["recall_by_visibility"]) == n - 1


def test_score_results_end_to_end(tmp_path, lmo_dev, data_dir):
    im_ids = lmo_dev.im_ids[:2]
    ests = gt_estimates(lmo_dev, im_ids)
    for e in ests:  # BOP's own GT rotations are rounded (obj 12 to 6 digits): re-orthonormalise
        U, _, Vt = np.linalg.svd(e.R)
        e.R = U @ Vt
    csv = write_results(tmp_path / "gt.csv", ests)
    scene_dir, models = data_dir / "lmo" / "dev", data_dir / "lmo" / "models"
    m = score_results(csv, scene_dir, models, models_info=LMO_INFO, im_ids=im_ids)
    assert m["ar_mssd"] == 1.0 and m["ar_mspd"] == 1.0 and m["add_recall"] == 1.0 and m["ar"] == 1.0
    assert m["visibility_source"] != VISIB_FROM_GT_INFO  # LM-O dev has no scene_gt_info.json
    assert m["ms_per_image"] == pytest.approx(40.0)
    assert 0 < m["n_gt"] <= m["n_gt_all"] == len(ests)
    out = write_metrics_json(tmp_path / "m.json", m)
    back = json.loads(out.read_text())
    for k in ("n_gt", "n_est", "add_recall", "ar_mssd", "ar_mspd", "ar_vsd", "ar", "re_median_deg",
              "te_median_mm", "per_object", "detection", "ms_per_image"):
        assert k in back, k
    assert back["ar_vsd"] is None and set(back["per_object"]) == {str(e.obj_id) for e in ests}

    empty = write_results(tmp_path / "empty.csv", [])
    z = score_results(empty, scene_dir, models, models_info=LMO_INFO, im_ids=im_ids)
    assert z["ar"] == 0.0 and z["n_est"] == 0 and z["ms_per_image"] is None

    with pytest.raises(UserError, match="unknown obj_id 99"):
        bad = write_results(tmp_path / "bad.csv", [Estimate(2, im_ids[0], 99, 1.0, np.eye(3), np.zeros(3))])
        score_results(bad, scene_dir, models, models_info=LMO_INFO, im_ids=im_ids)
    with pytest.raises(UserError, match="no ground truth"):
        score_results(csv, scene_dir, models, models_info=LMO_INFO, im_ids=[999999])


def test_scoring_the_instances_of_some_of_the_scenes_objects(tmp_path, lmo_dev, data_dir):
    """A bundle of two of the scene's eight objects is scored on their instances alone; the
    others still hide parts of them where their meshes are known, and are left out where not."""
    im_ids = lmo_dev.im_ids[:3]
    ests = [e for e in gt_estimates(lmo_dev, im_ids) if e.obj_id in (8, 11)]
    for e in ests:
        U, _, Vt = np.linalg.svd(e.R)
        e.R = U @ Vt
    csv = write_results(tmp_path / "two.csv", ests)
    scene_dir, models = data_dir / "lmo" / "dev", data_dir / "lmo" / "models"
    every = score_results(csv, scene_dir, models, models_info=LMO_INFO, im_ids=im_ids)
    assert every["add_recall"] < 1.0  # the six objects without estimates count as misses
    two = score_results(csv, scene_dir, models, models_info=LMO_INFO, im_ids=im_ids, obj_ids=[8, 11])
    assert two["add_recall"] == 1.0 and two["ar_mspd"] == 1.0 and set(two["per_object"]) == {"8", "11"}
    assert two["n_gt"] == every["per_object"]["8"]["n_gt"] + every["per_object"]["11"]["n_gt"] > 0
    assert two["n_gt_all"] == sum(1 for i in im_ids for g in lmo_dev.gt[i] if g.obj_id in (8, 11))
    only = tmp_path / "only_two"  # a bundle's meshes: the other six are unknown
    only.mkdir()
    for o in (8, 11):
        (only / f"obj_{o:06d}.ply").symlink_to(models / f"obj_{o:06d}.ply")
    alone = score_results(csv, scene_dir, only, models_info=LMO_INFO, im_ids=im_ids, obj_ids=[8, 11])
    assert alone["add_recall"] == 1.0 and alone["n_gt"] >= two["n_gt"]
    seen = score_results(csv, scene_dir, only, models_info=LMO_INFO, im_ids=im_ids, obj_ids=[8, 11],
                         visibility_models_dir=models)
    assert seen["n_gt"] == two["n_gt"] and seen["recall_by_visibility"] == two["recall_by_visibility"]
    with pytest.raises(UserError, match=r"object\(s\) \[1"):  # scoring everything still needs every mesh
        score_results(csv, scene_dir, only, models_info=LMO_INFO, im_ids=im_ids)


def test_models_info_is_computed_once_and_cached(tmp_path, data_dir, monkeypatch):
    import shutil

    from tracker.evaluation import scoring
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(data_dir / "lmo" / "models" / "obj_000001.ply", models)
    monkeypatch.setenv("AUTOPOSE_CACHE", str(tmp_path / "cache"))
    info = scoring.models_info_for(models)
    assert info[1]["diameter"] == pytest.approx(102.099, rel=1e-3) and "symmetries_discrete" not in info[1]
    (cached,) = (tmp_path / "cache").glob("models_info_*.json")
    scoring._INFO_CACHE.clear()
    assert scoring.models_info_for(models) == info  # read back from the file
    assert scoring.models_info_for(models, {"1": {"diameter": 5.0}}) == {1: {"diameter": 5.0}}


def test_vsd_hand_cases():
    from tracker.evaluation.metrics import vsd
    K = np.array([[500.0, 0, 50], [0, 500.0, 50], [0, 0, 1]])
    gt = np.zeros((100, 100))
    gt[20:60, 20:60] = 1000.0                      # a 40x40 px square at 1 m
    taus = [5.0, 20.0]
    assert np.allclose(vsd(gt, gt, gt, K, 15.0, taus), 0.0)  # perfect estimate: no discrepancy
    far = np.where(gt > 0, 1010.0, 0.0)            # 10 mm further away, same silhouette
    assert np.allclose(vsd(far, gt, gt, K, 15.0, taus), [1.0, 0.0])  # beyond tau 5, within tau 20
    shifted = np.zeros_like(gt)
    shifted[20:60, 40:80] = 1000.0                 # half the square overlaps
    e = vsd(shifted, gt, np.maximum(gt, 0), K, 15.0, taus)
    # visible GT 1600 px; the estimate's 1600 px are all visible (800 on the square, 800 where
    # the scene has no depth reading): union 2400, intersection 800
    assert np.allclose(e, 1600 / 2400)
    occl = gt.copy()
    occl[20:60, 20:40] = 500.0                     # the left half hidden by something in front
    assert np.allclose(vsd(gt, gt, occl, K, 15.0, taus), 0.0)  # the hidden part does not count
    assert vsd(np.zeros_like(gt), np.zeros_like(gt), gt, K, 15.0, taus).tolist() == [1.0, 1.0]


def test_vsd_in_scoring_on_a_synthetic_scene_with_depth(tmp_path, data_dir):
    """A synth scene with depth: the ground truth as estimates scores AR_VSD 1; poses pushed
    50 mm away lose most of it; without depth, ar_vsd is null."""
    from tracker.core.bop import Estimate, load_scene, write_results
    from tracker.evaluation.scoring import score_results
    from tracker.training.synth.engine import SynthConfig, generate
    cfg = SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                      obj_ids=[1, 5, 9], seed=3, objects_per_image=(3, 3), depth=True)
    generate(cfg, tmp_path / "split", 2, workers=1, progress=False)
    scene_dir = tmp_path / "split" / "000000"
    scene = load_scene(scene_dir, require_gt=True)
    assert scene.has_depth and scene.read_depth(0).max() > 300  # mm
    ests = [Estimate(0, i, g.obj_id, 1.0, g.R, g.t, 0.1) for i in scene.im_ids for g in scene.gt[i]]
    write_results(tmp_path / "gt.csv", ests)
    m = score_results(tmp_path / "gt.csv", scene_dir, data_dir / "lmo" / "models")
    assert m["ar_vsd"] == pytest.approx(1.0) and m["ar"] == pytest.approx(1.0)
    far = [Estimate(e.scene_id, e.im_id, e.obj_id, 1.0, e.R, e.t + np.array([0, 0, 50.0]), 0.1) for e in ests]
    write_results(tmp_path / "far.csv", far)
    m2 = score_results(tmp_path / "far.csv", scene_dir, data_dir / "lmo" / "models")
    assert m2["ar_vsd"] < 0.7
    import shutil
    shutil.rmtree(scene_dir / "depth")
    assert score_results(tmp_path / "gt.csv", scene_dir, data_dir / "lmo" / "models")["ar_vsd"] is None
