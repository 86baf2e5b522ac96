"""Verified candidates: an object's several detector boxes are all posed and the most confident
pose is kept (DetectorSpec.candidates), so a wrong top box loses to a right second one."""
import numpy as np
import pytest

from tests.conftest import REPO
from tests.test_detector import _maps
from tracker.runtime.detector import DetectorSpec, decode
from tracker.runtime.estimator import Detection, PoseEstimate, most_confident


def test_decode_groups_an_objects_candidates_and_keeps_presence_at_the_threshold():
    spec = DetectorSpec(classes=[1, 5], score_thresh=0.3, candidates=3, candidate_floor=0.05)
    m = _maps(spec, [(0, 5, 5, 0.9, 24, 24, 0, 0), (0, 20, 30, 0.2, 24, 24, 0, 0),   # object 1: two places
                     (0, 5, 6, 0.85, 24, 24, 0, 0),                                   # a near copy of its best
                     (0, 25, 2, 0.03, 24, 24, 0, 0),                                  # under the floor
                     (1, 12, 12, 0.25, 24, 24, 0, 0)])                                # object 5: under 0.3
    dets = decode(m, spec)
    # object 5's best peak is under the run-time threshold: not present, whatever its candidates
    assert [(d.obj_id, d.group, round(d.score, 2)) for d in dets] == [(1, 1, 0.9), (1, 1, 0.2)]
    spec.candidates = 1  # off: the one best box, no group, as before
    assert [(d.obj_id, d.group, round(d.score, 2)) for d in decode(m, spec)] == [(1, None, 0.9)]


def _pose(obj, score):
    return PoseEstimate(obj, np.eye(3), np.zeros(3), score, np.zeros(4))


def test_most_confident_keeps_one_pose_per_group_and_ungrouped_ones():
    a, b, c = Detection(1, np.zeros(4), 0.9, group=1), Detection(1, np.zeros(4), 0.4, group=1), Detection(2, np.zeros(4))
    pa, pb, pc = _pose(1, 0.2), _pose(1, 0.6), _pose(2, 0.1)
    assert most_confident([(a, pa), (c, pc), (b, pb)]) == [pb, pc]  # the group's best, at its first place
    tie = _pose(1, 0.2)
    assert most_confident([(a, pa), (b, tie)])[0] is pa                  # a tie keeps the detector's better box
    # ground-truth boxes of two instances of one object have no group: both kept
    assert most_confident([(Detection(1, np.zeros(4)), pa), (Detection(1, np.zeros(4)), pb)]) == [pa, pb]


def test_a_wrong_top_box_loses_to_the_right_second_one(data_dir):
    """models/lmo on a dev frame: the duck's top candidate is a box on the background, its second
    the duck's own box; the pose kept is the one made from the duck's box."""
    from tracker.core.bop import load_scene
    from tracker.evaluation.ground_truth import gt_boxes
    from tracker.core.meshes import load_models
    from tracker.runtime.estimator import PoseEstimator
    scene = load_scene(data_dir / "lmo" / "dev", require_gt=True)
    im = sorted(scene.gt)[0]
    models = load_models(data_dir / "lmo" / "models")
    box_of, _ = gt_boxes(scene, models, [im])
    k = next(j for j, g in enumerate(scene.gt[im]) if g.obj_id == 9)
    right = np.asarray(box_of[im][k][0], float)
    wrong = right.copy()
    wrong[:2] = (right[0] + 250) % 500, (right[1] + 180) % 360   # the same size, elsewhere
    est = PoseEstimator(REPO / "models" / "lmo")
    img, K = scene.read_rgb(im), scene.K(im)
    dets = [Detection(9, wrong, 0.9, group=9), Detection(9, right, 0.5, group=9)]
    (p,) = est.estimate(img, K, dets)
    assert np.allclose(p.box, right)
    gt = scene.gt[im][k]
    assert np.linalg.norm(p.t - gt.t) < 0.2 * np.linalg.norm(gt.t)   # a pose of the duck, near it
    # without the group the two boxes give two poses, the wrong one first
    both = est.estimate(img, K, [Detection(9, wrong, 0.9), Detection(9, right, 0.5)])
    assert len(both) == 2 and both[0].score < p.score == pytest.approx(both[1].score)


