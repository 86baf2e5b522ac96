"""``app.py join-heads``: one bundle whose pose head averages the head sets of several bundles
that share its encoder (:class:`tracker.regressors.HeadEnsemble`). No torch: the members are
fitted already (``train``, ``refit-heads``)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from .bop import load_models_info, symmetry_rotations
from .bundle import manifest_fields, open_bundle, read_verified_manifest, staged_bundle, write_manifest
from .errors import UserError
from .regressors import HeadEnsemble, PoseHead


def _origin(path, manifest: dict) -> dict:
    """Where a member's head set came from: its bundle and the command that fitted it."""
    heads = manifest.get("heads", {})
    if "ensemble" in heads:
        return {"bundle": str(path), "ensemble": heads["ensemble"]}
    return {"bundle": str(path), "command": heads.get("command", manifest.get("command")),
            "jitter_scale": heads.get("jitter_scale"), "seed": heads.get("seed")}


def join_heads(model_dir, others, out_dir=None, log=print, command: str | None = None) -> dict:
    """Write ``out_dir`` (default: ``model_dir`` in place): ``model_dir``'s bundle with a pose head
    that averages its own head set and those of ``others``. Every bundle must have the very same
    encoder (by SHA-256) and objects; the codebook, detector and meshes stay ``model_dir``'s."""
    src = open_bundle(model_dir)
    enc = src.manifest["artefacts"]["encoder"]
    enc_sha = src.manifest["files"][enc]["sha256"]
    heads, names = [src.load_joblib("pose_head", PoseHead)], [_origin(model_dir, src.manifest)]
    for o in others:
        b = open_bundle(o)
        if b.manifest["files"].get(b.manifest["artefacts"]["encoder"], {}).get("sha256") != enc_sha:
            raise UserError(f"{o}: its encoder is not {model_dir}'s (SHA-256 differs); only heads fitted on the "
                            "same encoder can be averaged (make them with 'app.py refit-heads --model "
                            f"{model_dir} --out DIR')")
        heads.append(b.load_joblib("pose_head", PoseHead))
        names.append(_origin(o, b.manifest))
    info = load_models_info(src.path("models_info"))
    obj_ids = heads[0].obj_ids
    missing = [o for o in obj_ids if o not in info]
    if missing:
        raise UserError(f"{model_dir}: its models_info lacks object(s) {missing}")
    syms = {o: symmetry_rotations(info[o]) for o in obj_ids}
    ensemble = HeadEnsemble(heads, syms)
    out = Path(out_dir) if out_dir else src.root
    import joblib
    m = manifest_fields(src.manifest)
    m["name"] = out.name
    m["heads"] = {**src.manifest.get("heads", {}),
                  "ensemble": {"members": len(ensemble.members), "from": names,
                               "note": "validation_synthetic is the first member's",
                               "command": command or "app.py " + " ".join(sys.argv[1:]),
                               "created": time.strftime("%Y-%m-%d %H:%M:%S")}}
    with staged_bundle(src.root, out) as stage:
        joblib.dump(ensemble, stage / src.manifest["artefacts"]["pose_head"], compress=3)
        write_manifest(stage, m)
    manifest = read_verified_manifest(out)
    log(f"bundle {out}: a pose head averaging {len(ensemble.members)} head sets")
    return manifest
