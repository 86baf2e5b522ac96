"""Where the repository and the shared data live."""
from __future__ import annotations

import os
from pathlib import Path

from tracker.core.errors import UserError

REPO = Path(__file__).resolve().parents[2]


def shared_data() -> Path:
    """The shared data folder: $AUTOPOSE_DATA, else ../shared/data beside the repo."""
    env = os.environ.get("AUTOPOSE_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


DEMO_RECORDING = REPO / "demo" / "lmo_dev"


def work_dir(bundle_dir) -> Path:
    """``<bundle>.work/`` beside a bundle: its training checkpoints and caches (never shipped)."""
    b = Path(bundle_dir)
    return b.parent / (b.name + ".work")


def cache_dir() -> Path:
    """Where derived files are cached between runs (models_info, parsed meshes):
    ``$AUTOPOSE_CACHE``, else ``$XDG_CACHE_HOME/autopose``, else ``~/.cache/autopose``."""
    env = os.environ.get("AUTOPOSE_CACHE")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "autopose"


def lmo_dev_scene() -> Path:
    return _must_exist(shared_data() / "lmo" / "dev")


def lmo_models() -> Path:
    return _must_exist(shared_data() / "lmo" / "models")


def _must_exist(p: Path) -> Path:
    if not p.exists():
        raise UserError(f"data not found: {p} (put the shared data beside the repo as ../shared/data "
                        f"or set AUTOPOSE_DATA)")
    return p
