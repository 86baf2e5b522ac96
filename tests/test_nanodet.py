"""The COCO-pretrained NanoDet in torch (issue 57 item 4): the converted weights reproduce the reference
ONNX conversion's outputs on a shipped photo and on noise, find the photo's documented COCO objects,
are the file NOTICE.md names, and the conversion script's npz writer is reproducible. No npm needed."""
import hashlib
import importlib.util
import re

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from tracker.training.nets.nanodet import WEIGHTS, NanoDet, decode, load_weights, nanodet_coco  # noqa: E402

# the reference ONNX's outputs, in the order of the torch head's: per stride 8 / 16 / 32 (scores, bins)
ONNX_OUTPUTS = ["Identity:0", "Identity_3:0", "Identity_1:0", "Identity_4:0", "Identity_2:0", "Identity_5:0"]


@pytest.fixture(scope="module")
def net():
    return nanodet_coco()


@pytest.fixture(scope="module")
def photo(data_dir):
    """ocv_messi5.jpg (548x342: a footballer kicking a ball), letterboxed to 416x416 as the detector
    does (centred, grey 114), RGB 0..1 NCHW as the ONNX expects; with its Letterbox."""
    import cv2
    from tracker.runtime.detector import letterbox
    im = cv2.cvtColor(cv2.imread(str(data_dir / "backgrounds" / "ocv_messi5.jpg")), cv2.COLOR_BGR2RGB)
    x, lb = letterbox(im, 416, 416)
    return x.astype(np.float32).transpose(2, 0, 1)[None] / 255.0, lb


def test_the_coco_head_matches_the_reference_onnx(net, photo, data_dir):
    sess = ort.InferenceSession(str(data_dir / "pretrained" / "nanodet_coco_416.onnx"),
                                providers=["CPUExecutionProvider"])
    noise = np.random.default_rng(0).random((1, 3, 416, 416), dtype=np.float32)
    for x in (photo[0], noise):
        ref = dict(zip([o.name for o in sess.get_outputs()], sess.run(None, {"input_1:0": x})))
        with torch.no_grad():
            feats, head = net(torch.from_numpy(x))
        assert [tuple(f.shape) for f in feats] == [(1, 128, 52, 52), (1, 128, 26, 26), (1, 128, 13, 13)]
        ours = [t.numpy() for pair in head for t in pair]
        for name, a in zip(ONNX_OUTPUTS, ours):
            assert a.shape == ref[name].shape, name
            assert np.abs(a - ref[name]).max() < 1e-4, name


def test_the_photo_shows_a_person_and_a_sports_ball(net, photo, data_dir):
    x, lb = photo
    names = (data_dir / "pretrained" / "coco.names").read_text().split("\n")
    with torch.no_grad():
        boxes, scores, labels = decode(net(torch.from_numpy(x))[1], (416, 416), score_thresh=0.3)
    found = [names[c] for c in labels]
    assert found[0] == "person" and scores[0] > 0.6 and "sports ball" in found
    ball = boxes[found.index("sports ball")]
    centre = ((ball[:2] + ball[2:]) / 2 - [lb.pad_x, lb.pad_y]) / [lb.sx, lb.sy]   # frame pixels
    assert np.abs(centre - [362, 313]).max() < 15    # where the ball is in the photo


def test_the_weights_are_the_ones_notice_names():
    notice = (WEIGHTS.parent / "NOTICE.md").read_text()
    m = re.search(r"`nanodet_coco\.npz` SHA-256 `([0-9a-f]{64})`", notice)
    assert m and hashlib.sha256(WEIGHTS.read_bytes()).hexdigest() == m.group(1)


def test_other_sizes_a_new_head_and_frozen_stages():
    """Sides that are multiples of 32 but not square; without the COCO head only the trunk and neck
    load; frozen stages get no gradient, the rest do."""
    net = load_weights(NanoDet(coco_head=False))
    assert net.freeze("stage2") == ["stem", "stage1", "stage2"]
    feats, head = net(torch.rand(2, 3, 256, 320))
    assert head is None and [tuple(f.shape) for f in feats] == [(2, 128, 32, 40), (2, 128, 16, 20), (2, 128, 8, 10)]
    sum(f.mean() for f in feats).backward()
    assert all(p.grad is None for p in net.backbone.stage2.parameters())
    assert all(p.grad is not None for p in net.backbone.stage3.parameters())


