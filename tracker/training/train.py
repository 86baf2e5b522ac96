"""``app.py train``: crops -> autoencoder -> latent regressors (+ AAE codebook) -> bundle.

Training needs the ``train`` extra (torch, onnx); the bundle it writes does not.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from tracker.core.bop import load_models_info, symmetry_rotations
from tracker.core.errors import UserError
from tracker.core.manifest import Manifest, ObjectEntry
from tracker.core.geometry import (box_offset_of_centre, centre_from_box_offset, focal_mean, rotation_error_deg,
                       translation_from_centre)
from tracker.runtime.overlay import LMO_NAMES
from tracker.core.paths import work_dir
from tracker.training.fit_heads import KNNRegressor, NumpyMLP
from tracker.runtime.heads import (Codebook, HeadEnsemble, PoseHead, apparent_size, centre_inputs, distance_inputs,
                                   rotation_inputs, save_codebook, save_head)

KNN_K = (1, 2, 3, 5, 8, 12, 20)
KNN_BOX_WEIGHT = (1.0, 3.0, 10.0)
# the distance KNN keeps its training codes: 30 k x 138 float32 = 17 MB of the bundle (with several
# head sets, this many among them all: three KNNs of 30 k made a one-object bundle of 55 MB)
KNN_MAX_ROWS = 30_000
# Rotation MLP widths. On models/lmo's frozen encoder (heads on jittered + exact boxes, LM-O dev
# frames, GT boxes): (512, 512, 512) for 5 min reached ADD(I) 0.127 / MSPD 0.476 / RE 37.2 deg,
# (256, 256) for 3 min 0.117 / 0.445 / 39.3 deg; one layer of 128, more weight decay, input
# noise or L2-normalised codes were all worse (docs/experiments/).
ROTATION_HIDDEN = (512, 512, 512)


OVERLAY_FACES = 1500


def require_torch():
    """torch, or a one-line error naming the extra that brings it."""
    try:
        import torch
    except ImportError:
        raise UserError("training needs the 'train' extra: .venv/bin/pip install -e '.[train]'") from None
    return torch


def _object_index(obj_ids, ids) -> np.ndarray:
    """Each of ``ids``' position in ``obj_ids`` (the one-hot's order)."""
    lut = {o: i for i, o in enumerate(obj_ids)}
    return np.array([lut[int(o)] for o in ids])


def _sym_rotations(obj_idx, obj_ids, models_info) -> np.ndarray:
    """(N, S, 3, 3): each sample's symmetry rotations, identity first, padded with identity."""
    per = [symmetry_rotations(models_info[o]) for o in obj_ids]
    S = max(len(p) for p in per)
    per = [np.concatenate([p, np.repeat(np.eye(3)[None], S - len(p), 0)]) for p in per]
    return np.stack(per)[obj_idx].astype(np.float32)


def _median_te(tz, centre, t, K) -> float:
    """Median whole-translation error (mm) of distances ``tz`` through the centres ``centre``."""
    est = translation_from_centre(centre, tz, K)
    return float(np.median(np.linalg.norm(est - t, axis=1)))


def choose_knn(Xtr, ytr, Xva, size_va, centre_va_t, t_va, K_va, log=print):
    """k and box weight by the whole-translation error on validation (thesis 4.2.2): one
    neighbour search per box weight gives every k."""
    best = None
    ks = [k for k in KNN_K if k <= len(Xtr)] or [1]
    for w in KNN_BOX_WEIGHT:
        preds = KNNRegressor(k=max(ks), box_weight=w).fit(Xtr, ytr).predict_ks(Xva, ks)
        for k in ks:
            err = _median_te(np.exp(preds[k]) / size_va, centre_va_t, t_va, K_va)
            if best is None or err < best[0]:
                best = (err, k, w)
    log(f"distance KNN: k={best[1]}, box weight {best[2]}: median translation error {best[0]:.1f} mm (validation)")
    return KNNRegressor(k=best[1], box_weight=best[2]).fit(Xtr, ytr), {"k": best[1], "box_weight": best[2],
                                                                        "val_te_median_mm": best[0]}


# a frozen front (encoder 'nanodet'): augmented versions of each crop whose outputs are cached, and
# the size of the reconstruction (a 128-pixel input reconstructed at 64: the decoder's cost a quarter)
FROZEN_AUGMENTATIONS = 3
FROZEN_RECON_SIZE = 64
MLP_EPOCHS = 300  # the regressors' epochs when a time budget (reg_minutes) ends them


def mlp_budget(reg_minutes: float, reg_epochs: int | None, share: float = 1.0) -> dict:
    """``epochs`` and ``minutes`` of one regressor MLP: ``reg_epochs`` epochs, whatever the time
    (the same fit on any machine, given the seed), or up to ``MLP_EPOCHS`` within ``share`` of
    ``reg_minutes`` (where a slower machine stops earlier and fits other weights)."""
    if reg_epochs is not None:
        return {"epochs": int(reg_epochs), "minutes": float("inf")}
    return {"epochs": MLP_EPOCHS, "minutes": reg_minutes * share}


