"""The detector's decoding, NMS, letterbox, COCO AP, and a tiny training run end to end."""
import json
import shutil

import numpy as np
import pytest

from tracker.evaluation.detection_metrics import box_errors, detection_ap
from tracker.runtime.detector import DetectorSpec, Letterbox, decode, letterbox, nms
from tracker.core.geometry import iou_matrix
from tracker.core.errors import UserError
from tracker.runtime.estimator import Detection


def _maps(spec, peaks_):
    """Hand-made network output: peaks = [(class index, y, x, score, w px, h px, off x, off y)]."""
    C = len(spec.classes)
    m = np.zeros((C + 4, 30, 40), np.float32)
    m[:C] = 0.01
    for c, y, x, s, w, h, ox, oy in peaks_:
        m[c, y, x] = s
        m[C:, y, x] = (np.log(w / spec.stride), np.log(h / spec.stride), ox, oy)
    return m


def test_decode_one_peak_in_input_and_frame_pixels():
    spec = DetectorSpec(classes=[1, 5, 6])
    m = _maps(spec, [(1, 10, 20, 0.9, 32, 16, 0.5, 0.25)])
    (d,) = decode(m, spec)
    assert d.obj_id == 5 and d.score == pytest.approx(0.9)
    cx, cy = 20.5 * 8, 10.25 * 8
    np.testing.assert_allclose(d.box, [cx - 16, cy - 8, 32, 16], atol=1e-4)
    # a 1280x960 frame letterboxed to 320x240 is scaled by 1/4: boxes come back 4x
    (d2,) = decode(m, spec, Letterbox(0.25, 0.25, 0, 0), (1280, 960))
    np.testing.assert_allclose(d2.box, 4 * d.box, atol=1e-3)


def test_decode_threshold_nms_and_one_per_class():
    spec = DetectorSpec(classes=[1, 5], score_thresh=0.3, max_per_class=1)
    assert decode(_maps(spec, [(0, 5, 5, 0.2, 20, 20, 0, 0)]), spec) == []  # below the threshold
    m = _maps(spec, [(0, 10, 10, 0.9, 40, 40, 0, 0), (0, 10, 13, 0.8, 40, 40, 0, 0),  # same object, twice
                     (1, 10, 11, 0.7, 40, 40, 0, 0)])                                   # another object
    dets = decode(m, spec)
    assert [d.obj_id for d in dets] == [1, 5]
    assert dets[0].score == pytest.approx(0.9)
    # with room for several per class (5, of which 2 are used), NMS alone decides: the two boxes of
    # class 0, 3 cells (24 px) apart, overlap by IoU 16*40 / (2*40*40 - 16*40) = 0.25; a threshold
    # below that makes them one object, one above it two
    spec.max_per_class = 5
    spec.nms_iou = 0.3
    dets = decode(m, spec)
    assert [(d.obj_id, round(d.score, 3)) for d in dets] == [(1, 0.9), (1, 0.8), (5, 0.7)]
    assert iou_matrix(dets[0].box[None], dets[1].box[None])[0, 0] == pytest.approx(0.25)
    spec.nms_iou = 0.2
    assert [(d.obj_id, round(d.score, 3)) for d in decode(m, spec)] == [(1, 0.9), (5, 0.7)]

    # NMS itself (several instances per class allowed, so not the one-per-class shortcut): two
    # peaks 2 cells apart (two local maxima) whose 80 px boxes overlap by IoU
    # 64*80 / (2*80*80 - 64*80) = 2/3 > 0.5 are one object and the weaker is suppressed; a
    # peak far away is a second instance of the same class and survives
    spec = DetectorSpec(classes=[1, 5], score_thresh=0.3, max_per_class=5, nms_iou=0.5)
    m = _maps(spec, [(0, 10, 10, 0.9, 80, 80, 0, 0), (0, 10, 12, 0.8, 80, 80, 0, 0),  # one object, twice
                     (0, 25, 35, 0.6, 40, 40, 0, 0),                                    # a second instance
                     (1, 10, 11, 0.7, 80, 80, 0, 0)])  # another class on top of them: NMS is class-wise
    dets = decode(m, spec)
    assert [(d.obj_id, round(d.score, 3)) for d in dets] == [(1, 0.9), (5, 0.7), (1, 0.6)]
    np.testing.assert_allclose(dets[0].box, [10 * 8 - 40, 10 * 8 - 40, 80, 80], atol=1e-4)  # the stronger one
    np.testing.assert_allclose(dets[2].box, [35 * 8 - 20, 25 * 8 - 20, 40, 40], atol=1e-4)
    # the same boxes with an IoU threshold above 2/3 are two instances: both kept ...
    spec.nms_iou = 0.7
    assert [round(d.score, 3) for d in decode(m, spec) if d.obj_id == 1] == [0.9, 0.8, 0.6]
    # ... and max_per_class caps what NMS keeps, best first
    spec.max_per_class = 2
    assert [round(d.score, 3) for d in decode(m, spec) if d.obj_id == 1] == [0.9, 0.8]


def test_nms_and_iou():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 10, 10], [50, 50, 10, 10]], float)
    assert iou_matrix(boxes[:1], boxes[1:2])[0, 0] == pytest.approx(81 / 119)
    assert nms(boxes, np.array([0.5, 0.9, 0.7]), 0.5) == [1, 2]


def test_letterbox_maps_boxes_back():
    img = np.zeros((720, 1280, 3), np.uint8)
    img[100:200, 300:500] = 255
    lb_img, lb = letterbox(img, 320, 240)
    assert lb_img.shape == (240, 320, 3)
    box_in = lb.to_input(np.array([[300, 100, 200, 100]]))
    ys, xs = np.nonzero(lb_img[..., 0] > 127)
    assert abs(xs.min() - box_in[0, 0]) <= 1 and abs(ys.min() - box_in[0, 1]) <= 1
    np.testing.assert_allclose(lb.to_frame(box_in), [[300, 100, 200, 100]], atol=1e-9)


def test_ap_hand_cases():
    gt = [[(1, np.array([10, 10, 20, 20.]))], [(1, np.array([50, 50, 20, 20.]))]]
    perfect = [[Detection(1, np.array([10, 10, 20, 20.]), 0.9)], [Detection(1, np.array([50, 50, 20, 20.]), 0.8)]]
    r = detection_ap(perfect, gt, [1])
    assert r["ap"] == pytest.approx(1.0) and r["recall50"] == 1.0
    # a false positive scored above both hits: precision 1/2 then 2/3 -> AP50 = 2/3 (envelope)
    fp = [perfect[0] + [Detection(1, np.array([200, 200, 20, 20.]), 0.95)], perfect[1]]
    assert detection_ap(fp, gt, [1])["ap50"] == pytest.approx(2 / 3, abs=1e-9)
    # one of the two missed: recall 0.5, AP 0.5
    r = detection_ap([perfect[0], []], gt, [1])
    assert r["recall50"] == 0.5 and r["ap50"] == pytest.approx(0.5, abs=0.01)
    # a box shifted to IoU ~0.6 counts at 0.5 but not at 0.75
    shifted = [[Detection(1, np.array([14, 10, 20, 20.]), 0.9)], perfect[1]]
    r = detection_ap(shifted, gt, [1])
    assert r["ap50"] == pytest.approx(1.0) and r["ap"] < 0.8
    # a detection on an ignored (< 10 % visible) instance is not a false positive ...
    ign = [[(1, np.array([200, 200, 20, 20.]))], []]
    assert detection_ap(fp, gt, [1], ignore=ign)["ap50"] == pytest.approx(1.0)
    # ... but, as in pycocotools, an ignored instance absorbs one detection only
    fp2 = [fp[0] + [Detection(1, np.array([201, 200, 20, 20.]), 0.97)], perfect[1]]
    assert detection_ap(fp2, gt, [1], ignore=ign)["ap50"] == pytest.approx(2 / 3, abs=1e-9)


