"""``build --ray``: rendering as Ray tasks over shards, training under Ray Train's TorchTrainer,
on a local Ray cluster of 2 CPUs. Tiny budgets and splits: this exercises the job, not accuracy."""
import json
import shutil
import sys
from pathlib import Path

import pytest

from tracker.core.errors import UserError
from tracker.training import cluster as cl

FIX = Path(__file__).parent / "fixtures" / "models"


def test_without_the_cluster_extra_ray_is_one_line_naming_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # as if not installed
    with pytest.raises(UserError, match=r"^build --ray needs Ray \(the 'cluster' extra\): pip install -e '\.\[cluster\]'$"):
        cl.RayCluster()


def test_without_the_extra_the_command_line_says_so_in_one_line(monkeypatch, tmp_path, capsys):
    from tracker.cli import main
    monkeypatch.setitem(sys.modules, "ray", None)
    (tmp_path / "m").mkdir()
    shutil.copy(FIX / "obj_000001.ply", tmp_path / "m")
    assert main(["build", "--models", str(tmp_path / "m"), "--out", str(tmp_path / "out"), "--ray"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install -e '.[cluster]'" in err[0]
    assert not (tmp_path / "out").exists()  # nothing rendered or written first


def test_without_ray_nothing_imports_it():
    """build's modules, the cluster module and the command line load without Ray: it is
    imported only when --ray is given (a fresh interpreter: this one may hold it)."""
    import subprocess
    code = ("import sys; import tracker.training.build, tracker.training.cluster; from tracker.cli.main import "
            "build_parser; build_parser().parse_args(['build', '--models', 'm', '--out', 'o']); "
            "print('ray' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "False", r.stderr


def test_shards_are_two_per_cpu_and_bounded_in_size():
    assert cl.shard_count(8, 2) == 4
    assert cl.shard_count(3, 2) == 3  # never more than the images
    assert cl.shard_count(10_000, 2) == 40  # at most SHARD_IMAGES each
    assert cl.shard_count(1, 64) == 1


def test_the_build_record_says_how_each_stage_ran():
    from tracker.training.build import executor_record
    ray = {"render": {"executor": "ray", "render_tasks": 4}, "render-det": {"executor": "ray", "render_tasks": 4},
           "encoder": {"executor": "ray", "training_workers": 2}, "detector": {"executor": "ray", "training_workers": 2},
           "check": {"executor": "ray", "render_tasks": 2}, "models": {}, "report": {}}
    r = executor_record(ray)
    assert (r["executor"], r["render_tasks"], r["training_workers"]) == ("ray", 10, 2)
    old = {k: {} for k in ray}  # recorded before --ray: local
    assert executor_record(old)["executor"] == "local"
    assert executor_record({**ray, "detector": {"executor": "local"}})["executor"] == "mixed"


# ---------------------------------------------------------------- on a local cluster

ray = pytest.importorskip("ray")
pytest.importorskip("torch")
from tracker.training import build as bb  # noqa: E402
from tracker.core.bundle import open_bundle  # noqa: E402
from tests.conftest import fixture_meshes  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray cluster of 2 CPUs for this module's tests, started as `build --ray` starts
    its own (the RayClusters of the tests find it connected and leave it open)."""
    with cl.RayCluster(num_cpus=2, log=lambda m: None) as c:
        assert c.started and c.cpus == 2
        yield


def _mesh(tmp_path):
    return fixture_meshes(tmp_path, ("obj_000001.ply",))


def _images(split: Path) -> dict:
    """Every file of a split's scenes by (image id, kind, name), with its bytes, and the
    annotations by image id: what must agree between two renders of one split."""
    files, gt = {}, {}
    for scene in sorted(p for p in split.iterdir() if p.is_dir()):
        for f in scene.rglob("*"):
            if f.is_file() and f.suffix in (".jpg", ".png"):
                files[(f.parent.name, f.name)] = f.read_bytes()
        for name in ("scene_gt", "scene_gt_info", "scene_camera", "clean_crops"):
            for k, v in json.loads((scene / f"{name}.json").read_text()).items():
                gt[(name, k)] = v
    return {"files": files, "gt": gt}


def work_of(out: Path) -> Path:
    return out.parent / (out.name + ".work") / "build"


def _build(tmp_path, log):
    recipe = bb.Recipe(models=str(_mesh(tmp_path)), minutes=0.05, workers=1, size=32, latent=16, head_sets=1)
    out = tmp_path / "models" / "mine"
    with cl.RayCluster(log=log) as cluster:
        assert not cluster.started  # the module's cluster, left open
        s = bb.build(recipe, out, log=log, cluster=cluster)
    return recipe, out, s


def test_build_on_a_local_ray_cluster_renders_in_tasks_and_trains_with_two_workers(local_ray, small, tmp_path):
    logs = []
    recipe, out, s = _build(tmp_path, logs.append)
    b = open_bundle(out)  # verified: every file hashed
    assert b.manifest.has_detector and b.manifest.obj_ids == [1]
    rec = b.manifest.extra["build"]
    # 8 + 8 images on 2 CPUs: 4 + 4 shards, the 4 held-out images in 1 (one scene for eval);
    # both networks trained by 2 gloo workers
    assert rec["executor"] == "ray" and rec["training_workers"] == 2 and rec["render_tasks"] == 9
    assert len(list((work_of(out) / "split_check").iterdir())) == 2  # one scene and its synth_config.json
    assert s["stages"]["check"]["detector"]["per_object"]["1"]["n_gt"] >= 2  # more than the first shard's image was scored
    assert set(rec["executor_by_stage"].values()) == {"ray"}
    assert s["stages"]["encoder"]["training_workers"] == s["stages"]["detector"]["training_workers"] == 2
    work = tmp_path / "models" / "mine.work" / "build"
    assert len(list((work / "split_encoder.shards").glob("0000?"))) == 4
    # the shards joined hold what one process renders from the same split: byte for byte
    from tracker.training.synth.engine import SynthConfig, generate
    cfg = json.loads((work / "split_encoder" / "synth_config.json").read_text())["config"]
    generate(SynthConfig(**cfg), tmp_path / "here", 8, workers=1, progress=False)
    here, there = _images(tmp_path / "here"), _images(work / "split_encoder")
    assert len(there["files"]) > 8 and here["files"].keys() == there["files"].keys()
    assert here["files"] == there["files"] and here["gt"] == there["gt"]
    # the bundle tracks: its detector and encoder over a scene of these renders
    from tracker.evaluation.track import track
    from tracker.runtime.loop import TrackConfig
    t = track(TrackConfig(str(tmp_path / "here" / "000000"), str(out), tmp_path / "run", rerun="off", max_frames=3,
                          boxes="detector", overlay=False), log=lambda m: None)
    assert t.frames == 3 and t.boxes == "detector" and t.accuracy["n_gt"] >= 3
    # the same command again: every stage cached, nothing sent to the cluster
    logs = []
    with cl.RayCluster(log=logs.append) as cluster:
        bb.build(recipe, out, log=logs.append, cluster=cluster)
    assert sum("done before (cached)" in m for m in logs) == 7


def test_a_killed_render_task_is_rendered_again_and_the_build_finishes(local_ray, small, tmp_path, monkeypatch):
    from tracker.training.synth.engine import CRASH_HOOK
    marker = tmp_path / "crashed"
    monkeypatch.setenv(CRASH_HOOK, f"3:{marker}")  # the task that renders image 3 dies once, as a segfault
    logs = []
    _, out, s = _build(tmp_path, logs.append)
    assert marker.is_file()  # it did die
    work = tmp_path / "models" / "mine.work" / "build"
    ids = sorted(int(f.stem) for f in (work / "split_encoder").glob("*/rgb/*.jpg"))
    assert ids == list(range(8))  # every image, once
    assert s["stages"]["render"]["images"] == 8
    assert open_bundle(out).manifest.extra["build"]["executor"] == "ray"


def test_ctrl_c_while_rendering_keeps_the_finished_shards_and_a_rerun_renders_the_rest(local_ray, tmp_path,
                                                                                         monkeypatch):
    from tracker.core.paths import shared_data
    from tracker.training.prepare import prepare_models
    from tracker.training.synth.engine import SynthConfig
    prepare_models(_mesh(tmp_path), tmp_path / "models", units="mm", log=lambda m: None)
    cfg = SynthConfig(models_dir=str(tmp_path / "models"), backgrounds_dir=str(shared_data() / "backgrounds"),
                      seed=5, obj_ids=[1])
    real = cl.RayCluster._keep
    calls = []

    def keep_then_interrupt(*a):
        real(*a)
        calls.append(1)
        raise KeyboardInterrupt
    monkeypatch.setattr(cl.RayCluster, "_keep", staticmethod(keep_then_interrupt))
    split = tmp_path / "split"
    with cl.RayCluster(log=lambda m: None) as cluster, pytest.raises(KeyboardInterrupt):
        cluster.render(cfg, split, 8, None, 8, "test", key="k")
    assert len(list((tmp_path / "split.shards").glob("0000?"))) == 1  # the finished shard stays
    monkeypatch.setattr(cl.RayCluster, "_keep", staticmethod(real))
    logs = []
    with cl.RayCluster(log=logs.append) as cluster:
        r = cluster.render(cfg, split, 8, None, 8, "test", key="k")
    assert "1 of 4 shards done before" in " ".join(logs)
    assert r["images"] == 8 and r["render_tasks"] == 4
    assert sorted(int(f.stem) for f in split.glob("*/rgb/*.jpg")) == list(range(8))
