"""Several detectors fused (``lab fuse-detectors``, tracker/runtime/fusion.py): the clustering on
hand-made detections, and a fused bundle that loads, runs both networks and refuses bad input."""
import json
import shutil

import numpy as np
import pytest

from tracker.core.errors import UserError
from tracker.runtime.estimator import Detection
from tracker.runtime.fusion import fuse, per_object


def _d(obj, box, score):
    return Detection(obj, np.array(box, float), score)


def test_fuse_averages_what_both_networks_see_and_halves_what_one_sees():
    a, a2 = [100, 100, 50, 50], [104, 100, 50, 50]
    net0 = [_d(1, a, 0.6), _d(1, [300, 300, 40, 40], 0.3), _d(1, [102, 101, 50, 50], 0.2)]
    net1 = [_d(1, a2, 0.4), _d(2, [0, 0, 20, 20], 0.5)]
    got = fuse([net0, net1], iou=0.5)
    assert [(d.obj_id, round(d.score, 3)) for d in got] == [(1, 0.5), (2, 0.25), (1, 0.15), (1, 0.1)]
    np.testing.assert_allclose(got[0].box, [0.6 * 100 + 0.4 * 104, 100, 50, 50])  # weighted by the scores
    # a network's second box on the same place starts its own cluster: one vote per network
    np.testing.assert_allclose(got[3].box, [102, 101, 50, 50])
    assert [len(v) for v in per_object(got, 1).values()] == [1, 1]
    assert [d.score for d in per_object(got, 5)[1]] == pytest.approx([0.5, 0.15, 0.1])


def test_a_wrong_top_box_loses_when_the_other_network_sees_the_right_one():
    wrong, right = [400, 50, 60, 60], [100, 100, 80, 80]
    got = fuse([[_d(8, wrong, 0.5), _d(8, right, 0.4)], [_d(8, [106, 98, 80, 84], 0.45)]])
    assert got[0].score == pytest.approx(0.425) and got[0].box[0] < 110
    assert got[1].score == pytest.approx(0.25) and got[1].box[0] == 400


def test_nothing_to_fuse_gives_nothing():
    assert fuse([[], []]) == []


def test_only_the_names_fusion_makes_are_member_files():
    from tracker.runtime.fusion import member_file, member_files, role_of
    assert [member_file(k) for k in (1, 2, 9)] == ["detector_2.onnx", "detector_3.onnx", "detector_10.onnx"]
    assert [role_of(member_file(k)) for k in (1, 9)] == ["detector_2", "detector_10"]
    entry = {"fusion": {"members": [{"file": "detector_2.onnx"}, {"file": "../x/detector_3.onnx"},
                                    {"file": "detector.onnx"}, {"file": "detector_01.onnx"}, {"file": 3}, 7]}}
    assert member_files(entry) == ["detector_2.onnx"]
    assert member_files({"fusion": {"members": 5}}) == member_files({"fusion": 1}) == member_files(None) == []


@pytest.fixture()
def fused(tiny_detector_bundle, tmp_path):
    from tracker.training.detector_fusion import fuse_detectors
    other = tmp_path / "other"
    shutil.copytree(tiny_detector_bundle, other)
    out = tmp_path / "fused"
    fuse_detectors(tiny_detector_bundle, [other], out_dir=out, score_thresh=0.01, floor=0.01, log=lambda *a: None)
    return out, other


