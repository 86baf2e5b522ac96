"""BOP-style scoring of pose estimates against a BOP scene with ground truth.

Semantics follow bop_toolkit (``eval_calc_errors.py``, ``eval_calc_scores.py``,
``pose_matching.py``, ``score.py``, ``eval_bop19_pose.py``), 6D localisation task:

- **Valid GT**: a ground-truth instance counts when its visible fraction is >= 0.1
  (``VISIB_GT_MIN``). Instances below are not targets and cannot be matched.
- **Targets**: per image and object, ``n`` = the number of valid instances of that object;
  only the ``n`` highest-scoring estimates of that object in that image are evaluated
  (BOP's ``n_top = -1``). Estimates of objects with no valid instance in the image are
  not evaluated (no false-positive penalty in the localisation task).
- **Matching, per error and per threshold**: estimates in order of decreasing score; each
  takes, among the valid GT instances of its object not matched yet, the one with the
  lowest error, provided that error is strictly below the threshold. A GT instance
  without a match is a miss (a missing estimate counts as wrong).
- **Recall** at a threshold = matched valid instances / valid instances (over all objects
  together; per object for ``per_object``). ``AR_X`` = mean recall over X's thresholds:
  MSSD 0.05..0.50 of the diameter, MSPD 5r..50r px with r = image width / 640. ``ar`` =
  mean of the available ARs (VSD needs depth; ``ar_vsd`` is null).
- ``add_recall``: ADD for objects without symmetries in models_info, ADI for the others,
  correct below 0.1 x diameter; ``recall_5deg5cm``: RE < 5 deg and TE < 50 mm; both
  matched as above.
- ``re_median_deg`` / ``te_median_mm``: over valid GT instances that got an estimate, the
  estimate given by the same greedy matching with no threshold on MSSD (for one instance
  per object and image, as in LM-O: the best-scoring estimate of that object). RE / TE
  are symmetry-aware here (and in ``recall_5deg5cm``): taken against the symmetric
  equivalent of the GT pose that attains the MSSD, so a 180-degree flip of the eggbox
  is not an error.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from tracker.evaluation import metrics
from tracker.core.bop import (Estimate, Scene, write_json, load_models_info, load_scene, read_results,
                  symmetry_transforms)
from tracker.core.errors import UserError
from tracker.core.paths import cache_dir

VISIB_GT_MIN = 0.1
MSSD_THS = np.arange(0.05, 0.51, 0.05)   # fractions of the diameter (BOP's exact values)
MSPD_THS = np.arange(5, 51, 5)           # pixels at 640 px width
ADD_TH = 0.1                             # fraction of the diameter
RETE_THS = (5.0, 50.0)                   # deg, mm
VISIB_BINS = (0.1, 0.3, 0.5, 0.7, 0.9, 1.0)
VSD_DELTA = 15.0                          # mm, BOP's tolerance for LM-O
VSD_TAUS = np.arange(0.05, 0.51, 0.05)    # misalignment tolerances, fractions of the diameter
VSD_THS = np.arange(0.05, 0.51, 0.05)     # correctness thresholds on the VSD error
VISIB_WINDOW = 128  # px: the window each instance is rendered alone into (as synth's clean targets)
VISIB_FROM_GT_INFO = "scene_gt_info"
VISIB_RENDERED = "rendered from known objects (upper bound: unknown occluders missed)"


# --------------------------------------------------------------------------- objects


@dataclass
class ObjectEval:
    """What the errors need of one object: points, symmetries, diameter."""

    obj_id: int
    pts: np.ndarray        # (N, 3) model vertices, mm
    diameter: float
    syms: np.ndarray       # (S, 4, 4), identity first
    symmetric: bool        # has symmetries in models_info: ADI instead of ADD
    _hull: np.ndarray | None = None
    _tree: cKDTree | None = None

    @property
    def hull(self) -> np.ndarray:
        if self._hull is None:
            self._hull = metrics.hull_points(self.pts)
        return self._hull

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.pts)
        return self._tree

    @classmethod
    def from_info(cls, obj_id: int, vertices: np.ndarray, info: dict) -> "ObjectEval":
        symmetric = bool(info.get("symmetries_discrete") or info.get("symmetries_continuous"))
        return cls(int(obj_id), np.asarray(vertices, dtype=np.float64).reshape(-1, 3),
                   float(info["diameter"]), symmetry_transforms(info), symmetric)


# --------------------------------------------------------------------------- models_info


_INFO_CACHE: dict[str, dict[int, dict]] = {}


def _models_key(models_dir: Path) -> str:
    from tracker.core.meshes import MODEL_RE
    h = hashlib.sha256()
    for p in sorted(models_dir.iterdir()):
        if MODEL_RE.match(p.name):
            h.update(p.name.encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:20]


def models_info_for(models_dir, models_info=None) -> dict[int, dict]:
    """models_info: the given dict or file; else ``models_dir/models_info.json``; else
    computed from the meshes (diameter, box, discrete symmetries; about 10 s for LM-O) and
    cached, in memory and in ``$AUTOPOSE_CACHE`` (default ``~/.cache/autopose``), keyed by
    the meshes' contents."""
    if isinstance(models_info, dict):
        return {int(k): v for k, v in models_info.items()}
    if models_info is not None:
        return load_models_info(models_info)
    models_dir = Path(models_dir)
    if (models_dir / "models_info.json").is_file():
        return load_models_info(models_dir / "models_info.json")
    if not models_dir.is_dir():
        raise UserError(f"models folder not found: {models_dir}")
    key = _models_key(models_dir)
    if key in _INFO_CACHE:
        return _INFO_CACHE[key]
    cached = cache_dir() / f"models_info_{key}.json"
    if cached.is_file():
        try:
            info = {int(k): v for k, v in json.loads(cached.read_text()).items()}
            _INFO_CACHE[key] = info
            return info
        except (ValueError, OSError):
            pass  # unreadable cache: recompute
    from tracker.core.meshes import compute_models_info, load_models
    info = compute_models_info(load_models(models_dir))
    _INFO_CACHE[key] = info
    try:
        write_json(cached, {str(k): v for k, v in info.items()})
    except OSError:
        pass  # a read-only home only costs the recomputation next time
    return info


