"""``app.py lab join-heads``: one bundle whose pose head averages the head sets of several bundles
that share its encoder (:class:`tracker.runtime.heads.HeadEnsemble`). No torch: the members are
fitted already (``train``, ``refit-heads``)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from tracker.core.bop import load_models_info, symmetry_rotations
from tracker.core.bundle import bundle_writer, open_bundle
from tracker.core.errors import UserError
from tracker.core.manifest import Manifest
from tracker.runtime.heads import HeadEnsemble, load_bundle_head, save_head


def _origin(path, manifest) -> dict:
    """Where a member's head set came from: its bundle and the command that fitted it."""
    heads = manifest.heads
    if "ensemble" in heads:
        return {"bundle": str(path), "ensemble": heads["ensemble"]}
    return {"bundle": str(path), "command": heads.get("command", manifest.command),
            "jitter_scale": heads.get("jitter_scale"), "seed": heads.get("seed")}


def join_heads(model_dir, others, out_dir=None, log=print, command: str | None = None) -> Manifest:
    """Write ``out_dir`` (default: ``model_dir`` in place): ``model_dir``'s bundle with a pose head
    that averages its own head set and those of ``others``. Every bundle must have the very same
    encoder (by SHA-256) and objects; the codebook, detector and meshes stay ``model_dir``'s."""
    src = open_bundle(model_dir)
    enc_sha = src.manifest.file_sha256("encoder")
    heads, names = [load_bundle_head(src)], [_origin(model_dir, src.manifest)]
    for o in others:
        b = open_bundle(o)
        if b.manifest.file_sha256("encoder") != enc_sha:
            raise UserError(f"{o}: its encoder is not {model_dir}'s (SHA-256 differs); only heads fitted on the "
                            "same encoder can be averaged (make them with 'app.py lab refit-heads --model "
                            f"{model_dir} --out DIR')")
        heads.append(load_bundle_head(b))
        names.append(_origin(o, b.manifest))
    info = load_models_info(src.path("models_info"))
    obj_ids = heads[0].obj_ids
    missing = [o for o in obj_ids if o not in info]
    if missing:
        raise UserError(f"{model_dir}: its models_info lacks object(s) {missing}")
    syms = {o: symmetry_rotations(info[o]) for o in obj_ids}
    ensemble = HeadEnsemble(heads, syms)
    out = Path(out_dir) if out_dir else src.root
    with bundle_writer(src, out) as w:
        m = w.manifest
        m.name = out.name
        m.heads = {**src.manifest.heads,
                   "ensemble": {"members": len(ensemble.members), "from": names,
                                "note": "validation_synthetic is the first member's",
                                "command": command or "app.py " + " ".join(sys.argv[1:]),
                                "created": time.strftime("%Y-%m-%d %H:%M:%S")}}
        save_head(ensemble, w.folder / m.artefacts["pose_head"], w.folder / m.artefacts["pose_head_arrays"])
    log(f"bundle {out}: a pose head averaging {len(ensemble.members)} head sets")
    return w.manifest