@pytest.mark.parametrize("threads", [1, 2])
def test_a_bundle_fused_with_a_copy_of_itself_finds_what_its_network_finds(fused, tiny_detector_bundle, lmo_dev,
                                                                           threads):
    """Two copies of one network: every cluster holds the same box twice, so the fused detector
    gives the single network's candidates, boxes and scores unchanged; with two threads the
    networks run side by side, with one in turn: the same."""
    from dataclasses import replace

    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import Detector, decode
    out, _ = fused
    b = open_bundle(out)  # every hash verified, detector_2.onnx included
    assert b.manifest.artefacts["detector_2"] == "detector_2.onnx"
    f = b.manifest.detector["fusion"]
    assert f["members"][0]["from"]["bundle"].endswith("other") and f["score_thresh"] == 0.01
    det = Detector(b, threads=threads)
    assert len(det.networks) == 2 and (det._pool is not None) == (threads == 2)
    single = Detector(open_bundle(tiny_detector_bundle))
    frame = lmo_dev.read_rgb(lmo_dev.im_ids[0])
    dets, cands = det.detect(frame, candidates=True)
    maps, lb = single.networks[0].maps(frame)
    wide = replace(single._wide(single.spec, 0.01), score_thresh=0.01)
    ref = decode(maps, wide, lb, frame.shape[1::-1])
    assert len(cands) == min(len(ref), 100) > 0
    by_obj = {}
    for d in ref:
        by_obj.setdefault(d.obj_id, d)
    assert sorted((d.obj_id, round(d.score, 6)) for d in dets) == \
        sorted((o, round(d.score, 6)) for o, d in by_obj.items())
    for d in dets:
        np.testing.assert_allclose(d.box, by_obj[d.obj_id].box, atol=1e-9)
    assert det(frame) and all(d.obj_id in det.spec.classes for d in det(np.zeros((720, 1280, 3), np.uint8)))


def test_eval_runs_a_fused_detector(fused, data_dir, tmp_path):
    from tracker.evaluation.evaluate import evaluate
    m = evaluate(fused[0], data_dir / "lmo" / "dev", tmp_path / "m.json", boxes="detector", max_frames=2,
                 progress=False)
    assert m["n_gt"] > 0 and "ap50" in m["detection"]


def test_fusing_refuses_what_it_cannot_fuse(fused, tiny_detector_bundle, tmp_path):
    from tracker.training.detector_ensemble import join_detectors
    from tracker.training.detector_fusion import fuse_detectors
    out, other = fused
    quiet = {"log": lambda *a: None}
    with pytest.raises(UserError, match="fuses several networks already"):
        fuse_detectors(out, [other], out_dir=tmp_path / "x", **quiet)
    with pytest.raises(UserError, match="fuses several networks already"):
        fuse_detectors(other, [out], out_dir=tmp_path / "x", **quiet)
    with pytest.raises(UserError, match="nothing to fuse"):
        fuse_detectors(other, [], out_dir=tmp_path / "x", **quiet)
    with pytest.raises(UserError, match="--score-thresh must lie between 0 and 1"):
        fuse_detectors(other, [tiny_detector_bundle], out_dir=tmp_path / "x", score_thresh=1.0, **quiet)
    with pytest.raises(UserError, match="fuses several networks"):  # joining needs single networks
        join_detectors(out, [], out_dir=tmp_path / "x", mirror="both", log=lambda *a: None)
    m = json.loads((other / "manifest.json").read_text())
    m["detector"]["boxes"] = "amodal"
    (other / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="other objects or boxes"):
        fuse_detectors(tiny_detector_bundle, [other], out_dir=tmp_path / "x", **quiet)
    m["detector"]["boxes"], m["detector"]["max_per_class"] = "visible", 3
    (other / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="one instance per object"):
        fuse_detectors(other, [tiny_detector_bundle], out_dir=tmp_path / "x", **quiet)
    assert not (tmp_path / "x").exists()


def test_a_fused_bundle_with_a_bad_entry_or_file_is_refused_in_one_line(fused, tmp_path):
    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import Detector
    out, _ = fused
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    m = json.loads((bad / "manifest.json").read_text())
    m["detector"]["fusion"]["score_thresh"] = 2
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="fusion 'score_thresh' must lie between 0 and 1"):
        Detector(open_bundle(bad))
    m["detector"]["fusion"]["score_thresh"] = 0.2
    m["detector"]["fusion"]["members"][0]["file"] = "../other/detector.onnx"  # outside the hashed files
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="is not one of the bundle's fused-network artefacts"):
        Detector(open_bundle(bad))
    m["detector"]["fusion"]["members"][0]["file"] = "detector.onnx"  # the first network twice
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="is not one of the bundle's fused-network artefacts"):
        Detector(open_bundle(bad))
    del m["detector"]["fusion"]["members"]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="malformed detector fusion entry"):
        Detector(open_bundle(bad))
    with open(out / "detector_2.onnx", "ab") as f:
        f.write(b"\0")
    with pytest.raises(UserError, match="detector_2.onnx"):
        open_bundle(out)


