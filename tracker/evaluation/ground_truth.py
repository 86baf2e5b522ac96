"""Ground-truth boxes of a BOP scene: ``scene_gt_info``'s visible boxes where it has them, else
boxes and visible fractions rendered from the known objects at their ground-truth poses."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tracker.core.bop import gt_instances_with_boxes  # noqa: F401  (re-exported: the instances a box list keeps)
from tracker.core.errors import UserError


def gt_boxes(scene, models, im_ids) -> tuple[dict[int, list], str]:
    """Visible GT boxes per image: scene_gt_info's bbox_visib, else rendered from the known objects."""
    from tracker.evaluation.scoring import VISIB_FROM_GT_INFO, VISIB_RENDERED, rendered_gt_visibility
    if all("bbox_visib" in g.info for i in im_ids for g in scene.gt.get(i, [])):
        return ({i: [(np.asarray(g.info["bbox_visib"], float), float(g.info.get("visib_fract", 1.0)))
                     for g in scene.gt.get(i, [])] for i in im_ids}, VISIB_FROM_GT_INFO)
    w, h = scene.frame_size(im_ids)
    recs = rendered_gt_visibility(scene, models, im_ids, w, h)
    return {i: [(np.asarray(v.bbox_visib, float), v.visib_fract) for v in recs[i]] for i in im_ids}, VISIB_RENDERED


def gt_object_ids(scene, im_ids, known, hint: str = "") -> list[int]:
    """The objects in the ground truth of ``im_ids``; an error names any not in ``known``."""
    ids = sorted({g.obj_id for i in im_ids for g in scene.gt.get(i, [])})
    unknown = [o for o in ids if o not in known]
    if unknown:
        raise UserError(f"{scene.root}: the ground truth has object(s) {unknown} that the bundle does not know "
                        f"({list(known)}){hint}")
    return ids


def scene_gt_boxes(scene, im_ids, bundle, hint: str = "") -> dict[int, list]:
    """Visible ground-truth boxes of ``im_ids`` for the objects of ``bundle`` (meshes from it);
    an error names any object of the ground truth the bundle does not know."""
    from tracker.core.meshes import load_models
    ids = gt_object_ids(scene, im_ids, bundle.manifest.obj_ids, hint)
    boxes, _ = gt_boxes(scene, load_models(bundle.root / "meshes", ids), im_ids)
    return boxes


def models_for_others(scene_dir, obj_ids, given=None) -> Path | None:
    """A folder with obj_NNNNNN.ply for every one of ``obj_ids``: ``given`` (an error if it
    lacks any), else BOP's ``models/`` beside or above the scene (``lmo/dev`` -> ``lmo/models``,
    ``lmo/test/000002`` -> ``lmo/models``), else None."""
    from tracker.core.meshes import model_files

    def has(d: Path) -> bool:
        return set(obj_ids) <= set(model_files(d))
    if given is not None:
        if not has(Path(given)):
            raise UserError(f"--gt-models {given}: needs obj_NNNNNN.ply for object(s) {sorted(obj_ids)}")
        return Path(given)
    here = Path(scene_dir).resolve()
    for d in (here.parent / "models", here.parent.parent / "models"):
        if has(d):
            return d
    return None
