"""The arithmetic of the training passes: bfloat16 where the CPU has it, float32 weights and
losses either way, a float32 model for export."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tracker.training.nets.autoencoder import AutoEncoder  # noqa: E402
from tracker.training.nets.fit import onehot, train_autoencoder  # noqa: E402
from tracker.training.nets.precision import native_bf16, resolve  # noqa: E402

CPUINFO = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f {}\nbogomips\t: 4000\n"


def test_native_bf16_is_read_from_the_cpu_flags():
    assert native_bf16(CPUINFO.format("avx512_bf16 avx512_vnni"))
    assert native_bf16(CPUINFO.format("amx_bf16 amx_tile"))
    assert not native_bf16(CPUINFO.format("avx512_vnni"))
    assert not native_bf16("")


def test_resolve_names_the_arithmetic_or_refuses():
    assert resolve("fp32") == "fp32" and resolve("bf16") == "bf16"
    assert resolve("auto") == ("bf16" if native_bf16() else "fp32")
    with pytest.raises(ValueError, match="unknown precision"):
        resolve("fp16")


@pytest.mark.parametrize("precision", ["bf16", "fp32"])
def test_training_passes_keep_a_float32_model_that_learns(tmp_path, precision):
    rng = np.random.default_rng(0)
    x = np.broadcast_to((rng.random((48, 1, 1, 3)) * 255).astype(np.uint8), (48, 16, 16, 3)).copy()  # flat colours
    c = onehot(rng.integers(0, 2, 48), 2)
    model = AutoEncoder("cvam", 16, 8, 2, widths=(8, 16))
    before = [p.detach().clone() for p in model.parameters()]
    hist = train_autoencoder(model, x[:40], x[:40], c[:40], x[40:], x[40:], c[40:], tmp_path, max_steps=15,
                             batch=8, patience=1000, precision=precision, log=lambda *a: None)  # 3 epochs of 5
    assert len(hist["epoch"]) == 3 and np.all(np.isfinite(hist["val_l2"]))
    assert hist["train_l2"][-1] < hist["train_l2"][0]
    for p in model.parameters():
        assert p.dtype == torch.float32 and p.is_contiguous()  # what the ONNX export gets
    assert any(not torch.equal(p, b) for p, b in zip(model.parameters(), before))


def test_the_device_is_a_gpu_only_where_torch_sees_one(monkeypatch):
    import torch

    from tracker.training.nets.precision import resolve_device
    from tracker.core.errors import UserError
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu" and resolve_device("cpu") == "cpu"
    with pytest.raises(UserError, match="no CUDA GPU"):
        resolve_device("cuda")
    with pytest.raises(UserError, match="unknown device"):
        resolve_device("tpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == "cuda"


def test_the_budget_schedule_anneals_over_the_time_budget():
    from tracker.training.nets.schedule import FLOOR, budget_lr
    assert budget_lr(1e-3, 0.0, 0) == pytest.approx(1e-3)
    assert budget_lr(1e-3, 0.5, 10**4) == pytest.approx(1e-3 * (FLOOR + (1 - FLOOR) / 2))
    assert budget_lr(1e-3, 1.0, 10**4) == budget_lr(1e-3, 7.0, 10**4) == pytest.approx(1e-3 * FLOOR)
    assert budget_lr(2e-3, 0.0, 49, warmup=200) == pytest.approx(2e-3 / 4)  # the detector's warm-up
    lrs = [budget_lr(1.0, f, 10**4) for f in np.linspace(0, 1, 11)]
    assert all(a > b for a, b in zip(lrs, lrs[1:]))


@pytest.mark.parametrize("schedule", ["budget", "plateau"])
def test_a_budgeted_autoencoder_ends_its_training_annealed_or_not(tmp_path, schedule, monkeypatch):
    import types

    from tracker.training.nets import fit
    ticks = iter(range(10**6))  # a clock of its own: 0.25 s a reading, whatever the machine's load
    monkeypatch.setattr(fit, "time", types.SimpleNamespace(perf_counter=lambda: 0.25 * next(ticks)))
    rng = np.random.default_rng(0)
    x = np.broadcast_to((rng.random((48, 1, 1, 3)) * 255).astype(np.uint8), (48, 16, 16, 3)).copy()
    c = onehot(rng.integers(0, 2, 48), 2)
    model = AutoEncoder("cvam", 16, 8, 2, widths=(8, 16))
    hist = train_autoencoder(model, x[:40], x[:40], c[:40], x[40:], x[40:], c[40:], tmp_path, minutes=0.1,
                             batch=8, patience=1000, precision="fp32", log=lambda *a: None, lr_schedule=schedule)
    assert hist["seconds"][-1] >= 0.1 * 60  # the time budget ended it, after several epochs
    assert len(hist["epoch"]) >= 2
    if schedule == "budget":  # the last step ran with 2-7 % of the step size
        assert hist["lr"][-1] < 0.1e-3 and hist["lr"][0] > hist["lr"][-1]
    else:  # no plateau of 3 epochs in a loss still falling: the step size stays
        assert hist["lr"][0] == pytest.approx(1e-3)


@pytest.mark.parametrize("schedule", ["budget", "plateau"])
def test_a_step_budget_ends_the_autoencoders_training_whatever_the_clock(tmp_path, schedule, monkeypatch):
    """``max_steps``: training ends after that many batches however long they take (a clock that
    says an hour has passed at every reading stops nothing), the 'budget' schedule anneals over
    the steps, and a resumed run counts the steps it ran before."""
    from tests.conftest import FakeClock
    from tracker.core.errors import UserError
    from tracker.training.nets import fit
    monkeypatch.setattr(fit, "time", FakeClock(tick=3600.0).module_time())
    rng = np.random.default_rng(0)
    x = np.broadcast_to((rng.random((48, 1, 1, 3)) * 255).astype(np.uint8), (48, 16, 16, 3)).copy()
    c = onehot(rng.integers(0, 2, 48), 2)
    steps = []
    real = fit.augment
    monkeypatch.setattr(fit, "augment", lambda *a, **k: steps.append(1) or real(*a, **k))  # once a batch

    def run(max_steps):
        model = AutoEncoder("cvam", 16, 8, 2, widths=(8, 16))
        return train_autoencoder(model, x[:40], x[:40], c[:40], x[40:], x[40:], c[40:], tmp_path, minutes=0.01,
                                 batch=8, patience=1000, precision="fp32", log=lambda *a: None,
                                 lr_schedule=schedule, max_steps=max_steps)
    hist = run(7)  # 5 batches an epoch: one whole epoch and 2 batches of the next
    assert len(steps) == 7 and hist["epoch"] == [0, 1]
    if schedule == "budget":  # the step size of the last step: 6 of 7 steps done
        from tracker.training.nets.schedule import budget_lr
        assert hist["lr"][-1] == pytest.approx(budget_lr(1e-3, 6 / 7, 6))
    steps.clear()
    hist = run(12)  # resumed (its checkpoint: after epoch 1): 12 - 10 = 2 steps more
    assert len(steps) == 2 and hist["epoch"] == [0, 1, 2]
    with pytest.raises(UserError, match="step budget"):
        run(0)


def test_an_unknown_schedule_is_refused(tmp_path):
    from tracker.core.errors import UserError
    model = AutoEncoder("cvam", 16, 8, 2, widths=(8, 16))
    x = np.zeros((4, 16, 16, 3), np.uint8)
    with pytest.raises(UserError, match="unknown step-size schedule"):
        train_autoencoder(model, x, x, onehot(np.zeros(4, int), 2), x, x, onehot(np.zeros(4, int), 2), tmp_path,
                          minutes=0.01, lr_schedule="cosine", log=lambda *a: None)
