"""Synthetic BOP splits: scenes of randomly posed objects, rendered, randomised, annotated.

Layout written under OUT (BOP, chunks of 1000 images per scene folder):

    OUT/synth_config.json                 how it was made (prior, seed, counts, command)
    OUT/NNNNNN/rgb/IIIIII.jpg             640x480 (by default) frames, JPEG at random quality
    OUT/NNNNNN/mask_visib/IIIIII_KKKKKK.png
    OUT/NNNNNN/clean/IIIIII_KKKKKK.png    reconstruction target: the object alone, neutral
                                          light, black background, whole object, CROPxCROP
    OUT/NNNNNN/scene_camera.json, scene_gt.json, scene_gt_info.json
    OUT/NNNNNN/clean_crops.json           {im_id: [[x0, y0, side], ...]} window of each clean crop

Every image is a pure function of (seed, global image index): the worker count changes speed,
never content. Workers (spawn) keep one renderer each for their whole life; they write image
files, the parent writes the JSON files (rewritten as it goes, so an interrupt loses at most
the images in flight).
"""
from __future__ import annotations

import multiprocessing as mp
import os
import resource
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from tracker.core.bop import write_json
from tracker.core.camera import LMO_K
from tracker.core.defaults import SYNTH_FACES
from tracker.core.errors import UserError
from tracker.core.visibility import scene_visibility
from tracker.core import priors
from tracker.training.synth.randomise import (Backgrounds, camera_effects, cast_shadows, composite, distractor_meshes, household_meshes,
                        jitter_colours, target_palette, texture_from_photos, tint_distractors,
                        list_backgrounds, list_occluders, occluder_meshes, sample_lights, sample_materials,
                        sample_overhead_lights, table_surface)

CHUNK = 1000
DEPTH_SCALE = 0.1  # mm per unit of the written depth PNGs (up to 6.5 m)
DISTRACTOR_BASE = 100000  # renderer ids of distractor meshes
HARD_DISTRACTORS_PER_IMAGE = (2, 8)
# per style: how many primitives and how many household shapes (mugs, cups, bottles)
DISTRACTOR_SETS = {"plain": (12, 0), "hard": (36, 0), "household": (18, 18)}
DISTRACTOR_STYLES = tuple(DISTRACTOR_SETS)
LIGHTING_STYLES = ("camera", "overhead")
PHOTO_DISTRACTORS = ("hard", "household")  # textured from the photos, tinted, 2-8 per image
SHADOW_POINTS = 400  # about this many of an object's vertices outline its shadow (randomise.cast_shadows)

DEFAULT_MESH_FACES = SYNTH_FACES  # SynthConfig.mesh_faces


