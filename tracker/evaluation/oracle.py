"""What limits a set of poses: each part of every estimate replaced by its ground truth's in turn
(the rotation, the translation, the depth along the estimate's own viewing ray, the viewing ray
at the estimate's own depth), each variant scored as BOP scores it and compared with the poses as
estimated, paired over frames (:func:`tracker.evaluation.compare.compare_rows`).

An estimate takes the ground truth of the instance of its object in its image nearest to its
translation; estimates of objects absent from their image stay as they are.
"""
from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from tracker.core.bop import Estimate, load_scene, read_results, write_results
from tracker.core.errors import UserError

SWAPS = {
    "rotation": "the true rotation",
    "translation": "the true translation",
    "depth": "the true depth along the estimate's own viewing ray",
    "ray": "the true viewing ray at the estimate's own depth",
}


def swap_with_truth(estimates: list[Estimate], scene, part: str) -> list[Estimate]:
    """``estimates`` with ``part`` (a key of :data:`SWAPS`) taken from the ground truth of
    ``scene`` (estimates of another scene id than their image's scene are the caller's to drop).
    An estimate at or behind the camera's plane has no viewing ray to keep: ``depth`` gives it
    the true translation."""
    if part not in SWAPS:
        raise UserError(f"unknown part '{part}' (choose from {', '.join(SWAPS)})")
    out = []
    for e in estimates:
        gts = [g for g in scene.gt.get(e.im_id, []) if g.obj_id == e.obj_id]
        if not gts:
            out.append(e)
            continue
        t = np.asarray(e.t, float).reshape(3)
        g = min(gts, key=lambda g: float(np.linalg.norm(np.asarray(g.t, float).reshape(3) - t)))
        tg = np.asarray(g.t, float).reshape(3)
        if part == "rotation":
            # the nearest rotation: a scene's may be up to 0.05 off orthonormal, a results file's 1e-2
            out.append(replace(e, R=Rotation.from_matrix(np.asarray(g.R, float).reshape(3, 3)).as_matrix()))
        elif part == "translation":
            out.append(replace(e, t=tg.copy()))
        elif part == "depth":
            out.append(replace(e, t=t * (tg[2] / t[2]) if t[2] > 0 else tg.copy()))
        else:
            out.append(replace(e, t=tg * (t[2] / tg[2])))
    return out


def oracle_swaps(results_csv, scene_dir, models_dir, models_info=None, parts=tuple(SWAPS),
                 n_boot: int = 10000, seed: int = 0, log=lambda *a: None) -> dict:
    """The poses of ``results_csv`` scored as estimated and with each of ``parts`` swapped for
    the truth: ``{"as_estimated": metrics, "swaps": {part: {"metrics", "compare"}}}``, each
    comparison B (swapped) - A (as estimated) with its paired-bootstrap interval."""
    from tracker.core.meshes import model_files
    from tracker.evaluation.compare import compare_rows
    from tracker.evaluation.scoring import per_instance_rows, score_results
    unknown = [p for p in parts if p not in SWAPS]
    if unknown:
        raise UserError(f"unknown part(s) {unknown} (choose from {', '.join(SWAPS)})")
    scene = load_scene(scene_dir, require_gt=True)
    if not Path(models_dir).is_dir():
        raise UserError(f"models folder not found: {models_dir}")
    estimates = read_results(results_csv, known_obj_ids=set(model_files(Path(models_dir))))
    if not estimates:
        raise UserError(f"{results_csv}: no estimates to swap")

    def scored(path):
        records = []
        m = score_results(path, scene_dir, models_dir, models_info=models_info, records_out=records)
        return m, per_instance_rows(records)

    log(f"scoring {results_csv} as estimated")
    base, base_rows = scored(results_csv)
    out = {"results": str(results_csv), "as_estimated": base, "swaps": {}}
    with tempfile.TemporaryDirectory(prefix="oracle_") as tmp:
        for part in parts:
            log(f"scoring with {SWAPS[part]}")
            path = write_results(Path(tmp) / f"{part}.csv", swap_with_truth(estimates, scene, part))
            m, rows = scored(path)
            out["swaps"][part] = {"what": SWAPS[part], "metrics": m,
                                  "compare": compare_rows(base_rows, rows, n_boot=n_boot, seed=seed)}
    return out
