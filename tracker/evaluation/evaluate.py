"""``app.py eval``: run a bundle on a BOP scene and score it with the BOP metrics."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tracker.core.bop import Estimate, load_scene, write_results
from tracker.core.errors import UserError
from tracker.evaluation.ground_truth import gt_boxes, gt_instances_with_boxes, models_for_others
from tracker.runtime.estimator import Detection, PoseEstimator


def bop_csv_name(method: str, dataset: str = "lmo", split: str = "test") -> str:
    """BOP's rule for result files: METHOD_DATASET-SPLIT.csv (no '_' inside METHOD)."""
    return f"{method.replace('_', '-')}_{dataset}-{split}.csv"


def evaluate(model_dir, scene_dir, json_path=None, boxes: str = "gt", mode: str = "regression",
             bop_csv=None, max_frames: int | None = None, progress: bool = True,
             detector_trees_weight: float | None = None, gt_models=None, per_instance=None,
             candidates_per_object: int | None = None, candidate_floor: float | None = None) -> dict:
    """``detector_trees_weight``: the trees' share of the distance for the detector's boxes in
    place of the bundle's (``app.py lab tune-heads`` tries several).

    A bundle of some of the scene's objects (``build --objects``) is scored on the instances
    of its objects; the others still hide parts of them when their meshes are found
    (``gt_models``, else a BOP ``models/`` folder beside or above the scene that has them),
    else they are left out (visibility from the bundle's objects alone, said on stderr).

    ``candidates_per_object`` / ``candidate_floor``: the detector's verified candidates per object and their
    score floor in place of the bundle's (:class:`tracker.runtime.detector.DetectorSpec`).

    ``per_instance``: a CSV to write with one row per scored ground-truth instance (its errors,
    pass / fail per threshold: :func:`tracker.evaluation.scoring.per_instance_rows`), the input of
    ``app.py lab compare``."""
    from tracker.core.meshes import load_models
    from tracker.evaluation.scoring import score_results, write_metrics_json
    if boxes not in ("gt", "detector"):
        raise UserError(f"--boxes must be gt or detector, not '{boxes}'")
    from tracker.core.bop import check_output_file
    for f, what in ((json_path, "--json"), (bop_csv, "--bop-csv"), (per_instance, "--per-instance")):
        if f is not None:
            check_output_file(f, what)
    est = PoseEstimator(model_dir)
    if detector_trees_weight is not None:
        est.trees_weight["detector"] = float(detector_trees_weight)
    detector = None
    if boxes == "detector":
        from tracker.runtime.detector import Detector
        detector = Detector(est.bundle, threads=2)
        from dataclasses import replace
        if candidates_per_object is not None:
            detector.spec = replace(detector.spec, candidates=int(candidates_per_object))
        if candidate_floor is not None:
            detector.spec = replace(detector.spec, candidate_floor=float(candidate_floor))
    scene = load_scene(scene_dir, require_gt=True)
    im_ids = sorted(scene.gt)[:max_frames] if max_frames else sorted(scene.gt)
    if not im_ids:
        raise UserError(f"{scene_dir}: its ground truth (scene_gt.json) lists no images; nothing to evaluate")
    mesh_dir = Path(model_dir) / "meshes"
    ours = set(est.obj_ids)
    gt_ids = sorted({g.obj_id for i in im_ids for g in scene.gt.get(i, [])})
    others = [o for o in gt_ids if o not in ours]
    vis_dir = mesh_dir
    if others:
        vis_dir = models_for_others(scene_dir, others, gt_models)
        scored = [o for o in gt_ids if o in ours]
        if not scored:
            raise UserError(f"{scene_dir}: its ground truth has none of the bundle's objects {sorted(ours)} "
                            f"(it has {gt_ids})")
        if vis_dir is None:
            print(f"eval: scoring objects {scored} only; the ground truth's objects {others} are not in the bundle "
                  f"and no meshes of them were found (--gt-models DIR), so they are left out of the visibility",
                  file=sys.stderr)
            scene, vis_dir = scene.only(ours), mesh_dir
        else:
            print(f"eval: scoring objects {scored} only (the bundle's); visibility from every object, meshes "
                  f"from {vis_dir}", file=sys.stderr)
        gt_ids = sorted({g.obj_id for i in im_ids for g in scene.gt.get(i, [])})
    models = load_models(vis_dir, gt_ids)
    box_of, _ = gt_boxes(scene, models, im_ids)
    results = []
    all_dets, all_candidates, det_ms = [], [], []
    t_all = 0.0
    for im_id in tqdm(im_ids, desc=f"eval ({mode}, {boxes} boxes)", unit="img", disable=not progress):
        img = scene.read_rgb(im_id)
        t0 = time.perf_counter()
        if detector is not None:
            dets, candidates = detector.detect(img, candidates=True)
            det_ms.append(1000 * (time.perf_counter() - t0))
            all_candidates.append(candidates)
        else:
            dets = [Detection(o, b, exact=True) for o, b, _ in gt_instances_with_boxes(scene.gt[im_id], box_of[im_id])
                    if o in ours]
        poses = est.estimate(img, scene.K(im_id), dets, mode=mode)
        if detector is not None:  # the operating point: the boxes the poses were made from
            grouped = any(d.group is not None for d in dets)
            all_dets.append([Detection(p.obj_id, p.box, p.detector_score) for p in poses] if grouped else dets)
        dt = time.perf_counter() - t0
        t_all += dt
        results += [Estimate(0, im_id, p.obj_id, p.score, p.R, p.t, dt) for p in poses]
    name = f"autopose-{est.method}" + ("" if mode == "regression" else f"-{mode}")
    if bop_csv is None:
        base = Path(json_path).parent if json_path else Path(".")
        bop_csv = base / bop_csv_name(name)
    write_results(bop_csv, results)
    records = []
    m = score_results(bop_csv, scene_dir, mesh_dir, models_info=mesh_dir / "models_info.json", im_ids=im_ids,
                      scene_id=0, ms_per_image=1000 * t_all / len(im_ids), obj_ids=sorted(ours) if others else None,
                      visibility_models_dir=vis_dir, records_out=records)
    if per_instance is not None:
        from tracker.evaluation.scoring import per_instance_rows, write_per_instance
        write_per_instance(per_instance, per_instance_rows(records))
        m["per_instance"] = str(per_instance)
    if detector is not None:
        from tracker.evaluation.detection_metrics import box_errors, detection_ap
        gts = [[(o, b) for o, b, _ in gt_instances_with_boxes(scene.gt[i], box_of[i], 0.1) if o in ours]
               for i in im_ids]
        ign = [[(o, b) for o, b, _ in gt_instances_with_boxes(scene.gt[i], box_of[i], 0.1, below=True) if o in ours]
               for i in im_ids]
        # AP as COCO defines it (the ranked candidates); the run-time detections (the manifest's
        # threshold, one per object) alongside, as the operating point the poses were made from
        m["detection"] = detection_ap(all_candidates, gts, est.obj_ids, ignore=ign)
        from tracker.runtime.detector import CANDIDATE_MAX, CANDIDATE_PER_CLASS, CANDIDATE_SCORE
        m["detection"]["protocol"] = (f"coco: candidates scoring >= {CANDIDATE_SCORE}, at most {CANDIDATE_PER_CLASS} "
                                      f"per object and {CANDIDATE_MAX} per image")
        m["detection"]["operating_point"] = detection_ap(all_dets, gts, est.obj_ids, ignore=ign)
        m["detection"]["box_errors"] = box_errors(all_dets, gts, est.obj_ids)
        m["detection"]["ms_per_image_median"] = float(np.median(det_ms))
        m["detection"]["candidates"] = {"per_object": detector.spec.candidates, "floor": detector.spec.candidate_floor}
        m["detection"]["visibility_source"] = m.get("visibility_source")
    if others:
        m["scored_obj_ids"] = sorted(ours & set(gt_ids))
        m["visibility_meshes"] = str(vis_dir)
    m.update({"boxes": boxes, "mode": mode, "model": str(model_dir),
              "bundle_manifest_sha256": est.bundle.manifest_sha256, "data": str(scene_dir), "max_frames": max_frames,
              "bop_csv": str(bop_csv), "method": name})
    if json_path:
        write_metrics_json(json_path, m)
    return m

