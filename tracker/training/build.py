"""``app.py build``: from a folder of meshes to a finished tracking bundle, in one time budget.

Stages, run in order; everything they make lives in ``MODEL_DIR.work/`` except the bundle:

1. ``models``    the meshes -> a BOP models folder in mm (:mod:`tracker.training.prepare`)
2. ``render``    a synthetic split (``synth``, the chosen pose prior, lit from the camera's side)
3. ``render-det`` another (another seed; hard distractors, lit from above: what the detectors
   of ``models/lmo`` were trained on). With fewer objects than a scene holds, both repeat
   objects (several instances per image), so a build of one or two objects gets as many crops
   per rendered image as one of eight
4. ``encoder``   the autoencoder and its pose heads (``train``) on both splits
5. ``detector``  the detector (``train-detector``) on both splits, at ``detector_input``, then
   stored int8 calibrated on its training renders (``lab join-detectors --int8``'s function;
   stop 65: NanoDet at 416 x 320 int8 against 320 x 240 float, dev detector-box mean +0.037
   [+0.019, +0.054] and 9.5 against 11.2 ms a frame), its weights in 7 bits (stop 66: the
   same on every CPU, no figure's interval below 8 bits')
6. ``check``     a fresh held-out render split, and ``eval`` on it with ground-truth and
   detector boxes
7. ``report``    ``MODEL_DIR/report/report.md`` + PNGs: sample renders next to their
   crops, accuracy per object on the held-out renders, timings

The budget (:func:`plan`): ``--minutes`` is split as 20 % rendering (half per split: each
renders for its share of the time, at least :data:`MIN_IMAGES` images, at most
:data:`MAX_RATE` images per second of it and at most what this machine's memory holds,
:func:`memory_cap`; a split that reaches its image count before its time leaves the rest to
the three training stages, in proportion to their shares: :func:`share_out`), 48 % encoder (of which 10 points for the heads: three
head sets averaged, :func:`tracker.training.train.fit_head_sets`; the autoencoder trains for what is
left of the 48 % after cutting the crops, and before the heads and the rest:
:func:`tracker.training.train.training_minutes`), 30 % detector (its loading, validation and
export included), 2 % held-out check and report (40 renders and two evaluations: seconds). Each stage is cached by a hash of its options
and of the stages it reads; a rerun of the same command skips finished stages, and
``train``/``train-detector`` resume from their checkpoints. Ctrl-C (or SIGTERM, as a cluster
scheduler sends) keeps what is done; a stage's recorded time adds up all its runs. The
recipe (every option and seed, the package versions) goes into the manifest (``build``), so
``build --from-manifest BUNDLE`` redoes it.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from tracker.core.defaults import SYNTH_FACES
from tracker.core.errors import UserError
from tracker.core.files import write_whole

SHARES = {"render": 0.10, "render-det": 0.10, "encoder": 0.38, "heads": 0.10, "detector": 0.30, "check": 0.02}
MAX_RATE = 50.0  # images per second of a split's time share: the cap on its size (2 workers here: ~30)
MIN_IMAGES = 60
# the memory a split's image holds at the build's peak, the encoder stage (two crop sets, their
# training copies, the heads' inputs): measured on a two-object build's 21,300 images (112,199
# crops at 64 px), 12.5 GB, about 0.55 MB an image over 1.5 GB; the detector stage held 6.2 GB
# for the same images (0.23 MB an image at 320 x 240). The splits' images are capped so that
# this stays within MEMORY_SHARE of the machine's memory (an 8-object build of several hours
# would otherwise render more than 24 GB can train on). Since stop 63 the encoder stage copies
# no crops for its training split and the heads keep no pixels: at 96 px, 14,106 images (73,801
# crops) peaked at 9.4 GB against 21.2 GB before, about 0.25 MB an image at 64 px. The cap keeps
# the older figure until a build shows that the renders it would add pay (they cost epochs).
BYTES_PER_IMAGE_64 = 0.55e6
DET_BYTES_PER_IMAGE = 0.23e6  # at 320 x 240; in proportion to the input's pixels
BASE_BYTES = 1.5e9
MEMORY_SHARE = 0.75
CHECK_IMAGES = 40
# the detector's peak learning rate by backbone: pretrained weights are fine-tuned at half the
# from-scratch recipe's (stop 57's arms, set before their run)
DETECTOR_LR = {"nanodet": 1e-3}
# the detector's recipe fields before stop 66 (320 x 240, float32): what older recipes read as,
# and what the stage keys leave out (so that older builds resume)
DETECTOR_BEFORE = {"detector_input": [320, 240], "detector_int8": False}
# the int8 detector's weight bits: 7 cannot saturate the 16-bit sums of CPUs without 8-bit dot
# products (AVX2), so every CPU computes the same; against 8 bits on the same network (stop 66),
# dev detector-box mean -0.004 [-0.017, +0.008], no figure's interval below 0
DETECTOR_WEIGHT_BITS = 7
STAGES = ("models", "render", "render-det", "encoder", "detector", "check", "report")


@dataclass
class Recipe:
    """What ``build`` was asked: everything that makes the bundle (and the manifest keeps)."""
    models: str
    minutes: float = 60.0
    objects: list[int] | None = None
    prior: str = "table"
    units: str = "auto"
    seed: int = 0
    method: str = "cvam"
    encoder: str = "plain"
    size: int = 64
    latent: int = 128
    # the COCO-pretrained NanoDet trunk (stop 57: against the plain one at the same data and 40-minute
    # budget, dev detector-box mean +0.038 [+0.010, +0.067], AP50 0.453 -> 0.547; detect 5 -> 12.5 ms)
    detector_backbone: str = "nanodet"
    # the detector's input [W, H] and whether it is stored int8 (stop 65: 416 x 320 int8 against
    # 320 x 240 float32, dev detector-box mean +0.037 [+0.019, +0.054], 9.5 against 11.2 ms a frame)
    detector_input: list[int] = field(default_factory=lambda: [416, 320])
    detector_int8: bool = True
    workers: int = 2
    device: str = "auto"
    # the renders' meshes decimated to about this many faces (synth's default); 0: the full meshes
    mesh_faces: int = SYNTH_FACES
    # head sets fitted on the encoder with seeds seed, seed + 1, ... and averaged
    head_sets: int = 3
    # the most images per split; None: what this machine's memory holds (memory_cap)
    max_images: int | None = None
    # object names that beat the file names ({"9": "duck"}; a names file's path is read into
    # this); None: a names.json beside the meshes, else the file names (tracker.training.prepare)
    names: dict[str, str] | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.names is not None:  # kept as {"id": name} in id order: as the manifest's JSON holds it
            from tracker.training.prepare import read_names
            where = str(self.names) if isinstance(self.names, (str, os.PathLike)) else "--names"
            self.names = {str(k): v for k, v in read_names(self.names, where).items()} or None

    @classmethod
    def from_dict(cls, d: dict) -> "Recipe":
        known = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
        known.setdefault("mesh_faces", 0)  # recorded before stop 47: the full meshes, as they were built
        known.setdefault("head_sets", 1)  # recorded before stop 51: one head set
        known.setdefault("detector_backbone", "plain")  # recorded before it was kept
        for k, v in DETECTOR_BEFORE.items():  # recorded before stop 66
            known.setdefault(k, v.copy() if isinstance(v, list) else v)
        return cls(**known)


def memory_cap(size: int = 64, ram_bytes: float | None = None, detector_input=(320, 240)) -> int:
    """The most images per split (two splits) whose crops at ``size`` px and detector inputs at
    ``detector_input`` fit in :data:`MEMORY_SHARE` of ``ram_bytes`` (default: this machine's
    memory) at the build's peak."""
    if ram_bytes is None:
        ram_bytes = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    w, h = detector_input
    per_image = max(BYTES_PER_IMAGE_64 * (size / 64) ** 2, DET_BYTES_PER_IMAGE * w * h / (320 * 240))
    return max(MIN_IMAGES, int((MEMORY_SHARE * ram_bytes - BASE_BYTES) / per_image / 2))