@dataclass
class SynthConfig:
    models_dir: str
    backgrounds_dir: str
    seed: int = 0
    prior: str = "table"
    width: int = 640
    height: int = 480
    K: list = field(default_factory=lambda: LMO_K.tolist())
    objects_per_image: tuple = (3, 8)
    # with fewer objects than an image draws: every object once, then repeats of them up to
    # the drawn count (several instances of one object in an image, as BOP allows), so a split
    # of one or two objects yields as many crops per image as one of eight
    repeat_objects: bool = False
    distractors_per_image: tuple = (0, 5)
    p_occluder: float = 0.35
    # 'table' prior: how often the table's surface is drawn (a photo laid on the plane the
    # objects stand on, with their soft shadows) instead of a photo behind floating objects
    p_table: float = 0.7
    # share of (image, object) pairs rendered with a glossy, partly metallic material instead
    # of the matte default (real plastic and ceramic show highlights that vertex colours lack);
    # drawn from their own random stream, so 0 reproduces the images of before byte for byte
    p_gloss: float = 0.0
    # the per-channel gain range of each object's colour jitter in the image (randomise.jitter_colours,
    # with a saturation change); 0: the objects' own colours (the real ones have fixed colours), the
    # same scenes otherwise
    colour_jitter: float = 0.15
    # exposure, contrast, saturation, white balance, blur and sensor noise on every image
    # (randomise.camera_effects); False: none of them (JPEG quality drawn as before), the same scenes
    camera_effects: bool = True
    # "plain": 12 primitives with noisy random colours, 0-5 per image (data made before);
    # "hard": 36 primitives textured from the background photos, 2-8 per image, tinted per
    # image, half the time with a target's colour (real clutter: yellow cups, white boxes);
    # "household": as "hard", with 18 of the 36 shapes mugs, cups and bottles
    distractors: str = "plain"
    # a folder of household meshes (.ply/.obj, mm, vertex colours; scripts/debian_assets.py
    # furniture): the distractors and occluders are drawn from it instead of the style's shapes,
    # in their own colours (neither textured from the photos nor tinted), as many per image as
    # the style draws; None: the style's shapes
    occluders_dir: str | None = None
    # "camera": 1-3 lights from the camera's side, ambient 0.15-0.5 (data made before);
    # "overhead": a strong key light from above the table, a weak fill, little ambient, drawn
    # from their own random stream (same scenes as "camera" with the same seed, other light)
    lighting: str = "camera"
    crop_size: int = 128  # clean targets, rendered in the visibility window (visibility.WINDOW_PAD)
    jpeg_quality: tuple = (70, 95)
    obj_ids: list | None = None
    # render the objects with their meshes decimated to about this many faces (the CPU
    # rasteriser's cost grows with triangles); None or 0: the full meshes. LM-O's 8 at 4,000
    # (from 12-46 k): 113 against 193 ms per image, masks' IoU with the full meshes' 0.998, clean
    # targets 2.1 / 255 apart; 2,000-3,000 were no faster. A bundle trained on full-mesh renders
    # scores the same on both renders of one split (docs/experiments/stop-47.md)
    mesh_faces: int | None = DEFAULT_MESH_FACES
    depth: bool = False  # write depth/NNNNNN.png (uint16, DEPTH_SCALE mm per unit), as BOP scenes have


@dataclass
class SynthReport:
    images: int
    instances: int
    crops_visib_ge_0_1: int
    seconds: float
    images_per_s: float
    crops_per_s: float
    peak_rss_mb_parent: float
    peak_rss_mb_worker: float
    workers: int
    interrupted: bool = False
    time_limited: bool = False  # stopped by ``seconds`` before ``n_images``


# --------------------------------------------------------------------------- worker side

_W = {}  # per-process state: renderers, meshes, backgrounds


def _init_worker(cfg_dict: dict, models: dict | None = None):
    """A pool worker's start (:func:`_init_state`). Its bad input (a photo cut short, an occluder
    that is not a mesh) is raised from its first batch: one error for the parent to show, where
    an initializer's exception breaks the pool with a traceback from every worker."""
    try:
        _init_state(cfg_dict, models)
    except UserError as e:
        _W.clear()
        _W["error"] = e