def test_eval_takes_the_candidates_and_records_them(data_dir, tmp_path):
    from tracker.evaluation.evaluate import evaluate
    kw = dict(boxes="detector", max_frames=2, progress=False)
    one = evaluate(REPO / "models" / "lmo", data_dir / "lmo" / "dev", tmp_path / "1.json", **kw)
    three = evaluate(REPO / "models" / "lmo", data_dir / "lmo" / "dev", tmp_path / "3.json", candidates_per_object=3,
                     candidate_floor=0.05, **kw)
    assert one["detection"]["candidates"] == {"per_object": 1, "floor": 0.05}  # the bundle's: off
    assert three["detection"]["candidates"] == {"per_object": 3, "floor": 0.05}
    assert three["n_est"] == one["n_est"]  # one pose per object either way: the most confident of its boxes


def _schedule(propagate, frames_dets, min_confidence=0.3):
    """A BoxSchedule on a scripted detector (one list of detections per call); the model points
    of object 1 and 5: a 100 mm cube."""
    from tracker.runtime.pipeline import BoxSchedule
    cube = np.array([[x, y, z] for x in (-50, 50) for y in (-50, 50) for z in (-50, 50)], float)
    calls = iter(frames_dets)
    return BoxSchedule(lambda rgb: next(calls), 1, {1: cube, 5: cube}, propagate=propagate,
                       min_confidence=min_confidence)


K_TEST = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def test_the_previous_pose_box_joins_the_objects_candidates_and_never_stands_alone_in_join():
    img = np.zeros((480, 640, 3), np.uint8)
    wrong = Detection(1, np.array([0.0, 0, 40, 40]), 0.8)
    s = _schedule("join", [[Detection(1, np.array([270.0, 190, 100, 100]), 0.9)], [wrong], []])
    first, src = s.boxes(img, K_TEST)
    assert src == "detector" and len(first) == 1  # no previous pose yet: the detector's boxes as they are
    at = PoseEstimate(1, np.eye(3), np.array([0.0, 0, 1000]), 0.7, first[0].box)
    s.update([at])
    dets, _ = s.boxes(img, K_TEST)
    # the detector's (wrong) box and the pose's box, one group, the pose box at the detector's score
    assert [d.obj_id for d in dets] == [1, 1] and dets[0].group == dets[1].group is not None
    assert np.allclose(dets[0].box, wrong.box) and dets[1].score == 0.8
    half = 50 * 500 / 950  # the cube's near face, 950 mm away, spans the box
    assert np.allclose(dets[1].box, [320 - half, 240 - half, 2 * half + 1, 2 * half + 1])  # pixels inclusive
    s.update([at])
    assert s.boxes(img, K_TEST)[0] == []  # the detector found nothing: 'join' adds nothing


def test_all_adds_a_missed_object_only_while_its_pose_was_confident():
    img = np.zeros((480, 640, 3), np.uint8)
    s = _schedule("all", [[], [], []])
    s.prev = [PoseEstimate(5, np.eye(3), np.array([0.0, 0, 1000]), 0.6, np.zeros(4))]
    s.lost = False
    (d,), _ = s.boxes(img, K_TEST)
    assert d.obj_id == 5 and d.group is None and d.score == 0.6  # the previous confidence carries (and fades)
    s.update([PoseEstimate(5, np.eye(3), np.array([0.0, 0, 1000]), 0.2, d.box)])  # verified weakly: below 0.3
    assert s.boxes(img, K_TEST)[0] == []  # not propagated again
    off = _schedule("off", [[]])
    off.prev, off.lost = [PoseEstimate(5, np.eye(3), np.array([0.0, 0, 1000]), 0.9, np.zeros(4))], False
    assert off.boxes(img, K_TEST)[0] == []


def test_an_unknown_propagation_mode_is_one_line():
    from tracker.core.errors import UserError
    with pytest.raises(UserError, match="--propagate sometimes"):
        _schedule("sometimes", [])
