"""Head sets kept one by one in the work folder while ``train`` or ``build`` fits them, so that an
interruption (Ctrl-C, SIGTERM, a session's end) loses at most the set in flight: a rerun on the
same codes and options loads the sets fitted before. A set is keyed by the latent codes, the
crops' objects, poses, boxes and cameras, the training/validation split, the fitting options and
its seed; its files are read with JSON and numpy ``allow_pickle=False`` (no code runs)."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from tracker.core.files import write_whole
from tracker.runtime.heads import load_codebook, load_head, save_codebook, save_head


class HeadSetCache:
    def __init__(self, folder, mu, cs, tr, va, obj_ids, options: dict):
        self.folder = Path(folder)
        h = hashlib.sha1()
        for a in (mu, cs.obj_id, cs.R, cs.t, cs.box, cs.K, tr, va):
            a = np.ascontiguousarray(a)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
        h.update(json.dumps([[int(o) for o in obj_ids], options], sort_keys=True, default=str).encode())
        self._base = h.hexdigest()

    def _stem(self, seed: int) -> Path:
        return self.folder / hashlib.sha1(f"{self._base}:{int(seed)}".encode()).hexdigest()[:16]

    def load(self, seed: int):
        """``(head, codebook, distance info, validation)`` of the set fitted before with ``seed``,
        or None (never fitted, or its files are incomplete or unreadable)."""
        s = self._stem(seed)
        info = s.with_suffix(".info.json")
        if not info.is_file():  # written last: the set's files are whole
            return None
        try:
            meta = json.loads(info.read_text())
            head = load_head(s.with_suffix(".head.json"), s.with_suffix(".head.npz"))
            codebook = load_codebook(s.with_suffix(".codebook.npz"))
        except (OSError, ValueError, KeyError):
            return None
        return head, codebook, meta["dist_info"], meta["validation"]

    def save(self, seed: int, head, codebook, dist_info, val) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        s = self._stem(seed)
        save_head(head, s.with_suffix(".head.json"), s.with_suffix(".head.npz"))
        save_codebook(codebook, s.with_suffix(".codebook.npz"))
        info = json.dumps({"seed": int(seed), "dist_info": dist_info, "validation": val},
                          default=lambda x: x.item() if hasattr(x, "item") else str(x))
        write_whole(s.with_suffix(".info.json"), lambda tmp: tmp.write_text(info))