def plan(recipe: Recipe, ram_bytes: float | None = None) -> dict:
    """Minutes per stage, seconds and most images per split for ``recipe.minutes`` (the rule above)."""
    m = float(recipe.minutes)
    cap = max(MIN_IMAGES, recipe.max_images or memory_cap(recipe.size, ram_bytes, recipe.detector_input))
    images = lambda share: max(MIN_IMAGES, min(cap, int(share * m * 60 * MAX_RATE)))  # noqa: E731
    return {"render_seconds": round(SHARES["render"] * m * 60, 1), "render_images": images(SHARES["render"]),
            "render_det_seconds": round(SHARES["render-det"] * m * 60, 1),
            "render_det_images": images(SHARES["render-det"]),
            "encoder_minutes": round(SHARES["encoder"] * m, 3),
            # each head set: three regressors' worth (the MLPs 2, the KNN's choice and the trees 1)
            "reg_minutes": round(SHARES["heads"] * m / (3 * recipe.head_sets), 3),
            "detector_minutes": round(SHARES["detector"] * m, 3), "check_images": CHECK_IMAGES,
            "max_images": cap}


def share_out(planned: dict, minutes: float, leftover_seconds: float) -> dict:
    """The plan after the renders: the seconds the splits did not use (they reached their image
    count first) go to the encoder, its heads and the detector in proportion to their shares."""
    if leftover_seconds <= 0:
        return planned
    train = SHARES["encoder"] + SHARES["heads"] + SHARES["detector"]
    scale = 1 + leftover_seconds / 60 / (train * float(minutes))
    return {**planned, **{k: round(planned[k] * scale, 3) for k in ("encoder_minutes", "reg_minutes", "detector_minutes")},
            "render_leftover_minutes": round(leftover_seconds / 60, 1)}


