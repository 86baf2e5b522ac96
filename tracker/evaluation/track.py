"""``app.py track`` and ``demo``: the run loop with the ground truth's boxes where a BOP scene
has them (``--boxes auto|gt``), and the poses scored against that ground truth at the end."""
from __future__ import annotations

from pathlib import Path

from tracker.core.errors import UserError
from tracker.evaluation.ground_truth import scene_gt_boxes
from tracker.runtime.loop import RunSummary, TrackConfig, run_track
from tracker.runtime.signals import Deferred


def _gt_boxes(scene, im_ids, bundle):
    return scene_gt_boxes(scene, im_ids, bundle, "; use --boxes detector, or a bundle trained on them")


def track(cfg: TrackConfig, log=print) -> RunSummary:
    """:func:`~tracker.runtime.loop.run_track`, then the accuracy of its poses where the source
    is a BOP scene with ground truth (not for looped, interrupted or object-subset runs, which
    would count what they skipped as missed)."""
    from tracker.core.bop import is_scene_dir, load_scene
    s = run_track(cfg, log=log, gt_boxes=_gt_boxes)
    out = Path(cfg.out)
    if cfg.loop or cfg.obj_ids or s.interrupted or not s.frames or not is_scene_dir(cfg.source):
        return s
    scene = load_scene(cfg.source)
    if not scene.gt:
        return s
    from tracker.core.bundle import open_bundle
    bundle = open_bundle(cfg.model)
    gt_objs = {g.obj_id for i in s.im_ids for g in scene.gt.get(i, [])}
    if not gt_objs <= set(bundle.manifest.obj_ids):
        return s
    from tracker.evaluation.scoring import score_results
    meshes = bundle.root / "meshes"
    with Deferred(log, "scoring the poses against the ground truth") as scoring:
        try:
            m = score_results(out / "poses.csv", scene.root, meshes, models_info=meshes / "models_info.json",
                              im_ids=s.im_ids, scene_id=s.scene_id)
            s.accuracy = {k: m[k] for k in ("n_gt", "add_recall", "ar_mssd", "ar_mspd", "re_median_deg",
                                            "te_median_mm", "visibility_source")}
        except KeyboardInterrupt:  # the second Ctrl-C: no accuracy, the rest stands
            s.accuracy_skipped = True
        except UserError as e:
            s.error = f"scoring: {e}"
            s.save(out)
            raise
        s.interrupted = scoring.hit  # a Ctrl-C came; the frames were all done (and scored, once)
        s.save(out)
    return s