def choose_distance(Xtr, ytr, Xva, yva, size_va, centre_va_t, t_va, K_va, reg_minutes: float, seed: int = 0,
                    log=print, reg_epochs: int | None = None, max_rows: int | None = None):
    """The distance head: the KNN of :func:`choose_knn` or an MLP, whichever has the lower
    whole-translation error on validation (the thesis prefers an MLP or RF once many objects
    share one model). The KNN keeps at most ``max_rows`` (default ``KNN_MAX_ROWS``) training codes, drawn at random,
    so that the bundle stays small. Returns ``(model, {"head", "val_te_median_mm", "knn"})``."""
    max_rows = KNN_MAX_ROWS if max_rows is None else max_rows
    keep = np.arange(len(Xtr))
    if len(keep) > max_rows:
        keep = np.sort(np.random.default_rng(seed).choice(len(Xtr), max_rows, replace=False))
    knn, knn_info = choose_knn(Xtr[keep], ytr[keep], Xva, size_va, centre_va_t, t_va, K_va, log=log)
    knn_info["rows"] = len(keep)
    log("distance MLP ...")
    mlp = NumpyMLP(hidden=(256, 256), loss="l1", weight_decay=1e-2, **mlp_budget(reg_minutes, reg_epochs, 0.5),
                   seed=seed).fit(Xtr, ytr[:, None], None, Xva, yva[:, None], log=log)
    err = _median_te(np.exp(mlp.predict(Xva)[:, 0]) / size_va, centre_va_t, t_va, K_va)
    log(f"distance MLP: median translation error {err:.1f} mm (validation)")
    if err < knn_info["val_te_median_mm"]:
        return mlp, {"head": "mlp", "val_te_median_mm": err, "knn": knn_info}
    return knn, {"head": "knn", "val_te_median_mm": knn_info["val_te_median_mm"], "knn": knn_info}


def choose_distance_by_rotation(R_tr, idx_tr, n_obj, box_tr, K_tr, y_tr, R_va_est, idx_va, box_va, K_va,
                                latent_va, size_va, centre_va, t_va, seed: int = 0, log=print):
    """Gradient-boosted trees from the true ray-frame rotation and the box to log(Tz * size)
    (:func:`tracker.runtime.heads.distance_by_rotation_inputs`), always kept: averaged with the
    latent distance head they help on real frames even where the renders' validation cannot
    tell (one encoder, three head seeds: dev mean +0.015 to +0.069, ADD(I) +0.00 to +0.12; the
    synthetic validation had dropped them by 0.03 mm, docs/experiments/stop-47.md). The
    validation's whole-translation errors, the latent head alone and averaged (``latent_va``,
    both fed estimated values ``R_va_est``), are recorded. Returns ``(trees, info)``. (An MLP
    on the same inputs, tried on models/lmo, raised that error from 33.1 to 36.1 mm where the
    trees lowered it to 31.3.)"""
    from tracker.training.fit_heads import BoostedTrees
    from tracker.runtime.heads import distance_by_rotation_inputs
    log("distance from rotation (gradient-boosted trees) ...")
    t0 = time.perf_counter()
    trees = BoostedTrees(seed=seed).fit(distance_by_rotation_inputs(R_tr, idx_tr, n_obj, box_tr, K_tr), y_tr)
    by_r = trees.predict(distance_by_rotation_inputs(R_va_est, idx_va, n_obj, box_va, K_va))
    err_latent = _median_te(np.exp(latent_va) / size_va, centre_va, t_va, K_va)
    err_both = _median_te(np.exp(0.5 * (latent_va + by_r)) / size_va, centre_va, t_va, K_va)
    log(f"distance from rotation: median translation error {err_latent:.1f} mm (latent head alone) -> "
        f"{err_both:.1f} mm (averaged) on the renders ({time.perf_counter() - t0:.0f} s)")
    return trees, {"used": True, "val_te_median_mm_latent": err_latent, "val_te_median_mm_averaged": err_both}


def with_exact_boxes(cs, mu, cs_exact, mu_exact, tr, va):
    """The heads' training set: every crop twice, on its jittered box (what a detector gives)
    and on the exact visible box (what ground truth gives), one split for both so that no
    instance is on both sides. Measured on models/lmo's synthetic validation: a distance MLP
    learnt from both is better on either kind of box than one learnt from either alone
    (median |dTz| 43.6 / 32.3 mm on jittered / exact boxes, against 46.8 / 41.5 from jittered
    boxes only, 59.9 / 31.5 from exact boxes only). Returns ``(cs, mu, tr, va)``; crops from
    ``len(cs)`` on are the exact-box ones."""
    from tracker.training.crops import CropSet
    if len(cs_exact) != len(cs) or not np.array_equal(cs_exact.obj_id, cs.obj_id):
        raise UserError("the exact-box crops do not match the jittered ones (different split or seed?)")
    n = len(cs)
    return (CropSet.concat(cs.labels(), cs_exact.labels()), np.concatenate([mu, mu_exact]),
            np.concatenate([tr, tr + n]), np.concatenate([va, va + n]))


