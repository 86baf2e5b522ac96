"""Light overlay meshes: each object's mesh decimated (quadric error) for the live overlay and
the rerun 3D view. The CPU rasteriser's cost grows with the triangle count: 8 LM-O objects at
320x240 took 71 ms with the full meshes (8-32 k faces each) and 17 ms at 1,500 faces.

``synth`` renders its objects decimated too (by default, at 4,000 faces). Decimation needs
``fast_simplification`` (a runtime dependency since synth's default uses it); the bundle stores
the overlay meshes, so tracking only reads PLY files."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from tracker.core.defaults import SYNTH_FACES  # noqa: F401  (synth's and build's default face count, stop 47)
from tracker.core.errors import UserError

# part of the cache's key: raise it when _decimate's result changes (not only the library's version)
CACHE_VERSION = 1


def decimate_mesh(mesh, faces: int, cache: bool = False):
    """Quadric decimation to about ``faces`` triangles, vertex colours carried over from the
    nearest original vertex. ``cache``: keep the result in ``cache_dir()/decimated_<sha>.npz``,
    keyed by the mesh's arrays, ``faces`` and fast_simplification's version (synth: every render
    worker of every run decimates every object, 0.25 s for LM-O's 8; a cached result is read in
    milliseconds). A missing, damaged or unwritable cache only costs the decimation."""
    if len(mesh.faces) <= faces:
        return mesh.copy()
    path = _cache_path(mesh, faces) if cache else None
    if path is not None:
        try:
            return _read(path)
        except Exception:  # no entry, or a damaged one (any error of a half-written zip): decimate
            pass
    small = _decimate(mesh, faces)
    if path is not None:
        _write(path, small)
    return small


def _decimate(mesh, faces: int):
    import trimesh
    from scipy.spatial import cKDTree
    try:
        small = mesh.simplify_quadric_decimation(face_count=faces)
    except ImportError:
        raise UserError("mesh decimation needs fast_simplification: pip install -e . (or synth --mesh-faces 0 "
                        "for the full meshes)") from None
    colours = getattr(mesh.visual, "vertex_colors", None)
    if colours is not None and len(colours) == len(mesh.vertices):
        _, j = cKDTree(np.asarray(mesh.vertices)).query(np.asarray(small.vertices))
        small.visual = trimesh.visual.ColorVisuals(small, vertex_colors=np.asarray(colours)[j])
    return small


def _cache_path(mesh, faces: int) -> Path | None:
    from importlib.metadata import PackageNotFoundError, version
    from tracker.core.paths import cache_dir
    try:
        v = version("fast_simplification")
    except PackageNotFoundError:
        return None  # decimating says what to install
    h = hashlib.sha256(f"{CACHE_VERSION} {faces} {v}".encode())
    for a in (mesh.vertices, mesh.faces, getattr(mesh.visual, "vertex_colors", np.zeros(0))):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str} {a.shape}".encode())
        h.update(a.tobytes())
    return cache_dir() / f"decimated_{h.hexdigest()[:24]}.npz"


def _read(path: Path):
    from tracker.core.meshes import read_cached_mesh
    return read_cached_mesh(path)


def _write(path: Path, small) -> None:
    from tracker.core.meshes import write_cached_mesh
    write_cached_mesh(path, small)


def add_overlay_meshes(bundle_dir, faces: int = 1500, log=print) -> dict[int, str]:
    """Write ``meshes/overlay/obj_NNNNNN.ply`` for every object of a bundle and list them in
    its manifest (``overlay_mesh`` per object), re-hashing the bundle."""
    from tracker.core.bundle import update_manifest
    from tracker.core.meshes import load_mesh
    root = Path(bundle_dir)
    out = {}

    def change(manifest, folder):  # runs once the bundle is verified, on a staged copy of it
        (folder / "meshes" / "overlay").mkdir(parents=True, exist_ok=True)
        for o in manifest.objects:
            m = load_mesh(folder / o.mesh, o.id).mesh
            small = decimate_mesh(m, faces)
            rel = f"meshes/overlay/obj_{o.id:06d}.ply"
            small.export(folder / rel)
            out[o.id] = rel
            o.overlay_mesh = rel
            log(f"{o.name or o.id}: {len(m.faces)} -> {len(small.faces)} faces")
        manifest.extra["overlay_faces"] = faces
    update_manifest(root, change)
    return out