def _init_state(cfg_dict: dict, models: dict | None = None):
    """A render worker's state: its meshes (``models``: the parent's, when it forked), the
    distractors, backgrounds and its two renderers."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    # llvmpipe rasterises in the worker's own thread: its default (a thread per core) and even
    # one thread of its own make two workers fight over 2 cores (measured at 640x480,
    # --mesh-faces 4000: 8.1 images/s with the default, 9.1 with one thread, 10.8 with none)
    os.environ.setdefault("LP_NUM_THREADS", "0")
    import warnings
    warnings.simplefilter("ignore")  # a colourless mesh warns once in the parent, not per worker
    cv2.setNumThreads(1)
    from tracker.core.meshes import cached_hull, load_models
    from tracker.runtime.render import Renderer
    cfg = SynthConfig(**cfg_dict)
    if models is None:
        models = load_models(cfg.models_dir, cfg.obj_ids)
    photo = cfg.distractors in PHOTO_DISTRACTORS
    n_primitives, n_household = DISTRACTOR_SETS[cfg.distractors]
    if cfg.occluders_dir:
        dis = occluder_meshes(list_occluders(cfg.occluders_dir), np.random.default_rng([cfg.seed, 11]))
        photo = False
    else:
        dis = distractor_meshes(np.random.default_rng([cfg.seed, 7]), n_primitives) + \
            household_meshes(np.random.default_rng([cfg.seed, 10]), n_household)
    bgs = Backgrounds(list_backgrounds(cfg.backgrounds_dir))
    if photo:
        texture_from_photos(dis, bgs.images, np.random.default_rng([cfg.seed, 8]))
    meshes = {k: m.mesh for k, m in models.items()}
    if cfg.mesh_faces:
        from tracker.training.decimate import decimate_mesh
        meshes = {k: decimate_mesh(m, cfg.mesh_faces, cache=True) for k, m in meshes.items()}
    targets = dict(meshes)
    meshes.update({DISTRACTOR_BASE + i: m for i, m in enumerate(dis)})
    verts = {**{k: np.asarray(m.vertices) for k, m in models.items()},
             **{DISTRACTOR_BASE + i: np.asarray(m.vertices) for i, m in enumerate(dis)}}
    # the hull's vertices give the same extremes as all of them (a resting height, a projected
    # box: a linear or linear-fractional function's extreme over a convex body is at a vertex)
    # at a fraction of the points (the full driller: 12,655; its hull: ~1,000)
    hulls = {k: cached_hull(v) for k, v in verts.items()}
    hull = {k: h for k, (h, _) in hulls.items()}
    _W.update(
        cfg=cfg,
        K=np.asarray(cfg.K, dtype=np.float64),
        obj_ids=sorted(models),
        verts=verts,
        hull=hull,
        shadow_verts={k: v[:: max(1, len(v) // SHADOW_POINTS)] for k, v in verts.items()},
        radius={k: d / 2 for k, (_, d) in hulls.items()},
        n_dis=len(dis),
        tint=photo,
        scene=Renderer(cfg.width, cfg.height, meshes),
        crop=Renderer(cfg.crop_size, cfg.crop_size, targets),
        bgs=bgs,
        palette=target_palette([models[k].mesh for k in sorted(models)], np.random.default_rng([cfg.seed, 9])),
    )


def _sample_instances(rng, cfg: SynthConfig):
    """Targets and distractors with their poses: [(renderer id, R, t)], the number of targets,
    the number standing on the table (the first ones) and the table's pose (None: no table)."""
    obj_ids, K = _W["obj_ids"], _W["K"]
    lo, hi = cfg.objects_per_image
    n_t = int(rng.integers(lo, hi + 1))
    if cfg.repeat_objects and len(obj_ids) < n_t:
        targets = [int(x) for x in rng.permutation(obj_ids)]
        targets += [int(x) for x in rng.choice(obj_ids, n_t - len(targets))]
    else:
        n_t = min(len(obj_ids), n_t)
        targets = [int(x) for x in rng.choice(obj_ids, n_t, replace=False)]
    lo_d, hi_d = HARD_DISTRACTORS_PER_IMAGE if cfg.distractors in PHOTO_DISTRACTORS else cfg.distractors_per_image
    n_d = int(rng.integers(lo_d, hi_d + 1))
    dis = [DISTRACTOR_BASE + int(x) for x in rng.integers(0, _W["n_dis"], n_d)]
    ids = targets + dis
    if cfg.prior == "table":
        poses, table = priors.sample_table_scene(rng, [_W["hull"][i] for i in ids], [_W["radius"][i] for i in ids])
    else:
        poses, table = priors.sample_sphere_scene(rng, [_W["radius"][i] for i in ids], K, (cfg.width, cfg.height)), None
    inst = [(i, R, t) for i, (R, t) in zip(ids, poses)]
    if rng.random() < cfg.p_occluder and targets:
        for _ in range(int(rng.integers(1, 3))):
            tgt = inst[int(rng.integers(n_t))]
            R, t = priors.table_occluder_pose(rng, tgt[2])
            inst.append((DISTRACTOR_BASE + int(rng.integers(_W["n_dis"])), R, t))
    return inst, n_t, len(ids), table


def _table_background(bg, rng, cfg: SynthConfig, inst, n_on_table, table, light_dir_c):
    """The table's surface over the photo where the camera sees it, with the shadows of the
    objects standing on it."""
    R_w2c, t_w2c = table
    top, mask = table_surface(_W["bgs"].sample(rng, cfg.width, cfg.height), _W["K"], R_w2c, t_w2c, rng)
    np.copyto(bg, top, where=mask[..., None])
    world = [((_W["shadow_verts"][i] @ R.T) + t - t_w2c) @ R_w2c for i, R, t in inst[:n_on_table]]
    return cast_shadows(bg, world, R_w2c.T @ np.asarray(light_dir_c, np.float64), _W["K"], R_w2c, t_w2c, rng)

