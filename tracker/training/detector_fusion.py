"""``app.py lab fuse-detectors``: a bundle whose detector runs its own network and other bundles'
networks on every frame and fuses their detections (:mod:`tracker.runtime.fusion`). Unlike
``join-detectors`` (one graph averaging the maps of networks of one input size) the networks
keep their own inputs, normalisation and decoding: a 320 x 240 CenterNet and a 416 x 320
NanoDet fuse. Copies files and writes the manifest; needs neither onnx nor torch."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from tracker.core.bundle import bundle_writer, sha256
from tracker.core.errors import UserError
from tracker.core.manifest import Manifest
from tracker.runtime.detector import DetectorSpec, bundle_with_detector
from tracker.runtime.fusion import Fusion, member_artefacts, member_file, member_problem


def fuse_detectors(model_dir, others, out_dir=None, score_thresh: float = Fusion.score_thresh,
                   iou: float = Fusion.iou, floor: float = Fusion.floor, log=print,
                   command: str | None = None) -> Manifest:
    """Write ``out_dir`` (default: ``model_dir`` in place): ``model_dir``'s bundle whose detector
    also runs the detectors of the bundles ``others`` (same objects and kind of box) and fuses
    their detections: ``score_thresh`` the fused run-time threshold, ``iou`` the overlap that
    joins a cluster, ``floor`` each network's lowest candidate score."""
    others = list(others or [])
    if not others:
        raise UserError("nothing to fuse: name the bundles whose detectors join with --from")
    settings = Fusion(members=[], iou=iou, floor=floor, score_thresh=score_thresh)
    if problem := settings.problem(lambda key: "--" + key.replace("_", "-")):
        raise UserError(problem)
    src = bundle_with_detector(model_dir)
    d0 = src.manifest.detector
    if "fusion" in d0:
        raise UserError(f"{model_dir}: its detector fuses several networks already; fuse from a bundle with one")
    spec0 = DetectorSpec.from_dict(d0)
    members = []
    for k, o in enumerate(others, start=1):
        b = bundle_with_detector(o)
        d = b.manifest.detector
        if "fusion" in d:
            raise UserError(f"{o}: its detector fuses several networks already; name the bundles it was fused from")
        if problem := member_problem(spec0, DetectorSpec.from_dict(d)):
            raise UserError(f"{o}: its detector cannot fuse with {model_dir}'s: {problem}")
        members.append((b, {**d, "file": member_file(k), "from": {"bundle": str(o), "detector_sha256":
                                                                  sha256(b.path("detector"))}}))
    settings.members = [m for _, m in members]
    fusion = settings.to_dict()
    fusion.update(command=command or "app.py " + " ".join(sys.argv[1:]), created=time.strftime("%Y-%m-%d %H:%M:%S"))
    out = Path(out_dir) if out_dir else src.root
    with bundle_writer(src, out) as w:
        w.manifest.name = out.name
        w.manifest.detector = {**d0, "fusion": fusion}
        for b, m in members:
            (w.folder / m["file"]).write_bytes(b.path("detector").read_bytes())
        w.manifest.artefacts.update(member_artefacts(w.manifest.detector))
    log(f"bundle {out}: its detector fuses {1 + len(members)} networks (run-time threshold {score_thresh}, "
        f"clusters at IoU {iou}, candidates from {floor})")
    return w.manifest
