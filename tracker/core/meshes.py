"""Object meshes: loading, and BOP ``models_info`` (diameter, bounding box, symmetries)."""
from __future__ import annotations

import hashlib
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, cKDTree
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from tracker.core.errors import UserError

GREY = np.array([160, 160, 160, 255], dtype=np.uint8)
MODEL_RE = re.compile(r"^obj_(\d{6})\.ply$")
# A 180-degree turn is taken as a symmetry when, after rigid refinement, every vertex of
# the turned model lies within this fraction of the diameter of the model. Measured on the
# 8 LM-O models: eggbox 0.055 and glue 0.051, nearest non-symmetric case 0.080
# (holepuncher about x), the others 0.12 and above.
SYMMETRY_HAUSDORFF = 0.065


@dataclass
class ObjectModel:
    obj_id: int
    path: Path
    mesh: trimesh.Trimesh
    has_colours: bool

    @property
    def vertices(self) -> np.ndarray:
        return np.asarray(self.mesh.vertices, dtype=np.float64)


def read_mesh(path) -> trimesh.Trimesh:
    """Any mesh file trimesh reads (a scene's meshes joined), checked: triangles, finite vertices."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"mesh not found: {path}")
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # trimesh raises many types for garbled files
        raise UserError(f"{path}: unreadable mesh ({e.__class__.__name__}: {str(e)[:80]})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) < 4 or len(mesh.faces) < 1:
        raise UserError(f"{path}: mesh has no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise UserError(f"{path}: mesh has non-finite vertices")
    faces = np.asarray(mesh.faces)
    bad = faces[(faces < 0) | (faces >= len(mesh.vertices))]
    if bad.size:
        raise UserError(f"{path}: a face names vertex {int(bad[0])} of {len(mesh.vertices)} (a broken file)")
    if not np.isfinite(mesh.area) or mesh.area <= 0:
        raise UserError(f"{path}: the mesh's triangles have no area (all its points on a line or at one place)")
    return mesh


def _cached_read(path: Path) -> trimesh.Trimesh:
    """:func:`read_mesh` for a BOP model (geometry and vertex colours; a textured mesh is never
    cached), through a cache
    of the parsed arrays keyed by the file's contents (``cache_dir()/mesh_<sha>.npz``): an
    ASCII PLY of LM-O takes about 0.15 s to parse, its cached arrays a few milliseconds, and
    every render worker loads every model. A missing, unreadable or unwritable cache only
    costs the parse."""
    from tracker.core.paths import cache_dir
    try:
        data = path.read_bytes()
    except OSError as e:
        raise UserError(f"{path}: unreadable mesh ({e.strerror})") from None
    cached = cache_dir() / f"mesh_{hashlib.sha256(data).hexdigest()[:24]}.npz"
    try:
        return read_cached_mesh(cached)
    except Exception:  # no entry, or a damaged one (any error of a half-written zip): parse
        pass
    mesh = read_mesh(path)
    if getattr(mesh.visual, "kind", None) in ("vertex", None):  # a texture or face colours: not cached
        write_cached_mesh(cached, mesh)
    return mesh


def read_cached_mesh(path: Path):
    """A mesh (vertices, faces, vertex colours) from a cache entry :func:`write_cached_mesh`
    wrote; raises on a missing or damaged entry."""
    with np.load(path, allow_pickle=False) as z:
        mesh = trimesh.Trimesh(z["vertices"], z["faces"], process=False)
        if "colours" in z.files:
            mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=z["colours"])
        return mesh


def write_cached_mesh(path: Path, mesh) -> None:
    """Store a mesh's vertices, faces and vertex colours as a cache entry (:func:`_save_cache_entry`)."""
    arrays = {"vertices": np.asarray(mesh.vertices, np.float64), "faces": np.asarray(mesh.faces, np.int64)}
    if getattr(mesh.visual, "kind", None) == "vertex":
        arrays["colours"] = np.asarray(mesh.visual.vertex_colors, np.uint8)
    _save_cache_entry(path, arrays)


def _save_cache_entry(path: Path, arrays: dict) -> None:
    """``arrays`` as the .npz cache entry ``path``, atomically (parallel workers never read half
    a file); an unwritable cache is skipped."""
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)


def load_mesh(path, obj_id: int | None = None) -> ObjectModel:
    """Load a PLY/OBJ mesh in millimetres; meshes without colours get a grey default.
    PLY files go through a cache of their parsed arrays (:func:`_cached_read`)."""
    path = Path(path)
    mesh = _cached_read(path) if path.suffix.lower() == ".ply" and path.is_file() else read_mesh(path)
    has_colours = getattr(mesh.visual, "kind", None) == "vertex"
    if not has_colours:
        warnings.warn(f"{path.name}: no vertex colours, rendering it grey", stacklevel=2)
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile(GREY, (len(mesh.vertices), 1)))
    if obj_id is None:
        m = MODEL_RE.match(path.name)
        obj_id = int(m.group(1)) if m else 0
    return ObjectModel(obj_id, path, mesh, has_colours)


def model_files(models_dir) -> dict[int, Path]:
    """{obj_id: path} of the ``obj_NNNNNN.ply`` in a folder ({} for a missing folder)."""
    d = Path(models_dir)
    if not d.is_dir():
        return {}
    found = {int(MODEL_RE.match(p.name).group(1)): p for p in sorted(d.iterdir()) if MODEL_RE.match(p.name)}
    if 0 in found:
        raise UserError(f"{found[0]}: object ids start at 1 (BOP); rename it (obj_000001.ply, ...)")
    return found