# --------------------------------------------------------------------------- visibility


def gt_visibility(scene: Scene, models: dict, im_ids, width: int, height: int
                  ) -> tuple[dict[int, list[float]], str]:
    """Visible fraction of every GT instance of ``im_ids``: {im_id: [visib_fract, ...]}.

    From ``scene_gt_info.json`` when every instance has ``visib_fract`` there; otherwise
    rendered from the known objects at their GT poses (``models``: {obj_id: ObjectModel},
    :func:`tracker.core.visibility.scene_visibility`). Returns the fractions and their source.
    """
    if all("visib_fract" in g.info for i in im_ids for g in scene.gt.get(i, [])):
        return {i: [float(g.info["visib_fract"]) for g in scene.gt.get(i, [])] for i in im_ids}, VISIB_FROM_GT_INFO
    recs = rendered_gt_visibility(scene, models, im_ids, width, height)
    return {i: [v.visib_fract for v in recs[i]] for i in im_ids}, VISIB_RENDERED


def rendered_gt_visibility(scene: Scene, models: dict, im_ids, width: int, height: int) -> dict[int, list]:
    """{im_id: [InstanceVisibility, ...]} of the GT instances, rendered from the known objects."""
    from tracker.runtime.render import Renderer
    from tracker.core.visibility import scene_visibility
    used = sorted({g.obj_id for i in im_ids for g in scene.gt.get(i, [])})
    meshes = {k: models[k].mesh for k in used}
    verts = {k: models[k].vertices for k in used}
    out = {}
    with Renderer(width, height, meshes) as full, Renderer(VISIB_WINDOW, VISIB_WINDOW, meshes) as crop:
        for i in im_ids:
            insts = [(g.obj_id, g.R, g.t) for g in scene.gt.get(i, [])]
            out[i] = scene_visibility(full, crop, scene.K(i), insts, verts) if insts else []
    return out


# --------------------------------------------------------------------------- matching