def test_occlusion_pastes_clutter_and_drops_hidden_boxes():
    torch = pytest.importorskip("torch")
    from tracker.training.detector_train import occlude
    x = torch.zeros(2, 3, 60, 80)
    x[1] = 1.0  # the second item is the only source of clutter for the first
    # class, x, y, w, h: a box over the whole image and a tiny one
    boxes = [np.array([[0, 0, 0, 80, 60], [1, 10, 10, 2, 2]], np.float32), np.zeros((0, 5), np.float32)]
    out, kept = occlude(x.clone(), boxes, np.random.default_rng(0), p=1.0)
    pasted = out[0, 0] > 0.5
    assert 0 < pasted.float().mean() < 0.5       # some clutter, never most of the image
    assert torch.equal(out[1], x[1])             # its only source shows an object everywhere: no clutter
    assert kept[0][0, 0] == 0                    # the big box is mostly visible: kept
    hidden_small = bool(pasted[10:12, 10:12].float().mean() > 0.5)
    assert (1 in kept[0][:, 0]) != hidden_small  # the tiny box survives exactly when not hidden
    same, same_boxes = occlude(x.clone(), boxes, np.random.default_rng(0), p=0.0)
    assert torch.equal(same, x) and same_boxes[0] is boxes[0]


def test_hue_turns_keep_grey_and_cycle_the_channels():
    from tracker.training.detector_train import hue_turns
    R = hue_turns([0.0, 2 * np.pi / 3, 1.0])
    assert np.allclose(R[0], np.eye(3), atol=1e-6)
    assert np.allclose(R[1] @ [1, 0, 0], [0, 1, 0], atol=1e-6)   # a third of a turn: red -> green
    assert np.allclose(R[2] @ [0.5, 0.5, 0.5], [0.5, 0.5, 0.5], atol=1e-6)  # grey stays grey
    assert not np.allclose(R[2] @ [1, 0, 0], [1, 0, 0], atol=1e-2)


def test_strong_colour_changes_colours_not_boxes():
    torch = pytest.importorskip("torch")
    from tracker.training.detector_train import augment_batch
    x = torch.rand(16, 3, 48, 64)
    boxes = [np.array([[0, 10, 8, 30, 20]], np.float32) for _ in range(16)]
    torch.manual_seed(0)
    std, b_std = augment_batch(x.clone(), boxes, np.random.default_rng(3), torch)
    torch.manual_seed(0)
    again, _ = augment_batch(x.clone(), boxes, np.random.default_rng(3), torch, colour="standard")
    strong, b_strong = augment_batch(x.clone(), boxes, np.random.default_rng(3), torch, colour="strong")
    for a, b in zip(b_std, b_strong):   # zoom and shift are drawn first: the same boxes
        assert np.array_equal(a, b)
    assert not torch.allclose(std, strong, atol=0.05)
    assert torch.equal(std, again)      # the default is the standard path, draw for draw
    torch.manual_seed(0)
    mild, _ = augment_batch(x.clone(), boxes, np.random.default_rng(3), torch, colour="mild")
    grey = x.clone()
    grey[:] = x.mean(dim=1, keepdim=True)  # grey pixels: saturation and white balance are all that differ
    torch.manual_seed(0)
    g_std, _ = augment_batch(grey.clone(), boxes, np.random.default_rng(3), torch)
    torch.manual_seed(0)
    g_mild, _ = augment_batch(grey.clone(), boxes, np.random.default_rng(3), torch, colour="mild")
    def tint(y):  # each image's mean colour away from grey (the noise averages out)
        c = y.mean(dim=(2, 3))
        return float((c - c.mean(dim=1, keepdim=True)).abs().max())
    assert tint(g_mild) < 0.005 < 0.02 < tint(g_std) and not torch.equal(mild, std)


def test_pasted_objects_join_the_targets():
    torch = pytest.importorskip("torch")
    from tracker.training.detector_train import occlude
    x = torch.zeros(2, 3, 60, 80)
    x[1, :, 20:30, 40:52] = 1.0  # item 1's object, class 3: the only bright pixels
    boxes = [np.zeros((0, 5), np.float32), np.array([[3, 40, 20, 12, 10]], np.float32)]
    out, kept = occlude(x.clone(), boxes, np.random.default_rng(1), p=1.0, objects=1.0)
    assert len(kept[0]) >= 1 and set(kept[0][:, 0]) == {3}
    for _, bx, by, bw, bh in kept[0]:  # each new target's box shows the pasted object
        assert 0 <= bx and bx + bw <= 80 and 0 <= by and by + bh <= 60
        assert out[0, 0, int(by):int(by + bh), int(bx):int(bx + bw)].min() == 1.0
    assert torch.equal(out[1], x[1]) and np.array_equal(kept[1], boxes[1])  # nothing to take from item 0
    # without objects the random stream and the result are those of plain clutter
    a, ka = occlude(x.clone(), boxes, np.random.default_rng(2), p=1.0)
    b, kb = occlude(x.clone(), boxes, np.random.default_rng(2), p=1.0, objects=0.0)
    assert torch.equal(a, b) and all(np.array_equal(u, v) for u, v in zip(ka, kb))


def _write_cutouts(folder):
    import cv2
    folder.mkdir(parents=True, exist_ok=True)
    im = np.zeros((40, 60, 4), np.uint8)  # BGRA: a red 20x30 block in a clear border
    im[10:30, 15:45] = (0, 0, 255, 255)
    im[10:30, 45] = (255, 0, 0, 128)      # and a half-clear blue column beside it
    cv2.imwrite(str(folder / "block.png"), im)
    cv2.imwrite(str(folder / "opaque.png"), np.full((20, 20, 4), 255, np.uint8))  # nothing cut out
    cv2.imwrite(str(folder / "photo.png"), np.full((20, 20, 3), 90, np.uint8))    # no alpha at all
    (folder / "notes.txt").write_text("not an image")