def render_one(index: int, out_root: str) -> dict:
    """Render, annotate and write global image ``index``; returns its JSON records."""
    cfg: SynthConfig = _W["cfg"]
    K = _W["K"]
    rng = np.random.default_rng([cfg.seed, index])
    chunk, im_id = divmod(index, CHUNK)
    root = Path(out_root) / f"{chunk:06d}"
    inst, n_t, n_on_table, table = _sample_instances(rng, cfg)
    scene, crop_r = _W["scene"], _W["crop"]

    lights, ambient = sample_lights(rng)  # drawn either way: the scene's later draws stay the same
    if cfg.lighting == "overhead":
        # straight down in the scene: the table's -z, or the image's downward axis without a table
        down_c = table[0] @ np.array([0.0, 0.0, -1.0]) if table is not None else np.array([0.0, 1.0, 0.3])
        lights, ambient = sample_overhead_lights(np.random.default_rng([cfg.seed, index, 3]), down_c)
    if cfg.p_gloss > 0:
        sample_materials(scene, _W["obj_ids"], cfg.p_gloss, np.random.default_rng([cfg.seed, index, 1]))
    if _W["tint"]:
        tint_distractors(scene, [DISTRACTOR_BASE + i for i in range(_W["n_dis"])], _W["palette"],
                         np.random.default_rng([cfg.seed, index, 2]))
    scene.set_lights(lights)
    scene.set_ambient(ambient)
    rgb, depth = scene.render(K, inst)
    rgb = rgb.copy()

    gts, infos, windows = [], [], []
    crop_r.set_lights([((0.0, 0.0, 1.0), (1.0, 1.0, 1.0), 2.5)])  # neutral light for the targets
    crop_r.set_ambient(0.45)
    labels = scene.render_labels(K, inst)
    for k, vis in enumerate(scene_visibility(scene, crop_r, K, inst, _W["hull"], n_t, labels, keep_rgb=True)):
        oid, R, t = inst[k]
        jitter_colours(rgb, vis.mask_visib, vis.bbox_visib, rng, cfg.colour_jitter)
        win = vis.window
        cv2.imwrite(str(root / "clean" / f"{im_id:06d}_{k:06d}.png"),
                    cv2.cvtColor(vis.alone_rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "mask_visib" / f"{im_id:06d}_{k:06d}.png"), vis.mask_visib.astype(np.uint8) * 255)
        gts.append({"cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": t.ravel().tolist(), "obj_id": oid})
        infos.append({"bbox_obj": vis.bbox_obj, "bbox_visib": vis.bbox_visib, "px_count_all": vis.px_count_all,
                      "px_count_valid": vis.px_count_valid, "px_count_visib": vis.px_count_visib,
                      "visib_fract": round(vis.visib_fract, 6)})
        windows.append([win.x0, win.y0, win.side])

    bg = _W["bgs"].sample(rng, cfg.width, cfg.height)
    if table is not None and cfg.p_table > 0 and rng.random() < cfg.p_table:  # 0: the draws of before
        bg = _table_background(bg, rng, cfg, inst, n_on_table, table, lights[0][0])
    img = composite(bg, rgb, depth > 0)
    shot = camera_effects(img, rng)  # drawn either way: the same scenes with and without
    img = shot if cfg.camera_effects else img
    q = int(rng.integers(cfg.jpeg_quality[0], cfg.jpeg_quality[1] + 1))
    cv2.imwrite(str(root / "rgb" / f"{im_id:06d}.jpg"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_JPEG_QUALITY, q])
    if cfg.depth:
        d = np.clip(np.round(depth / DEPTH_SCALE), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(root / "depth" / f"{im_id:06d}.png"), d)
    return {"index": index, "chunk": chunk, "im_id": im_id, "gt": gts, "info": infos, "windows": windows,
            "cam": {"cam_K": K.ravel().tolist(), "depth_scale": DEPTH_SCALE if cfg.depth else 1.0}}


# tests make a worker die at one image, as a Mesa segfault would: "INDEX:MARKER_PATH" once
# (the marker file remembers it), "INDEX:" every time
CRASH_HOOK = "AUTOPOSE_TEST_SYNTH_CRASH"


