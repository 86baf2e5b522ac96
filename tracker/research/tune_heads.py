"""``app.py lab tune-heads``: how much the pose head's distance leans on the distance-from-rotation
trees for the detector's boxes, chosen on renders.

The trees turn the estimated rotation and the box's size into the distance; they help exact
boxes most and pass a detector box's size error on (docs/experiments/stops-30-36.md, stops 30-31 and 33). The
latent MLP sees the crop and can make up for part of it. This job evaluates the bundle with its
detector's boxes on a ``synth`` split for each weight, keeps the one with the best ADD(I)
(then AR_MSSD), and records every figure in the manifest. Exact (ground-truth) boxes keep their
weight."""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from tracker.core.bop import is_scene_dir
from tracker.core.bundle import bundle_writer, open_bundle
from tracker.core.errors import UserError
from tracker.core.manifest import Manifest

WEIGHTS = (0.0, 0.25, 0.5, 0.75)
FIGURES = ("add_recall", "ar_mssd", "ar_mspd", "te_median_mm")


def _scenes(data) -> list[Path]:
    from tracker.training.crops import split_scene_dirs
    return [Path(data)] if is_scene_dir(data) else split_scene_dirs(data)


def tune_trees_weight(model_dir, data, weights=WEIGHTS, out_dir=None, max_frames: int | None = None,
                      log=print, command: str | None = None) -> Manifest:
    """Write ``out_dir`` (default: ``model_dir`` in place) with ``heads.trees_weight.detector``
    set to the best of ``weights`` on ``data`` (a ``synth`` split or scene: renders, never the
    evaluation frames), ``max_frames`` per scene."""
    from tracker.runtime.estimator import trees_weights
    from tracker.runtime.heads import load_bundle_head
    from tracker.evaluation.evaluate import evaluate
    weights = sorted({float(w) for w in weights})
    if not weights or any(not 0 <= w <= 1 for w in weights):
        raise UserError(f"--weights must lie in [0, 1], got {weights}")
    scenes = _scenes(data)
    b = open_bundle(model_dir)
    if not b.manifest.has_detector:
        raise UserError(f"{model_dir}: this bundle has no detector; the weight is for the detector's boxes")
    head = load_bundle_head(b)
    weights_now = trees_weights(b.manifest)
    if not any(getattr(h, "distance_by_rotation", None) is not None for h in getattr(head, "members", [head])):
        raise UserError(f"{model_dir}: its pose head has no distance-from-rotation trees; nothing to tune")
    table = {}
    with tempfile.TemporaryDirectory() as tmp:
        for w in weights:
            n, sums = 0, dict.fromkeys(FIGURES, 0.0)
            for k, scene in enumerate(scenes):
                m = evaluate(b.root, scene, boxes="detector", bop_csv=Path(tmp) / f"w{w}_{k}.csv",
                             max_frames=max_frames, progress=False, detector_trees_weight=w)
                n += m["n_gt"]
                for f in FIGURES:
                    sums[f] += (m[f] or 0.0) * m["n_gt"]
            table[w] = {f: round(v / max(n, 1), 4) for f, v in sums.items()} | {"instances": n}
            log(f"trees weight {w:.2f}: ADD(I) {table[w]['add_recall']:.3f}, AR_MSSD {table[w]['ar_mssd']:.3f}, "
                f"AR_MSPD {table[w]['ar_mspd']:.3f}, TE median {table[w]['te_median_mm']:.1f} mm ({n} instances)")
    best = max(weights, key=lambda w: (table[w]["add_recall"], table[w]["ar_mssd"],
                                       w == weights_now["detector"]))  # ties: keep the bundle's
    out = Path(out_dir) if out_dir else b.root
    with bundle_writer(b, out) as writer:
        m = writer.manifest
        m.name = out.name
        m.heads = {**m.heads, "trees_weight": {
            "exact": weights_now["exact"], "detector": best, "chosen_on": str(data),
            "by_weight": {str(w): v for w, v in table.items()}, "max_frames": max_frames,
            "command": command or "app.py " + " ".join(sys.argv[1:]), "created": time.strftime("%Y-%m-%d %H:%M:%S")}}
    log(f"bundle {out}: the trees' share of the distance for detector boxes {best:.2f} "
        f"(exact boxes {m.heads['trees_weight']['exact']:.2f})")
    return writer.manifest
