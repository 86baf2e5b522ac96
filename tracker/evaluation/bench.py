"""``app.py bench``: per-stage latency of the live pipeline, from a run's timings."""
from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from tracker.runtime.loop import RunSummary, TrackConfig


def bench(cfg: TrackConfig, skip_first: int = 2, log=print) -> tuple[dict, RunSummary]:
    """Run ``cfg`` (into ``cfg.out``, or a temporary folder when it is None) and summarise its
    timings: the bench JSON (docs/formats.md) and the run's summary. ``skip_first``: warm-up
    frames (GL, first inference) left out of the statistics."""
    from tracker.evaluation.track import track
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(cfg.out) if cfg.out else Path(tmp)
        s = track(replace(cfg, out=out), log=log)
        rows = [line.split(",") for line in (out / "timings.csv").read_text().splitlines()]
    head, rows = rows[0], rows[1:]
    col = {h: i for i, h in enumerate(head)}
    per = {k: np.array([float(r[col[k]]) for r in rows]) for k in head[2:]}
    if skip_first and len(rows) > skip_first:
        per = {k: v[skip_first:] for k, v in per.items()}
    objs = s.poses / max(s.frames, 1)
    total = per["total"]
    res = {"frames": int(len(total)), "objects_per_frame": round(objs, 2),
           "fps": round(1000.0 / float(np.median(total)), 2) if len(total) else None,
           "ms_per_object": round(float(np.median(per["encode"] + per["regress"])) / objs, 3) if objs else None,
           "stages_ms": {k: {"median": round(float(np.median(v)), 3), "p95": round(float(np.percentile(v, 95)), 3)}
                         for k, v in per.items()},
           "source": str(cfg.source), "model": str(cfg.model), "rerun": cfg.rerun, "overlay": cfg.overlay,
           "boxes": s.boxes, "detect_every": cfg.detect_every, "obj_ids": cfg.obj_ids,
           "accuracy": s.accuracy, "interrupted": s.interrupted}
    return res, s
