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
from dataclasses import dataclass
from pathlib import Path

from tracker.core.errors import UserError
from tracker.core.manifest import FORMAT, MANIFEST, Manifest


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
    """The folder swap under :func:`bundle_writer` (jobs use that: it also hashes and verifies the
    manifest). Where a job writes a changed bundle: yields a copy of the bundle at ``src_root`` (None: an
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
    moved = False
    try:  # two renames: a signal between them puts the old bundle back
        if out.exists():
            out.rename(old)
            moved = True
        stage.rename(out)
    except BaseException:
        if moved and not out.exists():
            old.rename(out)
        shutil.rmtree(stage, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)


class BundleWriter:
    """What :func:`bundle_writer` yields: ``folder``, the staged copy of the bundle to write files
    into, and ``manifest``, the manifest to write there when the block ends (a copy of the source
    bundle's to edit or replace; None for a new bundle until the caller sets it). After the block,
    ``manifest`` is the bundle's verified manifest."""

    def __init__(self, folder: Path, manifest: Manifest | None):
        self.folder = folder
        self.manifest = manifest

    def apply(self, step) -> None:
        """Run ``step(folder)``, a job that opens the staged copy as a bundle and changes it with
        its own staged write (:func:`update_manifest`, e.g.
        :func:`tracker.training.decimate.add_overlay_meshes`): ``manifest`` is hashed into the copy
        first and read back, verified, after."""
        write_manifest(self.folder, self.manifest)
        step(self.folder)
        self.manifest = read_verified_manifest(self.folder)


@contextlib.contextmanager
def bundle_writer(src, out=None):
    """The one way to write a bundle: yields a :class:`BundleWriter` on a staged copy of ``src`` (a
    :class:`Bundle`; a bundle folder, verified first; None: an empty folder for a new bundle at
    ``out``); the caller writes files into ``writer.folder`` and edits (or sets)
    ``writer.manifest``. When the block ends without error, the manifest is written with every
    file's SHA-256 (:func:`write_manifest`), the staged bundle is verified
    (:func:`read_verified_manifest`) and it takes ``out``'s place (default: ``src``'s folder, in
    place); ``writer.manifest`` is then the verified manifest. Anything that stops it before (an
    error, Ctrl-C, a file that fails its hash) leaves ``out`` as it was and no staging folder
    behind (:func:`staged_bundle`)."""
    if src is not None and not isinstance(src, Bundle):
        src = open_bundle(src)
    if out is None:
        if src is None:
            raise ValueError("bundle_writer: a new bundle (src None) needs out")
        out = src.root
    with staged_bundle(None if src is None else src.root, out) as stage:
        writer = BundleWriter(stage, None if src is None else src.manifest.copy())
        yield writer
        if writer.manifest is None:
            raise ValueError("bundle_writer: no manifest was set for the new bundle")
        write_manifest(stage, writer.manifest)
        verified = read_verified_manifest(stage)
    writer.manifest = verified


def update_manifest(bundle_dir, change) -> Manifest:
    """Verify a bundle, then change it in place through :func:`bundle_writer`:
    ``change(manifest, folder)`` edits a copy of the manifest and writes its files into ``folder``
    (a staged copy of the bundle), which is re-hashed, verified and takes the bundle's place only
    when all of it went well (an interrupted change leaves the bundle as it was). Returns the new
    manifest."""
    with bundle_writer(bundle_dir) as w:
        change(w.manifest, w.folder)
    return w.manifest


def open_bundle(bundle_dir) -> Bundle:
    d = Path(bundle_dir)
    return Bundle(d, read_verified_manifest(d))