def load_models(models_dir, obj_ids=None) -> dict[int, ObjectModel]:
    """All ``obj_NNNNNN.ply`` of a BOP models folder (or just ``obj_ids``)."""
    d = Path(models_dir)
    if not d.is_dir():
        raise UserError(f"models folder not found: {d}")
    found = model_files(d)
    if not found:
        raise UserError(f"{d}: no obj_NNNNNN.ply models")
    if obj_ids is not None:
        missing = sorted(set(obj_ids) - set(found))
        if missing:
            raise UserError(f"{d}: no model for object id(s) {missing}")
        found = {k: found[k] for k in obj_ids}
    return {k: load_mesh(p, k) for k, p in found.items()}


def genus(mesh) -> int | None:
    """Topological genus (number of handles) of a closed mesh from its Euler characteristic,
    V - E + F = 2 - 2g per component; None if the mesh is not watertight. LM-O: the can has
    genus 2 and the holepuncher 3, the others 0 (the thesis's Section 4.3.3 uses genus as a
    shape attribute the latent space may encode)."""
    m = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=False)
    if not m.is_watertight:
        return None
    n_comp = len(m.split(only_watertight=False))
    return int(round((2 * n_comp - m.euler_number) / 2))


def hull_vertices(vertices: np.ndarray) -> np.ndarray:
    """The vertices on the convex hull (all of them for a degenerate, flat model): the same
    extremes of any linear or linear-fractional function (a projection) as all vertices."""
    v = np.asarray(vertices, dtype=np.float64)
    return v[_hull_index(v)]


def _hull_index(v: np.ndarray) -> np.ndarray:
    try:
        return ConvexHull(v).vertices
    except Exception:  # degenerate (flat) models: all vertices
        return np.arange(len(v))


def diameter(vertices: np.ndarray) -> float:
    """Largest distance between two vertices (over the convex hull's vertices)."""
    return float(pdist(hull_vertices(vertices)).max())


HULL_CACHE_VERSION = 1


def cached_hull(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """(:func:`hull_vertices`, :func:`diameter`) of ``vertices``, kept in
    ``cache_dir()/hull_<sha>.npz`` keyed by the vertices' bytes: synth's every render worker
    needs both for every object and distractor (0.33 s of a worker's 0.9 s start for LM-O's 8
    and the plain distractors); read back in milliseconds. A missing, damaged or unwritable
    entry only costs computing them."""
    from tracker.core.paths import cache_dir
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    h = hashlib.sha256(f"{HULL_CACHE_VERSION} {v.shape}".encode())
    h.update(v.tobytes())
    path = cache_dir() / f"hull_{h.hexdigest()[:24]}.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            return v[z["index"]], float(z["diameter"])
    except Exception:  # no entry, or a damaged one
        pass
    index = _hull_index(v)
    hull = v[index]
    d = float(pdist(hull).max()) if len(hull) > 1 else 0.0
    _save_cache_entry(path, {"index": index.astype(np.int64), "diameter": np.float64(d)})
    return hull, d


def _kabsch(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transform with R @ A_i + t ~ B_i."""
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def refine_self_alignment(vertices: np.ndarray, R0: np.ndarray, iters: int = 30,
                          sample: int = 3000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """ICP of the model onto itself from the rotation R0 (about the centroid).

    Returns the refined R, t and the Hausdorff distance (max over vertices of the
    distance of the transformed vertex to the nearest model vertex) in mm.
    """
    v = np.asarray(vertices, dtype=np.float64)
    tree = cKDTree(v)
    rng = np.random.default_rng(seed)
    sub = v[rng.choice(len(v), min(sample, len(v)), replace=False)]
    c = v.mean(0)
    R, t = R0, c - R0 @ c
    for _ in range(iters):
        _, idx = tree.query(sub @ R.T + t)
        R, t = _kabsch(sub, v[idx])
    d_fwd, _ = tree.query(v @ R.T + t)
    d_bwd, _ = cKDTree(v @ R.T + t).query(v)
    return R, t, float(max(d_fwd.max(), d_bwd.max()))


def find_discrete_symmetries(vertices: np.ndarray, diam: float,
                             threshold: float = SYMMETRY_HAUSDORFF) -> list[dict]:
    """2-fold (180 degree) symmetries about the model axes, each checked by Hausdorff distance.

    Returns ``[{"T": 4x4, "axis": "x|y|z", "hausdorff_mm": float}]``.
    """
    out = []
    for name, axis in zip("xyz", np.eye(3)):
        R0 = Rotation.from_rotvec(axis * np.pi).as_matrix()
        R, t, h = refine_self_alignment(vertices, R0)
        if h <= threshold * diam:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            out.append({"T": T, "axis": name, "hausdorff_mm": h})
    return out


def models_info_entry(model: ObjectModel, symmetries: bool = True) -> dict:
    v = model.vertices
    lo, hi = v.min(0), v.max(0)
    d = diameter(v)
    info = {"diameter": d,
            "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
            "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]), "size_z": float(hi[2] - lo[2])}
    if symmetries:
        syms = find_discrete_symmetries(v, d)
        if syms:
            info["symmetries_discrete"] = [s["T"].ravel().tolist() for s in syms]
    return info


def compute_models_info(models: dict[int, ObjectModel], symmetries: bool = True) -> dict[int, dict]:
    return {k: models_info_entry(m, symmetries) for k, m in sorted(models.items())}
