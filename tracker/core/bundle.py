"""Model bundles: ``models/NAME/`` with ``manifest.json`` naming every file and its SHA-256.

Loading checks every hash *before* any file is read or handed to onnxruntime, and refuses a
bundle with a missing, extra-listed or altered file. Nothing in a bundle is a pickle: the pose
head is JSON + ``.npz`` read with ``allow_pickle=False``, so loading one cannot run code.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import tempfile
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

from tracker.core.errors import UserError
from tracker.core.manifest import FORMAT, MANIFEST, Manifest

# what reading a malformed pose head or codebook can raise (numpy, zipfile, zlib, JSON)
_UNREADABLE = (ValueError, KeyError, TypeError, OSError, AttributeError, IndexError, EOFError, zipfile.BadZipFile,
               zlib.error)


def sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_manifest(bundle_dir, manifest: Manifest) -> Manifest:
    """The one writer: hash every file of the bundle (but the manifest) into ``manifest.json``."""
    d = Path(bundle_dir)
    files = sorted(p for p in d.rglob("*") if p.is_file() and p.name != MANIFEST)
    manifest = manifest.copy()
    manifest.format = FORMAT
    manifest.files = {str(p.relative_to(d)): {"sha256": sha256(p), "bytes": p.stat().st_size} for p in files}
    (d / MANIFEST).write_text(json.dumps(manifest.to_dict(), indent=1))
    return manifest


def read_verified_manifest(bundle_dir) -> Manifest:
    """The one reader: ``manifest.json`` parsed and checked, every file it lists verified."""
    d = Path(bundle_dir)
    mpath = d / MANIFEST
    if not d.is_dir():
        raise UserError(f"model bundle not found: {d}")
    if not mpath.is_file():
        raise UserError(f"{d}: not a model bundle (no {MANIFEST})")
    try:
        raw = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise UserError(f"{mpath}: unreadable manifest") from None
    manifest = Manifest.from_dict(raw, mpath)
    for rel, meta in manifest.files.items():
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
    manifest: Manifest

    def path(self, key: str) -> Path:
        rel = self.manifest.artefacts.get(key)
        if rel is None:
            raise UserError(f"{self.root}: the manifest names no '{key}' artefact")
        if rel not in self.manifest.files:
            raise UserError(f"{self.root}: artefact '{rel}' is not hashed in the manifest; refusing it")
        return self.root / rel

    def load_head(self):
        """The pose head (:mod:`tracker.runtime.heads`): JSON + arrays, no pickles."""
        from tracker.runtime.heads import load_head
        spec, arrays = self.path("pose_head"), self.path("pose_head_arrays")
        try:
            return load_head(spec, arrays)
        except _UNREADABLE as e:
            raise UserError(f"{spec}: unreadable pose head ({e.__class__.__name__}: {str(e)[:100]}); the bundle "
                            f"was built broken: rebuild it") from None

    def load_codebook(self):
        """The AAE codebook (``eval --mode aae``)."""
        from tracker.runtime.heads import load_codebook
        path = self.path("codebook")
        try:
            return load_codebook(path)
        except _UNREADABLE as e:
            raise UserError(f"{path}: unreadable codebook ({e.__class__.__name__}: {str(e)[:100]}); the bundle "
                            f"was built broken: rebuild it") from None

    def overlay_mesh_path(self, obj) -> Path:
        """The light mesh of an object when the bundle has one, else its full mesh."""
        return self.root / (obj.overlay_mesh or obj.mesh)

    @property
    def objects(self):
        return self.manifest.objects

    @property
    def manifest_sha256(self) -> str:
        """The manifest's hash: it names every file's hash, so it stands for the whole bundle."""
        return sha256(self.root / MANIFEST)


@contextlib.contextmanager
def staged_bundle(src_root, out):
    """Where a job writes a changed bundle: yields a copy of the bundle at ``src_root`` (None: an
    empty folder, for a new bundle) in a staging folder beside ``out``; when the block ends without
    error that folder takes ``out``'s place (``out`` may be ``src_root``: in place). An interrupted
    job (Ctrl-C, a crash, a refusal) leaves ``out`` as it was and no staging folder behind."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        if src_root is not None:
            shutil.copytree(Path(src_root), stage, dirs_exist_ok=True)
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    old = stage.with_name(stage.name + ".old")
    if out.exists():
        out.rename(old)
    stage.rename(out)
    shutil.rmtree(old, ignore_errors=True)


def update_manifest(bundle_dir, change) -> Manifest:
    """Verify a bundle, then change it through :func:`staged_bundle`: ``change(manifest, folder)``
    edits a copy of the manifest and writes its files into ``folder`` (a staged copy of the
    bundle), which is re-hashed and takes the bundle's place only when all of it went well (an
    interrupted change leaves the bundle as it was). Returns the new manifest."""
    b = open_bundle(bundle_dir)
    with staged_bundle(b.root, b.root) as stage:
        manifest = b.manifest.copy()
        change(manifest, stage)
        write_manifest(stage, manifest)
    return read_verified_manifest(b.root)


def open_bundle(bundle_dir) -> Bundle:
    d = Path(bundle_dir)
    return Bundle(d, read_verified_manifest(d))