def fit_heads(mu, cs, obj_ids, models_info, tr, va, rng, reg_minutes: float = 5.0, codebook_per_object: int = 1500,
              seed: int = 0, n_jittered: int | None = None, keep: PoseHead | None = None, log=print,
              reg_epochs: int | None = None, validate: bool = True, knn_max_rows: int | None = None):
    """The regressors and the AAE codebook on frozen latent codes ``mu`` of the crops ``cs``.

    Rotations are learnt relative to the viewing ray through the object's centre (the crop
    shows that rotation; ``PoseHead`` turns it back through the estimated centre).
    ``n_jittered``: crops from this index on are on exact boxes (:func:`with_exact_boxes`);
    the validation figures are then also given for each kind of box. ``keep``: a ray-frame
    head whose rotation, centre and latent distance regressors are kept as they are (only the
    distance-from-rotation trees and the codebook are fitted). Returns ``(head, codebook,
    distance-head info, synthetic validation figures)`` (figures None without ``validate``)."""
    idx = _object_index(obj_ids, cs.obj_id)
    n_obj = len(obj_ids)
    symR = _sym_rotations(idx, obj_ids, models_info)
    K = cs.K
    centres = cs.centres()
    R_ray = cs.R_ray(centres)  # the rotation the crop shows
    offsets = box_offset_of_centre(cs.box, centres)
    size_feat = apparent_size(cs.box, K)
    log_tz_size = np.log(cs.t[:, 2] * size_feat)

    if keep is not None:
        if keep.rotation_frame != "ray" or keep.obj_ids != [int(o) for o in obj_ids]:
            raise UserError("the kept regressors must be ray-frame ones for the same objects")
        rot, cen, dist = keep.rotation, keep.centre, keep.distance
        dist_info = None
        log("rotation, centre and latent distance regressors kept")
    else:
        log("rotation MLP (6D, L1 on R, symmetry-aware, relative to the viewing ray) ...")
        rot = NumpyMLP(hidden=ROTATION_HIDDEN, loss="l1_rotation", weight_decay=1e-2, **mlp_budget(reg_minutes, reg_epochs),
                       seed=seed).fit(rotation_inputs(mu[tr], idx[tr], n_obj), R_ray[tr], symR[tr],
                                      rotation_inputs(mu[va], idx[va], n_obj), R_ray[va], symR[va], log=log)
        log(f"rotation MLP: best validation epoch {rot.best_epoch_}")
        log("centre MLP ...")
        cen = NumpyMLP(hidden=(256,), loss="l1", weight_decay=1e-2, **mlp_budget(reg_minutes, reg_epochs, 0.5),
                       seed=seed).fit(centre_inputs(mu[tr], idx[tr], n_obj, cs.box[tr], K[tr]), offsets[tr], None,
                                      centre_inputs(mu[va], idx[va], n_obj, cs.box[va], K[va]), offsets[va], log=log)
    cen_va = centre_from_box_offset(cs.box[va], cen.predict(centre_inputs(mu[va], idx[va], n_obj, cs.box[va], K[va])))
    if keep is None:
        dist, dist_info = choose_distance(distance_inputs(mu[tr], idx[tr], n_obj, cs.box[tr], K[tr]), log_tz_size[tr],
                                          distance_inputs(mu[va], idx[va], n_obj, cs.box[va], K[va]), log_tz_size[va],
                                          size_feat[va], cen_va, cs.t[va], K[va], reg_minutes, seed=seed, log=log,
                                          reg_epochs=reg_epochs, max_rows=knn_max_rows)
    by_rot, by_rot_info = choose_distance_by_rotation(
        R_ray[tr], idx[tr], n_obj, cs.box[tr], K[tr], log_tz_size[tr],
        rot.predict(rotation_inputs(mu[va], idx[va], n_obj)), idx[va], cs.box[va], K[va],
        np.ravel(dist.predict(distance_inputs(mu[va], idx[va], n_obj, cs.box[va], K[va]))),
        size_feat[va], cen_va, cs.t[va], seed=seed, log=log)
    dist_info = {**(dist_info or {}), "by_rotation": by_rot_info}
    # AAE baseline: codebook of training views (subsampled per object to keep the bundle small)
    cb_idx = np.concatenate([rng.permutation(tr[idx[tr] == i])[:codebook_per_object] for i in range(n_obj)])
    codebook = Codebook().fit(mu[cb_idx], cs.obj_id[cb_idx], R_ray[cb_idx], cs.t[cb_idx, 2] * size_feat[cb_idx])
    head = PoseHead(obj_ids, rot, cen, dist, rotation_frame="ray", distance_by_rotation=by_rot)

    val = validate_head(PoseHead(obj_ids, rot, cen, dist, codebook, rotation_frame="ray", distance_by_rotation=by_rot),
                        mu, cs, va, symR, n_jittered, log) if validate else None
    return head, codebook, dist_info, val