def test_cutouts_load_cropped_premultiplied_rgba_and_skip_images_without_transparency(tmp_path):
    from tracker.training.detector_train import load_cutouts
    _write_cutouts(tmp_path / "cut" / "sub")
    logs = []
    (c,), ident = load_cutouts(tmp_path / "cut", logs.append)  # found in a subfolder
    assert c.shape == (20, 31, 4)                                 # cropped to its non-clear pixels
    assert (c[:, :30] == (255, 0, 0, 255)).all()                  # RGB order inside
    assert (c[:, 30] == (0, 0, 128, 128)).all()                   # colour times alpha
    assert "2 skipped" in logs[0] and ident.startswith("1 images, id ")
    (tmp_path / "cut" / "sub" / "more.png").write_bytes((tmp_path / "cut" / "sub" / "block.png").read_bytes())
    assert load_cutouts(tmp_path / "cut", log=lambda *a: None)[1].startswith("2 images")
    (tmp_path / "none").mkdir()
    with pytest.raises(UserError, match="no images with transparency"):
        load_cutouts(tmp_path / "none", log=lambda *a: None)
    with pytest.raises(UserError, match="no such folder"):
        load_cutouts(tmp_path / "missing", log=lambda *a: None)


def test_cutouts_are_blended_by_their_alpha_and_hide_boxes():
    torch = pytest.importorskip("torch")
    from tracker.training.detector_train import paste_cutouts
    cut = np.zeros((20, 40, 4), np.uint8)   # premultiplied: pure red on the right, clear on the left
    cut[:, 20:] = (255, 0, 0, 255)
    grid = np.array([[k, 4 * (k % 20), 4 * (k // 20), 4, 4] for k in range(300)], np.float32)  # 4x4 boxes tiling 80x60
    boxes = [grid] * 8
    x = torch.full((8, 3, 60, 80), 0.2)
    out, kept = paste_cutouts(x.clone(), boxes, np.random.default_rng(0), [cut], p=1.0)
    n_hidden = 0
    for img, k in zip(out, kept):
        g = img[1].numpy()                   # the cut-out has no green: green = 0.2 x (1 - alpha)
        assert torch.equal(img[1], img[2])   # the background shows through by (1 - alpha) alone
        clear = g == np.float32(0.2)
        assert 0 < (~clear).mean() < 0.5 and (img[0].numpy()[clear] == np.float32(0.2)).all()
        opaque = g < 0.1                     # alpha > 127
        for c, bx, by, bw, bh in grid:
            hidden = opaque[int(by):int(by + bh), int(bx):int(bx + bw)].mean() > 0.5
            assert (c in k[:, 0]) != hidden  # a box leaves the targets exactly when hidden
            n_hidden += hidden
    assert n_hidden > 0
    # the same draws with an opaque cut-out: the clear half showed nothing, the opaque half all
    full, _ = paste_cutouts(x.clone(), boxes, np.random.default_rng(0), [np.zeros_like(cut) + np.uint8([255, 0, 0, 255])], p=1.0)
    half, whole = (out[:, 1] < 0.2).numpy(), (full[:, 1] < 0.2).numpy()
    assert not (half & ~whole).any() and 0.4 < half.sum() / whole.sum() < 0.6
    same, same_boxes = paste_cutouts(x.clone(), boxes, np.random.default_rng(0), [cut], p=0.0)
    assert torch.equal(same, x) and same_boxes[0] is boxes[0]


def test_cutout_options_are_checked_before_training(tiny_bundle, tmp_path):
    from tracker.training.detector_train import train_detector
    with pytest.raises(UserError, match="--cutouts .*no such folder"):
        train_detector(tiny_bundle.parent / "split", tiny_bundle, max_steps=5, cutouts=tmp_path / "nope")
    with pytest.raises(UserError, match="--cutout-share .* needs --cutouts"):
        train_detector(tiny_bundle.parent / "split", tiny_bundle, max_steps=5, cutout_share=0.3)


def test_pasting_objects_without_occlusion_is_refused(tiny_bundle):
    pytest.importorskip("torch")
    from tracker.training.detector_train import train_detector
    with pytest.raises(UserError, match="--occlusion"):
        train_detector(tiny_bundle.parent / "split", tiny_bundle, max_steps=5, paste_objects=0.5)


def test_a_stage_budget_caps_the_detectors_training(tiny_bundle, tmp_path, monkeypatch):
    """build's detector stage: loading the images, validation and export come out of the same
    budget, so the training itself gets less than ``minutes``. Counted in steps: the detector's
    clock is the test's, one second a reading (about one a step), whatever the machine's load."""
    from tests.conftest import FakeClock
    import tracker.training.detector_train as dt
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    monkeypatch.setattr(dt, "time", FakeClock(tick=1.0).module_time())
    d = dt.train_detector(tiny_bundle.parent / "split", root, minutes=5.0, width=8, batch=2, log=lambda *a: None,
                          stage_minutes=dt.AFTER_MINUTES + 0.05)
    # 0.05 min (3 readings) left to train: a few steps, not the 5 minutes (about 300) asked
    assert 1 <= d["training"]["steps"] <= 3 and d["training"]["minutes"] <= 0.1


def test_a_bundle_with_a_detector_can_train_another(tiny_detector_bundle, tiny_bundle, tmp_path):
    from tracker.core.bundle import open_bundle
    from tracker.training.detector_train import train_detector
    root = tmp_path / "lmo"
    shutil.copytree(tiny_detector_bundle, root)
    before = open_bundle(root).manifest.files["detector.onnx"]["sha256"]
    train_detector(tiny_bundle.parent / "split", root, max_steps=10, width=4, batch=2, log=lambda *a: None)
    after = open_bundle(root).manifest  # hashes verified: the new detector replaced the old one
    assert after.detector["training"]["width"] == 4
    assert after.files["detector.onnx"]["sha256"] != before


def test_a_detector_can_start_from_another_runs_weights(tiny_detector_bundle, tiny_bundle, tmp_path):
    from tracker.core.bundle import open_bundle
    from tracker.training.detector_train import train_detector
    src = next((tiny_detector_bundle.parent / "lmo.work").glob("detector_ckpt_*.pt"))
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    logs = []
    train_detector(tiny_bundle.parent / "split", root, max_steps=5, width=8, batch=2, init_from=src, log=logs.append)
    assert any(str(ln).startswith("started from the weights of") for ln in logs)
    assert open_bundle(root).manifest.detector["training"]["init_from"] == str(src)
    with pytest.raises(UserError, match="width 8 .* this run has width 4"):
        train_detector(tiny_bundle.parent / "split", tmp_path / "lmo", max_steps=5, width=4, batch=2,
                       init_from=src, log=lambda *a: None)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(UserError, match="not a detector checkpoint"):
        train_detector(tiny_bundle.parent / "split", tmp_path / "lmo", max_steps=5, width=4, batch=2,
                       init_from=tmp_path / "junk.pt", log=lambda *a: None)


def test_a_detector_can_start_from_a_bundles_exported_network(tiny_detector_bundle, tiny_bundle, tmp_path, monkeypatch):
    """Weights read back from the ONNX graph (BatchNorms folded) give the exported network's
    output; the fine-tune keeps its BatchNorms frozen, and joined networks are refused."""
    pytest.importorskip("onnx")
    from tracker.core.bundle import open_bundle
    from tracker.training.detector_train import _init_weights, train_detector
    from tracker.training.nets.detector import CenterNetLite
    from tracker.training.train import require_torch
    torch = require_torch()
    classes = open_bundle(tiny_detector_bundle).manifest.detector["classes"]
    sd, frozen = _init_weights(torch, tiny_detector_bundle, 8, classes)  # checks itself against onnxruntime
    assert frozen
    m = CenterNetLite(len(classes), 8)
    m.load_state_dict(sd)
    bns = [b for b in m.modules() if isinstance(b, torch.nn.BatchNorm2d)]
    assert bns and all(torch.all(b.running_mean == 0) and torch.all(b.weight == 1) for b in bns)
    from tracker.runtime.detector import run_graph as _run
    spec = DetectorSpec.from_dict(open_bundle(tiny_detector_bundle).manifest.detector)
    x = np.random.default_rng(1).uniform(-2, 2, (1, 3, spec.input_h, spec.input_w)).astype(np.float32)
    with torch.no_grad():
        y = m.eval()(torch.from_numpy(x)).numpy()
    assert np.abs(_run(tiny_detector_bundle / spec.file, x) - y).max() < 1e-4
    with pytest.raises(UserError, match="not a width-4 network"):
        _init_weights(torch, tiny_detector_bundle, 4, classes)
    with pytest.raises(UserError, match="classes"):
        _init_weights(torch, tiny_detector_bundle, 8, classes[:-1])
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    seen = []
    import tracker.training.nets.detector as nd
    freeze = nd.freeze_batchnorm
    monkeypatch.setattr(nd, "freeze_batchnorm", lambda model: (seen.append(1), freeze(model)))
    train_detector(tiny_bundle.parent / "split", root, max_steps=5, width=8, batch=2, init_from=tiny_detector_bundle,
                   lr=1e-4, log=lambda *a: None)
    d = open_bundle(root).manifest.detector["training"]
    assert seen and d["frozen_batchnorm"] is True and d["init_from"] == str(tiny_detector_bundle)
    with pytest.raises(UserError, match=r"with --init-from a bundle \(its BatchNorms frozen\): rerun"):
        train_detector(tiny_bundle.parent / "split", root, max_steps=10, width=8, batch=2, lr=1e-4, log=lambda *a: None)
    joined = tmp_path / "joined"
    from tracker.training.detector_ensemble import join_detectors
    join_detectors(tiny_detector_bundle, [], out_dir=joined, mirror="both", log=lambda *a: None)
    with pytest.raises(UserError, match="joined or quantised already; start from the bundle of one"):
        _init_weights(torch, joined, 8, classes)


def test_amodal_targets_are_whole_silhouettes_clipped_to_the_image(tiny_bundle, tmp_path):
    from tracker.runtime.detector import DetectorSpec
    from tracker.training.detector_ensemble import join_detectors
    from tracker.training.detector_train import load_detection_set, target_box, train_detector
    info = {"bbox_visib": [10, 20, 30, 40], "bbox_obj": [-5, 15, 50, 60]}
    assert target_box(info, "visible", 640, 480) == [10, 20, 30, 40]
    assert target_box(info, "amodal", 40, 480) == [0, 15, 40, 60]
    assert target_box({"bbox_visib": [10, 20, 30, 40], "bbox_obj": [11, 19, 28, 40]}, "amodal", 640, 480) == [10, 19, 30, 41]
    split = tiny_bundle.parent / "split"
    classes = [1, 5, 6, 8, 9, 10, 11, 12]
    _, vis = load_detection_set(split, DetectorSpec(classes=classes), max_images=3, log=lambda *a: None)
    _, am = load_detection_set(split, DetectorSpec(classes=classes, boxes="amodal"), max_images=3, log=lambda *a: None)
    v, a = np.concatenate(vis), np.concatenate(am)
    assert len(v) == len(a) and np.all(a[:, 3] * a[:, 4] >= v[:, 3] * v[:, 4] - 1e-3)
    with pytest.raises(UserError, match="--boxes must be one of visible, amodal"):
        train_detector(split, tiny_bundle, max_steps=5, box_kind="whole")
    pytest.importorskip("torch")
    quiet = dict(log=lambda *a: None)
    a_dir, v_dir = tmp_path / "amodal", tmp_path / "visible"
    for d, kind in ((a_dir, "amodal"), (v_dir, "visible")):
        shutil.copytree(tiny_bundle, d)
        train_detector(split, d, max_steps=5, width=4, batch=2, box_kind=kind, **quiet)
    from tracker.core.bundle import open_bundle
    assert open_bundle(a_dir).manifest.detector["boxes"] == "amodal"
    with pytest.raises(UserError, match="differs from .* in boxes"):
        join_detectors(v_dir, [a_dir], out_dir=tmp_path / "j", **quiet)


def test_a_run_resumes_only_with_its_own_options(tiny_detector_bundle, tiny_bundle, tmp_path):
    from tracker.training.detector_train import train_detector
    root = tmp_path / "lmo"
    shutil.copytree(tiny_detector_bundle, root)
    shutil.copytree(tiny_detector_bundle.parent / "lmo.work", tmp_path / "lmo.work")
    logs = []
    train_detector(tiny_bundle.parent / "split", root, max_steps=12, width=8, batch=2, log=logs.append)
    assert any(str(ln).startswith("resumed from") for ln in logs)
    with pytest.raises(UserError, match=r"with --occlusion 0\.0: rerun with those options"):
        train_detector(tiny_bundle.parent / "split", root, max_steps=10, width=8, batch=2, occlusion=0.5,
                       log=lambda *a: None)
    with pytest.raises(UserError, match=r"with --colour standard: rerun"):
        train_detector(tiny_bundle.parent / "split", root, max_steps=10, width=8, batch=2, colour="strong",
                       log=lambda *a: None)
    with pytest.raises(UserError, match=r"--colour must be one of"):
        train_detector(tiny_bundle.parent / "split", root, max_steps=10, width=8, batch=2, colour="vivid",
                       log=lambda *a: None)
    _write_cutouts(tmp_path / "cut")
    with pytest.raises(UserError, match=r"with no --cutouts: rerun"):
        train_detector(tiny_bundle.parent / "split", root, max_steps=10, width=8, batch=2, cutouts=tmp_path / "cut",
                       log=lambda *a: None)


def test_a_split_rendered_again_is_cut_again_and_its_old_checkpoint_refused(tiny_bundle, tmp_path):
    """The caches are named for the split's folder; what the folder holds is checked apart: the
    images are cut again, and a checkpoint trained on the old images is not resumed."""
    import json
    from tracker.training.detector_train import train_detector
    split = tmp_path / "split"
    shutil.copytree(tiny_bundle.parent / "split", split)
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    train_detector(split, root, max_steps=5, width=8, batch=2, log=lambda *a: None)
    (cache,), (ckpt,) = (sorted((tmp_path / "lmo.work").glob(p)) for p in ("det_images_*.npz", "detector_ckpt_*.pt"))
    gt_path = next(split.glob("*/scene_gt.json"))
    gt = json.loads(gt_path.read_text())
    first = gt[next(iter(gt))][0]
    first["cam_t_m2c"] = [v + 1.0 for v in first["cam_t_m2c"]]  # as a new render would: other poses
    gt_path.write_text(json.dumps(gt))
    logs = []
    with pytest.raises(UserError, match="trained on an earlier version of .*split.*: delete it to start afresh"):
        train_detector(split, root, max_steps=5, width=8, batch=2, log=logs.append)
    assert any("cutting its images again" in str(m) for m in logs), logs
    ckpt.unlink()
    logs = []
    train_detector(split, root, max_steps=5, width=8, batch=2, log=logs.append)
    assert not any("cutting its images again" in str(m) or "resumed from" in str(m) for m in logs), logs
    assert any(str(m).startswith("loaded ") for m in logs)  # the cache cut for the new split serves it
    assert sorted(p.name for p in (tmp_path / "lmo.work").iterdir() if p.suffix in (".npz", ".pt")) == \
        sorted([cache.name, ckpt.name])  # the same names, their contents renewed; nothing part-written


def test_tiny_training_exports_and_loads(tiny_detector_bundle, lmo_dev):
    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import Detector
    b = open_bundle(tiny_detector_bundle)
    spec = b.manifest.detector
    assert spec["classes"] == [o.id for o in b.objects]
    assert spec["training"]["onnx_max_abs_diff"] <= 1e-4
    assert spec["training"]["steps"] >= 1
    det = Detector(b)
    frame = lmo_dev.read_rgb(lmo_dev.im_ids[0])
    from tracker.runtime.detector import letterbox, normalise
    x = normalise(letterbox(frame, spec["input_w"], spec["input_h"])[0][None], det.spec)
    maps = det.session.run(None, {det.input_name: x})[0]
    assert maps.shape == (1, len(spec["classes"]) + 4, spec["input_h"] // 8, spec["input_w"] // 8)
    assert np.all((maps[0, :8] >= 0) & (maps[0, :8] <= 1))  # sigmoid heatmaps in the graph
    for small in (frame[:300, :500].copy(), np.zeros((720, 1280, 3), np.uint8)):  # other frame sizes
        assert all(o.obj_id in spec["classes"] for o in det(small))


def test_candidates_for_ap_extend_the_run_time_detections(tiny_detector_bundle, lmo_dev):
    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import CANDIDATE_PER_CLASS, CANDIDATE_SCORE, Detector
    det = Detector(open_bundle(tiny_detector_bundle))
    det.spec.score_thresh = 0.5  # a tiny network's scores are low: few or no run-time detections
    frame = lmo_dev.read_rgb(lmo_dev.im_ids[0])
    dets, cands = det.detect(frame, candidates=True)
    assert [(d.obj_id, d.score) for d in dets] == [(d.obj_id, d.score) for d in det(frame)]
    assert det.detect(frame)[1] == []
    assert len(cands) > len(dets)
    assert all(c.score >= CANDIDATE_SCORE for c in cands)
    assert max(sum(c.obj_id == o for c in cands) for o in det.spec.classes) <= CANDIDATE_PER_CLASS
    assert {(d.obj_id, d.score) for d in dets} <= {(c.obj_id, c.score) for c in cands}


def test_eval_with_the_detector_reports_coco_ap_and_the_operating_point(tiny_detector_bundle, data_dir, tmp_path):
    from tracker.evaluation.evaluate import evaluate
    m = evaluate(tiny_detector_bundle, data_dir / "lmo" / "dev", tmp_path / "m.json", boxes="detector",
                 max_frames=2, progress=False)
    d = json.loads((tmp_path / "m.json").read_text())["detection"]
    assert d["ap50"] == m["detection"]["ap50"] and "coco" in d["protocol"]
    op = d["operating_point"]
    assert set(op["per_object"]) == set(d["per_object"])
    # more candidates can only add recall
    assert all(d["per_object"][k]["recall50"] >= op["per_object"][k]["recall50"]
               for k in d["per_object"] if d["per_object"][k]["n_gt"])


def test_detector_classes_must_match_bundle(tiny_detector_bundle, tmp_path):
    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import Detector
    bad = tmp_path / "lmo"
    shutil.copytree(tiny_detector_bundle, bad)
    m = json.loads((bad / "manifest.json").read_text())
    m["detector"]["classes"] = m["detector"]["classes"][:-1] + [99]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="not objects of this bundle"):
        Detector(open_bundle(bad))
    m["detector"]["classes"] = m["detector"]["classes"][:-1]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="output channels"):
        Detector(open_bundle(bad))


def test_box_schedule_runs_detector_every_n():
    from tracker.runtime.estimator import PoseEstimate
    from tracker.runtime.pipeline import BoxSchedule
    calls = []

    def fake_detector(rgb):
        calls.append(1)
        return [Detection(1, np.array([100, 100, 50, 50.]), 0.9)]

    K = np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1.]])
    pts = {1: np.array([[-30, -30, 0], [30, 30, 0.]])}
    s = BoxSchedule(fake_detector, 3, pts)
    img = np.zeros((480, 640, 3), np.uint8)
    pose = [PoseEstimate(1, np.eye(3), np.array([0, 0, 500.]), 0.9, np.zeros(4))]
    sources = []
    for _ in range(7):
        dets, how = s.boxes(img, K)
        sources.append(how)
        s.update(pose)
    assert sources == ["detector", "pose", "pose", "detector", "pose", "pose", "detector"]
    s.update(pose)
    d, how = s.boxes(img, K)
    np.testing.assert_allclose(d[0].box, [290, 210, 61, 61])  # the points projected at the previous pose
    s.update([])  # the object was lost: the next frame runs the detector
    assert s.boxes(img, K)[1] == "detector"
    s.update(pose)
    assert s.boxes(img, K)[1] == "pose"
    s.reset()  # a cut (a looped replay starting again): the detector, not the old pose
    assert s.boxes(img, K)[1] == "detector"


