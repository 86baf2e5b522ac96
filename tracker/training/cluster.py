"""``app.py build --ray [ADDRESS]``: a build's stages on a Ray cluster.

- Rendering: each split is cut into shards (:func:`tracker.training.synth.engine.shard_range`,
  the code of ``synth --shard``), and each shard is a Ray task that renders it with one process
  (:func:`tracker.training.synth.engine.generate`). Images are pure functions of (seed, index),
  so the shards joined (:func:`tracker.training.synth.join.join_splits`) hold the images and
  annotations that one process makes, byte for byte.
- What a task reads and writes travels through Ray's **object store**, not a shared path: the
  meshes and backgrounds (~16 MB for LM-O) go out once as a tar, each rendered shard comes back
  as a tar (JPEG and PNG files, no recompression) and is unpacked into the build's work folder.
  So rendering needs nothing of the machines but the installed package: no NFS, no copies by
  hand, and a worker machine keeps no files (its shard is written to a temporary folder).
- Training: the encoder and detector stages run the same functions as ``torchrun`` does
  (:mod:`tracker.training.nets.distributed`) under Ray Train's ``TorchTrainer``: one worker per
  CPU (gloo) or GPU (NCCL) of the cluster, ``--workers N`` at most. Training reads the rendered
  split and writes checkpoints and the bundle in the build's folder, so on several machines
  that folder must be the same path on all of them (a shared file system); on one machine it
  simply is.

Faults. A render task whose process dies (a Mesa segfault, a lost node) is retried by Ray
(:data:`RETRIES` times) and its shard rendered again from scratch; a task that returns nothing
for :data:`tracker.training.synth.engine.STALL_S` is cancelled and submitted again; a shard that
keeps failing ends the build with an error naming it. Finished shards stay in the work folder,
so a rerun renders only the missing ones. A training worker lost mid-run makes Ray Train start
the group again (:data:`RETRIES` times), and the training functions resume from their own
checkpoints (the autoencoder's inside epochs, the detector's every 5 minutes). Ctrl-C (or
SIGTERM) cancels this build's tasks; leaving Ray ends the cluster's work that this driver owns.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import shutil
import tarfile
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

from tracker.core.errors import UserError

EXTRA = "pip install -e '.[cluster]'"
RETRIES = 3
# the most images a render task makes: a lost task costs at most this much, and the tasks of a
# big split spread over the cluster's CPUs as they free up (about 20 s of one process here)
SHARD_IMAGES = 250
TRAINING = {"encoder": ("tracker.training.train", "train_bundle"),
            "detector": ("tracker.training.detector_train", "train_detector")}


def require_ray():
    """Ray and Ray Train, or a one-line error naming the extra that brings them."""
    try:
        import ray
        import ray.train.torch  # noqa: F401
    except ImportError:
        raise UserError(f"build --ray needs Ray (the 'cluster' extra): {EXTRA}") from None
    return ray


def shard_count(n_images: int, slots: int) -> int:
    """Shards of an ``n_images`` split on ``slots`` CPUs: two per CPU (the last ones fill the
    gaps of the slow), more where a shard would hold over :data:`SHARD_IMAGES`, never more than
    the images."""
    return max(1, min(n_images, max(2 * slots, math.ceil(n_images / SHARD_IMAGES))))


def _tar(folder: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as t:
        for p in sorted(folder.rglob("*")):
            t.add(p, arcname=str(p.relative_to(folder)), recursive=False)
    return buf.getvalue()


def _untar(data: bytes, dest: Path) -> None:
    with tarfile.open(fileobj=io.BytesIO(data)) as t:
        t.extractall(dest, filter="data")  # plain files and folders under dest only


def _assets(models_dir: Path, backgrounds_dir: Path) -> bytes:
    """The meshes and backgrounds a render task reads, as one tar (models/, backgrounds/)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as t:
        t.add(models_dir, arcname="models")
        t.add(backgrounds_dir, arcname="backgrounds")
    return buf.getvalue()