def validate_head(h: PoseHead, mu, cs, va, symR, n_jittered: int | None, log=print) -> dict:
    """Median RE / TE of ``h`` (its regressors, and its codebook: 'aae') on the validation crops
    ``va``, also per kind of box when crops from ``n_jittered`` on are on exact boxes."""
    def figures(re, te):
        return {"re_median_deg": float(np.median(re)), "te_median_mm": float(np.median(te)),
                "re_lt_15deg": float(np.mean(re < 15))}

    val = {}
    for mode in ("regression", "aae"):
        R_va, t_va = h.predict(mu[va], cs.obj_id[va], cs.box[va], cs.K[va], mode=mode)
        re = np.array([min(rotation_error_deg(R_va[i], cs.R[va][i] @ S) for S in symR[va][i]) for i in range(len(va))])
        te = np.linalg.norm(t_va - cs.t[va], axis=1)
        val[mode] = figures(re, te)
        parts = {"all": np.ones(len(va), bool)}
        if n_jittered is not None:
            parts = {"jittered boxes": va < n_jittered, "exact boxes": va >= n_jittered}
            val[mode].update({k.replace(" ", "_"): figures(re[m], te[m]) for k, m in parts.items()})
        for k, m in parts.items():
            log(f"validation ({mode}, {k}): median RE {np.median(re[m]):.1f} deg, median TE {np.median(te[m]):.1f} mm")
    return val


def fit_head_sets(mu, cs, obj_ids, models_info, tr, va, rng, n_sets: int = 1, seed: int = 0,
                  n_jittered: int | None = None, log=print, cache_dir=None, **fit_options):
    """:func:`fit_heads` ``n_sets`` times, with seeds ``seed``, ``seed + 1``, ..., averaged in one
    :class:`HeadEnsemble` (one set: its :class:`PoseHead`). The codebook and the distance-head
    info are the first set's (``rng`` draws the codebook, as with one set); the validation
    figures are the average's. Their distance KNNs (where chosen) keep ``KNN_MAX_ROWS`` codes
    among them all, so that the bundle stays as small as with one set. Three sets on one encoder:
    dev mean +0.018 and +0.021 over the single sets' mean (stops 47 and 49); in ``build`` +0.051
    (stop 51). ``cache_dir``: each set fitted is kept there, and one fitted before on the same
    codes and options is loaded instead (:class:`~tracker.training.head_cache.HeadSetCache`)."""
    fit_options["knn_max_rows"] = KNN_MAX_ROWS // n_sets
    cache = None
    if cache_dir is not None:
        from tracker.training.head_cache import HeadSetCache
        cache = HeadSetCache(cache_dir, mu, cs, tr, va, obj_ids,
                             {**fit_options, "n_jittered": n_jittered, "validate": n_sets == 1})

    def one(i: int, set_rng, **extra):
        got = cache.load(seed + i) if cache else None
        if got is not None:
            log(f"head set {i + 1} of {n_sets} (seed {seed + i}): fitted before (cached)")
            return got
        if i:
            log(f"head set {i + 1} of {n_sets} (seed {seed + i})")
        got = fit_heads(mu, cs, obj_ids, models_info, tr, va, set_rng, seed=seed + i, log=log, **extra, **fit_options)
        if cache:
            cache.save(seed + i, *got)
        return got

    head, codebook, dist_info, val = one(0, rng, n_jittered=n_jittered, validate=n_sets == 1)
    if n_sets == 1:
        return head, codebook, dist_info, val
    heads = [head]
    for i in range(1, n_sets):
        heads.append(one(i, np.random.default_rng(seed + i), validate=False)[0])
    ensemble = HeadEnsemble(heads, {o: symmetry_rotations(models_info[o]) for o in obj_ids})
    ensemble.codebook = codebook
    symR = _sym_rotations(_object_index(obj_ids, cs.obj_id), obj_ids, models_info)
    log(f"validation of the {n_sets} head sets averaged:")
    return ensemble, codebook, dist_info, validate_head(ensemble, mu, cs, va, symR, n_jittered, log)


def export_encoder(model, size: int, n_cond: int, path: Path, x_check: np.ndarray, c_check=None) -> float:
    """ONNX with a dynamic batch; returns the max |onnx - torch| on ``x_check``."""
    torch = require_torch()
    enc = model.encoder.cpu().eval()
    x = torch.from_numpy(x_check[:2])
    args = (x,) if not n_cond else (x, torch.from_numpy(c_check[:2]))
    names = ["image"] + (["object"] if n_cond else [])
    dyn = {n: {0: "batch"} for n in names + ["mu"]}
    torch.onnx.export(enc, args, str(path), input_names=names, output_names=["mu"], dynamic_axes=dyn,
                      opset_version=17, dynamo=False)
    from tracker.runtime.estimator import make_session
    sess = make_session(path)
    feeds = {"image": x_check}
    if n_cond:
        feeds["object"] = c_check
    got = sess.run(None, feeds)[0]
    with torch.no_grad():
        ref = enc(torch.from_numpy(x_check), None if not n_cond else torch.from_numpy(c_check)).numpy()
    return float(np.abs(got - ref).max())


# this CPU, per crop of a split (a 60-minute two-object build, 45,616 crops at 64 px): cutting one
# crop set 1.5 ms; encoding them twice, the validations, codebook and export beyond the heads'
# own minutes 3.3 ms (build's encoder stage ran 4.6 min past its share before these were kept),
# 1.8 ms since stop 49 (the distance KNN's choice: one neighbour search per box weight, 21 -> 3;
# on 66 k crops 135 -> 21 s)
CUT_S_PER_CROP = 1.5e-3
AFTER_S_PER_CROP = 1.8e-3
MIN_TRAIN_MINUTES = 0.05