def test_box_schedule_counts_only_the_tracked_objects():
    from tracker.runtime.estimator import PoseEstimate
    from tracker.runtime.pipeline import BoxSchedule

    def two_objects(rgb):
        return [Detection(1, np.array([100, 100, 50, 50.]), 0.9), Detection(5, np.array([300, 100, 50, 50.]), 0.8)]

    K = np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1.]])
    s = BoxSchedule(two_objects, 3, {1: np.array([[-30, -30, 0], [30, 30, 0.]])}, obj_ids=[1])
    dets, how = s.boxes(np.zeros((480, 640, 3), np.uint8), K)
    assert [d.obj_id for d in dets] == [1] and how == "detector"
    s.update([PoseEstimate(1, np.eye(3), np.array([0, 0, 500.]), 0.9, np.zeros(4))])
    assert s.boxes(np.zeros((480, 640, 3), np.uint8), K)[1] == "pose"  # object 5 is not 'lost'
    with pytest.raises(UserError, match="detect-every"):
        BoxSchedule(two_objects, 0, {})


def test_loop_with_the_detector_on_the_bundled_recording(tiny_detector_bundle, tmp_path):
    from tracker.core.bop import read_results
    from tracker.evaluation.track import track
    from tracker.runtime.loop import TrackConfig
    from tracker.core.paths import DEMO_RECORDING
    out = tmp_path / "run"
    s = track(TrackConfig(str(DEMO_RECORDING), str(tiny_detector_bundle), out, rerun="off", max_frames=3,
                              boxes="detector", detect_every=2, smooth=0.5), log=lambda m: None)
    assert s.frames == 3 and s.boxes == "detector" and s.detector_frames >= 2
    assert s.accuracy["n_gt"] > 20  # scored against the recording's ground truth
    assert len((out / "timings.csv").read_text().splitlines()) == 4
    assert all(e.im_id in (3, 8, 17) for e in read_results(out / "poses.csv"))