def test_the_conversion_reads_a_manifest_and_writes_the_same_npz_twice(tmp_path):
    path = WEIGHTS.parents[3] / "scripts" / "nanodet_weights.py"
    spec = importlib.util.spec_from_file_location("nanodet_weights", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    model = {"weightsManifest": [{"paths": ["x.bin"], "weights": [
        {"name": "k", "shape": [2, 2], "dtype": "float32",
         "quantization": {"dtype": "float16", "original_dtype": "float32"}},
        {"name": "p/perm", "shape": [3], "dtype": "int32"}]}]}
    blob = np.array([1, -2, 0.5, 3], "<f2").tobytes() + np.array([0, 2, 1], "<i4").tobytes()
    w = script.read_weights(model, blob)
    assert w["k"].dtype == np.float16 and w["k"].tolist() == [[1, -2], [0.5, 3]] and w["p/perm"].tolist() == [0, 2, 1]
    script.write_npz(tmp_path / "a.npz", w)
    script.write_npz(tmp_path / "b.npz", dict(reversed(w.items())))
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    with np.load(tmp_path / "a.npz", allow_pickle=False) as z:
        assert sorted(z.files) == ["k", "p/perm"] and np.array_equal(z["k"], w["k"])


def test_a_detector_trains_on_the_coco_trunk_and_exports(tiny_bundle, tmp_path, monkeypatch):
    """A tiny run of train-detector --backbone nanodet: the COCO trunk and neck under our heads,
    input RGB / 255, ONNX export within 1e-4 (checked by train_detector), the trunk's weights
    moved from COCO's, and the run-time detector decodes its output."""
    import shutil
    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import Detector
    from tracker.training.detector_train import train_detector
    from tracker.training.nets.detector import COCO_MEAN_STD, CenterNetCoco
    from tracker.training.nets import nanodet
    loads = []
    real = nanodet.load_weights
    monkeypatch.setattr(nanodet, "load_weights", lambda net, path=WEIGHTS: loads.append(path) or real(net, path))
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    d = train_detector(tiny_bundle.parent / "split", root, max_steps=2, batch=2, input_w=128, input_h=96,
                       backbone="nanodet", log=lambda *a: None)
    assert loads == [WEIGHTS]  # the run started from the COCO weights
    assert (d["mean"], d["std"]) == COCO_MEAN_STD and d["training"]["backbone"] == "nanodet"
    assert d["training"]["pretrained"] and d["training"]["onnx_max_abs_diff"] <= 1e-4
    out = Detector(open_bundle(root))(np.full((480, 640, 3), 120, np.uint8))
    assert all(o.obj_id in open_bundle(root).manifest.obj_ids for o in out)
    coco, control = CenterNetCoco(8), CenterNetCoco(8, pretrained=False)
    w = "backbone.stem.0.weight"
    assert not torch.equal(coco.trunk.state_dict()[w], control.trunk.state_dict()[w])  # COCO's, not random


def test_a_detector_trains_with_its_early_stages_frozen(tiny_bundle, tmp_path):
    """train-detector --freeze-through stage2: the stem through stage 2 keep COCO's weights to the
    bit, stage 3 and the heads move; the manifest says what was frozen; a resumed run must ask for
    the same; the option needs NanoDet's weights."""
    import shutil
    from tracker.core.errors import UserError
    from tracker.core.paths import work_dir
    from tracker.training.detector_train import train_detector
    from tracker.training.nets.detector import CenterNetCoco
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    split = tiny_bundle.parent / "split"
    kw = dict(batch=2, input_w=128, input_h=96, backbone="nanodet", log=lambda *a: None)
    d = train_detector(split, root, max_steps=3, freeze_through="stage2", **kw)
    assert d["training"]["freeze_through"] == "stage2" and d["training"]["steps"] == 3
    (ckpt,) = work_dir(root).glob("detector_ckpt_*.pt")
    trained = torch.load(ckpt, weights_only=True)["model"]
    coco = CenterNetCoco(len(d["classes"])).state_dict()
    for k, v in coco.items():
        if k.startswith(("trunk.backbone.stem.", "trunk.backbone.stage1.", "trunk.backbone.stage2.")):
            assert torch.equal(trained[k], v), k
    assert not torch.equal(trained["trunk.backbone.stage3.in_conv.weight"], coco["trunk.backbone.stage3.in_conv.weight"])
    with pytest.raises(UserError, match="a run with --freeze-through stage2: rerun"):
        train_detector(split, root, max_steps=4, **kw)  # the checkpoint's run froze stage 2
    for bad in (dict(kw, backbone="plain"), dict(kw, pretrained=False)):
        with pytest.raises(UserError, match="--freeze-through keeps part of NanoDet"):
            train_detector(split, root, max_steps=1, freeze_through="stage2", **bad)
    with pytest.raises(UserError, match="must be one of stem, stage1"):
        train_detector(split, root, max_steps=1, freeze_through="neck", **kw)


def test_missing_or_altered_weights_are_one_line_errors(tmp_path, monkeypatch):
    from tracker.core.errors import UserError
    from tracker.training.nets import nanodet
    with pytest.raises(UserError, match="weights are missing"):
        load_weights(NanoDet(), tmp_path / "none.npz")
    altered = tmp_path / "nanodet_coco.npz"
    data = bytearray(WEIGHTS.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one byte of one weight changed
    altered.write_bytes(bytes(data))
    monkeypatch.setattr(nanodet, "WEIGHTS", altered)
    with pytest.raises(UserError, match="does not match its SHA-256"):
        load_weights(NanoDet(), altered)
    garbled = tmp_path / "garbled.npz"
    garbled.write_bytes(b"not a zip")
    with pytest.raises(UserError, match="not a readable weights file"):
        load_weights(NanoDet(), garbled)
