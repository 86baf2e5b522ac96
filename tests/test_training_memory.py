"""Training processes keep freed memory for the next step instead of faulting it in again."""
import subprocess
import sys

import pytest

from tests.conftest import REPO

PROBE = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from tracker.training.nets.memory import keep_freed_memory
    assert keep_freed_memory()
faults = []
for _ in range(3):  # a step's buffer: allocated, written, freed
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(64 * 2**20 // 8)
    del a
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(faults[-1])
"""


def _faults(mode: str) -> int:
    p = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert p.returncode == 0, p.stderr
    return int(p.stdout.split()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_a_freed_64_mb_buffer_is_reused_without_page_faults():
    # by default the block is mapped afresh and faulted in again every time (in huge pages where
    # numpy asks for them: about 500 faults for 64 MB here); kept, the heap serves it again
    assert _faults("default") > 100
    assert _faults("keep") < 10


def test_a_training_split_of_the_crops_is_taken_when_indexed_and_trains_as_a_copy_would(tmp_path):
    """``Rows`` hands training the rows of its split without copying the crops (the copies doubled
    the encoder stage's peak memory): it indexes as the copy would, and a run on it ends with the
    same weights and losses as a run on copies."""
    np = pytest.importorskip("numpy")
    torch = pytest.importorskip("torch")
    from tracker.training.nets import fit
    from tracker.training.nets.autoencoder import AutoEncoder
    rng = np.random.default_rng(0)
    x = (rng.random((48, 16, 16, 3)) * 255).astype(np.uint8)
    c = fit.onehot(rng.integers(0, 2, 48), 2)
    tr, va = rng.permutation(48)[:40], np.arange(47, 39, -1)
    view = fit.Rows(x, tr)
    assert len(view) == 40 and np.shares_memory(view.arr, x)
    assert np.array_equal(view[np.array([3, 0, 39])], x[tr][[3, 0, 39]]) and np.array_equal(view[5:9], x[tr][5:9])

    def run(xt, xv, out):
        out.mkdir()
        torch.manual_seed(7)
        model = AutoEncoder("cvam", 16, 8, 2, widths=(8, 16))
        hist = fit.train_autoencoder(model, xt, xt, c[tr], xv, xv, c[va], out, max_steps=6, batch=8,
                                     patience=1000, precision="fp32", max_epochs=2, log=lambda *a: None)
        return model, hist

    m_copy, h_copy = run(x[tr], x[va], tmp_path / "copy")
    m_view, h_view = run(fit.Rows(x, tr), fit.Rows(x, va), tmp_path / "view")
    assert h_view["val_l2"] == h_copy["val_l2"] and len(h_view["val_l2"]) >= 1
    for a, b in zip(m_copy.state_dict().values(), m_view.state_dict().values()):
        assert torch.equal(a, b)


def test_the_heads_crop_set_carries_no_pixels():
    """The heads learn from latent codes: their training set (jittered + exact-box crops) keeps the
    poses, boxes and intrinsics of every crop but none of its pixels."""
    np = pytest.importorskip("numpy")
    pytest.importorskip("torch")
    from tracker.training.crops import CropSet
    from tracker.training.train import with_exact_boxes
    rng = np.random.default_rng(1)
    n = 10

    def crops(shift):
        return CropSet(np.full((n, 8, 8, 3), shift, np.uint8), np.zeros((n, 8, 8, 3), np.uint8), np.arange(n) % 3,
                       np.repeat(np.eye(3)[None], n, 0), rng.random((n, 3)), rng.random((n, 4)) + shift,
                       np.repeat(np.eye(3)[None], n, 0), np.ones(n))

    cs, ex = crops(0), crops(1)
    mu = rng.random((n, 4)).astype(np.float32)
    cs_h, mu_h, tr_h, va_h = with_exact_boxes(cs, mu, ex, mu + 1, np.arange(8), np.arange(8, 10))
    assert len(cs_h) == 2 * n and cs_h.x.nbytes == 0 and cs_h.y.nbytes == 0
    assert np.array_equal(cs_h.box, np.concatenate([cs.box, ex.box])) and np.array_equal(cs_h.t[n:], ex.t)
    assert np.array_equal(tr_h, np.r_[0:8, 10:18]) and len(cs_h.subset(tr_h)) == 16