def _unpacked_assets(assets: bytes, key: str) -> Path:
    """The assets unpacked once per machine (a folder named by their hash; made beside it and
    renamed into place, so tasks running at once on one machine never see half of it)."""
    root = Path(tempfile.gettempdir()) / "autopose-ray" / key
    if not root.is_dir():
        root.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=root.parent))
        _untar(assets, tmp)
        try:
            tmp.rename(root)
        except OSError:  # another task of this machine was first
            shutil.rmtree(tmp, ignore_errors=True)
    return root


def render_shard(cfg_dict: dict, assets: bytes, assets_key: str, n_images: int, shard: tuple[int, int],
                 deadline: float | None, min_images: int, command: str) -> bytes:
    """A Ray task's work: shard ``shard`` of the split, rendered by this process into a
    temporary folder and returned as a tar (its ``synth_config.json`` included). ``deadline``:
    the build's render budget as a wall-clock time (``time.time()``), or None."""
    from tracker.training.synth.engine import SynthConfig, generate
    root = _unpacked_assets(assets, assets_key)
    cfg = SynthConfig(**{**cfg_dict, "models_dir": str(root / "models"),
                         "backgrounds_dir": str(root / "backgrounds")})
    seconds = None if deadline is None else max(0.0, deadline - time.time())
    with tempfile.TemporaryDirectory(prefix="autopose-shard-") as tmp:
        out = Path(tmp) / "split"
        generate(cfg, out, n_images, workers=1, progress=False, command=command, shard=shard,
                 seconds=seconds, min_images=min_images)
        return _tar(out)


def _train_loop(config: dict) -> None:
    """A Ray Train worker: the stage's training function, as under torchrun (Ray Train made the
    process group and set RANK and WORLD_SIZE; :mod:`tracker.training.nets.distributed` joins
    it). A bad-input error is written for the driver and not retried (it would fail again)."""
    import importlib
    module, name = TRAINING[config["stage"]]
    fn = getattr(importlib.import_module(module), name)
    try:
        import torch
        if torch.cuda.is_available():  # this worker's own GPU, not the first of the node's
            import ray.train.torch
            torch.cuda.set_device(ray.train.torch.get_device())
        fn(**config["kwargs"], log=lambda m: print(m, flush=True))
    except UserError as e:
        if int(os.environ.get("RANK", "0")) == 0:
            Path(config["error_file"]).write_text(str(e))