def leftover_seconds(planned: dict, stages: dict) -> float:
    """The seconds of their shares that the render stages did not use: only a split that stopped
    at its image count (``time_limited`` False) leaves any; one over its time takes none from
    the others, and one recorded before stop 52 (no ``time_limited``) none either."""
    return sum(max(0.0, planned[key] - stages[name]["seconds"])
               for name, key in (("render", "render_seconds"), ("render-det", "render_det_seconds"))
               if stages[name].get("time_limited") is False)


def versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version
    out = {"python": sys.version.split()[0]}
    for pkg in ("numpy", "onnxruntime", "torch", "trimesh", "pyrender", "opencv-python-headless", "autopose"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            pass
    return out


class _State:
    """``MODEL_DIR.work/build/state.json``: per stage the key it was made with and its result."""

    def __init__(self, path: Path):
        self.path = path
        self.d = json.loads(path.read_text()) if path.is_file() else {}

    def done(self, stage: str, key: str) -> dict | None:
        s = self.d.get(stage)
        return s if s and s.get("key") == key and s.get("done") else None

    def spent_before(self, stage: str, key: str) -> float:
        """The seconds earlier, interrupted runs spent on ``stage`` with the same ``key``."""
        s = self.d.get(stage)
        return float(s.get("seconds", 0.0)) if s and s.get("key") == key and not s.get("done") else 0.0

    def mark(self, stage: str, key: str, done: bool = True, **result) -> None:
        self.d[stage] = {"key": key, "done": done, **result}
        write_whole(self.path, lambda tmp: tmp.write_text(json.dumps(self.d, indent=1)))


def mesh_fingerprint(folder) -> list:
    """The mesh folder as the build's cache sees it: each file's name and SHA-256 of its bytes.
    Not its path or times, so a copy, a move or a fresh checkout of the same meshes keeps every
    stage made from them (keyed on modification times, a re-provisioned folder redid the build)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted((f.name, hashlib.sha256(f.read_bytes()).hexdigest()) for f in folder.iterdir() if f.is_file())


def _forget(work: Path, patterns, log) -> None:
    """Delete the work folder's files that a new split or recipe made stale (crops and detector
    images cut from the old split are gigabytes each; checkpoints of another recipe must not be
    resumed)."""
    gone = [f for pat in patterns for f in sorted(work.glob(pat))]
    size = sum(f.stat().st_size for f in gone)
    for f in gone:
        f.unlink()
    if gone:
        log(f"removed {len(gone)} stale file(s) from {work} ({size / 1e9:.2f} GB): {', '.join(f.name for f in gone)}")


def _key(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


def detector_changes(recipe: Recipe) -> dict:
    """The detector's recipe fields whose values differ from before stop 66 (:data:`DETECTOR_BEFORE`)."""
    now = {"detector_input": list(recipe.detector_input), "detector_int8": recipe.detector_int8}
    return {k: v for k, v in now.items() if v != DETECTOR_BEFORE[k]}