def _render_batch(args):
    indices, out_root = args
    if "error" in _W:  # the worker could not start (_init_worker)
        raise _W["error"]
    hook = os.environ.get(CRASH_HOOK)
    if hook:
        at, marker = hook.split(":", 1)
        if int(at) in indices and not (marker and os.path.exists(marker)):
            if marker:
                Path(marker).write_text("crashed")
            os._exit(139)
    return [render_one(i, out_root) for i in indices]


# --------------------------------------------------------------------------- parent side


class _ChunkWriter:
    """Collects records and (re)writes each chunk's JSON files."""

    def __init__(self, out: Path):
        self.out = out
        self.chunks: dict[int, dict] = {}

    def add(self, rec: dict):
        c = self.chunks.setdefault(rec["chunk"], {"cam": {}, "gt": {}, "info": {}, "win": {}})
        k = str(rec["im_id"])
        c["cam"][k], c["gt"][k], c["info"][k], c["win"][k] = rec["cam"], rec["gt"], rec["info"], rec["windows"]

    def flush(self):
        for chunk, c in self.chunks.items():
            root = self.out / f"{chunk:06d}"
            order = sorted(c["cam"], key=int)
            for name, key in (("scene_camera", "cam"), ("scene_gt", "gt"), ("scene_gt_info", "info"),
                              ("clean_crops", "win")):
                write_json(root / f"{name}.json", {k: c[key][k] for k in order})

    def prune(self, n_chunks: int):
        """After an interruption: delete the files of images whose records never arrived (a
        worker stopped between writing them and returning), and chunk folders left empty,
        so that what remains is a loadable split."""
        for chunk in range(n_chunks):
            root = self.out / f"{chunk:06d}"
            kept = set(self.chunks.get(chunk, {"cam": {}})["cam"])
            if not kept:
                shutil.rmtree(root, ignore_errors=True)
                continue
            for sub in ("rgb", "mask_visib", "clean", "depth"):
                for f in (root / sub).glob("*") if (root / sub).is_dir() else ():
                    if str(int(f.name.split("_")[0].split(".")[0])) not in kept:
                        f.unlink()


RETRIES = 3  # pools in a row that may die without finishing a batch before the split is given up
STALL_S = 600.0  # no batch finished for this long: the workers are taken as hung


def start_method() -> str:
    """How ``synth`` starts its workers: 'fork' where that is safe, 'spawn' otherwise.

    A forked worker starts with the parent's modules and meshes; a spawned one starts an
    interpreter, imports and loads them again (~0.6 s more each here). Forking is unsafe after this process made
    a GL context (Mesa's state is not fork-safe: the child hangs), once another thread runs
    (its locks are copied mid-use; tqdm's monitor, a pool's manager) or torch is loaded (its
    OpenMP pool): then spawn."""
    import threading
    render = sys.modules.get("tracker.runtime.render")
    if ("fork" not in mp.get_all_start_methods() or threading.active_count() > 1 or "torch" in sys.modules
            or (render is not None and render.contexts_made() > 0)):
        return "spawn"
    return "fork"


def _start_pool(cfg: SynthConfig, pending: dict, workers: int, models: dict | None):
    """A pool with every pending batch submitted (its workers are started here)."""
    import concurrent.futures as cf
    method = start_method()
    pool = cf.ProcessPoolExecutor(workers, mp_context=mp.get_context(method), initializer=_init_worker,
                                  initargs=(asdict(cfg), models if method == "fork" else None))
    return pool, {pool.submit(_render_batch, pending[k]): k for k in pending}


def _pooled(cfg: SynthConfig, pending: dict, workers: int, bar, started=None, models: dict | None = None):
    """The batches' records as they finish, rendered by ``workers`` processes
    (``concurrent.futures``, which notices a worker that dies; ``started``: the first pool,
    from :func:`_start_pool`). A batch whose worker died (a Mesa segfault, say) or hung is
    rendered again by a fresh pool: images are drawn from their own seeds, so the new render
    is the same image, and it overwrites any files the lost one left. :data:`RETRIES` pools in
    a row that die without finishing a batch end the job with an error (a batch that kills
    every renderer)."""
    import concurrent.futures as cf
    fruitless = 0
    while pending:
        pool, futures = started or _start_pool(cfg, pending, workers, models)
        started = None
        broken, finished_any = False, False
        try:
            while futures and not broken:
                finished, _ = cf.wait(futures, timeout=STALL_S, return_when=cf.FIRST_COMPLETED)
                if not finished:  # hung: nothing came back for STALL_S seconds
                    broken = True
                    break
                for f in finished:
                    k = futures.pop(f)
                    try:
                        recs = f.result()
                    except cf.process.BrokenProcessPool:
                        broken = True
                        continue
                    del pending[k]
                    finished_any = True
                    yield recs
        except BaseException:
            _stop(pool)
            raise
        if broken:
            _stop(pool)
            fruitless = 0 if finished_any else fruitless + 1
            if fruitless >= RETRIES:
                left = sorted(i for k in pending for i in pending[k][0])
                raise UserError(f"synth: the renderer died {RETRIES} times in a row without finishing an image "
                                f"(images {left[0]}-{left[-1]} left); run again into a new folder, or with --workers 1")
            bar.write(f"synth: a render worker died; rendering {sum(len(pending[k][0]) for k in pending)} "
                      "images again in a fresh pool")
        else:
            pool.shutdown(wait=True)