def match_greedy(errors: np.ndarray, order: np.ndarray, valid: np.ndarray, ths) -> np.ndarray:
    """BOP's greedy matching of one image and object.

    ``errors``: (n_est, n_gt, E) errors of each estimate against each GT instance, with E
    error elements (1, or 2 for RE + TE); ``order``: estimate indices by decreasing score;
    ``valid``: (n_gt,) bool; ``ths``: E thresholds. Each estimate in turn takes the unmatched
    valid instance whose every error element is the lowest so far and below its threshold.
    Returns, per GT instance, the index of the matched estimate or -1.
    """
    n_gt = errors.shape[1]
    match = np.full(n_gt, -1)
    ths = np.asarray(ths, dtype=np.float64).reshape(-1)
    for e in order:
        best, best_err = -1, ths
        for g in range(n_gt):
            if valid[g] and match[g] < 0 and np.all(errors[e, g] < best_err):
                best, best_err = g, errors[e, g]
        if best >= 0:
            match[best] = e
    return match


# --------------------------------------------------------------------------- scoring


@dataclass
class _GtRecord:
    obj_id: int
    visib: float
    mssd_hit: np.ndarray   # (len(MSSD_THS),) bool
    mspd_hit: np.ndarray
    add_hit: bool
    rete_hit: bool
    re: float | None       # of the estimate matched without threshold (None: no estimate)
    te: float | None
    vsd_hit: np.ndarray | None = None  # (len(VSD_TAUS), len(VSD_THS)) bool, with depth only
    im_id: int = -1
    gt_index: int = -1                 # its index in the image's scene_gt.json list
    mssd: float | None = None          # errors of the estimate matched without threshold: / diameter,
    mspd: float | None = None          # px at 640 px width,
    add: float | None = None           # / diameter (ADI for symmetric objects)


def _errors(est: list[Estimate], gts: list, obj: ObjectEval, K: np.ndarray, r: float,
            depth_test: np.ndarray | None = None, renderer=None) -> dict:
    """All errors of ``est`` against ``gts`` (one object), each (n_est, n_gt, ·); VSD (one
    value per tau) too when the scene's depth image and a depth renderer are given."""
    ne, ng = len(est), len(gts)
    out = {k: np.zeros((ne, ng, 1)) for k in ("mssd", "mspd", "add")}
    out["rete"] = np.zeros((ne, ng, 2))
    if depth_test is not None:
        out["vsd"] = np.ones((ne, ng, len(VSD_TAUS)))
        d_gt = [renderer.render(K, [(obj.obj_id, g.R, g.t)], depth_only=True)[1] for g in gts]
        for a, e in enumerate(est):
            d_est = renderer.render(K, [(obj.obj_id, e.R, e.t)], depth_only=True)[1]
            for b in range(ng):
                out["vsd"][a, b] = metrics.vsd(d_est, d_gt[b], depth_test, K, VSD_DELTA, VSD_TAUS, obj.diameter)
    for a, e in enumerate(est):
        for b, g in enumerate(gts):
            per_sym = metrics.mssd_per_symmetry(e.R, e.t, g.R, g.t, obj.hull, obj.syms)
            s = int(np.argmin(per_sym))
            out["mssd"][a, b, 0] = per_sym[s] / obj.diameter
            out["mspd"][a, b, 0] = metrics.mspd(e.R, e.t, g.R, g.t, K, obj.pts, obj.syms) / r
            d = (metrics.adi(e.R, e.t, g.R, g.t, obj.pts, tree=obj.tree) if obj.symmetric
                 else metrics.add(e.R, e.t, g.R, g.t, obj.pts))
            out["add"][a, b, 0] = d / obj.diameter
            S = obj.syms[s]
            R_gs, t_gs = g.R @ S[:3, :3], g.R @ S[:3, 3] + g.t
            out["rete"][a, b] = (metrics.re(e.R, R_gs), metrics.te(e.t, t_gs))
    return out