def training_minutes(stage_minutes: float, minutes: float, spent_minutes: float, n_crops: int,
                     reg_minutes: float, exact_cached: bool, head_sets: int = 1) -> float:
    """The autoencoder's minutes when the whole of ``train_bundle`` must fit ``stage_minutes``:
    what is left after the time spent so far (cutting or loading the crops), the exact-box crops
    still to cut, the three regressors and the rest of the work after training."""
    # the heads: their MLPs' 2 x reg_minutes (rotation 1, centre and distance 0.5 each), the
    # distance KNN's choice and the distance-from-rotation trees (about one more)
    after = 3 * reg_minutes * head_sets + n_crops * ((0.0 if exact_cached else CUT_S_PER_CROP) + AFTER_S_PER_CROP) / 60
    return min(minutes, max(MIN_TRAIN_MINUTES, stage_minutes - spent_minutes - after))


def train_bundle(data_dir, out_dir, method: str = "cvam", size: int = 64, latent: int = 128,
                 minutes: float = 45.0, seed: int = 0, max_images: int | None = None,
                 models_info_path=None, codebook_per_object: int = 1500, reg_minutes: float = 5.0,
                 log=print, command: str | None = None, encoder: str = "plain", init_from=None,
                 precision: str = "auto", reg_epochs: int | None = None, lr: float = 1e-3, batch: int = 128,
                 pretrained: bool = True, device: str = "auto", kl_warmup: int = 0,
                 stage_minutes: float | None = None, lr_schedule: str = "plateau",
                 head_sets: int = 1, max_steps: int | None = None) -> Manifest | None:
    """``stage_minutes``: the whole call's budget (``build``): the autoencoder trains for
    ``minutes`` or less, so that cutting both crop sets, the heads and the export fit in it too
    (:func:`training_minutes`). ``encoder``: plain | resnet | lite0 | lite1 | lite2 (an ImageNet-pretrained trunk; with
    ``pretrained=False`` the same network from random weights, the control). ``lr``, ``batch``:
    the autoencoder's AdamW step size and batch. ``device``: auto | cpu | cuda (auto: a CUDA GPU
    where torch sees one). Under ``torchrun --nproc_per_node N`` the N processes train the
    autoencoder together (each takes 1/N of every batch: the same recipe, N times the compute);
    the first one then fits the heads and writes the bundle, the others return None.
    ``head_sets``: head sets fitted (seeds ``seed``, ``seed + 1``, ...) and averaged
    (:func:`fit_head_sets`), each with ``reg_minutes``. ``max_steps``: the autoencoder's budget in
    training steps instead of ``minutes`` (the same run on any machine; with ``reg_epochs``, the
    whole bundle is; :func:`tracker.training.nets.fit.train_autoencoder`)."""
    torch = require_torch()
    from tracker.training.crops import CropSet, build_training_crops, crops_cache_path, train_val_split
    from tracker.core.meshes import load_models
    from tracker.training.nets.autoencoder import (ENCODERS, FROZEN, FROZEN_THROUGH, METHODS, AutoEncoder,
                                                   crop_size_problem)
    from tracker.training.nets.fit import (CachedInputs, Rows, cache_frozen_outputs, encode_all, onehot, to_tensor,
                                           train_autoencoder)
    from tracker.training.nets.precision import resolve, resolve_device
    if method not in METHODS:
        raise UserError(f"unknown method '{method}' (choose from {', '.join(METHODS)})")
    if encoder not in ENCODERS:
        raise UserError(f"unknown encoder '{encoder}' (choose from {', '.join(ENCODERS)})")
    if problem := crop_size_problem(encoder, size):
        raise UserError(problem)
    from tracker.training.nets import distributed as dd
    device = resolve_device(device)
    rank, n_proc = dd.init_from_env(device)  # under torchrun: several processes train the autoencoder
    from tracker.training.nets.memory import keep_freed_memory
    torch.set_num_threads(2 if n_proc == 1 else max(1, (os.cpu_count() or 2) // n_proc))
    keep_freed_memory()  # no page faults for every step's buffers (nets/memory.py)
    if rank != 0:
        log = lambda *a, **k: None  # noqa: E731  (the first process reports)
    precision = resolve(precision, device)
    data_dir, out = Path(data_dir), Path(out_dir)
    cfg_path = data_dir / "synth_config.json"
    if not cfg_path.is_file():
        raise UserError(f"{data_dir}: no synth_config.json; make training data with 'app.py synth'")
    synth = json.loads(cfg_path.read_text())
    mdir = Path(synth["config"]["models_dir"])  # the bundle's meshes: missing, before the training, not after it
    if not mdir.is_dir():
        raise UserError(f"{data_dir}: the meshes it was rendered from ({mdir}) are gone; run from the folder "
                        f"'synth' ran in, or re-render the split")
    work = work_dir(out)  # checkpoints and caches, outside the bundle
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def crops(jitter: bool) -> CropSet:
        cache = crops_cache_path(work, data_dir, size, seed, max_images, jitter)
        if cache.is_file():
            c = CropSet.load(cache)
            log(f"loaded {len(c)} crops from {cache}")
        else:
            t1 = time.perf_counter()
            c = build_training_crops(data_dir, size, seed=seed, max_images=max_images, jitter=jitter)
            c.save(cache)
            log(f"cut {len(c)} crops at {size}x{size} on {'jittered' if jitter else 'exact'} boxes "
                f"({time.perf_counter() - t1:.0f} s)")
        return c

    cs = dd.first_then_rest(lambda: crops(jitter=True))  # detector-like boxes; the first process cuts and caches
    obj_ids = sorted(int(o) for o in np.unique(cs.obj_id))
    idx = _object_index(obj_ids, cs.obj_id)
    n_obj = len(obj_ids)

    rng = np.random.default_rng(seed)
    rng.permutation(len(cs))  # advances the generator as before, so the codebook draws below stay reproducible
    tr, va = train_val_split(len(cs), seed)
    c_all = onehot(idx, n_obj)

    if stage_minutes is not None:
        exact_cached = crops_cache_path(work, data_dir, size, seed, max_images, False).is_file()
        minutes = training_minutes(stage_minutes, minutes, (time.perf_counter() - t0) / 60, len(cs),
                                   reg_minutes, exact_cached, head_sets)
        minutes = dd.max_over_ranks(minutes)  # one budget (and step-size schedule) on every process
    frozen_front = encoder in FROZEN
    recon = min(size, FROZEN_RECON_SIZE) if frozen_front else size
    torch.manual_seed(seed)  # the starting weights from the seed too (else from whatever ran before)
    model = AutoEncoder(method, size, latent, n_obj, encoder=encoder, pretrained=pretrained, recon_size=recon)
    n_params = sum(p.numel() for p in model.parameters())
    log(f"{method}: {n_params / 1e6:.2f} M parameters, {len(tr)} train / {len(va)} validation crops, "
        f"{n_obj} objects, budget {f'{max_steps} steps' if max_steps is not None else f'{minutes:.0f} min'}, "
        f"{precision} training passes")
    x_in, y_out = cs.x, cs.y
    if frozen_front:  # the frozen front's outputs cached once (the first process), the targets at the decoder's size
        key = crops_cache_path(work, data_dir, size, seed, max_images, True).stem
        path = work / f"frozen_{encoder}_aug{FROZEN_AUGMENTATIONS}_{key}.npy"
        x_in = dd.first_then_rest(lambda: CachedInputs(path) if path.is_file() else cache_frozen_outputs(
            model.encoder.frozen, cs.x, path, n_aug=FROZEN_AUGMENTATIONS, seed=seed, log=log))
        if recon != size:
            y_out = np.stack([cv2.resize(im, (recon, recon), interpolation=cv2.INTER_AREA) for im in cs.y])
    hist = train_autoencoder(model, x_in.subset(tr) if frozen_front else Rows(x_in, tr), Rows(y_out, tr), c_all[tr],
                             x_in.subset(va) if frozen_front else Rows(x_in, va), Rows(y_out, va), c_all[va], work,
                             minutes=minutes, seed=seed, init_from=init_from, precision=precision, log=log,
                             lr=lr, batch=batch, device=device, kl_warmup=kl_warmup, lr_schedule=lr_schedule,
                             max_steps=max_steps)

    if rank != 0:  # the heads, the codebook and the export are the first process's
        dd.finish()
        return None
    dd.finish()
    cond = c_all if method == "cvam" else None
    mu = encode_all(model, cs.x, cond)
    export_x = cs.x[va[:16]]  # the export's parity check; from here on the heads need no pixels
    del x_in, y_out
    cs = cs.labels()
    cs_exact = crops(jitter=False)
    mu_exact = encode_all(model, cs_exact.x, cond)
    cs_exact = cs_exact.labels()
    cs_h, mu_h, tr_h, va_h = with_exact_boxes(cs, mu, cs_exact, mu_exact, tr, va)

    models_info = load_models_info(models_info_path) if models_info_path else None
    if models_info is None:
        from tracker.core.meshes import compute_models_info
        models_info = compute_models_info(load_models(mdir, obj_ids))
    head, codebook, dist_info, val = fit_head_sets(mu_h, cs_h, obj_ids, models_info, tr_h, va_h, rng, n_sets=head_sets,
                                                   seed=seed, n_jittered=len(cs), log=log, reg_minutes=reg_minutes,
                                                   cache_dir=work / "head_sets",
                                                   codebook_per_object=codebook_per_object, reg_epochs=reg_epochs)

    # ---- export (a detector already in the bundle, for the same objects, is kept)
    kept_detector = None
    if (out / "manifest.json").is_file():
        old = json.loads((out / "manifest.json").read_text())
        det = old.get("detector")
        from tracker.runtime.fusion import member_artefacts, member_files
        files = [det["file"], *member_files(det)] if isinstance(det, dict) and isinstance(det.get("file"), str) else []
        if files and sorted(det.get("classes", [])) == obj_ids and all((out / f).is_file() for f in files):
            kept_detector = (det, {f: (out / f).read_bytes() for f in files})  # a fused detector's networks too
            log(f"keeping the bundle's detector ({', '.join(files)})")

    def _write_bundle(dest: Path, name: str) -> Manifest:  # the files; the manifest to hash
        (dest / "meshes").mkdir(parents=True, exist_ok=True)
        save_head(head, dest / "pose_head.json", dest / "pose_head.npz")
        save_codebook(codebook, dest / "codebook.npz")
        xs = to_tensor(export_x).numpy()
        diff = export_encoder(model, size, model.n_cond, dest / "encoder.onnx", xs, c_all[va[:16]].numpy() if model.n_cond else None)
        log(f"encoder.onnx: max |onnx - torch| = {diff:.2e}")
        if diff > 1e-4:
            raise UserError(f"exported encoder differs from torch by {diff:.2e} (> 1e-4)")
        from tracker.core.bop import save_models_info
        models = load_models(mdir, obj_ids)
        from tracker.training.prepare import object_names
        given = object_names(mdir)  # a folder made by 'lab prepare-models' names its objects
        objects = []
        for o in obj_ids:
            mesh_rel = f"meshes/obj_{o:06d}.ply"
            models[o].mesh.export(dest / mesh_rel)  # binary PLY with vertex colours
            info = models_info[o]
            objects.append(ObjectEntry(id=o, name=given.get(o, LMO_NAMES.get(o, f"obj_{o}")), mesh=mesh_rel, diameter=info["diameter"],
                                       symmetries_discrete=info.get("symmetries_discrete", []),
                                       symmetries_continuous=info.get("symmetries_continuous", [])))
        save_models_info(dest / "meshes" / "models_info.json", {o: models_info[o] for o in obj_ids})
        Kt = np.asarray(synth["config"]["K"])
        manifest = Manifest(
            name=name, method=method, encoder=encoder, input_size=size, latent_size=latent, objects=objects,
            training_camera={"K": Kt.tolist(), "width": synth["config"]["width"], "height": synth["config"]["height"],
                             "focal_mean": focal_mean(Kt)},
            pose_prior=synth["config"]["prior"],
            extra={"colour_order": "RGB", "crop": "square on the box, side = longer side, bicubic, pixel values / 255"},
            artefacts={"encoder": "encoder.onnx", "pose_head": "pose_head.json", "pose_head_arrays": "pose_head.npz",
                       "codebook": "codebook.npz", "models_info": "meshes/models_info.json"},
            training={"data": str(data_dir), "synth_images": synth.get("images_written", synth.get("images")),
                      "crops": len(cs), "train": len(tr), "validation": len(va), "ae_parameters": n_params,
                      "ae_epochs": len(hist["epoch"]), "ae_best_val_l2": float(min(hist["val_l2"])),
                      "ae_minutes": round(hist["seconds"][-1] / 60, 1) if hist["seconds"] else 0.0,
                      **({"ae_max_steps": max_steps} if max_steps is not None else {}),
                      "total_minutes": round((time.perf_counter() - t0) / 60, 1),
                      "knn": dist_info["knn"], "seed": seed, "precision": precision, "device": device, "lr": lr, "lr_schedule": lr_schedule, "batch": batch,
                      # BatchNorm after every conv (folded into the exported convs), read off the network
                      "ae_norm": "batch" if any(isinstance(m, torch.nn.BatchNorm2d) for m in model.decoder.modules())
                      else "none",
                      **({"processes": n_proc} if n_proc > 1 else {}),
                      **({"pretrained": pretrained} if encoder not in ("plain", "resnet") else {}),
                      **({"frozen_front": f"NanoDet stem..stage{FROZEN_THROUGH[encoder]} (COCO)",
                          "frozen_augmentations": FROZEN_AUGMENTATIONS,
                          "recon_size": recon} if frozen_front else {}),
                      **({"init_from": str(init_from)} if init_from else {}), "onnx_max_abs_diff": diff},
            validation_synthetic=val,
            heads={"rotation_frame": head.rotation_frame, "distance": dist_info["head"],
                   "distance_val_te_median_mm": dist_info["val_te_median_mm"],
                   "distance_by_rotation": dist_info["by_rotation"], "boxes": "jittered and exact",
                   "reg_minutes": None if reg_epochs else reg_minutes, "reg_epochs": reg_epochs,
                   **({"ensemble": {"members": head_sets, "seeds": list(range(seed, seed + head_sets)),
                                    "note": "the distance head and knn are the first member's"}}
                      if head_sets > 1 else {})},
            command=command or "app.py " + " ".join(sys.argv[1:]),
            created=time.strftime("%Y-%m-%d %H:%M:%S"),
        )
        if kept_detector is not None:
            det, blobs = kept_detector
            for f, blob in blobs.items():
                (dest / f).write_bytes(blob)
            manifest.detector = det
            manifest.artefacts["detector"] = det["file"]
            manifest.artefacts.update(member_artefacts(det))
        return manifest

    from tracker.training.decimate import add_overlay_meshes
    from tracker.core.bundle import bundle_writer
    with bundle_writer(None, out) as w:  # the old bundle stays until the new one is whole
        w.manifest = _write_bundle(w.folder, out.name)
        w.apply(lambda folder: add_overlay_meshes(folder, OVERLAY_FACES, log=lambda *a: None))  # for the live overlay
    total = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    log(f"bundle {out}: {total / 1e6:.1f} MB, {(time.perf_counter() - t0) / 60:.1f} min in all")
    return w.manifest


def refit_heads(model_dir, data_dir, out_dir=None, seed: int = 0, reg_minutes: float = 5.0,
                codebook_per_object: int = 1500, keep_regressors: bool = False, log=print,
                command: str | None = None, jitter_scale: float | None = None, reg_epochs: int | None = None) -> Manifest:
    """Refit a bundle's regressors and AAE codebook on its frozen encoder (ONNX), without
    retraining the autoencoder; writes the bundle to ``out_dir`` (default: in place).
    ``keep_regressors``: keep its rotation, centre and latent distance regressors and fit only
    the distance-from-rotation trees and the codebook (for a ray-frame bundle made before the
    trees existed). ``jitter_scale``: the log-size noise of the jittered boxes (default
    :data:`~tracker.training.crops.JITTER_SCALE`, what the autoencoder trained on)."""
    require_torch()  # the MLPs train with torch
    from tracker.core.bundle import bundle_writer
    from tracker.training.crops import JITTER_SCALE, bundle_training_crops, crops_cache_path, train_val_split
    from tracker.runtime.estimator import PoseEstimator
    jitter_scale = JITTER_SCALE if jitter_scale is None else jitter_scale
    t0 = time.perf_counter()
    est = PoseEstimator(model_dir, threads=2, single_thread_math=False)
    if keep_regressors and isinstance(est.head, HeadEnsemble):
        raise UserError(f"{model_dir}: its pose head averages {len(est.head.members)} head sets ('join-heads'); "
                        "--keep-regressors needs one: refit without it, or keep the regressors of a member bundle")
    work = work_dir(est.bundle.root)

    def codes(crops, jitter: bool) -> np.ndarray:
        """The encoder's codes of ``crops``, cached per encoder (its hash) and split."""
        encoder_sha = est.bundle.manifest.file_sha256("encoder")[:10]
        stem = crops_cache_path(work, data_dir, est.size, seed, jitter=jitter, jitter_scale=jitter_scale).stem
        path = work / f"codes_{encoder_sha}_{stem}.npy"
        if path.is_file():
            mu = np.load(path, allow_pickle=False)
            if len(mu) == len(crops):
                return mu
        mu = est.encode_crops(crops.x, crops.obj_id)
        work.mkdir(parents=True, exist_ok=True)
        np.save(path, mu)
        return mu

    src = est.bundle
    out = Path(out_dir) if out_dir else src.root
    if not (Path(data_dir) / "synth_config.json").is_file():
        raise UserError(f"{data_dir}: no synth_config.json; make training data with 'app.py synth'")
    cs = bundle_training_crops(src.root, src.manifest, data_dir, seed=seed, log=log, jitter_scale=jitter_scale)
    cs_exact = bundle_training_crops(src.root, src.manifest, data_dir, seed=seed, jitter=False, log=log)
    mu, mu_exact = codes(cs, True), codes(cs_exact, False)
    cs, cs_exact = cs.labels(), cs_exact.labels()  # the heads need no pixels
    log(f"codes of {len(cs) + len(cs_exact)} crops in {time.perf_counter() - t0:.0f} s")
    rng = np.random.default_rng(seed)
    rng.permutation(len(cs))  # the draws of train_bundle, so the codebook views are the same
    tr, va = train_val_split(len(cs), seed)
    cs_h, mu_h, tr_h, va_h = with_exact_boxes(cs, mu, cs_exact, mu_exact, tr, va)
    models_info = load_models_info(src.path("models_info"))
    keep = est.head if keep_regressors else None
    if keep is not None and keep.rotation_frame != "ray":
        raise UserError(f"{model_dir}: its regressors predict camera-frame rotations; refit them all "
                        "(without --keep-regressors)")
    head, codebook, dist_info, val = fit_heads(mu_h, cs_h, est.obj_ids, models_info, tr_h, va_h, rng,
                                               reg_minutes=reg_minutes, codebook_per_object=codebook_per_object,
                                               seed=seed, n_jittered=len(cs), keep=keep, log=log,
                                               reg_epochs=reg_epochs)
    m = src.manifest.copy()
    m.name = out.name
    old = src.manifest.heads
    if keep is None:
        m.training = {**m.training, "knn": dist_info["knn"]}
    m.validation_synthetic = val
    m.heads = {"rotation_frame": head.rotation_frame, "distance": dist_info.get("head", old.get("distance")),
                  "distance_val_te_median_mm": dist_info.get("val_te_median_mm", old.get("distance_val_te_median_mm")),
                  "distance_by_rotation": dist_info["by_rotation"], "kept_regressors": keep is not None,
                  "boxes": "jittered and exact", "jitter_scale": jitter_scale,
                  "data": str(data_dir), "seed": seed,
                  "reg_minutes": None if reg_epochs else reg_minutes, "reg_epochs": reg_epochs,
                  "minutes": round((time.perf_counter() - t0) / 60, 1),
                  "command": command or "app.py " + " ".join(sys.argv[1:]),
                  "created": time.strftime("%Y-%m-%d %H:%M:%S")}
    with bundle_writer(src, out) as w:
        w.manifest = m
        save_head(head, w.folder / src.manifest.artefacts["pose_head"], w.folder / src.manifest.artefacts["pose_head_arrays"])
        save_codebook(codebook, w.folder / src.manifest.artefacts["codebook"])
    log(f"bundle {out}: heads refitted in {(time.perf_counter() - t0) / 60:.1f} min")
    return w.manifest
