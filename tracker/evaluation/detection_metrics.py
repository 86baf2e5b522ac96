"""COCO-style detection metrics: AP over IoU 0.50:0.95, AP50 and recall at IoU 0.5, per object
and averaged over objects (101-point interpolated precision, greedy matching by score, as
pycocotools does). Ground truth below 10 % visibility is 'ignore': a detection on it is
neither a hit nor a false positive."""
from __future__ import annotations

import numpy as np

from tracker.core.geometry import iou_matrix, square_crop

IOU_THRESHOLDS = np.round(np.arange(0.5, 0.951, 0.05), 2)
RECALL_POINTS = np.linspace(0, 1, 101)


def _ap_one(scores, hits, n_gt) -> tuple[float, float]:
    """AP (101-point) and final recall from detections sorted by score."""
    if n_gt == 0:
        return float("nan"), float("nan")
    if len(scores) == 0:
        return 0.0, 0.0
    tp = np.cumsum(hits)
    fp = np.cumsum(~hits)
    rec = tp / n_gt
    prec = tp / np.maximum(tp + fp, 1e-12)
    prec = np.maximum.accumulate(prec[::-1])[::-1]  # precision envelope
    idx = np.searchsorted(rec, RECALL_POINTS, side="left")
    p = np.where(idx < len(prec), prec[np.minimum(idx, len(prec) - 1)], 0.0)
    return float(p.mean()), float(rec[-1])


def detection_ap(detections, ground_truth, classes, ignore=None) -> dict:
    """``detections``: per image a list of objects with ``obj_id``, ``box`` (x, y, w, h),
    ``score``; ``ground_truth``: per image a list of (obj_id, box); ``ignore``: per image a
    list of (obj_id, box) that neither count nor penalise."""
    ignore = ignore or [[] for _ in ground_truth]
    per = {}
    for c in classes:
        dets = [(i, d.score, np.asarray(d.box, float)) for i, ds in enumerate(detections) for d in ds if d.obj_id == c]
        dets.sort(key=lambda x: -x[1])
        gt = [np.array([b for o, b in g if o == c], float).reshape(-1, 4) for g in ground_truth]
        ig = [np.array([b for o, b in g if o == c], float).reshape(-1, 4) for g in ignore]
        n_gt = sum(len(g) for g in gt)
        aps, recs = [], []
        for thr in IOU_THRESHOLDS:
            used = [np.zeros(len(g), bool) for g in gt]
            used_ig = [np.zeros(len(g), bool) for g in ig]  # an ignored instance absorbs one detection
            hits, keep = [], []
            for i, _, b in dets:
                ious = iou_matrix(b[None], gt[i])[0] if len(gt[i]) else np.zeros(0)
                ious = np.where(used[i], -1, ious)
                iig = np.where(used_ig[i], -1, iou_matrix(b[None], ig[i])[0]) if len(ig[i]) else np.zeros(0)
                if len(ious) and ious.max() >= thr:
                    used[i][int(ious.argmax())] = True
                    hits.append(True)
                    keep.append(True)
                elif len(iig) and iig.max() >= thr:
                    used_ig[i][int(iig.argmax())] = True
                    keep.append(False)  # on an ignored instance: not counted
                    hits.append(False)
                else:
                    hits.append(False)
                    keep.append(True)
            keep = np.array(keep, bool)
            ap, rec = _ap_one(np.array([d[1] for d in dets])[keep] if dets else np.zeros(0),
                              np.array(hits, bool)[keep] if dets else np.zeros(0, bool), n_gt)
            aps.append(ap)
            recs.append(rec)
        per[int(c)] = {"ap": float(np.mean(aps)) if n_gt else None, "ap50": aps[0] if n_gt else None,
                       "recall50": recs[0] if n_gt else None, "n_gt": n_gt, "n_det": len(dets)}
    have = [v for v in per.values() if v["n_gt"]]

    def mean(k):
        return float(np.mean([v[k] for v in have])) if have else None
    return {"ap": mean("ap"), "ap50": mean("ap50"), "recall50": mean("recall50"), "per_object": per}


def box_errors(detections, ground_truth, classes, iou_min: float = 0.5) -> dict:
    """How the right boxes among ``detections`` (those overlapping an instance of their object
    in their image by IoU >= ``iou_min``; each instance matched once, best score first) differ
    from the truth, in the pose crop's terms (a square of the box's longer side about its
    centre): ``side_log_ratio`` = log(longer side / the truth's), below 0 when boxes are too
    short (the depth from a box follows it); ``shift`` = the centre's distance from the truth's
    over the truth's longer side. Per object (by obj_id) and over all right boxes ("all"):
    ``n_gt``, ``n_right``, ``iou_median``, ``side_log_ratio_mean``, ``side_log_ratio_median``,
    ``side_log_ratio_sd``, ``shift_median``; None where no box is right. Inputs as for
    :func:`detection_ap` (meant for the run-time detections: one per object)."""
    rows = {int(c): [] for c in classes}
    n_gt = {int(c): 0 for c in classes}
    for dets, gts in zip(detections, ground_truth):
        for c in rows:
            gt = np.array([b for o, b in gts if o == c], float).reshape(-1, 4)
            n_gt[c] += len(gt)
            used = np.zeros(len(gt), bool)
            for d in sorted((d for d in dets if d.obj_id == c), key=lambda d: -d.score):
                if not len(gt):
                    break
                b = np.asarray(d.box, float)
                if not (b[2] > 0 and b[3] > 0):
                    continue  # a degenerate box overlaps nothing
                ious = np.where(used, -1.0, iou_matrix(b[None], gt)[0])
                k = int(ious.argmax())
                if ious[k] < iou_min:
                    continue
                used[k] = True
                cd, cg = square_crop(b, 1), square_crop(gt[k], 1)  # the pose crops of both boxes
                shift = np.hypot(cd.x0 + cd.side / 2 - cg.x0 - cg.side / 2, cd.y0 + cd.side / 2 - cg.y0 - cg.side / 2)
                rows[c].append((float(ious[k]), float(np.log(cd.side / cg.side)), float(shift / cg.side)))

    def stats(r, n) -> dict:
        a = np.array(r, float).reshape(-1, 3)
        some = len(a) > 0
        return {"n_gt": int(n), "n_right": len(a),
                "iou_median": float(np.median(a[:, 0])) if some else None,
                "side_log_ratio_mean": float(a[:, 1].mean()) if some else None,
                "side_log_ratio_median": float(np.median(a[:, 1])) if some else None,
                "side_log_ratio_sd": float(a[:, 1].std()) if some else None,
                "shift_median": float(np.median(a[:, 2])) if some else None}
    out = {"per_object": {c: stats(rows[c], n_gt[c]) for c in rows}, "iou_min": iou_min}
    out["all"] = stats([x for r in rows.values() for x in r], sum(n_gt.values()))
    return out