def detector_key(recipe: Recipe, k_enc: str, k_render_det: str, minutes: float) -> str:
    """The detector stage's key: its input and int8 only where they differ from before stop 66
    (320 x 240, float32), so that a build begun before then resumes its detector stage."""
    changed = detector_changes(recipe)
    return _key("detector", k_enc, k_render_det, minutes, recipe.detector_backbone, recipe.seed,
                *([changed["detector_input"]] if "detector_input" in changed else []),
                *(["int8"] if changed.get("detector_int8") else []))


def build(recipe: Recipe, out_dir, log=print, cluster=None) -> dict:
    """Run (or resume) every stage; returns the report's summary. ``cluster``: a
    :class:`tracker.training.cluster.RayCluster` (entered) that renders and trains instead of
    this process (``build --ray``); the stages, their keys and the bundle are the same."""
    from tracker.core.paths import shared_data, work_dir
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder for the bundle")
    if recipe.prior not in ("table", "sphere"):
        raise UserError(f"--prior must be table or sphere, not '{recipe.prior}'")
    if not recipe.minutes > 0:
        raise UserError(f"--minutes must be positive, not {recipe.minutes}")
    if not (isinstance(recipe.head_sets, int) and recipe.head_sets >= 1):
        raise UserError(f"--head-sets must be a whole number of at least 1, not {recipe.head_sets}")
    if recipe.max_images is not None and not (isinstance(recipe.max_images, int) and recipe.max_images >= 1):
        raise UserError(f"--max-images must be a whole number of at least 1, not {recipe.max_images}")
    if problem := detector_input_problem(recipe.detector_input):
        raise UserError(f"--detector-input {problem}")
    from tracker.training.prepare import mesh_files
    mesh_files(recipe.models)  # a bad --models fails before anything is written
    from tracker.training.train import require_torch
    require_torch()  # and so does a missing 'train' extra, before minutes of rendering
    from tracker.training.nets.autoencoder import crop_size_problem
    if problem := crop_size_problem(recipe.encoder, recipe.size):  # and a crop the encoder cannot take
        raise UserError(problem)
    root = work_dir(out) / "build"
    root.mkdir(parents=True, exist_ok=True)
    state = _State(root / "state.json")
    t_start = time.perf_counter()
    summary = {"stages": {}}

    def stage(i: int, name: str, key: str, run):
        """Skip a stage made with the same key; else (re)do it and record what it gave."""
        done = state.done(name, key)
        if done:
            log(f"[{i}/{len(STAGES)}] {name}: done before (cached)")
            summary["stages"][name] = done
            return done
        spent = (time.perf_counter() - t_start) / 60
        # the stages before it took what they recorded (a split that stopped at its count left time)
        used = sum(state.d[s].get("seconds", 0.0) for s in STAGES[:i - 1] if s in state.d) / 60
        log(f"[{i}/{len(STAGES)}] {name}: {spent:.1f} min used this run, about "
            f"{max(0.0, recipe.minutes - used):.1f} min of the budget left")
        before = state.spent_before(name, key)
        t = time.perf_counter()
        try:
            result = run() or {}
        except BaseException:  # Ctrl-C, SIGTERM, an error: the time spent is kept for the rerun's record
            state.mark(name, key, done=False, seconds=round(before + time.perf_counter() - t, 1))
            raise
        # the stage's time over all its runs (an interrupted one's included)
        result["seconds"] = round(before + time.perf_counter() - t, 1)
        state.mark(name, key, **result)
        summary["stages"][name] = state.d[name]
        return state.d[name]

    # 1. meshes -> BOP models folder
    models_dir = root / "models"
    # (names only when given: the key of builds made before they could be)
    k_models = _key("models", mesh_fingerprint(recipe.models), recipe.units, recipe.objects,
                    *([recipe.names] if recipe.names else []))

    def do_models():
        from tracker.training.prepare import prepare_models
        shutil.rmtree(models_dir, ignore_errors=True)
        rep = prepare_models(recipe.models, models_dir, units=recipe.units, log=log, names=recipe.names)
        if recipe.objects:
            unknown = sorted(set(recipe.objects) - set(rep))
            if unknown:
                raise UserError(f"--objects {','.join(map(str, unknown))}: not among the meshes' ids {sorted(rep)}")
        return {"objects": {str(k): v["name"] for k, v in rep.items()}}
    got = stage(1, "models", k_models, do_models)
    obj_ids = recipe.objects or sorted(int(k) for k in got["objects"])

    # 2-3. the synthetic splits
    from tracker.training.synth.engine import SynthConfig, generate
    backgrounds = str(shared_data() / "backgrounds")
    p = plan(recipe)
    log(f"at most {p['max_images']:,} images per rendered split "
        f"({'--max-images' if recipe.max_images else 'what this machine can train on; --max-images N sets it'})")

    def render(split: Path, n: int, seed: int, seconds: float | None = None, trains: bool = True, key: str = "",
               **opts):
        """A render stage's work; ``trains`` False: the held-out check's split, one scene (on a
        cluster one task: its 40 images are seconds of work, and ``evaluate`` reads one scene)."""
        def run():
            if trains:  # what training cut from the split before is stale
                _forget(work_dir(out), ("crops_*.npz", "det_images_*.npz"), log)
            cfg = SynthConfig(models_dir=str(models_dir), backgrounds_dir=backgrounds, seed=seed, prior=recipe.prior,
                              obj_ids=list(obj_ids), mesh_faces=recipe.mesh_faces or None, **opts)
            if cluster is not None:  # shards as tasks; those finished by an interrupted run are kept
                return {**cluster.render(cfg, split, n, seconds, min(n, MIN_IMAGES), f"build stage {split.name}",
                                         key, tasks=None if trains else 1), "executor": "ray"}
            shutil.rmtree(split, ignore_errors=True)  # a split left half-made by an interruption
            shutil.rmtree(split.with_name(split.name + ".shards"), ignore_errors=True)
            rep = generate(cfg, split, n, workers=recipe.workers, command=f"build stage {split.name}",
                           seconds=seconds, min_images=min(n, MIN_IMAGES))
            if rep.interrupted:
                raise KeyboardInterrupt
            return {"images": rep.images, "images_per_s": round(rep.images_per_s, 2),
                    "time_limited": rep.time_limited, "executor": "local"}
        return run

    split_enc, split_det = root / "split_encoder", root / "split_detector"
    # the full meshes as before (0) keep the keys that stages of older builds were cached under
    faces = [recipe.mesh_faces] if recipe.mesh_faces else []
    k_render = _key("render", k_models, p["render_images"], p["render_seconds"], recipe.seed, recipe.prior, obj_ids,
                    "repeat", *faces)
    stage(2, "render", k_render, render(split_enc, p["render_images"], recipe.seed, p["render_seconds"],
                                        key=k_render, repeat_objects=True))
    det_opts = {"distractors": "hard", "lighting": "overhead", "repeat_objects": True}
    k_render_det = _key("render-det", k_models, p["render_det_images"], p["render_det_seconds"], recipe.seed,
                        recipe.prior, obj_ids, det_opts, *faces)
    stage(3, "render-det", k_render_det, render(split_det, p["render_det_images"], recipe.seed + 1,
                                                p["render_det_seconds"], key=k_render_det, **det_opts))
    # a split that stopped at its image count (not its time) leaves the rest of its share
    p = share_out(p, recipe.minutes, leftover_seconds(p, state.d))

    # both splits train both networks: linked into one (no copies) once both are made
    split_all = root / "split_all"

    def joined() -> Path:
        from tracker.training.synth.join import join_splits
        shutil.rmtree(split_all, ignore_errors=True)
        join_splits(split_all, [split_enc, split_det], command="build")
        return split_all

    # 4. encoder and heads
    k_enc = _key("encoder", k_render, k_render_det, recipe.method, recipe.encoder, recipe.size, recipe.latent,
                 p["encoder_minutes"], p["reg_minutes"], recipe.seed,
                 *([recipe.head_sets] if recipe.head_sets != 1 else []))

    def trained(name: str, kwargs: dict, minutes: float) -> dict:
        """``name``'s training function with ``kwargs``, here or on the cluster; how it ran."""
        if cluster is None:
            from tracker.training.cluster import TRAINING
            import importlib
            module, fn = TRAINING[name]
            getattr(importlib.import_module(module), fn)(**kwargs, log=log)
            return {"executor": "local"}
        return {"executor": "ray", "training_workers": cluster.train(name, kwargs, work_dir(out), minutes)}

    def do_encoder():
        from tracker.core.bundle import open_bundle
        prev = state.d.get("encoder", {}).get("key")
        if prev and prev != k_enc:  # another recipe: its checkpoints must not be resumed
            _forget(work_dir(out), ("ae_checkpoint.pt", "ae_best.pt"), log)
        minutes = p["encoder_minutes"] + 3 * recipe.head_sets * p["reg_minutes"]
        how = trained("encoder", dict(
            data_dir=joined(), out_dir=out, method=recipe.method, size=recipe.size, latent=recipe.latent,
            minutes=p["encoder_minutes"], seed=recipe.seed, reg_minutes=p["reg_minutes"], stage_minutes=minutes,
            head_sets=recipe.head_sets, models_info_path=models_dir / "models_info.json", encoder=recipe.encoder,
            device=recipe.device, command=f"app.py build --models {recipe.models} --out {out}"), minutes)
        v = _written(open_bundle, out, "encoder").manifest.validation_synthetic
        return {"re_median_deg": v["regression"]["re_median_deg"], "te_median_mm": v["regression"]["te_median_mm"],
                **how}
    stage(4, "encoder", k_enc, do_encoder)

    # 5. detector
    k_det = detector_key(recipe, k_enc, k_render_det, p["detector_minutes"])

    def do_detector():
        from tracker.core.bundle import open_bundle
        prev = state.d.get("detector", {}).get("key")
        if prev and prev != k_det:  # another recipe or split: its checkpoint must not be resumed
            _forget(work_dir(out), ("detector_ckpt_*.pt",), log)
        n = int(state.d["render"]["images"]) + int(state.d["render-det"]["images"])  # a tiny budget: < a batch
        how = trained("detector", dict(
            data_dir=joined(), bundle_dir=out, minutes=p["detector_minutes"], seed=recipe.seed, occlusion=0.5,
            stage_minutes=p["detector_minutes"], batch=min(32, max(2, n // 2)),
            lr=DETECTOR_LR.get(recipe.detector_backbone, 2e-3), backbone=recipe.detector_backbone,
            input_w=recipe.detector_input[0], input_h=recipe.detector_input[1],
            device=recipe.device, command=f"app.py build --models {recipe.models} --out {out}"),
            p["detector_minutes"])
        v = (_written(open_bundle, out, "detector").manifest.detector or {})["training"]["validation_synthetic"]
        if recipe.detector_int8:  # here, not on the cluster: seconds of work on the renders it trained on
            from tracker.training.detector_ensemble import join_detectors
            q = join_detectors(out, [], int8_data=split_all, weight_bits=DETECTOR_WEIGHT_BITS, log=log,
                               command=f"app.py build --models {recipe.models} --out {out}").detector["int8"]
            how["int8_heatmap_max_abs_diff"] = round(q["heatmap_max_abs_diff"], 4)
        return {"ap": v["ap"], "ap50": v["ap50"], **how}
    stage(5, "detector", k_det, do_detector)

    # 6. held-out check on fresh renders
    split_check = root / "split_check"
    k_check = _key("check", k_det, k_models, CHECK_IMAGES, recipe.seed, *faces)

    def do_check():
        from tracker.evaluation.evaluate import evaluate
        how = render(split_check, CHECK_IMAGES, recipe.seed + 1000, trains=False, key=k_check)()
        res = {k: how[k] for k in ("executor", "render_tasks") if k in how}
        for boxes in ("gt", "detector"):
            m = evaluate(out, split_check / "000000", root / f"check_{boxes}.json", boxes=boxes,
                         bop_csv=root / f"check_{boxes}.csv", progress=False)
            res[boxes] = {k: m[k] for k in ("add_recall", "ar_mssd", "ar_mspd", "re_median_deg", "te_median_mm")}
            res[boxes]["per_object"] = {o: {k: v.get(k) for k in ("n_gt", "add_recall", "ar_mssd", "ar_mspd")}
                                        for o, v in m["per_object"].items()}
            if boxes == "detector":
                res[boxes]["ap50"] = m["detection"]["ap50"]
            res[boxes]["ms_per_image"] = m["ms_per_image"]
        return res
    stage(6, "check", k_check, do_check)

    # 7. report, and the recipe into the manifest
    def do_report():
        _record_recipe(out, root, recipe, p, state.d)
        return {"report": str(out / "report" / "report.md")}
    # (mesh_faces 0, max_images and names None, the detector's input and int8 as before stop 66:
    # the keys of builds made before they were recorded)
    recorded = {k: v for k, v in asdict(recipe).items()
                if (k != "mesh_faces" or v) and (k not in ("max_images", "names") or v is not None)
                and k not in DETECTOR_BEFORE} | detector_changes(recipe)
    stage(7, "report", _key("report", k_check, recorded), do_report)
    summary["minutes"] = round((time.perf_counter() - t_start) / 60, 1)
    summary["minutes_all_runs"] = round(sum(state.d[s].get("seconds", 0.0) for s in STAGES) / 60, 1)
    summary["budget_minutes"] = recipe.minutes
    summary["report"] = state.d["report"]["report"]
    return summary


def _record_recipe(out: Path, root: Path, recipe: Recipe, planned: dict, stages: dict) -> None:
    """The report into the bundle (report/) and the recipe into its manifest, in one staged write."""
    from tracker.training.report import write_build_report
    from tracker.core.bundle import update_manifest

    def change(manifest, folder):
        write_build_report(folder, root, stages, recipe, planned, stages["models"]["objects"])
        manifest.extra["build"] = {"recipe": asdict(recipe), "plan": planned, "versions": versions(),
                                   "stage_seconds": {k: v.get("seconds") for k, v in stages.items()},
                                   **executor_record(stages), "artefacts_sha256": built_artefacts(manifest)}
    update_manifest(out, change)


def built_artefacts(manifest) -> dict:
    """SHA-256 of each artefact (encoder, pose head, codebook, detector) as the build wrote it:
    ``build --from-manifest`` names those replaced since (a detector joined in, heads refitted)."""
    return {role: manifest.file_sha256(role) for role in sorted(manifest.artefacts)
            if role != "models_info" and manifest.file_sha256(role)}


def changed_since_build(manifest) -> list[str]:
    """The artefacts whose files are not the ones the bundle's build wrote (empty for a bundle
    built before the build recorded them)."""
    built = manifest.extra.get("build", {}).get("artefacts_sha256") or {}
    now = built_artefacts(manifest) if built else {}
    return sorted(role for role in built.keys() | now.keys() if built.get(role) != now.get(role))


def executor_record(stages: dict) -> dict:
    """How the stages that render or train ran: ``executor`` local, ray (``build --ray``) or
    mixed (a build resumed the other way), the render tasks of the cluster's render stages and
    its most training workers."""
    ran = {k: v.get("executor", "local") for k, v in stages.items()
           if k in ("render", "render-det", "encoder", "detector", "check")}
    kinds = set(ran.values())
    return {"executor": kinds.pop() if len(kinds) == 1 else "mixed", "executor_by_stage": ran,
            "render_tasks": sum(int(v.get("render_tasks", 0)) for v in stages.values()),
            "training_workers": max([int(v.get("training_workers", 0)) for v in stages.values()] + [0])}


def _written(open_bundle, out: Path, stage: str):
    """The bundle the training stage wrote (verified); on a cluster whose first training worker
    ran on another machine without the work folder shared, it is not here: said in one line."""
    try:
        return open_bundle(out)
    except UserError as e:
        raise UserError(f"after the {stage} stage: {e} (with --ray on several machines, --out must be on a "
                        f"file system every machine shares)") from None


def recipe_from_manifest(bundle_dir, log=None) -> Recipe:
    """``build --from-manifest``: the recipe a built bundle records. Names set on the bundle
    after its build (``set_object_names``) join the recipe, so the rebuild keeps them; a part
    that came from another run (a detector with ``provenance``, or any artefact whose hash is not
    the one the build recorded) is said, since the recipe rebuilds its own."""
    from tracker.core.bundle import open_bundle
    b = open_bundle(bundle_dir)
    built = b.manifest.extra.get("build")
    rec = built.get("recipe") if isinstance(built, dict) else None
    if not isinstance(rec, dict):
        raise UserError(f"{bundle_dir}: its manifest records no build recipe (it was not made by 'app.py build')")
    rec = dict(rec)
    if b.manifest.extra.get("object_names"):  # renamed after its build: the names it has now
        rec["names"] = {str(o.id): o.name for o in b.manifest.objects}
    det = b.manifest.detector or {}
    changed = changed_since_build(b.manifest)
    from tracker.runtime.fusion import member_files
    fused = len(member_files(det))
    if log is not None and (det.get("provenance") or changed or fused):
        p = det.get("provenance") or {}
        why = f" ({p.get('note', p)})" if p else ""
        if fused:  # lab fuse-detectors: networks of other runs beside it
            why += f", fused with {fused} more network(s) of other runs (lab fuse-detectors)"
        parts = ", ".join(changed) if changed else "detector"
        log(f"build: note: {bundle_dir}'s {parts} came from another run than its build{why}; this recipe "
            f"makes its own, so those of the rebuilt bundle differ")
    problem = recipe_problem(rec)
    if problem:
        raise UserError(f"{bundle_dir}: its manifest's build recipe is malformed ({problem}); build from --models")
    return Recipe.from_dict(rec)


# the recorded recipe's fields and what each must hold (a manifest's JSON can be edited by hand)
_WHOLE = ("seed", "size", "latent", "workers", "mesh_faces", "head_sets")
_TEXT = ("models", "prior", "units", "method", "encoder", "detector_backbone", "device")


def detector_input_problem(wh) -> str | None:
    """What is wrong with a detector input [W, H] (None: nothing): two whole numbers, multiples
    of the detector's stride (8), 64 to 1280."""
    if not (isinstance(wh, (list, tuple)) and len(wh) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) for v in wh)):
        return f"must be two whole numbers W H, not {wh!r}"
    if not all(64 <= v <= 1280 and v % 8 == 0 for v in wh):
        return f"must be two multiples of 8 from 64 to 1280 (e.g. 416 320), not {wh[0]} x {wh[1]}"
    return None


