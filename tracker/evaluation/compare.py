"""``app.py lab compare A B``: two runs on the same scene, paired frame by frame.

Each figure (ADD(I), AR_MSSD, AR_MSPD and their mean) is a mean over ground-truth instances,
so a frame contributes the sum of its instances' values and its instance count. The paired
bootstrap resamples frames with replacement, the same frames for A and B, and takes the
difference B - A of the ratio of sums; the interval is the percentile interval of those
differences. Frames, not instances, are resampled: the instances of one frame share its
lighting, clutter and detector, so they are not independent.

The rule (docs/experiments/README.md): B is kept over A only when the interval of its gain on
the mean lies above 0 and no figure's interval lies below 0.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from tracker.core.errors import UserError

# figure -> the per-instance column whose mean over instances it is
FIGURES = {"add_recall": "add_pass", "ar_mssd": "mssd_recall", "ar_mspd": "mspd_recall"}
KEY = ("im_id", "gt_index", "obj_id")


def read_per_instance(path) -> list[dict]:
    """The rows of an ``eval --per-instance`` CSV, checked: one line of error for a file that
    is missing, empty or lacks a column the comparison needs."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such per-instance file (write one with app.py eval ... --per-instance FILE)")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # a spreadsheet's byte-order mark is read past
            rows = list(csv.DictReader(f))
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text CSV (expected the file written by app.py eval --per-instance)") from None
    need = set(KEY) | set(FIGURES.values())
    if not rows:
        raise UserError(f"{path}: no rows; expected the CSV written by app.py eval --per-instance")
    missing = sorted(need - set(rows[0]))
    if missing:
        raise UserError(f"{path}: not a per-instance file of app.py eval (no column {', '.join(missing)})")
    out = []
    for n, r in enumerate(rows, start=2):
        try:
            row = {**{k: int(r[k]) for k in KEY}, **{c: float(r[c]) for c in FIGURES.values()}}
        except (TypeError, ValueError):
            raise UserError(f"{path}, line {n}: a number was expected in {', '.join(sorted(need))}") from None
        bad = [c for c in FIGURES.values() if not 0.0 <= row[c] <= 1.0]  # NaN fails too
        if bad:
            raise UserError(f"{path}, line {n}: {bad[0]} is {r[bad[0]]}; a pass or recall lies in [0, 1]")
        out.append(row)
    return out


def _frame_sums(rows: list[dict], frames: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(F, figures) sums of each figure's column per frame, (F,) instances per frame."""
    pos = {f: k for k, f in enumerate(frames)}
    sums = np.zeros((len(frames), len(FIGURES)))
    counts = np.zeros(len(frames))
    for r in rows:
        k = pos[r["im_id"]]
        counts[k] += 1
        sums[k] += [r[c] for c in FIGURES.values()]
    return sums, counts


def compare_rows(a: list[dict], b: list[dict], n_boot: int = 10000, level: float = 0.95, seed: int = 0) -> dict:
    """B - A for every figure with its paired-bootstrap interval over frames, and the rule's verdict."""
    keys_a = {tuple(r[k] for k in KEY) for r in a}
    keys_b = {tuple(r[k] for k in KEY) for r in b}
    if len(keys_a) != len(a) or len(keys_b) != len(b):
        raise UserError("a per-instance file lists an instance twice (im_id, gt_index, obj_id)")
    if keys_a != keys_b:
        only = sorted(keys_a ^ keys_b)[0]
        raise UserError(f"the two files score different instances (first: im_id {only[0]}, gt_index {only[1]}, "
                        f"obj_id {only[2]} is in one only): compare runs on the same scene, frames and objects")
    frames = sorted({r["im_id"] for r in a})
    sa, n = _frame_sums(a, frames)
    sb, _ = _frame_sums(b, frames)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(frames), size=(n_boot, len(frames)))
    cnt = n[idx].sum(1)[:, None]
    fa, fb = sa[idx].sum(1) / cnt, sb[idx].sum(1) / cnt                # (n_boot, figures)
    da = np.concatenate([fb - fa, (fb - fa).mean(1, keepdims=True)], 1)  # the figures, then their mean
    pa, pb = sa.sum(0) / n.sum(), sb.sum(0) / n.sum()
    lo_q, hi_q = (1 - level) / 2, 1 - (1 - level) / 2
    out = {}
    for k, name in enumerate([*FIGURES, "mean"]):
        va, vb = (pa[k], pb[k]) if k < len(FIGURES) else (pa.mean(), pb.mean())
        lo, hi = np.quantile(da[:, k], [lo_q, hi_q])
        out[name] = {"a": float(va), "b": float(vb), "diff": float(vb - va), "ci": [float(lo), float(hi)]}
    falls = [f for f in FIGURES if out[f]["ci"][1] < 0]
    keep = out["mean"]["ci"][0] > 0 and not falls
    per_object = {}
    for o in sorted({r["obj_id"] for r in a}):
        ra = [r for r in a if r["obj_id"] == o]
        rb = [r for r in b if r["obj_id"] == o]
        per_object[str(o)] = {"n": len(ra), **{f: float(np.mean([r[c] for r in rb]) - np.mean([r[c] for r in ra]))
                                               for f, c in FIGURES.items()}}
    return {"n_frames": len(frames), "n_instances": len(a), "bootstrap": int(n_boot), "level": level,
            "seed": seed, "figures": out, "per_object_diff": per_object,
            "verdict": {"keep_b": bool(keep), "falls": falls,
                        "rule": "keep B when the interval of its gain on the mean lies above 0 and no figure's "
                                "interval lies below 0"}}


def compare_files(a_path, b_path, n_boot: int = 10000, level: float = 0.95, seed: int = 0) -> dict:
    res = compare_rows(read_per_instance(a_path), read_per_instance(b_path), n_boot=n_boot, level=level, seed=seed)
    return {"a": str(a_path), "b": str(b_path), **res}
