"""Model bundles: ``models/NAME/`` with ``manifest.json`` naming every file and its SHA-256.

Loading checks every hash *before* anything is unpickled (joblib files can run code) or
handed to onnxruntime, and refuses a bundle with a missing, extra-listed or altered file.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from .bop import positive_number
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
        if not isinstance(files, dict) or not all(isinstance(m, dict) for m in files.values()):
            raise TypeError
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError):
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

    def load_joblib(self, key: str, expected: type | None = None):
        """Unpickle an artefact (its hash was verified when the bundle was opened); with
        ``expected``, refuse anything that is not an instance of it."""
        import joblib
        path = self.path(key)
        try:
            obj = joblib.load(path)
        except Exception as e:
            raise UserError(f"{path}: unreadable {key} ({e.__class__.__name__}); the bundle was "
                            f"built broken: rebuild it") from None
        if expected is not None and not isinstance(obj, expected):
            raise UserError(f"{path}: holds a {type(obj).__name__}, not a {expected.__name__}; "
                            f"the bundle was built broken: rebuild it")
        return obj

    @property
    def objects(self) -> list[dict]:
        return self.manifest["objects"]

    @property
    def manifest_sha256(self) -> str:
        """The manifest's hash: it names every file's hash, so it stands for the whole bundle."""
        return sha256(self.root / MANIFEST)


@contextlib.contextmanager
def staged_bundle(src_root, out):
    """Where a job writes a changed bundle: yields a copy of the bundle at ``src_root`` in a
    staging folder beside ``out``; when the block ends without error that folder takes ``out``'s
    place (``out`` may be ``src_root``: in place). An interrupted job (Ctrl-C, a crash, a refusal)
    leaves ``out`` as it was and no staging folder behind."""
    src_root, out = Path(src_root), Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        shutil.copytree(src_root, stage, dirs_exist_ok=True)
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    old = stage.with_name(stage.name + ".old")
    if out.exists():
        out.rename(old)
    stage.rename(out)
    shutil.rmtree(old, ignore_errors=True)


def manifest_fields(manifest: dict) -> dict:
    """A manifest without what :func:`write_manifest` derives (the files' hashes, the format):
    what a job that changes a bundle edits and writes back."""
    return {k: v for k, v in manifest.items() if k not in ("files", "format")}


def update_manifest(bundle_dir, change) -> dict:
    """Verify a bundle, let ``change(manifest)`` edit its manifest (files already written into
    the folder), then re-hash every file. Returns the new manifest."""
    b = open_bundle(bundle_dir)
    manifest = manifest_fields(b.manifest)
    change(manifest)
    write_manifest(b.root, manifest)
    return read_verified_manifest(b.root)


def check_manifest(manifest: dict, where) -> None:
    """The keys that every reader of a bundle relies on, with their types."""
    def bad(what):
        raise UserError(f"{where}: malformed manifest ({what}); rebuild the bundle")
    objs = manifest.get("objects")
    if not isinstance(objs, list) or not objs:
        bad("no 'objects' list")
    for o in objs:
        if not isinstance(o, dict):
            bad("an object entry is not a mapping")
        for key, kind in (("id", int), ("mesh", str), ("diameter", (int, float))):
            if not isinstance(o.get(key), kind) or isinstance(o.get(key), bool):
                bad(f"object {o.get('id', '?')}: '{key}' missing or not a {getattr(kind, '__name__', 'number')}")
        if not positive_number(o["diameter"]):
            bad(f"object {o['id']}: 'diameter' must be positive (mm), not {o['diameter']}")
    for key in ("detector", "heads"):
        if key in manifest and not isinstance(manifest[key], dict):
            bad(f"'{key}' is not a mapping")
    if isinstance(manifest.get("detector"), dict) and not isinstance(manifest["detector"].get("classes"), list):
        bad("the detector's 'classes' list is missing")
    for key in ("input_size", "latent_size"):
        v = manifest.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            bad(f"'{key}' missing or not a positive integer")


def open_bundle(bundle_dir) -> Bundle:
    d = Path(bundle_dir)
    manifest = read_verified_manifest(d)
    check_manifest(manifest, d)
    return Bundle(d, manifest)