def score_estimates(estimates: list[Estimate], scene: Scene, objects: dict[int, ObjectEval],
                    visib: dict[int, list[float]], image_width: int, im_ids=None,
                    visibility_source: str | None = None, ms_per_image: float | None = None,
                    detection: dict | None = None, depth_renderer=None, records_out: list | None = None) -> dict:
    """Metrics JSON (CONVENTIONS.md) of ``estimates`` on ``scene``'s images ``im_ids``.

    ``estimates`` must already be those of this scene (any scene_id); ``objects`` covers
    every object of the GT and the estimates; ``visib`` gives every GT instance's visible
    fraction (:func:`gt_visibility`). ``records_out``: a list that gets every scored
    ground-truth instance's record (:func:`per_instance_rows` turns them into rows).
    """
    if scene.gt is None:
        raise UserError(f"{scene.root}: no scene_gt.json, nothing to score against")
    im_ids = sorted(scene.gt) if im_ids is None else sorted(im_ids)
    r = image_width / 640.0
    by_im: dict[int, dict[int, list[Estimate]]] = {}
    for e in estimates:
        by_im.setdefault(e.im_id, {}).setdefault(e.obj_id, []).append(e)
    records: list[_GtRecord] = []
    n_gt_all = 0
    n_est_obj: dict[int, int] = {}
    for i in im_ids:
        gts, vis = scene.gt[i], visib[i]
        n_gt_all += len(gts)
        for oid, lst in by_im.get(i, {}).items():
            n_est_obj[oid] = n_est_obj.get(oid, 0) + len(lst)
        for oid in sorted({g.obj_id for g in gts}):
            idx = [j for j, g in enumerate(gts) if g.obj_id == oid]
            valid = np.array([vis[j] >= VISIB_GT_MIN for j in idx])
            n_valid = int(valid.sum())
            if n_valid == 0:
                continue  # not a target
            cand = by_im.get(i, {}).get(oid, [])
            # top-n by decreasing score; Python's sort is stable, as BOP's
            cand = sorted(cand, key=lambda e: e.score, reverse=True)[:n_valid]
            order = np.arange(len(cand))
            depth = scene.read_depth(i) if depth_renderer is not None else None
            err = _errors(cand, [gts[j] for j in idx], objects[oid], scene.K(i), r, depth, depth_renderer)
            vsd_hit = None
            if "vsd" in err:
                vsd_hit = np.stack([np.stack([match_greedy(err["vsd"][:, :, [k]], order, valid, [th]) >= 0
                                              for th in VSD_THS], 1) for k in range(len(VSD_TAUS))], 1)
            mssd_hit = np.stack([match_greedy(err["mssd"], order, valid, [th]) >= 0 for th in MSSD_THS], 1)
            mspd_hit = np.stack([match_greedy(err["mspd"], order, valid, [th]) >= 0 for th in MSPD_THS], 1)
            add_hit = match_greedy(err["add"], order, valid, [ADD_TH]) >= 0
            rete_hit = match_greedy(err["rete"], order, valid, RETE_THS) >= 0
            loose = match_greedy(err["mssd"], order, valid, [np.inf])
            for k, j in enumerate(idx):
                if not valid[k]:
                    continue
                m = loose[k]
                got = m >= 0
                records.append(_GtRecord(oid, float(vis[j]), mssd_hit[k], mspd_hit[k], bool(add_hit[k]),
                                         bool(rete_hit[k]),
                                         float(err["rete"][m, k, 0]) if got else None,
                                         float(err["rete"][m, k, 1]) if got else None,
                                         None if vsd_hit is None else vsd_hit[k], im_id=int(i), gt_index=int(j),
                                         mssd=float(err["mssd"][m, k, 0]) if got else None,
                                         mspd=float(err["mspd"][m, k, 0]) if got else None,
                                         add=float(err["add"][m, k, 0]) if got else None))
    if records_out is not None:
        records_out.extend(records)
    n_est = sum(n_est_obj.values())
    out = _summary(records, n_est)
    out["confidence"] = confidence_ranking(by_im, scene, objects, visib, im_ids)
    out["n_gt_all"] = n_gt_all
    out["n_images"] = len(im_ids)
    out["recall_by_visibility"] = _by_visibility(records)
    gt_objs = {g.obj_id for i in im_ids for g in scene.gt[i]}
    out["per_object"] = {str(k): _summary([rc for rc in records if rc.obj_id == k], n_est_obj.get(k, 0))
                         for k in sorted(gt_objs | set(n_est_obj))}
    out["thresholds"] = {"vsd_delta_mm": VSD_DELTA, "vsd_taus_diameter_fraction": [round(float(t), 6) for t in VSD_TAUS],
                         "vsd_ths": [round(float(t), 6) for t in VSD_THS],
                         "mssd_diameter_fraction": [round(float(t), 6) for t in MSSD_THS],
                         "mspd_px": [round(float(t * r), 6) for t in MSPD_THS],
                         "add_diameter_fraction": ADD_TH, "re_deg": RETE_THS[0], "te_mm": RETE_THS[1],
                         "visib_gt_min": VISIB_GT_MIN}
    out["visibility_source"] = visibility_source
    out["detection"] = detection
    out["ms_per_image"] = None if ms_per_image is None else float(ms_per_image)
    return out


