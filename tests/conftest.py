import atexit
import os
import shutil
import sys
import tempfile
import time
import types
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

# hypothesis: no per-example deadline (its default, 200 ms, fails examples that are merely slow on a
# busy 2-core CI machine or that pay a first call's imports); examples are still bounded by the
# per-test timeout in pyproject.toml. HYPOTHESIS_PROFILE=default restores hypothesis's own settings
settings.register_profile("ci", deadline=None, suppress_health_check=[HealthCheck.too_slow], print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
# every test's caches (parsed meshes, hulls, decimated meshes, models_info: tracker.core.paths.cache_dir)
# go to a folder of this run, never the user's ~/.cache/autopose, whatever the environment says;
# the subprocesses that tests start inherit it. Set before anything is imported or collected
TEST_CACHE = tempfile.mkdtemp(prefix="autopose-test-cache-")
os.environ["AUTOPOSE_CACHE"] = TEST_CACHE
atexit.register(shutil.rmtree, TEST_CACHE, ignore_errors=True)

from tracker.core.paths import shared_data  # noqa: E402

DATA = shared_data()


class FakeClock:
    """A ``time.perf_counter`` that moves only when told (``advance``) or, with ``tick``, by that
    much at every reading: code that budgets or records seconds then runs the same number of
    steps on any machine, however busy. ``module_time`` is a stand-in for a module's ``time``."""

    def __init__(self, tick: float = 0.0):
        self.now, self.tick, self.readings = 0.0, tick, 0

    def __call__(self) -> float:
        t = self.now
        self.now += self.tick
        self.readings += 1
        return t

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def module_time(self):
        """The ``time`` module with this clock for ``perf_counter`` and ``monotonic``:
        ``monkeypatch.setattr(module, "time", clock.module_time())``."""
        names = {k: getattr(time, k) for k in dir(time) if not k.startswith("_")}
        return types.SimpleNamespace(**{**names, "perf_counter": self, "monotonic": self})


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.fail(f"shared data not found at {DATA}: CI runs with ../shared beside the repo")
    return DATA


@pytest.fixture(scope="session")
def lmo_dev(data_dir):
    from tracker.core.bop import load_scene
    return load_scene(data_dir / "lmo" / "dev", require_gt=True)


@pytest.fixture(scope="session")
def lmo_models(data_dir):
    from tracker.core.meshes import load_models
    return load_models(data_dir / "lmo" / "models")


@pytest.fixture(scope="session")
def tiny_bundle(tmp_path_factory, data_dir):
    """A bundle for all 8 LM-O objects, trained for a few steps: exercises code paths only. Step
    and epoch budgets, not minutes: the same bundle on any machine, however busy."""
    pytest.importorskip("torch")
    from tracker.training.synth.engine import SynthConfig, generate
    from tracker.training.train import train_bundle
    root = tmp_path_factory.mktemp("tiny_bundle")
    cfg = SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                      seed=4, objects_per_image=(8, 8))
    generate(cfg, root / "split", 3, workers=1, progress=False)
    train_bundle(root / "split", root / "lmo", method="cvam", size=32, latent=16, max_steps=20, reg_epochs=20,
                 models_info_path=REPO / "models" / "lmo_models_info.json", log=lambda *a: None)
    return root / "lmo"


@pytest.fixture(scope="session")
def tiny_detector_bundle(tiny_bundle, tmp_path_factory):
    """``tiny_bundle`` with a detector trained for 10 steps (code paths only)."""
    import shutil

    from tracker.training.detector_train import train_detector
    root = tmp_path_factory.mktemp("det") / "lmo"
    shutil.copytree(tiny_bundle, root)
    train_detector(tiny_bundle.parent / "split", root, max_steps=10, width=8, batch=2, log=lambda *a: None)
    return root


FIXTURE_MESHES = Path(__file__).parent / "fixtures" / "models"


@pytest.fixture()
def small(monkeypatch):
    """``build`` with tiny splits: plan() gives MIN_IMAGES (8) for a budget this small."""
    from tracker.training import build as bb
    monkeypatch.setattr(bb, "MIN_IMAGES", 8)
    monkeypatch.setattr(bb, "CHECK_IMAGES", 4)
    monkeypatch.setattr(bb, "MAX_RATE", 0.01)


def fixture_meshes(tmp_path, names=("obj_000001.ply", "obj_000002.ply")) -> Path:
    """A folder ``tmp_path/meshes`` holding copies of the named fixture meshes."""
    src = tmp_path / "meshes"
    src.mkdir()
    for f in names:
        shutil.copy(FIXTURE_MESHES / f, src / f)
    return src


def assert_bundle_poses_a_split_frame(bundle_dir, split) -> None:
    """The bundle poses the visible instances of the split's first frame from their ground-truth
    boxes: at least one pose, every rotation orthonormal."""
    import numpy as np
    from tracker.core.bop import load_scene
    from tracker.runtime.estimator import Detection, PoseEstimator
    est = PoseEstimator(bundle_dir)
    scene = load_scene(Path(split) / "000000", require_gt=True)
    dets = [Detection(g.obj_id, np.asarray(g.info["bbox_visib"], float)) for g in scene.gt[0]
            if g.info["bbox_visib"][2] > 1]
    poses = est.estimate(scene.read_rgb(0), scene.K(0), dets)
    assert poses and all(np.allclose(p.R @ p.R.T, np.eye(3), atol=1e-5) for p in poses)
