"""The runtime never imports torch: the demo and ``eval`` run in a process where importing
torch fails, and importing the runtime's modules loads neither torch nor the training code."""
import json
import os
import subprocess
import sys

from tests.conftest import REPO

# a meta-path hook that makes torch (and its submodules) unimportable, then app.py as __main__; with
# MODULES_OUT set, the names of the modules loaded when the process ends are written to that file
BLOCK = """
import atexit, os, sys, runpy
if os.environ.get("MODULES_OUT"):
    atexit.register(lambda: open(os.environ["MODULES_OUT"], "w").write("\\n".join(sorted(sys.modules))))
class NoTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("torch is blocked in this test")
        return None
sys.meta_path.insert(0, NoTorch())
sys.argv = ["app.py"] + sys.argv[1:]
runpy.run_path("app.py", run_name="__main__")
"""


def _app(*args, cwd=REPO, env=None):
    return subprocess.run([sys.executable, "-c", BLOCK, *map(str, args)], cwd=cwd, capture_output=True, text=True,
                          timeout=240, env={"PYOPENGL_PLATFORM": "egl", "PATH": "/usr/bin:/bin",
                                            "AUTOPOSE_CACHE": os.environ["AUTOPOSE_CACHE"], **(env or {})})


def test_the_demo_runs_with_torch_unimportable(data_dir, tmp_path):
    p = _app("demo", "--max-frames", 3, "--out", tmp_path / "demo")
    assert p.returncode == 0, p.stderr[-2000:]
    s = json.loads((tmp_path / "demo" / "summary.json").read_text())
    assert s["frames"] == 3 and s["poses"] > 10 and s["error"] is None
    assert (tmp_path / "demo" / "recording.rrd").stat().st_size > 0


def test_the_demo_imports_no_training_code(tmp_path):
    """The real entry point: everything app.py demo loaded, read when its process ends."""
    modules = tmp_path / "modules.txt"
    p = _app("demo", "--max-frames", 2, "--rerun", "off", "--out", tmp_path / "demo", env={"MODULES_OUT": str(modules)})
    assert p.returncode == 0, p.stderr[-2000:]
    loaded = modules.read_text().split("\n")
    assert {"tracker.cli.main", "tracker.runtime.loop", "tracker.evaluation.track"} <= set(loaded)  # the demo ran
    training = [m for m in loaded if m in ("torch", "tracker.training", "tracker.research", "sklearn")
                or m.startswith(("torch.", "tracker.training.", "tracker.research.", "sklearn."))]
    assert training == []


def test_eval_runs_with_torch_unimportable(data_dir, tmp_path):
    for boxes in ("gt", "detector"):
        p = _app("eval", "--model", REPO / "models" / "lmo", "--data", data_dir / "lmo" / "dev", "--boxes", boxes,
                 "--max-frames", 3, "--json", tmp_path / f"{boxes}.json")
        assert p.returncode == 0, p.stderr[-2000:]
        assert json.loads((tmp_path / f"{boxes}.json").read_text())["n_est"] > 10


def test_the_blocker_does_block_torch():
    p = subprocess.run([sys.executable, "-c", BLOCK.replace('runpy.run_path("app.py", run_name="__main__")',
                                                             "import torch")], capture_output=True, text=True)
    assert p.returncode != 0 and "torch is blocked" in p.stderr


def test_runtime_modules_import_neither_torch_nor_the_training_code():
    code = ("import sys\n"
            "import tracker.cli, tracker.runtime.loop, tracker.runtime.pipeline, tracker.runtime.detector, "
            "tracker.evaluation.track, tracker.evaluation.evaluate, tracker.evaluation.bench\n"
            "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith(('torch.', 'tracker.training', "
            "'tracker.research', 'sklearn')))\n"
            "print(bad)\n")
    p = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]", p.stdout
