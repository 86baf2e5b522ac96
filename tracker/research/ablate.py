"""``app.py lab ablate``: the thesis's regressor ablations on the synthetic validation split,
with a bundle's frozen encoder.

- Table 4.1 (rotation): MLP / random forest x 6D / quaternion / axis-angle, and nearest-
  neighbour search (the AAE codebook, cosine); ADD(I) recall with the true translation and the
  median rotation error (symmetry-aware).
- Table 4.2a (centre): MLP / RF / KNN / the box centre; error of the projected centre in px.
- Table 4.2b (distance): MLP / RF / KNN, and the bundle's trees on the estimated rotation
  alone and averaged with the MLP; |Tz error| in mm.

Crops, split and features are those of training (``crops.train_val_split``, ``regressors``),
so the rows differ only in the regressor. Torch is needed (the MLPs train with it).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from tracker.training.crops import bundle_training_crops, train_val_split
from tracker.core.errors import UserError
from tracker.core.geometry import (axis_angle_from_matrix, box_offset_of_centre, centre_from_box_offset, matrix_from_axis_angle,
                       matrix_from_quat, matrix_from_rot6d, quat_from_matrix, rot6d_from_matrix, rotation_error_deg)
from tracker.training.fit_heads import BoostedTrees, KNNRegressor, NumpyMLP
from tracker.runtime.heads import (Codebook, apparent_size, centre_inputs, distance_by_rotation_inputs, distance_inputs,
                                   rotation_inputs)

REPRESENTATIONS = {
    "6D": (rot6d_from_matrix, None),  # decoded by NumpyMLP / matrix_from_rot6d
    "quaternion": (quat_from_matrix, matrix_from_quat),  # w >= 0: one of the two signs
    "axis-angle": (axis_angle_from_matrix, matrix_from_axis_angle),
}


def _rf(seed):
    from sklearn.ensemble import RandomForestRegressor
    return RandomForestRegressor(n_estimators=30, max_features=0.3, min_samples_leaf=2, n_jobs=2, random_state=seed)


def _add_true_t(R_est, R_gt, obj_ids, points, symmetric):
    """ADD (ADI for symmetric objects) with the true translation, in mm, per sample."""
    from scipy.spatial import cKDTree
    out = np.empty(len(R_est))
    for i, (Re, Rg, o) in enumerate(zip(R_est, R_gt, obj_ids)):
        p = points[int(o)]
        pe, pg = p @ Re.T, p @ Rg.T
        if symmetric[int(o)]:
            out[i] = cKDTree(pg).query(pe)[0].mean()
        else:
            out[i] = np.linalg.norm(pe - pg, axis=1).mean()
    return out


def ablate(model_dir, data_dir, json_path=None, mlp_minutes: float = 1.0, max_train: int | None = 20000,
           seed: int = 0, log=print) -> dict:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise UserError("ablate trains MLPs: install the extras, pip install -e '.[train]'") from None
    from tracker.runtime.estimator import PoseEstimator
    from tracker.core.meshes import load_mesh
    t0 = time.perf_counter()
    est = PoseEstimator(model_dir)
    b = est.bundle
    cs = bundle_training_crops(model_dir, b.manifest, data_dir, seed=seed, log=log)
    tr, va = train_val_split(len(cs), seed)
    if max_train and len(tr) > max_train:
        tr = np.sort(np.random.default_rng(seed).choice(tr, max_train, replace=False))
    mu = est.encode_crops(cs.x, cs.obj_id)
    log(f"encoded in {time.perf_counter() - t0:.0f} s; {len(tr)} train / {len(va)} validation crops")
    n = len(est.obj_ids)
    idx = est.head.index(cs.obj_id)
    objs = {o.id: o for o in b.objects}
    points, symmetric = {}, {}
    for o in est.obj_ids:
        v = np.asarray(load_mesh(b.root / objs[o].mesh, o).mesh.vertices)
        points[o] = v[:: max(1, len(v) // 1000)]
        symmetric[o] = bool(objs[o].symmetries_discrete or objs[o].symmetries_continuous)
    diam = np.array([objs[int(o)].diameter for o in cs.obj_id[va]])
    Xr_tr, Xr_va = rotation_inputs(mu[tr], idx[tr], n), rotation_inputs(mu[va], idx[va], n)

    centres = cs.centres()
    R_obs = cs.R_ray(centres)  # what the crop shows; with the true centre, errors equal those in the camera frame

    def rot_row(name, R_va):
        add = _add_true_t(R_va, R_obs[va], cs.obj_id[va], points, symmetric)
        re = rotation_error_deg(R_va, R_obs[va])
        row = {"method": name, "add_recall_true_t": float(np.mean(add < 0.1 * diam)),
               "re_median_deg": float(np.median(re))}
        log(f"  {name:24s} ADD(I) {row['add_recall_true_t']:.3f}  RE median {row['re_median_deg']:.1f} deg")
        return row

    log("Table 4.1 - rotation")
    t41 = []
    for rep, (enc, dec) in REPRESENTATIONS.items():
        Y = enc(R_obs[tr])
        mlp = NumpyMLP(hidden=(256, 256), loss="l1", epochs=300, weight_decay=1e-2, minutes=mlp_minutes, seed=seed)
        if rep == "6D":  # the bundle's rotation loss: L1 on the matrix via Gram-Schmidt
            mlp.loss = "l1_rotation"
            mlp.fit(Xr_tr, R_obs[tr], np.repeat(np.eye(3)[None, None], len(tr), 0),
                    Xr_va, R_obs[va], np.repeat(np.eye(3)[None, None], len(va), 0))
            R_mlp = R_6d = mlp.predict(Xr_va)
        else:
            mlp.fit(Xr_tr, Y, None, Xr_va, enc(R_obs[va]))
            R_mlp = dec(mlp.predict(Xr_va))
        t41.append(rot_row(f"MLP + {rep}", R_mlp))
        rf = _rf(seed).fit(Xr_tr, Y.reshape(len(tr), -1))
        out = rf.predict(Xr_va)
        t41.append(rot_row(f"RF + {rep}", matrix_from_rot6d(out) if rep == "6D" else dec(out)))
    cb = Codebook().fit(mu[tr], cs.obj_id[tr], R_obs[tr], np.ones(len(tr)))
    t41.append(rot_row("NNS (codebook, cosine)", cb.predict(mu[va], cs.obj_id[va])[0]))

    log("Table 4.2a - centre")
    off = box_offset_of_centre(cs.box, centres)
    Xc_tr = centre_inputs(mu[tr], idx[tr], n, cs.box[tr], cs.K[tr])
    Xc_va = centre_inputs(mu[va], idx[va], n, cs.box[va], cs.K[va])
    from sklearn.neighbors import KNeighborsRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    preds = {
        "MLP": NumpyMLP(hidden=(256,), loss="l1", epochs=300, weight_decay=1e-2, minutes=mlp_minutes, seed=seed)
        .fit(Xc_tr, off[tr], None, Xc_va, off[va]).predict(Xc_va),
        "RF": _rf(seed).fit(Xc_tr, off[tr]).predict(Xc_va),
        "KNN": make_pipeline(StandardScaler(), KNeighborsRegressor(8, weights="distance")).fit(Xc_tr, off[tr]).predict(Xc_va),
        "box centre": np.zeros((len(va), 2)),
    }
    t42a = []
    for name, o in preds.items():
        err = np.linalg.norm(centre_from_box_offset(cs.box[va], o) - centres[va], axis=1)
        t42a.append({"method": name, "centre_err_mean_px": float(err.mean()), "centre_err_median_px": float(np.median(err))})
        log(f"  {name:12s} centre error mean {err.mean():.2f} px, median {np.median(err):.2f} px")

    log("Table 4.2b - distance")
    size_f = apparent_size(cs.box, cs.K)
    y = np.log(cs.t[:, 2] * size_f)
    Xd_tr = distance_inputs(mu[tr], idx[tr], n, cs.box[tr], cs.K[tr])
    Xd_va = distance_inputs(mu[va], idx[va], n, cs.box[va], cs.K[va])
    knn = b.manifest.training.get("knn", {})
    preds = {
        "MLP": NumpyMLP(hidden=(256,), loss="l1", epochs=300, weight_decay=1e-2, minutes=mlp_minutes, seed=seed)
        .fit(Xd_tr, y[tr, None], None, Xd_va, y[va, None]).predict(Xd_va)[:, 0],
        "RF": _rf(seed).fit(Xd_tr, y[tr]).predict(Xd_va),
        "KNN": KNNRegressor(k=knn.get("k", 8), box_weight=knn.get("box_weight", 3.0)).fit(Xd_tr, y[tr]).predict(Xd_va),
    }
    # the bundle's second distance head: trees on the true rotation, fed the MLP + 6D's estimate
    trees = BoostedTrees(seed=seed).fit(distance_by_rotation_inputs(R_obs[tr], idx[tr], n, cs.box[tr], cs.K[tr]), y[tr])
    preds["trees on estimated rotation"] = trees.predict(distance_by_rotation_inputs(R_6d, idx[va], n, cs.box[va],
                                                                                       cs.K[va]))
    preds["MLP + trees (log average)"] = 0.5 * (preds["MLP"] + preds["trees on estimated rotation"])
    t42b = []
    for name, p in preds.items():
        err = np.abs(np.exp(p) / size_f[va] - cs.t[va, 2])
        t42b.append({"method": name, "tz_err_mean_mm": float(err.mean()), "tz_err_median_mm": float(np.median(err))})
        log(f"  {name:12s} |Tz error| mean {err.mean():.1f} mm, median {np.median(err):.1f} mm")

    res = {"model": str(model_dir), "data": str(data_dir), "train": len(tr), "validation": len(va),
           "mlp_minutes": mlp_minutes, "seed": seed, "minutes": round((time.perf_counter() - t0) / 60, 1),
           "note": "synthetic validation crops (jittered ground-truth boxes), frozen encoder of the bundle",
           "table_4_1": t41, "table_4_2a": t42a, "table_4_2b": t42b}
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(res, indent=1))
    return res