def recipe_problem(rec: dict) -> str | None:
    """What is wrong with a recorded recipe (None: nothing), before :class:`Recipe` is made of it."""
    def whole(v) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)
    if not isinstance(rec.get("models"), str) or not rec["models"]:
        return "'models' must name the meshes' folder"
    m = rec.get("minutes", 60.0)
    if isinstance(m, bool) or not isinstance(m, (int, float)) or not 0 < m < float("inf"):
        return f"'minutes' must be a positive number, not {m!r}"
    for k in _WHOLE:
        if k in rec and not (whole(rec[k]) and rec[k] >= 0):
            return f"'{k}' must be a whole number >= 0, not {rec[k]!r}"
    for k in _TEXT:
        if k in rec and not isinstance(rec[k], str):
            return f"'{k}' must be text, not {rec[k]!r}"
    objs = rec.get("objects")
    if objs is not None and not (isinstance(objs, list) and all(whole(o) and o >= 1 for o in objs)):
        return f"'objects' must be a list of object ids, not {objs!r}"
    mx = rec.get("max_images")
    if mx is not None and not (whole(mx) and mx >= 1):
        return f"'max_images' must be a whole number >= 1, not {mx!r}"
    if "detector_input" in rec and (problem := detector_input_problem(rec["detector_input"])):
        return f"'detector_input' {problem}"
    if "detector_int8" in rec and not isinstance(rec["detector_int8"], bool):
        return f"'detector_int8' must be true or false, not {rec['detector_int8']!r}"
    return None
