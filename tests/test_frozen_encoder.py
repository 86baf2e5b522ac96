"""The pose encoder on the COCO-pretrained NanoDet backbone, frozen through stride 16 with its
outputs cached (issue 58 item 2b): the cache equals the live front, training runs and exports,
bad input is one line."""
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tests.conftest import assert_bundle_poses_a_split_frame  # noqa: E402
from tracker.core.errors import UserError  # noqa: E402
from tracker.training.nets.autoencoder import AutoEncoder  # noqa: E402
from tracker.training.nets.fit import CachedInputs, augment, batch_inputs, cache_frozen_outputs, to_tensor  # noqa: E402


def _crops(n=10, size=64, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.integers(0, 255, (n, size, size, 3), dtype=np.uint8)
    x[:, size // 4: 3 * size // 4, size // 4: 3 * size // 4] = rng.integers(0, 255, 3, dtype=np.uint8)  # a block
    return x


def test_the_front_is_the_coco_backbone_frozen_and_stage_4_trains():
    from tracker.training.nets.nanodet import nanodet_coco
    ae = AutoEncoder("cvam", 64, 16, n_objects=2, encoder="nanodet", recon_size=32)
    enc = ae.encoder
    assert not any(p.requires_grad for p in enc.frozen.parameters())
    assert all(p.requires_grad for p in enc.trunk.parameters())
    x = to_tensor(_crops(2))
    ref = nanodet_coco(coco_head=False).backbone
    with torch.no_grad():
        c3, c4, c5 = ref(x)
        assert torch.allclose(enc.frozen(x), c4, atol=1e-5)  # stride 16, 256 channels: COCO's weights
        assert torch.allclose(enc.trunk(enc.frozen(x)), c5, atol=1e-5)  # stage 4 starts from COCO's too
    c = torch.eye(2)
    recon, mu, _ = ae(x, c)
    assert recon.shape == (2, 3, 32, 32) and mu.shape == (2, 16)
    mu.sum().backward()
    assert enc.trunk[0].in_conv.weight.grad is not None
    assert all(p.grad is None for p in enc.frozen.parameters())
    # nanodet32: stage 4 frozen too, only the layers after it train
    enc32 = AutoEncoder("cvam", 64, 16, n_objects=2, encoder="nanodet32", recon_size=32).encoder
    assert len(enc32.trunk) == 0 and not any(p.requires_grad for p in enc32.frozen.parameters())
    with torch.no_grad():
        assert torch.allclose(enc32.frozen(x), c5, atol=1e-5)


def test_cached_outputs_equal_the_live_front_and_augmented_versions_differ(tmp_path):
    ae = AutoEncoder("cvam", 64, 16, n_objects=2, encoder="nanodet", recon_size=32).eval()
    x = _crops(10)
    cache = cache_frozen_outputs(ae.encoder.frozen, x, tmp_path / "f.npy", n_aug=2, seed=0, batch=4,
                                 log=lambda *a: None)
    assert cache.versions == 3 and len(cache) == 10 and not (tmp_path / "f.part.npy").exists()
    c = torch.eye(2)[np.arange(10) % 2]
    with torch.no_grad():
        live = ae.encoder(to_tensor(x), c)
        cached = ae.encoder(cache.batch(np.arange(10)), c)
        assert torch.allclose(live, cached, atol=1e-4, rtol=1e-3)  # float16 storage
    # the augmented versions are the front's outputs of augmented crops (the same draws)
    g = torch.Generator().manual_seed(0 + 7919)
    first = torch.cat([augment(to_tensor(x[i:i + 4]), g) for i in range(0, 10, 4)])
    with torch.no_grad():
        want = ae.encoder.frozen(first).numpy()
    assert np.allclose(cache.arr[1].astype(np.float32), want, atol=2e-2, rtol=1e-2)
    assert not np.array_equal(cache.arr[1], cache.arr[0])
    # a subset indexes its own rows; a training batch draws versions 1..A only, reproducibly
    sub = cache.subset([7, 2])
    assert np.array_equal(sub.batch([0]).numpy(), cache.arr[0, [7]].astype(np.float32))
    b1 = batch_inputs(sub, [0, 1], torch.Generator().manual_seed(3))
    b2 = batch_inputs(sub, [0, 1], torch.Generator().manual_seed(3))
    assert torch.equal(b1, b2)
    for row, got in zip((7, 2), b1):
        assert any(np.array_equal(got.numpy(), cache.arr[v, row].astype(np.float32)) for v in (1, 2))
    assert isinstance(CachedInputs(tmp_path / "f.npy"), CachedInputs)


def test_a_tiny_training_run_caches_once_exports_and_estimates(data_dir, tmp_path):
    from tracker.training.synth.engine import SynthConfig, generate
    from tracker.training.train import train_bundle
    split = tmp_path / "split"
    generate(SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                         obj_ids=[1, 9], seed=5, objects_per_image=(2, 2)), split, 4, workers=1, progress=False)
    logs = []
    m = train_bundle(split, tmp_path / "b", method="cvam", size=64, latent=16, max_steps=3, reg_epochs=2,
                     encoder="nanodet", batch=8, log=logs.append)
    assert m.encoder == "nanodet" and m.input_size == 64 and m.training["onnx_max_abs_diff"] <= 1e-4
    assert sum("cached the frozen front" in str(s) for s in logs) == 1
    work = tmp_path / "b.work"
    assert len(list(work.glob("frozen_nanodet_*.npy"))) == 1
    assert_bundle_poses_a_split_frame(tmp_path / "b", split)
    # a second run on the same split into the same work folder reads the cache instead of making it
    logs.clear()
    (work / "ae_checkpoint.pt").unlink()
    train_bundle(split, tmp_path / "b", method="cvam", size=64, latent=16, max_steps=1, reg_epochs=2,
                 encoder="nanodet", batch=8, log=logs.append)
    assert not any("cached the frozen front" in str(s) for s in logs)
    assert json.loads((tmp_path / "b" / "manifest.json").read_text())["encoder"] == "nanodet"


def test_a_crop_size_the_trunk_cannot_take_is_refused_before_training(data_dir, tmp_path):
    from tracker.training.train import train_bundle
    with pytest.raises(UserError, match="multiple of 32"):
        train_bundle(tmp_path / "nowhere", tmp_path / "b", size=48, encoder="nanodet")
    with pytest.raises(UserError, match="multiple of 16"):  # the plain trunk would reconstruct 64 of 70
        train_bundle(tmp_path / "nowhere", tmp_path / "b", size=70, encoder="plain")
    assert not (tmp_path / "b.work").exists()