class RayCluster:
    """One build's connection to Ray: ``address`` None starts a local cluster for the build
    (``num_cpus``: its CPUs, default all), ``auto`` or ``ray://host:port`` joins one. A process
    that is connected already (``ray.init`` before) is used as it is and left connected.
    ``workers``: the most training workers and render tasks at once (default: the cluster's
    CPUs, or its GPUs for training where it has any)."""

    def __init__(self, address: str | None = None, workers: int | None = None, num_cpus: int | None = None,
                 log=print):
        self.ray = require_ray()
        self.address, self.cap, self.num_cpus, self.log = address, workers, num_cpus, log
        self.started = False

    def __enter__(self) -> "RayCluster":
        ray = self.ray
        if not ray.is_initialized():
            import logging
            os.environ.setdefault("RAY_TRAIN_ENABLE_PRINT_PATCH", "0")  # workers' prints once, not twice
            if self.address is None:  # a cluster of this build's own: its workers at the build's priority
                os.environ.setdefault("RAY_worker_niceness", "0")  # (Ray's default, 15, starved them here)
            try:
                # the workers' Python logging at ERROR: without the dashboard (not in the extra) Ray
                # Train's placement-group cleaner warns every few seconds that it cannot ask for state
                ray.init(address=self.address, num_cpus=self.num_cpus if self.address is None else None,
                         include_dashboard=False, logging_level=logging.WARNING, log_to_driver=True,
                         logging_config=ray.LoggingConfig(log_level="ERROR"))
            except ConnectionError as e:
                raise UserError(f"--ray {self.address}: no Ray cluster there ({str(e).splitlines()[0]}); "
                                f"start one with 'ray start --head', or give no address for a local one") from None
            self.started = True
        res = ray.cluster_resources()
        self.cpus, self.gpus = int(res.get("CPU", 0)), int(res.get("GPU", 0))
        if self.cpus < 1:
            raise UserError("--ray: the cluster offers no CPUs (every node started with --num-cpus 0?)")
        self.log(f"ray: {'a local cluster' if self.address is None else self.address}, {self.cpus} CPUs, "
                 f"{self.gpus} GPUs, {len(ray.nodes())} node(s)")
        return self

    def __exit__(self, *exc) -> None:
        if self.started:
            self.ray.shutdown()

    def slots(self) -> int:
        return max(1, min(self.cpus, self.cap or self.cpus))

    # ------------------------------------------------------------------ rendering

    def render(self, cfg, split: Path, n_images: int, seconds: float | None, min_images: int,
               command: str, key: str, tasks: int | None = None) -> dict:
        """Render ``n_images`` of ``cfg`` into ``split`` as shards on the cluster; returns the
        stage's record. Shards finished by an earlier run of the same ``key`` are kept. Each
        shard is a scene of the joined split; ``tasks`` 1: one task, one scene (what ``eval``
        reads), else :func:`shard_count`."""
        from tracker.training.synth.engine import STALL_S
        from tracker.training.synth.join import join_splits
        ray = self.ray
        shards_dir = split.with_name(split.name + ".shards")
        tasks = tasks or shard_count(n_images, self.slots())
        plan = {"key": key, "images": n_images, "tasks": tasks}
        plan_file = shards_dir / "plan.json"
        if not (plan_file.is_file() and json.loads(plan_file.read_text()) == plan):
            shutil.rmtree(shards_dir, ignore_errors=True)
            shards_dir.mkdir(parents=True)
            plan_file.write_text(json.dumps(plan))
        todo = [k for k in range(tasks) if not (shards_dir / f"{k:05d}").is_dir()]
        if len(todo) < tasks:
            self.log(f"{split.name}: {tasks - len(todo)} of {tasks} shards done before")
        models_dir, backgrounds_dir = Path(cfg.models_dir).resolve(), Path(cfg.backgrounds_dir).resolve()
        assets = _assets(models_dir, backgrounds_dir)
        assets_ref = ray.put(assets)
        assets_key = hashlib.sha256(assets).hexdigest()[:16]
        deadline = None if seconds is None else time.time() + seconds
        share = lambda k: math.ceil(min_images * len(range(k * n_images // tasks, (k + 1) * n_images // tasks))  # noqa: E731
                                    / n_images)
        from tracker.training.synth.engine import CRASH_HOOK
        hook = {"runtime_env": {"env_vars": {CRASH_HOOK: os.environ[CRASH_HOOK]}}} if os.environ.get(CRASH_HOOK) else {}
        task = ray.remote(render_shard).options(num_cpus=1, max_retries=RETRIES, name=f"render {split.name}", **hook)
        cfg_dict = asdict(cfg)
        t0 = time.perf_counter()
        attempts = dict.fromkeys(todo, 0)
        running: dict = {}
        pending = list(todo)
        self.log(f"{split.name}: {n_images} images in {tasks} render tasks, {self.slots()} at a time")
        try:
            while pending or running:
                while pending and len(running) < self.slots():
                    k = pending.pop(0)
                    attempts[k] += 1
                    running[task.remote(cfg_dict, assets_ref, assets_key, n_images, (k, tasks), deadline, share(k),
                                        f"{command} (shard {k}/{tasks})")] = k
                done, _ = ray.wait(list(running), num_returns=1, timeout=STALL_S)
                if not done:  # nothing came back for STALL_S: the tasks in flight are taken as hung
                    for ref, k in running.items():
                        ray.cancel(ref, force=True)
                        self._again(k, attempts, pending, "hung")
                    running = {}
                    continue
                ref = done[0]
                k = running.pop(ref)
                try:
                    data = ray.get(ref)
                except ray.exceptions.RayError as e:  # the task's own error, its process or node lost
                    cause = getattr(e, "cause", None)
                    if isinstance(cause, UserError):
                        raise UserError(str(cause)) from None
                    self._again(k, attempts, pending, type(e).__name__)
                    continue
                self._keep(data, shards_dir / f"{k:05d}", models_dir, backgrounds_dir)
        except BaseException:  # Ctrl-C, an error: this build's tasks stop; finished shards stay
            for ref in running:
                ray.cancel(ref, force=True)
            raise
        dt = time.perf_counter() - t0
        shutil.rmtree(split, ignore_errors=True)
        parts = [shards_dir / f"{k:05d}" for k in range(tasks)]
        metas = [json.loads((p / "synth_config.json").read_text()) for p in parts]
        if len(parts) == 1:
            shutil.copytree(parts[0], split, symlinks=True)
        else:
            join_splits(split, parts, command=command)
        images = sum(int(m.get("images_written", m.get("images", 0))) for m in metas)
        return {"images": images, "images_per_s": round(images / max(dt, 1e-9), 2),
                "time_limited": any(m.get("time_limited", False) for m in metas), "render_tasks": tasks}

    def _again(self, k: int, attempts: dict, pending: list, why: str) -> None:
        if attempts[k] > RETRIES:
            raise UserError(f"render task {k} failed {attempts[k]} times ({why}); rerun the same command to "
                            f"render the missing shards again, or build without --ray")
        self.log(f"ray: render task {k} {why}; submitting it again")
        pending.append(k)

    @staticmethod
    def _keep(data: bytes, dest: Path, models_dir: Path, backgrounds_dir: Path) -> None:
        """A returned shard into the work folder (unpacked beside, then renamed: a folder there
        is a finished shard), its config pointing at this machine's meshes and backgrounds, as a
        split rendered here records them."""
        part = dest.with_name(dest.name + ".part")
        shutil.rmtree(part, ignore_errors=True)
        _untar(data, part)
        meta = json.loads((part / "synth_config.json").read_text())
        meta["config"].update(models_dir=str(models_dir), backgrounds_dir=str(backgrounds_dir))
        (part / "synth_config.json").write_text(json.dumps(meta, indent=1))
        part.rename(dest)

    # ------------------------------------------------------------------ training

    def train(self, stage: str, kwargs: dict, work: Path, budget_minutes: float) -> int:
        """``stage``'s training function (:data:`TRAINING`) with ``kwargs`` on the cluster's
        workers; returns how many trained. The function writes the bundle as under torchrun."""
        from ray.train import FailureConfig, RunConfig, ScalingConfig
        from ray.train.torch import TorchConfig, TorchTrainer
        use_gpu = self.gpus > 0 and kwargs.get("device", "auto") != "cpu"
        n = max(1, min(self.gpus if use_gpu else self.cpus, self.cap or 10 ** 6))
        error_file = work / f"ray_{stage}_error.txt"
        error_file.unlink(missing_ok=True)
        # the first worker fits the heads or validates while the others wait at the group's
        # barrier: the group's timeout must outlast that
        timeout = int(max(1800, 2 * 60 * budget_minutes))
        trainer = TorchTrainer(
            _train_loop, train_loop_config={"stage": stage, "kwargs": kwargs, "error_file": str(error_file)},
            torch_config=TorchConfig(backend="nccl" if use_gpu else "gloo", timeout_s=timeout),
            scaling_config=ScalingConfig(num_workers=n, use_gpu=use_gpu),
            run_config=RunConfig(name=f"{stage}-{int(time.time())}", storage_path=str(work / "ray"),
                                 failure_config=FailureConfig(max_failures=RETRIES)))
        self.log(f"ray: {stage} on {n} training worker(s) ({'NCCL, GPUs' if use_gpu else 'gloo, CPUs'})")
        try:
            trainer.fit()
        except Exception as e:  # a worker that kept dying: the error's first line, not Ray's trace
            raise UserError(f"the {stage} stage failed on the cluster: {str(e).strip().splitlines()[0]}; "
                            f"its checkpoints are kept, rerun the same command to resume") from None
        if error_file.is_file():
            raise UserError(error_file.read_text())
        return n