def test_retraining_keeps_or_replaces_the_fused_detector_whole(fused, tiny_bundle):
    """A new encoder on a fused bundle keeps every network of its detector; a new detector
    replaces all of them (no network left behind that nothing runs)."""
    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import Detector
    from tracker.training.detector_train import train_detector
    from tracker.training.train import train_bundle
    from tests.conftest import REPO
    out, _ = fused
    split = tiny_bundle.parent / "split"
    train_bundle(split, out, method="cvam", size=32, latent=16, max_steps=2, reg_epochs=1,
                 models_info_path=REPO / "models" / "lmo_models_info.json", log=lambda *a: None)
    b = open_bundle(out)
    assert "fusion" in b.manifest.detector and b.manifest.artefacts["detector_2"] == "detector_2.onnx"
    assert len(Detector(b).networks) == 2
    train_detector(split, out, max_steps=2, width=4, batch=2, log=lambda *a: None)
    b = open_bundle(out)
    assert "fusion" not in b.manifest.detector and "detector_2" not in b.manifest.artefacts
    assert not (out / "detector_2.onnx").exists() and len(Detector(b).networks) == 1


def test_networks_of_other_inputs_fuse_as_their_own_decodings_say(tiny_detector_bundle, tiny_bundle, lmo_dev,
                                                                  tmp_path):
    """A 320 x 240 and a 160 x 120 network: each letterboxes the frame to its own input and
    decodes its own maps; the fused run-time detections and AP candidates are fuse() of those,
    and verified candidates group an object's next clusters."""
    from dataclasses import replace

    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import CANDIDATE_SCORE, Detector, decode
    from tracker.training.detector_fusion import fuse_detectors
    from tracker.training.detector_train import train_detector
    small = tmp_path / "small"
    shutil.copytree(tiny_bundle, small)
    train_detector(tiny_bundle.parent / "split", small, max_steps=3, width=4, batch=2, input_w=160, input_h=120,
                   log=lambda *a: None)
    out = tmp_path / "fused"
    fuse_detectors(tiny_detector_bundle, [small], out_dir=out, score_thresh=0.02, floor=0.02, log=lambda *a: None)
    det = Detector(open_bundle(out), threads=2)
    assert [(n.spec.input_w, n.spec.input_h) for n in det.networks] == [(320, 240), (160, 120)]
    frame = lmo_dev.read_rgb(lmo_dev.im_ids[0])
    outs = [n.maps(frame) for n in det.networks]
    assert [o[0].shape[1:] for o in outs] == [(30, 40), (15, 20)]

    def by_hand(floor):
        return fuse([decode(m, replace(Detector._wide(n.spec, floor), score_thresh=floor), lb, (640, 480))
                     for n, (m, lb) in zip(det.networks, outs)])
    dets, cands = det.detect(frame, candidates=True)
    want = {}
    for d in by_hand(0.02):
        want.setdefault(d.obj_id, d)
    assert sorted((d.obj_id, round(d.score, 6)) for d in dets) == \
        sorted((o, round(d.score, 6)) for o, d in want.items() if d.score >= 0.02)
    ranked = by_hand(CANDIDATE_SCORE)  # AP's list: at most 10 clusters of an object, 100 in all
    per = [sum(d.obj_id == o for d in ranked) for o in det.spec.classes]
    assert len(cands) == min(100, sum(min(10, k) for k in per)) >= len(dets) and max(per) > 10
    det.spec = replace(det.spec, candidates=3, candidate_floor=0.02)
    grouped = det(frame)
    assert all(d.group == d.obj_id for d in grouped)
    assert max(sum(d.obj_id == o for d in grouped) for o in det.spec.classes) <= 3
    assert {d.obj_id for d in grouped} == {d.obj_id for d in dets}
