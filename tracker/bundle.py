"""Model bundles: ``models/NAME/`` with ``manifest.json`` naming every file and its SHA-256.

Loading checks every hash *before* anything is unpickled (joblib files can run code) or
handed to onnxruntime, and refuses a bundle with a missing, extra-listed or altered file.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from .errors import UserError

MANIFEST = "manifest.json"
FORMAT = 1


def sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_manifest(bundle_dir, info: dict) -> Path:
    """Hash every file of the bundle (but the manifest) into ``manifest.json``."""
    d = Path(bundle_dir)
    files = sorted(p for p in d.rglob("*") if p.is_file() and p.name != MANIFEST)
    manifest = dict(info)
    manifest["format"] = FORMAT
    manifest["files"] = {str(p.relative_to(d)): {"sha256": sha256(p), "bytes": p.stat().st_size} for p in files}
    (d / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return d / MANIFEST


def read_verified_manifest(bundle_dir) -> dict:
    d = Path(bundle_dir)
    mpath = d / MANIFEST
    if not d.is_dir():
        raise UserError(f"model bundle not found: {d}")
    if not mpath.is_file():
        raise UserError(f"{d}: not a model bundle (no {MANIFEST})")
    try:
        manifest = json.loads(mpath.read_text())
        files = manifest["files"]
    except (json.JSONDecodeError, KeyError, TypeError):
        raise UserError(f"{mpath}: unreadable manifest") from None
    for rel, meta in files.items():
        p = d / rel
        if not p.resolve().is_relative_to(d.resolve()):
            raise UserError(f"{mpath}: file '{rel}' points outside the bundle")
        if not p.is_file():
            raise UserError(f"{d}: file '{rel}' listed in the manifest is missing")
        if sha256(p) != meta.get("sha256"):
            raise UserError(f"{d}: '{rel}' does not match its SHA-256 in the manifest "
                            f"(altered or corrupt); refusing to load the bundle")
    return manifest


@dataclass
class Bundle:
    root: Path
    manifest: dict

    def path(self, key: str) -> Path:
        rel = self.manifest.get("artefacts", {}).get(key)
        if rel is None:
            raise UserError(f"{self.root}: the manifest names no '{key}' artefact")
        if rel not in self.manifest["files"]:
            raise UserError(f"{self.root}: artefact '{rel}' is not hashed in the manifest; refusing it")
        return self.root / rel

    def load_joblib(self, key: str):
        import joblib
        return joblib.load(self.path(key))  # hashes were verified when the bundle was opened

    @property
    def objects(self) -> list[dict]:
        return self.manifest["objects"]


def update_manifest(bundle_dir, change) -> dict:
    """Verify a bundle, let ``change(manifest)`` edit its manifest (files already written into
    the folder), then re-hash every file. Returns the new manifest."""
    b = open_bundle(bundle_dir)
    manifest = {k: v for k, v in b.manifest.items() if k not in ("files", "format")}
    change(manifest)
    write_manifest(b.root, manifest)
    return read_verified_manifest(b.root)


def open_bundle(bundle_dir) -> Bundle:
    d = Path(bundle_dir)
    return Bundle(d, read_verified_manifest(d))
