"""``app.py lab join-splits``: one training split made of several ``synth`` splits.

The scenes of every split are linked (not copied) into the new folder under consecutive
numbers, in the order given, so training reads them one after the other; the splits must
agree on what a bundle records of its data (meshes, objects, camera, pose prior)."""
from __future__ import annotations

import json
import time
from pathlib import Path

from tracker.core.bop import load_scene
from tracker.training.crops import split_scene_dirs
from tracker.core.errors import UserError

MUST_AGREE = ("models_dir", "obj_ids", "prior", "width", "height", "K")


def join_splits(out_dir, splits, command: str | None = None) -> dict:
    """Link the scenes of ``splits`` into ``out_dir`` and write its ``synth_config.json``
    (the first split's settings, plus every split's own). Returns that config."""
    out = Path(out_dir)
    if len(splits) < 2:
        raise UserError("join-splits needs two or more splits")
    metas = []
    for s in splits:
        p = Path(s) / "synth_config.json"
        if not p.is_file():
            raise UserError(f"{s}: no synth_config.json (not a 'synth' split)")
        try:
            metas.append(json.loads(p.read_text()))
            metas[-1]["config"]["obj_ids"]
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError):
            raise UserError(f"{p}: unreadable (not written by 'app.py synth')") from None
    for s, m in zip(splits[1:], metas[1:]):
        differ = [k for k in MUST_AGREE if m["config"].get(k) != metas[0]["config"].get(k)]
        if differ:
            raise UserError(f"{s} and {splits[0]} differ in {', '.join(differ)}: they cannot train one bundle")
    _check_disjoint(splits, metas)
    scenes = [d.resolve() for s in splits for d in split_scene_dirs(s)]
    if out.exists() and any(out.iterdir()):
        raise UserError(f"{out} exists and is not empty; choose a new folder")
    for d in scenes:  # every scene must load (annotations readable, an image for each), before linking any
        load_scene(d, require_gt=True)
    out.mkdir(parents=True, exist_ok=True)
    for i, d in enumerate(scenes):
        (out / f"{i:06d}").symlink_to(d, target_is_directory=True)
    meta = {"config": metas[0]["config"], "scenes": len(scenes),
            "joined": [{"split": str(Path(s).resolve()), "command": m.get("command"), "config": m["config"],
                        "images_written": m.get("images_written", m.get("images"))} for s, m in zip(splits, metas)],
            "images_written": sum(int(m.get("images_written", m.get("images", 0))) for m in metas),
            "command": command, "created": time.strftime("%Y-%m-%d %H:%M:%S")}
    (out / "synth_config.json").write_text(json.dumps(meta, indent=1))
    return meta


def _check_disjoint(splits, metas) -> None:
    """Splits made with the same settings and seed hold the same images unless they are
    disjoint shards of one split (``synth --shard K/N``): refuse images twice."""
    seen: dict[str, list] = {}
    for s, m in zip(splits, metas):
        key = json.dumps(m["config"], sort_keys=True)
        first = int(m.get("first_image", 0))
        span = (first, first + int(m.get("images", 0)))
        for other, (a, b) in seen.get(key, []):
            if span[0] < b and a < span[1]:
                raise UserError(f"{s} and {other} were made with the same settings and seed and share images "
                                f"{max(a, span[0])}-{min(b, span[1]) - 1}: join different seeds, or disjoint "
                                f"shards of one split (synth --shard K/N)")
        seen.setdefault(key, []).append((s, span))
