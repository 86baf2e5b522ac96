import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from tracker.paths import shared_data  # noqa: E402

DATA = shared_data()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.fail(f"shared data not found at {DATA}: CI runs with ../shared beside the repo")
    return DATA


@pytest.fixture(scope="session")
def lmo_dev(data_dir):
    from tracker.bop import load_scene
    return load_scene(data_dir / "lmo" / "dev", require_gt=True)


@pytest.fixture(scope="session")
def lmo_models(data_dir):
    from tracker.meshes import load_models
    return load_models(data_dir / "lmo" / "models")
