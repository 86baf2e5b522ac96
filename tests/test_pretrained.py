"""The ImageNet-pretrained trunk of the pose encoder (issue 38): weights, normalisation,
frozen BatchNorm, a tiny training run through export, and the error when the extra is missing."""
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("efficientnet_lite_pytorch")

from tracker.training.nets.backbone import LiteTrunk, imagenet_input, load_efficientnet  # noqa: E402
from tracker.core.errors import UserError  # noqa: E402


def _photo(data_dir, rgb=True):
    import cv2
    im = cv2.imread(str(data_dir / "backgrounds" / "lomiri_Dragonfly_by_Bolly.jpg"))
    if rgb:
        im = cv2.cvtColor(im, cv2.COLOR_BGR2RGB)
    h, w = im.shape[:2]
    s = min(h, w)
    im = cv2.resize(im[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s], (224, 224),
                    interpolation=cv2.INTER_LINEAR)
    return torch.from_numpy(im).permute(2, 0, 1)[None].float() / 255.0


def test_the_imagenet_weights_load_and_see_the_dragonfly(data_dir):
    """Loaded strictly; RGB in [0, 1] through the weights' normalisation gives ImageNet class 319
    (dragonfly) for the shared dragonfly photo; the same photo as BGR does not."""
    net = load_efficientnet("lite0").eval()
    with torch.no_grad():
        assert int(net(imagenet_input(_photo(data_dir))).argmax()) == 319
        assert int(net(imagenet_input(_photo(data_dir, rgb=False))).argmax()) != 319


def test_the_trunk_keeps_its_batchnorm_frozen_while_its_convolutions_learn():
    trunk = LiteTrunk("lite0").train()
    bns = [m for m in trunk.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert bns and not any(m.training for m in bns)
    before_stats = [m.running_mean.clone() for m in bns]
    before_w = trunk.net._conv_stem.weight.detach().clone()
    opt = torch.optim.SGD([p for p in trunk.parameters() if p.requires_grad], lr=0.1)
    x = torch.rand(2, 3, 64, 64)
    trunk(x).square().mean().backward()
    opt.step()
    assert all(torch.equal(a, m.running_mean) for a, m in zip(before_stats, bns))
    assert all(not p.requires_grad for m in bns for p in m.parameters())
    assert not torch.equal(before_w, trunk.net._conv_stem.weight)
    assert trunk(x).shape == (2, 1280, 2, 2)


def test_random_weights_differ_from_the_pretrained_ones():
    a, b = load_efficientnet("lite0"), load_efficientnet("lite0", pretrained=False)
    assert not torch.equal(a._conv_stem.weight, b._conv_stem.weight)


def test_a_missing_weights_package_is_a_one_line_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "efficientnet_lite_pytorch", None)
    with pytest.raises(UserError, match=r"'train' extra"):
        load_efficientnet("lite0")
    with pytest.raises(UserError, match="unknown trunk"):
        load_efficientnet("lite9")


def test_a_tiny_training_run_with_the_pretrained_trunk_exports_and_estimates(data_dir, tmp_path):
    from tracker.training.synth.engine import SynthConfig, generate
    from tests.conftest import assert_bundle_poses_a_split_frame
    from tracker.training.train import train_bundle
    split = tmp_path / "split"
    generate(SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                         obj_ids=[1, 9], seed=5, objects_per_image=(2, 2)), split, 4, workers=1, progress=False)
    m = train_bundle(split, tmp_path / "b", method="cvam", size=32, latent=16, max_steps=2, reg_epochs=2,
                     encoder="lite0", lr=3e-4, batch=8, log=lambda *a: None)
    assert m.encoder == "lite0" and m.training["pretrained"] and m.training["onnx_max_abs_diff"] <= 1e-4
    assert_bundle_poses_a_split_frame(tmp_path / "b", split)


def test_the_trunk_gives_stride_8_16_32_features_at_the_detectors_input():
    from tracker.training.nets.backbone import LiteTrunk
    trunk = LiteTrunk("lite0", pretrained=False)
    with torch.no_grad():
        f8, f16, f32 = trunk.pyramid(torch.zeros(1, 3, 240, 320))
    assert [tuple(f.shape[-2:]) for f in (f8, f16)] == [(30, 40), (15, 20)] and f32.shape[-1] == 10
    assert f32.shape[-2] in (7, 8)  # 15 rows halved (the trunk rounds down)
    assert trunk.pyramid_channels() == [f8.shape[1], f16.shape[1], f32.shape[1]]


def test_a_detector_trains_on_the_pretrained_trunk_and_exports(tiny_bundle, tmp_path):
    """A tiny run: the ImageNet trunk under the detector's neck and heads, BatchNorm frozen,
    the spec's normalisation the weights' own, ONNX export within 1e-4 (checked by
    train_detector), and the run-time detector decodes its output."""
    import shutil
    from tracker.training.detector_train import train_detector
    from tracker.training.nets.detector import IMAGENET_MEAN_STD, CenterNetPretrained
    from tracker.core.bundle import open_bundle
    from tracker.runtime.detector import Detector
    root = tmp_path / "lmo"
    shutil.copytree(tiny_bundle, root)
    d = train_detector(tiny_bundle.parent / "split", root, max_steps=3, width=4, batch=2, input_w=128, input_h=96,
                       backbone="lite0", log=lambda *a: None)
    assert (d["mean"], d["std"]) == IMAGENET_MEAN_STD and d["training"]["backbone"] == "lite0"
    assert d["training"]["pretrained"] and d["training"]["onnx_max_abs_diff"] <= 1e-4
    det = Detector(open_bundle(root))
    out = det(np.full((480, 640, 3), 120, np.uint8))
    assert isinstance(out, list) and all(o.obj_id in open_bundle(root).manifest.obj_ids for o in out)
    m = CenterNetPretrained(8, 4, "lite0", pretrained=False).train()  # the control: BatchNorm learns
    assert all(b.training for b in m.trunk.modules() if isinstance(b, torch.nn.BatchNorm2d))
    with pytest.raises(UserError, match="--backbone"):
        train_detector(tiny_bundle.parent / "split", root, max_steps=1, backbone="resnet", log=lambda *a: None)


def test_the_random_weights_control_trains_its_batchnorm():
    """From random weights (the control) BatchNorm's initial statistics mean nothing: they learn."""
    trunk = LiteTrunk("lite0", pretrained=False).train()
    bns = [m for m in trunk.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert bns and all(m.training for m in bns)
    before = bns[0].running_mean.clone()
    trunk(torch.rand(2, 3, 64, 64))
    assert not torch.equal(before, bns[0].running_mean)
    assert all(p.requires_grad for m in bns for p in m.parameters())
    assert not any(m.training for m in trunk.train(False).modules() if isinstance(m, torch.nn.BatchNorm2d))
