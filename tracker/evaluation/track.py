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
    would count what they skipped as missed). Where the ground truth has objects the bundle does
    not know, the bundle's are scored as ``eval`` scores them."""
    s = run_track(cfg, log=log, gt_boxes=_gt_boxes)
    if cfg.loop or cfg.obj_ids or s.interrupted or not s.frames or s.scene_root is None:
        return s
    out = Path(cfg.out)
    with Deferred(log, "scoring the poses against the ground truth") as scoring:
        try:
            from tracker.core.bop import load_scene_gt
            root = Path(s.scene_root)
            gt = load_scene_gt(root / "scene_gt.json") if (root / "scene_gt.json").is_file() else {}
            scored = [i for i in s.im_ids if i in gt]  # frames without an entry have no annotation
            gt_objs = {g.obj_id for i in scored for g in gt[i]}
            ours = set(s.bundle_obj_ids)
            if gt and gt_objs & ours:
                from tracker.evaluation.ground_truth import models_for_others
                from tracker.evaluation.scoring import score_results
                meshes = Path(cfg.model) / "meshes"
                others = sorted(gt_objs - ours)
                m = score_results(out / "poses.csv", root, meshes, models_info=meshes / "models_info.json",
                                  im_ids=scored, scene_id=s.scene_id, obj_ids=sorted(ours) if others else None,
                                  visibility_models_dir=(models_for_others(root, others) or meshes) if others else None)
                s.accuracy = {k: m[k] for k in ("n_gt", "add_recall", "ar_mssd", "ar_mspd", "re_median_deg",
                                                "te_median_mm", "visibility_source")}
        except KeyboardInterrupt:  # the second Ctrl-C: no accuracy, the rest stands
            s.accuracy_skipped = True
        except UserError as e:
            s.error = f"scoring: {e}"
            s.save(out)
            if s.viewer is not None:  # nobody will hold a viewer on a failed run
                s.viewer.stop()
            raise
        s.interrupted = scoring.hit  # a Ctrl-C came; the frames were all done (and scored, once)
        s.save(out)
    return s
