"""An autoencoder run stopped part-way through an epoch (Ctrl-C, or killed after a checkpoint
inside the epoch) goes on from the batch it stopped at: the resumed run ends with the weights of
a run never stopped."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tracker.training.nets import fit  # noqa: E402
from tracker.training.nets.autoencoder import AutoEncoder  # noqa: E402


def _data():
    rng = np.random.default_rng(0)
    x = (rng.random((48, 16, 16, 3)) * 255).astype(np.uint8)
    return x, fit.onehot(rng.integers(0, 2, 48), 2)


def _train(out, logs=None):
    out.mkdir(exist_ok=True)
    x, c = _data()
    torch.manual_seed(7)
    model = AutoEncoder("cvam", 16, 8, 2, widths=(8, 16))
    hist = fit.train_autoencoder(model, x[:40], x[:40], c[:40], x[40:], x[40:], c[40:], out, max_steps=10, batch=8,
                                 patience=1000, precision="fp32", max_epochs=2,
                                 log=(logs.append if logs is not None else lambda *a: None))
    return model, hist


@pytest.mark.parametrize("how", ["ctrl-c", "killed"])
def test_an_epoch_stopped_part_way_resumes_at_its_batch(tmp_path, monkeypatch, how):
    whole, hist_whole = _train(tmp_path / "whole")  # 5 batches an epoch, 2 epochs: 10 steps, whatever the time

    real, calls = fit.augment, []

    def stopping(x, g, *a, **k):  # the 8th batch: the third of epoch 1, before it draws anything
        calls.append(1)
        if len(calls) == 8:
            raise KeyboardInterrupt if how == "ctrl-c" else RuntimeError("the process died")
        return real(x, g, *a, **k)

    monkeypatch.setattr(fit, "augment", stopping)
    if how == "killed":  # no handler runs: what is on disk is the last checkpoint inside the epoch
        monkeypatch.setattr(fit, "CHECKPOINT_SECONDS", 0.0)
    with pytest.raises(KeyboardInterrupt if how == "ctrl-c" else RuntimeError):
        _train(tmp_path / "stopped")
    st = torch.load(tmp_path / "stopped" / "ae_checkpoint.pt", weights_only=True)
    assert st["epoch"] == 1 and st["part"]["pos"] == 2 and len(st["hist"]["epoch"]) == 1

    monkeypatch.setattr(fit, "augment", real)
    logs = []
    resumed, hist = _train(tmp_path / "stopped", logs)
    assert any("at epoch 1, batch 2" in str(m) for m in logs), logs
    assert hist["epoch"] == [0, 1] and np.allclose(hist["train_l2"], hist_whole["train_l2"], rtol=1e-5)
    a, b = whole.state_dict(), resumed.state_dict()
    assert all(torch.allclose(a[k].float(), b[k].float(), rtol=0, atol=1e-6) for k in a)
    st = torch.load(tmp_path / "stopped" / "ae_checkpoint.pt", weights_only=True)
    assert "part" not in st and st["epoch"] == 1  # the epoch finished: an ordinary checkpoint again


def test_a_checkpoint_write_stopped_midway_leaves_the_last_one(tmp_path, monkeypatch):
    from tracker.core.files import write_whole
    path = tmp_path / "ae_checkpoint.pt"
    write_whole(path, lambda tmp: torch.save({"epoch": 3}, tmp))

    def cut_short(tmp):
        open(tmp, "wb").write(b"PK\x03")  # a few bytes, then the signal
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_whole(path, cut_short)
    assert torch.load(path, weights_only=True) == {"epoch": 3}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ae_checkpoint.pt"]  # nothing part-written left