def test_join_detectors_averages_the_networks_and_quantises_them(tiny_detector_bundle, tiny_bundle, lmo_dev, tmp_path,
                                                                 monkeypatch):
    pytest.importorskip("onnx")
    import onnx
    from tracker.core.bundle import open_bundle, update_manifest
    from tracker.runtime.detector import Detector, letterbox, normalise
    from tracker.training.detector_ensemble import join_detectors
    from tracker.training.detector_train import train_detector
    quiet = dict(log=lambda *a: None)
    split = tiny_bundle.parent / "split"
    second = tmp_path / "second"
    shutil.copytree(tiny_bundle, second)
    # a number of steps, not of seconds: the second network and the int8 figures below are the same
    # on a busy machine
    train_detector(split, second, max_steps=20, width=4, batch=2, seed=1, **quiet)
    assert open_bundle(second).manifest.detector["training"]["steps"] == 20
    m = join_detectors(tiny_detector_bundle, [second], out_dir=tmp_path / "joined", **quiet)
    ens = m.detector["ensemble"]
    a_thresh = open_bundle(tiny_detector_bundle).manifest.detector["score_thresh"]
    assert ens["members"] == 2 and ens["from"][1]["bundle"] == str(second)
    frame = lmo_dev.read_rgb(lmo_dev.im_ids[0])

    def maps(bundle):
        d = Detector(open_bundle(bundle))  # hashes verified, classes and output channels checked
        x = normalise(letterbox(frame, d.spec.input_w, d.spec.input_h, d.spec.pad_value)[0][None], d.spec)
        return d.session.run(None, {d.input_name: x})[0]

    def maps_of(bundle, x):
        d = Detector(open_bundle(bundle))
        return d.session.run(None, {d.input_name: np.ascontiguousarray(x)})[0]
    a, b, joined = maps(tiny_detector_bundle), maps(second), maps(tmp_path / "joined")
    assert not np.allclose(a, b, atol=1e-3)  # two networks, so their mean is neither
    assert np.abs(joined - (a + b) / 2).max() < 1e-5
    # a member of another normalisation (a pretrained network's) gets its own from the shared input
    other = tmp_path / "other_norm"
    shutil.copytree(second, other)
    update_manifest(other, lambda mf, stage: mf.detector.update(mean=0.0, std=1.0))
    mixed = join_detectors(tiny_detector_bundle, [other], out_dir=tmp_path / "mixed", **quiet)
    b_own = maps(other)  # the second graph on its own normalisation of the frame
    assert not np.allclose(b_own, b, atol=1e-3)
    assert np.abs(maps(tmp_path / "mixed") - (a + b_own) / 2).max() < 1e-5
    assert mixed.detector["ensemble"]["from"][1]["normalisation"] == [0.0, 1.0]
    assert (mixed.detector["mean"], mixed.detector["std"]) == (m.detector["mean"], m.detector["std"])

    q = join_detectors(tiny_detector_bundle, [second], out_dir=tmp_path / "int8", int8_data=split,
                       calibration_images=3, score_thresh=0.15, **quiet)
    assert q.detector["int8"]["calibration_images"] == 3
    assert q.detector["score_thresh"] == 0.15 and m.detector["score_thresh"] == a_thresh
    ops = {n.op_type for n in onnx.load(str(tmp_path / "int8" / "detector.onnx")).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear", "Mean"} <= ops
    C = len(q.detector["classes"])
    # on the images it was calibrated on (min-max ranges: nothing clipped) int8 follows the float graph;
    # a real frame can reach past the ranges of three renders of a network trained for a second
    from tracker.training.detector_ensemble import calibration_inputs
    x_cal = calibration_inputs(split, Detector(open_bundle(tmp_path / "int8")).spec, 3)
    for x in x_cal[:, None]:
        assert np.abs(maps_of(tmp_path / "int8", x)[0, :C] - maps_of(tmp_path / "joined", x)[0, :C]).max() < 0.1
    assert all(d.obj_id in q.detector["classes"] for d in Detector(open_bundle(tmp_path / "int8"))(frame))
    assert "reduce_range" not in q.detector["int8"]["method"]  # 8-bit weights unless asked
    _check_requantise(tmp_path, split, x_cal, C, maps_of, quiet)

    with pytest.raises(UserError, match="not a folder"):
        join_detectors(tiny_detector_bundle, [second], out_dir=tmp_path / "n", int8_data=tmp_path / "none", **quiet)
    with pytest.raises(UserError, match="between 0 and 1"):
        join_detectors(tiny_detector_bundle, [second], out_dir=tmp_path / "t", score_thresh=1.5, **quiet)
    with pytest.raises(UserError, match="joined or quantised already"):
        join_detectors(tmp_path / "joined", [second], out_dir=tmp_path / "again", **quiet)
    with pytest.raises(UserError, match="has no detector"):
        join_detectors(tiny_detector_bundle, [tiny_bundle], out_dir=tmp_path / "none", **quiet)
    with pytest.raises(UserError, match="nothing to join"):
        join_detectors(tiny_detector_bundle, [], out_dir=tmp_path / "alone", **quiet)
    # one network alone, quantised: int8 that follows that network
    one = join_detectors(tiny_detector_bundle, [], out_dir=tmp_path / "one8", int8_data=split, calibration_images=3,
                         weight_bits=7, **quiet)
    assert one.detector["ensemble"]["members"] == 1 and "reduce_range" in one.detector["int8"]["method"]
    for x in x_cal[:, None]:
        assert np.abs(maps_of(tmp_path / "one8", x)[0, :C] - maps_of(tiny_detector_bundle, x)[0, :C]).max() < 0.1
    # or with its weights stored in float16: about half the file, float32 arithmetic, outputs as before
    hw = join_detectors(tiny_detector_bundle, [], out_dir=tmp_path / "half", half=True, **quiet).detector["half_weights"]
    assert hw["tensors"] > 0 and hw["max_abs_diff_on_noise"] < 0.01
    size = lambda b: (b / "detector.onnx").stat().st_size  # noqa: E731
    assert size(tmp_path / "half") < 0.6 * size(tiny_detector_bundle)
    for x in x_cal[:, None]:
        assert np.abs(maps_of(tmp_path / "half", x) - maps_of(tiny_detector_bundle, x)).max() < 0.01
    with pytest.raises(UserError, match="exclude each other"):
        join_detectors(tiny_detector_bundle, [], out_dir=tmp_path / "hq", half=True, int8_data=split, **quiet)
    with pytest.raises(UserError, match="give --int8 SPLIT too"):
        join_detectors(tiny_detector_bundle, [], out_dir=tmp_path / "h7", half=True, weight_bits=7, **quiet)
    with pytest.raises(UserError, match="must be 7 or 8"):
        join_detectors(tiny_detector_bundle, [], out_dir=tmp_path / "q6", int8_data=split, weight_bits=6, **quiet)
    with pytest.raises(UserError, match="alternate needs two networks"):
        join_detectors(tiny_detector_bundle, [], out_dir=tmp_path / "ha", half=True, mirror="alternate", **quiet)

    # one network and its mirror image: the joined output is mirror-symmetric (x offsets turned)
    mm = join_detectors(tiny_detector_bundle, [], out_dir=tmp_path / "mirror", mirror="both", **quiet)
    assert mm.detector["ensemble"]["mirror"] == "both" and mm.detector["ensemble"]["members"] == 1
    from tracker.training.detector_ensemble import mirror_fix
    d = Detector(open_bundle(tmp_path / "mirror"))
    x = normalise(letterbox(frame, d.spec.input_w, d.spec.input_h, d.spec.pad_value)[0][None], d.spec)
    scale, shift = mirror_fix(a.shape[1])
    run = lambda inp: d.session.run(None, {d.input_name: np.ascontiguousarray(inp)})[0]
    plain, mirrored = run(x), run(x[..., ::-1])
    assert np.abs(plain - (a + (maps_of(tiny_detector_bundle, x[..., ::-1])[..., ::-1] * scale + shift)) / 2).max() < 1e-5
    assert np.abs(mirrored[..., ::-1] * scale + shift - plain).max() < 1e-5
    assert not np.allclose(plain, a, atol=1e-3)
    # two networks by turns: the second sees only the mirror image, at no extra work
    join_detectors(tiny_detector_bundle, [second], out_dir=tmp_path / "alt", mirror="alternate", **quiet)
    alt = maps_of(tmp_path / "alt", x)
    assert np.abs(alt - (a + maps_of(second, x[..., ::-1])[..., ::-1] * scale + shift) / 2).max() < 1e-5
    with pytest.raises(UserError, match="--mirror must be one of"):
        join_detectors(tiny_detector_bundle, [second], out_dir=tmp_path / "m", mirror="sideways", **quiet)
    other = tmp_path / "other"
    shutil.copytree(second, other)
    update_manifest(other, lambda man, folder: man.detector.update(input_w=256))
    with pytest.raises(UserError, match="input_w"):
        join_detectors(tiny_detector_bundle, [other], out_dir=tmp_path / "bad", **quiet)

    # Ctrl-C before the manifest is re-hashed: an in-place join leaves the bundle as it was
    import tracker.core.bundle as core_bundle  # (join_detectors writes through its bundle_writer)
    from tracker.core.bundle import sha256
    inplace = tmp_path / "inplace" / "b"
    shutil.copytree(tiny_detector_bundle, inplace)
    before = sha256(inplace / "detector.onnx")

    def interrupted(*args, **kw):
        raise KeyboardInterrupt
    monkeypatch.setattr(core_bundle, "write_manifest", interrupted)
    with pytest.raises(KeyboardInterrupt):
        join_detectors(inplace, [second], **quiet)
    assert sha256(inplace / "detector.onnx") == before and [p.name for p in inplace.parent.iterdir()] == ["b"]
    Detector(open_bundle(inplace))


def _as_written(path, x):
    """A graph's output with onnxruntime's fusions off: each DequantizeLinear, float Conv and
    QuantizeLinear run as written, the exact arithmetic that a CPU with int8 dot products (VNNI)
    reproduces and an AVX2 one reproduces only when no int16 pair sum saturates."""
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    s = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    return s.run(None, {s.get_inputs()[0].name: np.ascontiguousarray(x)})[0]


def _check_requantise(tmp_path, split, x_cal, C, maps_of, quiet):
    """``requantise-detector`` on the int8 bundle that the join test wrote at ``tmp_path / 'int8'``."""
    import onnx
    from onnx import numpy_helper
    from tracker.core.bundle import sha256
    from tracker.training.detector_ensemble import dequantise_graph, requantise_detector
    from tracker.runtime.detector import run_graph
    int8 = tmp_path / "int8" / "detector.onnx"
    n = dequantise_graph(int8, tmp_path / "float.onnx")
    graph = onnx.load(str(tmp_path / "float.onnx")).graph
    assert n["weights"] > 0 and n["activations"] > 0
    assert not {"QuantizeLinear", "DequantizeLinear"} & {m.op_type for m in graph.node}
    assert not {onnx.TensorProto.INT8, onnx.TensorProto.UINT8, onnx.TensorProto.INT32} & {t.data_type for t in graph.initializer}
    # the float32 graph computes what the int8 one does, but for the rounding of activations
    for x in x_cal[:, None]:
        assert np.abs(run_graph(tmp_path / "float.onnx", x)[0, :C] - maps_of(tmp_path / "int8", x)[0, :C]).max() < 0.05

    r = requantise_detector(tmp_path / "int8", split, out_dir=tmp_path / "int8b", calibration_images=3, **quiet)
    was = r.detector["int8"]["requantised_from"]
    assert was["detector_sha256"] == sha256(int8) and was["calibration_images"] == 3 and "command" in r.detector["int8"]
    assert "reduce_range" in r.detector["int8"]["method"]
    new = tmp_path / "int8b" / "detector.onnx"
    weights = [numpy_helper.to_array(t) for t in onnx.load(str(new)).graph.initializer if t.data_type == onnx.TensorProto.INT8]
    assert weights and all(np.abs(w).max() <= 64 for w in weights)  # 7 bits: no int16 pair sum overflows
    # this CPU's int8 path computes about what the graph means (no int16 saturation; activations that
    # round to the other side of a tie, and uint8 Resize and Add, remain). Measured on AVX2 without
    # VNNI: 8-bit weights 0.08-0.31 apart, 7-bit 0-0.002
    for x in x_cal[:, None]:
        assert np.abs(maps_of(tmp_path / "int8b", x) - _as_written(new, x)).max() < 0.02
        assert np.abs(maps_of(tmp_path / "int8b", x)[0, :C] - maps_of(tmp_path / "int8", x)[0, :C]).max() < 0.1
    with pytest.raises(UserError, match="is not int8"):
        requantise_detector(tmp_path / "joined", split, out_dir=tmp_path / "r1", **quiet)
    with pytest.raises(UserError, match="not a folder"):
        requantise_detector(tmp_path / "int8", tmp_path / "none", out_dir=tmp_path / "r2", **quiet)


def test_tune_heads_picks_the_trees_weight_on_renders(tiny_bundle, tmp_path):
    from tests.conftest import REPO
    from tracker.core.bundle import open_bundle, sha256
    from tracker.research.tune_heads import tune_trees_weight
    split = tiny_bundle.parent / "split"
    src = REPO / "models" / "lmo"
    before = sha256(src / "manifest.json")
    m = tune_trees_weight(src, split, weights=(1.0, 0.0), out_dir=tmp_path / "tuned", max_frames=2, log=lambda *a: None)
    tw = m.heads["trees_weight"]
    table = tw["by_weight"]
    assert set(table) == {"0.0", "1.0"} and table["0.0"]["instances"] > 0
    assert table["0.0"]["te_median_mm"] != table["1.0"]["te_median_mm"]  # the weight reaches the poses
    figures = lambda w: (table[w]["add_recall"], table[w]["ar_mssd"])  # noqa: E731
    assert figures(str(tw["detector"])) == max(map(figures, table))  # the best (ties: the test below)
    assert tw["exact"] == 0.5 and tw["chosen_on"] == str(split)
    assert sha256(src / "manifest.json") == before  # --out: the source bundle untouched
    open_bundle(tmp_path / "tuned")
    with pytest.raises(UserError, match="in \\[0, 1\\]"):
        tune_trees_weight(src, split, weights=(1.5,), out_dir=tmp_path / "bad", log=lambda *a: None)
    with pytest.raises(UserError, match="has no detector"):
        tune_trees_weight(tiny_bundle, split, out_dir=tmp_path / "bad", log=lambda *a: None)


def test_tune_heads_ranks_by_add_then_mssd_and_keeps_the_bundles_weight_on_a_tie(tmp_path, monkeypatch):
    """tune_trees_weight's own rule on figures made up for each weight (its evaluations faked):
    the best ADD(I), then the best AR_MSSD; a tie on both keeps the weight the bundle has, and
    among others the smallest weight."""
    from tests.conftest import REPO
    import tracker.evaluation.evaluate as ev
    from tracker.research.tune_heads import tune_trees_weight
    from tracker.runtime.heads import TREES_WEIGHT
    scene = REPO / "tests" / "fixtures" / "scene" / "000001"  # never read: the evaluations are faked
    made_up = {}

    def evaluate(model_dir, scene_dir, boxes, bop_csv, max_frames, progress, detector_trees_weight):
        add, mssd = made_up[detector_trees_weight]
        return {"n_gt": 10, "add_recall": add, "ar_mssd": mssd, "ar_mspd": 0.5, "te_median_mm": 30.0}
    monkeypatch.setattr(ev, "evaluate", evaluate)

    def chosen(src, figures, out):
        made_up.clear()
        made_up.update(figures)
        m = tune_trees_weight(src, scene, weights=tuple(figures), out_dir=tmp_path / out, log=lambda *a: None)
        assert m.heads["trees_weight"]["by_weight"]["0.0"]["add_recall"] == figures[0.0][0]
        return m.heads["trees_weight"]["detector"]

    src = REPO / "models" / "lmo"
    assert TREES_WEIGHT == 0.5 and "trees_weight" not in json.loads((src / "manifest.json").read_text())["heads"]
    assert chosen(src, {0.0: (0.30, 0.9), 0.25: (0.32, 0.1), 0.5: (0.31, 0.9), 0.75: (0.29, 0.9)}, "a") == 0.25
    assert chosen(src, {0.0: (0.30, 0.40), 0.25: (0.28, 0.9), 0.5: (0.29, 0.9), 0.75: (0.30, 0.45)}, "b") == 0.75
    tie = {0.0: (0.30, 0.40), 0.25: (0.28, 0.9), 0.5: (0.30, 0.40), 0.75: (0.30, 0.40)}
    assert chosen(src, tie, "c") == 0.5  # the bundle's (the default), not the first or the last of the tie
    assert chosen(src, {**tie, 0.5: (0.29, 0.9)}, "d") == 0.0  # the bundle's not among the best: the smallest
    # a bundle whose weight was chosen before (0.75 in "b") keeps that one on a tie
    assert chosen(tmp_path / "b", tie, "e") == 0.75


def test_ema_averages_the_weights_and_is_what_is_exported(tiny_bundle, tmp_path):
    torch = pytest.importorskip("torch")
    from tracker.training.detector_train import ema_update, train_detector
    net = torch.nn.Sequential(torch.nn.Conv2d(1, 1, 1), torch.nn.BatchNorm2d(1))
    avg = {k: v.float().clone() for k, v in net.state_dict().items() if v.is_floating_point()}
    assert "1.num_batches_tracked" not in avg  # integer counters are not averaged
    with torch.no_grad():
        net[0].weight.add_(1.0)
    w0 = float(avg["0.weight"])
    ema_update(avg, net, 0.9, step=0)  # the ramp: decay (1 + 0) / (10 + 0) = 0.1 at the first step
    assert float(avg["0.weight"]) == pytest.approx(0.1 * w0 + 0.9 * (w0 + 1), abs=1e-6)
    ema_update(avg, net, 0.9, step=1000)  # then the decay itself
    assert float(avg["0.weight"]) == pytest.approx(0.9 * (0.1 * w0 + 0.9 * (w0 + 1)) + 0.1 * (w0 + 1), abs=1e-6)
    with pytest.raises(UserError, match=r"--ema is a decay in \[0, 1\)"):
        train_detector(tiny_bundle.parent / "split", tiny_bundle, max_steps=5, ema=1.0)
    # a tiny run: the exported network is the average (not the last weights), and a resume keeps the recipe
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    logs = []
    d = train_detector(tiny_bundle.parent / "split", root, max_steps=5, width=4, batch=2, ema=0.99, log=logs.append)
    assert d["training"]["ema"] == 0.99 and any("moving average" in str(ln) for ln in logs)
    ckpt = torch.load(next((tmp_path / "lmo.work").glob("detector_ckpt_*.pt")), weights_only=True)
    assert set(ckpt["ema"]) < set(ckpt["model"]) and any(
        not torch.equal(ckpt["ema"][k], ckpt["model"][k].float()) for k in ckpt["ema"])
    with pytest.raises(UserError, match=r"with --ema 0\.99: rerun"):
        train_detector(tiny_bundle.parent / "split", root, max_steps=10, width=4, batch=2, log=lambda *a: None)


def test_join_detectors_refuses_a_from_that_is_no_bundle(tiny_detector_bundle, tmp_path):
    from tracker.training.detector_ensemble import join_detectors
    with pytest.raises(UserError, match=f"{tmp_path}: not a model bundle"):
        join_detectors(tiny_detector_bundle, [tmp_path], out_dir=tmp_path / "j", log=lambda *a: None)
    assert not (tmp_path / "j").exists()


def test_box_errors_hand_cases():
    """The right boxes' size and centre errors in the crop's terms, per object and over all."""
    gt = [[(1, np.array([0, 0, 100, 50.])), (2, np.array([300, 300, 40, 40.]))],
          [(1, np.array([200, 100, 100, 80.]))]]
    dets = [[Detection(1, np.array([5, 0, 80, 40.]), 0.9),      # IoU 0.64, longer side 80 of 100, centre (5, 5) px off
             Detection(2, np.array([100, 100, 40, 40.]), 0.8)],  # elsewhere: not right
            [Detection(1, np.array([200, 100, 110, 80.]), 0.7),   # IoU 0.91, 110 of 100, centre 5 px off
             Detection(1, np.array([201, 100, 100, 80.]), 0.6)]]  # the instance is taken: not counted again
    r = box_errors(dets, gt, [1, 2])
    one = r["per_object"][1]
    assert one["n_gt"] == 2 and one["n_right"] == 2
    assert one["side_log_ratio_mean"] == pytest.approx((np.log(0.8) + np.log(1.1)) / 2)
    assert one["shift_median"] == pytest.approx((np.hypot(5, 5) / 100 + 0.05) / 2)
    two = r["per_object"][2]
    assert two["n_gt"] == 1 and two["n_right"] == 0 and two["side_log_ratio_mean"] is None
    assert r["all"]["n_gt"] == 3 and r["all"]["n_right"] == 2
    # a stricter IoU leaves only the tight box
    assert box_errors(dets, gt, [1, 2], iou_min=0.7)["all"]["side_log_ratio_mean"] == pytest.approx(np.log(1.1))