def _stop(pool) -> None:
    """Shut a pool down now: queued batches cancelled, its workers killed (a hung one too)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())  # (no public way to kill a hung worker)
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.kill()
    for p in procs:
        p.join(timeout=5)


def _peak_rss_mb(who) -> float:
    return resource.getrusage(who).ru_maxrss / 1024.0


def shard_range(n_images: int, shard: tuple[int, int] | None) -> range:
    """The images of shard ``(k, n)`` of an ``n_images`` split: the k-th of n contiguous,
    disjoint blocks that together are the whole split (None: all of it). Every image is drawn
    from its own index's seeds, so the shards joined (``app.py lab join-splits``) hold the
    same images as the split rendered at once."""
    if shard is None:
        return range(n_images)
    k, n = shard
    if not (n >= 1 and 0 <= k < n):
        raise UserError(f"--shard {k}/{n}: give K/N with 0 <= K < N, e.g. 0/4 ... 3/4")
    if n > n_images:
        raise UserError(f"--shard {k}/{n}: more shards than the {n_images} images")
    return range(k * n_images // n, (k + 1) * n_images // n)


def generate(cfg: SynthConfig, out_dir, n_images: int, workers: int = 2, batch: int | None = None,
             progress: bool = True, command: str | None = None, shard: tuple[int, int] | None = None,
             seconds: float | None = None, min_images: int = 0) -> SynthReport:
    """Render images 0 .. ``n_images`` - 1 of the split ``cfg`` describes into ``out_dir``, or
    only those of ``shard`` (:func:`shard_range`).

    ``seconds``: a time limit (``build``'s budget): once it has passed and at least
    ``min_images`` are done, rendering stops; the split holds the images finished by then
    (each still the same image its index always gives; the batches in flight are dropped),
    and ``synth_config.json`` says ``time_limited``."""
    if n_images <= 0:
        raise UserError(f"--images must be positive, got {n_images}")
    mine = shard_range(n_images, shard)
    if cfg.prior not in priors.PRIORS:
        raise UserError(f"unknown prior '{cfg.prior}' (choose from {', '.join(priors.PRIORS)})")
    if not 0.0 <= cfg.p_table <= 1.0:
        raise UserError(f"--p-table must be between 0 and 1, got {cfg.p_table}")
    if not 0.0 <= cfg.p_gloss <= 1.0:
        raise UserError(f"--gloss must be between 0 and 1, got {cfg.p_gloss}")
    if not 0.0 <= cfg.colour_jitter < 1.0:
        raise UserError(f"--colour-jitter must be at least 0 and below 1, got {cfg.colour_jitter}")
    if cfg.distractors not in DISTRACTOR_STYLES:
        raise UserError(f"unknown distractor style '{cfg.distractors}' (choose from {', '.join(DISTRACTOR_STYLES)})")
    if cfg.lighting not in LIGHTING_STYLES:
        raise UserError(f"unknown lighting '{cfg.lighting}' (choose from {', '.join(LIGHTING_STYLES)})")
    list_backgrounds(cfg.backgrounds_dir)  # fail early, in the parent (photos are decoded in the
    # workers: OpenCV's threads started here would hang forked workers)
    if cfg.occluders_dir:  # the ones the workers will draw, read and checked
        occluder_meshes(list_occluders(cfg.occluders_dir), np.random.default_rng([cfg.seed, 11]))
        cfg.occluders_dir = str(Path(cfg.occluders_dir).resolve())
    from tracker.core.meshes import load_models
    models = load_models(cfg.models_dir, cfg.obj_ids)  # fail early (and warn once) on bad meshes
    if cfg.mesh_faces:  # here, once (a missing library is one error, not a broken pool); workers read the cache
        from tracker.training.decimate import decimate_mesh
        for m in models.values():
            decimate_mesh(m.mesh, cfg.mesh_faces, cache=True)
    if cfg.obj_ids is None:
        cfg.obj_ids = sorted(models)
    # absolute, so that the split's synth_config.json still finds them from another working
    # folder (train reads the meshes from it; a build resumed elsewhere)
    cfg.models_dir, cfg.backgrounds_dir = str(Path(cfg.models_dir).resolve()), str(Path(cfg.backgrounds_dir).resolve())
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"--out {out} is not an empty folder: give a new one (old images would be mixed in)")
    chunks = list(range(mine[0] // CHUNK, mine[-1] // CHUNK + 1))
    for chunk in chunks:
        for sub in ("rgb", "mask_visib", "clean") + (("depth",) if cfg.depth else ()):
            (out / f"{chunk:06d}" / sub).mkdir(parents=True, exist_ok=True)
    meta = {"config": asdict(cfg), "images": len(mine), "chunk": CHUNK,
            **({"shard": list(shard), "split_images": n_images, "first_image": mine[0]} if shard else {}),
            "command": command or " ".join(sys.argv), "created": time.strftime("%Y-%m-%d %H:%M:%S")}
    write_json(out / "synth_config.json", meta)

    if batch is None:  # up to 4 images a task, and at least 8 tasks per worker (no long wait for the last)
        batch = max(1, min(4, len(mine) // (8 * max(1, workers))))
    tasks = [(list(mine[i:i + batch]), str(out)) for i in range(0, len(mine), batch)]
    writer = _ChunkWriter(out)
    done = n_inst = n_crops = 0
    interrupted = time_limited = False
    t0 = time.perf_counter()
    pending = dict(enumerate(tasks))
    # the workers start before the progress bar (its monitor thread would rule out forking)
    started = _start_pool(cfg, pending, workers, models) if workers > 1 else None
    from tqdm import tqdm
    bar = tqdm(total=len(mine), unit="img", desc="synth" + (f" {shard[0]}/{shard[1]}" if shard else ""),
               disable=not progress)
    if workers <= 1:
        _init_state(asdict(cfg), models)
    results = map(_render_batch, tasks) if workers <= 1 else _pooled(cfg, pending, workers, bar, started, models)
    try:
        last_flush = time.perf_counter()
        for recs in results:
            for rec in recs:
                writer.add(rec)
                n_inst += len(rec["info"])
                n_crops += sum(i["visib_fract"] >= 0.1 for i in rec["info"])
            done += len(recs)
            bar.update(len(recs))
            if seconds is not None and done >= min_images and done < len(mine) and time.perf_counter() - t0 > seconds:
                time_limited = True
                break
            if time.perf_counter() - last_flush > 10:
                writer.flush()
                last_flush = time.perf_counter()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if hasattr(results, "close"):
            results.close()  # the pool's workers stopped (killed, on an interrupt) before the files are settled
        if started is not None:
            _stop(started[0])  # (an interrupt before the first batch came back left it running)
        bar.close()
        writer.flush()
        if workers <= 1:
            for k in ("scene", "crop"):
                if k in _W:
                    _W.pop(k).close()
        if done < len(mine):  # interrupted, out of time, or a failure: a consistent split of what was done
            writer.prune(chunks[-1] + 1)
            if not (interrupted or time_limited):
                meta.update(images_written=done, failed=True)
                write_json(out / "synth_config.json", meta)
    dt = time.perf_counter() - t0
    meta.update(images_written=done, seconds=round(dt, 1), interrupted=interrupted,
                **({"time_limited": True, "time_limit_s": seconds} if time_limited else {}))
    write_json(out / "synth_config.json", meta)
    return SynthReport(done, n_inst, n_crops, dt, done / dt, n_crops / dt, _peak_rss_mb(resource.RUSAGE_SELF),
                       _peak_rss_mb(resource.RUSAGE_CHILDREN), workers, interrupted, time_limited)