GOOD_POSE_AR_MSSD = 0.5  # an estimate is "good" when its own AR_MSSD (recall over MSSD_THS) reaches this


def ranking_auc(scores, labels) -> float | None:
    """Area under the ROC curve of ``scores`` separating true ``labels`` from false ones
    (Mann-Whitney; ties count half); None when one of the classes is empty."""
    from scipy.stats import rankdata
    s, y = np.asarray(scores, np.float64), np.asarray(labels, bool)
    n1, n0 = int(y.sum()), int((~y).sum())
    if n1 == 0 or n0 == 0:
        return None
    ranks = rankdata(s)
    return float((ranks[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def confidence_ranking(by_im: dict, scene: Scene, objects: dict, visib: dict, im_ids) -> dict:
    """How well the estimates' scores rank good poses above bad ones: every estimate (not only
    the top ones scoring uses) is good when its AR_MSSD against the closest valid instance of
    its object in the image is >= :data:`GOOD_POSE_AR_MSSD` (estimates of objects that are not
    in the image are bad); ``auc``: :func:`ranking_auc` of the scores."""
    scores, good = [], []
    for i in im_ids:
        gts, vis = scene.gt[i], visib[i]
        for oid, lst in by_im.get(i, {}).items():
            targets = [g for j, g in enumerate(gts) if g.obj_id == oid and vis[j] >= VISIB_GT_MIN]
            for e in lst:
                ar = 0.0
                for g in targets:
                    o = objects[oid]
                    err = metrics.mssd(e.R, e.t, g.R, g.t, o.hull, o.syms) / o.diameter
                    ar = max(ar, float(np.mean(err < MSSD_THS)))
                scores.append(e.score)
                good.append(ar >= GOOD_POSE_AR_MSSD)
    return {"auc": ranking_auc(scores, good), "n_estimates": len(scores), "n_good": int(np.sum(good)),
            "good_if_ar_mssd_at_least": GOOD_POSE_AR_MSSD}


def _mean_or_none(x) -> float | None:
    return float(np.mean(x)) if len(x) else None


def _summary(records: list[_GtRecord], n_est: int) -> dict:
    n = len(records)
    if n:
        rec_mssd = np.mean([rc.mssd_hit for rc in records], axis=0)
        rec_mspd = np.mean([rc.mspd_hit for rc in records], axis=0)
        ar_mssd, ar_mspd = float(rec_mssd.mean()), float(rec_mspd.mean())
        ar_vsd = (float(np.mean([rc.vsd_hit for rc in records]))
                  if all(rc.vsd_hit is not None for rc in records) else None)
        ar = float(np.mean([a for a in (ar_vsd, ar_mssd, ar_mspd) if a is not None]))
    else:
        rec_mssd = rec_mspd = None
        ar_mssd = ar_mspd = ar = ar_vsd = None
    matched = [rc for rc in records if rc.re is not None]
    return {
        "n_gt": n,
        "n_est": int(n_est),
        "add_recall": _mean_or_none([rc.add_hit for rc in records]),
        "ar_mssd": ar_mssd,
        "ar_mspd": ar_mspd,
        "ar_vsd": ar_vsd,
        "ar": ar,
        "recall_5deg5cm": _mean_or_none([rc.rete_hit for rc in records]),
        "re_median_deg": float(np.median([rc.re for rc in matched])) if matched else None,
        "te_median_mm": float(np.median([rc.te for rc in matched])) if matched else None,
        "n_matched": len(matched),
        "recall_mssd": None if rec_mssd is None else [float(v) for v in rec_mssd],
        "recall_mspd": None if rec_mspd is None else [float(v) for v in rec_mspd],
    }


def _by_visibility(records: list[_GtRecord]) -> list[dict]:
    out = []
    for k, (lo, hi) in enumerate(zip(VISIB_BINS[:-1], VISIB_BINS[1:])):
        last = k == len(VISIB_BINS) - 2
        sel = [rc for rc in records if lo <= rc.visib and (rc.visib < hi or (last and rc.visib <= hi + 1e-9))]
        s = _summary(sel, 0)
        out.append({"visib_min": lo, "visib_max": hi, "n_gt": s["n_gt"], "ar_mssd": s["ar_mssd"],
                    "ar_mspd": s["ar_mspd"], "ar": s["ar"], "add_recall": s["add_recall"]})
    return out


def per_instance_rows(records: list[_GtRecord], scene_id: int = 0) -> list[dict]:
    """One row per scored ground-truth instance: its matched estimate's errors (empty where
    nothing was estimated) and pass (1) / fail (0) at every threshold of ADD(I), MSSD, MSPD and
    5 deg 5 cm; ``mssd_recall`` / ``mspd_recall`` are its share of thresholds passed (the mean of
    a column over the instances is the AR): the file ``eval --per-instance`` writes."""
    def num(v, nd):
        return "" if v is None else round(float(v), nd)
    rows = []
    for rc in sorted(records, key=lambda r: (r.im_id, r.gt_index)):
        row = {"scene_id": scene_id, "im_id": rc.im_id, "gt_index": rc.gt_index, "obj_id": rc.obj_id,
               "visib_fract": round(rc.visib, 4), "estimated": int(rc.re is not None),
               "add": num(rc.add, 5), "mssd": num(rc.mssd, 5), "mspd_px": num(rc.mspd, 3),
               "re_deg": num(rc.re, 3), "te_mm": num(rc.te, 3),
               "add_pass": int(rc.add_hit), "rete_pass": int(rc.rete_hit),
               "mssd_recall": round(float(np.mean(rc.mssd_hit)), 4),
               "mspd_recall": round(float(np.mean(rc.mspd_hit)), 4)}
        row.update({f"mssd_pass@{t:.2f}": int(h) for t, h in zip(MSSD_THS, rc.mssd_hit)})
        row.update({f"mspd_pass@{t:g}": int(h) for t, h in zip(MSPD_THS, rc.mspd_hit)})
        rows.append(row)
    return rows


def write_per_instance(path, rows: list[dict]) -> Path:
    """The per-instance CSV (written whole)."""
    import csv
    from tracker.core.files import write_whole
    if not rows:
        raise UserError("no ground-truth instance was scored; nothing to write per instance")

    def write(tmp):
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return write_whole(path, write)


# --------------------------------------------------------------------------- files


def _pick_scene_id(estimates: list[Estimate], scene: Scene, scene_id: int | None) -> int | None:
    if scene_id is not None:
        return int(scene_id)
    ids = sorted({e.scene_id for e in estimates})
    if len(ids) <= 1:
        return ids[0] if ids else None
    name = scene.root.resolve().name
    if name.isdigit() and int(name) in ids:
        return int(name)
    raise UserError(f"the results hold scenes {ids[:10]} and the scene folder '{name}' is not one of "
                    f"them by name; keep one scene per results file")


def score_results(results_csv, scene_dir, models_dir, models_info=None, im_ids=None,
                  scene_id: int | None = None, ms_per_image: float | None = None,
                  detection: dict | None = None, obj_ids=None, visibility_models_dir=None,
                  records_out: list | None = None) -> dict:
    """Score a BOP results CSV against the BOP scene ``scene_dir`` (with ground truth).

    ``models_info``: dict or file; by default ``models_dir/models_info.json``, else computed
    (see :func:`models_info_for`). ``im_ids``: score only these images. ``scene_id``: the
    results' scene to take (default: the only one, or the one named like the folder).
    ``ms_per_image``: by default the mean of the CSV's ``time`` per image (x 1000) when every
    row has time >= 0 (BOP's average time per image), else null. ``obj_ids``: score only the
    instances (and estimates) of these objects, e.g. a bundle's few of the scene's many; the
    others still occlude them where their meshes are known (``visibility_models_dir``, default
    ``models_dir``: meshes for the visible fractions), and are left out of the scene where not.
    """
    from tracker.core.meshes import load_models, model_files
    scene = load_scene(scene_dir, require_gt=True)
    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise UserError(f"models folder not found: {models_dir}")
    known = set(model_files(models_dir))
    if not known:
        raise UserError(f"{models_dir}: no obj_NNNNNN.ply models")
    estimates = read_results(results_csv, known_obj_ids=known)
    sid = _pick_scene_id(estimates, scene, scene_id)
    estimates = [e for e in estimates if e.scene_id == sid]

    if im_ids is None:
        im_ids = sorted(scene.gt)
    else:
        im_ids = sorted({int(i) for i in im_ids})
        missing = [i for i in im_ids if i not in scene.gt]
        if missing:
            raise UserError(f"{scene.root}: no ground truth for image(s) {missing[:5]}")
    if not im_ids:
        raise UserError(f"{scene.root}/scene_gt.json has no images")
    im_set = set(im_ids)
    if estimates and not any(e.im_id in im_set for e in estimates):
        raise UserError(f"{results_csv}: none of its {len(estimates)} estimates is for an image of "
                        f"{scene.root} (image ids {im_ids[0]}..{im_ids[-1]})")
    estimates = [e for e in estimates if e.im_id in im_set]

    gt_objs = {g.obj_id for i in im_ids for g in scene.gt[i]}
    scored = gt_objs if obj_ids is None else gt_objs & {int(o) for o in obj_ids}
    if obj_ids is not None:
        estimates = [e for e in estimates if e.obj_id in set(map(int, obj_ids))]
    unknown = sorted(scored - known)
    if unknown:
        raise UserError(f"{scene.root}/scene_gt.json has object(s) {unknown} with no model in {models_dir}")
    vis_dir = Path(visibility_models_dir) if visibility_models_dir is not None else models_dir
    vis_known = set(model_files(vis_dir))
    if gt_objs - vis_known - scored:  # others with no mesh: visibility from the scored objects alone
        scene = scene.only(gt_objs & vis_known | scored)
        gt_objs = {g.obj_id for i in im_ids for g in scene.gt[i]}
    need = sorted(scored | {e.obj_id for e in estimates})
    info = models_info_for(models_dir, models_info)
    lacking = [k for k in need if k not in info]
    if lacking:
        raise UserError(f"models_info has no entry for object(s) {lacking}")
    models = load_models(models_dir, need)
    objects = {k: ObjectEval.from_info(k, models[k].vertices, info[k]) for k in need}
    vis_from = set(gt_objs) - (scored if vis_dir == models_dir else set())
    vis_models = {**(load_models(vis_dir, sorted(vis_from)) if vis_from else {}),
                  **({k: models[k] for k in scored} if vis_dir == models_dir else {})}

    width, height = scene.frame_size(im_ids)
    visib, source = gt_visibility(scene, vis_models, im_ids, width, height)
    if obj_ids is not None:  # the others occluded; now the scored objects' instances alone
        visib = {i: [v for v, g in zip(visib[i], scene.gt[i]) if g.obj_id in scored] for i in im_ids}
        scene = scene.only(scored)
    depth_renderer = None
    if scene.has_depth:
        from tracker.runtime.render import Renderer
        depth_renderer = Renderer(width, height, {k: models[k].mesh for k in need})

    if ms_per_image is None:
        times = {}
        for e in estimates:
            times[e.im_id] = e.time
        if times and all(t >= 0 for t in times.values()):
            ms_per_image = 1000.0 * float(np.mean(list(times.values())))
    try:
        return score_estimates(estimates, scene, objects, visib, width, im_ids, source, ms_per_image, detection,
                               depth_renderer, records_out=records_out)
    finally:
        if depth_renderer is not None:
            depth_renderer.close()


def write_metrics_json(path, metrics_dict: dict) -> Path:
    """Write the metrics JSON (atomically; numpy values become plain numbers)."""
    return write_json(path, metrics_dict)
