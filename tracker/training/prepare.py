"""A user's meshes -> a BOP models folder that every other job reads.

Any mesh trimesh reads (PLY, OBJ, STL, GLB/glTF, OFF) becomes ``obj_NNNNNN.ply`` in
millimetres with vertex colours (a texture is sampled at the vertices; a mesh without colour
gets a grey one, with a warning), plus ``models_info.json`` (diameter, bounding box, discrete
symmetries) and ``names.json`` (the object names: a names file's, :func:`read_names`, else the
file names). Units are checked: BOP
meshes are in millimetres, and a mesh whose diameter is under :data:`METRES_BELOW` units looks
like metres, so it is refused unless ``units`` says which it is (``m`` converts to mm)."""
from __future__ import annotations

import json
import os
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from tracker.core.errors import UserError

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".gltf", ".off")
METRES_BELOW = 5.0  # a diameter under 5 units: metres (a 5 m object), not a 5 mm one
LARGEST_MM = 1e5  # an object over 100 m across is in other units, not one to track from a camera
# a mesh farther from its origin than this many times its size: float32 (a PLY's vertices) keeps
# about 1e-7 of the distance, so its shape would blur to 1e-3 of its size
FARTHEST = 1e4
UNITS = {"auto": None, "mm": 1.0, "cm": 10.0, "m": 1000.0}
BOP_NAME = re.compile(r"^obj_(\d{6})(?:[_-](.+))?$")  # obj_000009 or obj_000009_duck: id 9 (named duck)
NAMES = "names.json"  # {"9": "duck", ...}: beside the meshes, or given (--names)


def mesh_files(src) -> list[Path]:
    d = Path(src)
    if not d.is_dir():
        raise UserError(f"--models {d}: not a folder of meshes")
    files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    if not files:
        raise UserError(f"--models {d}: no meshes ({', '.join(MESH_SUFFIXES)})")
    return files


def _load_any(path: Path):
    from tracker.core.meshes import read_mesh
    mesh = read_mesh(path)
    if getattr(mesh.visual, "kind", None) == "texture":
        mesh.visual = mesh.visual.to_color()  # the texture sampled at the vertices
    return mesh


def read_names(names, where=None, unique: bool = True) -> dict[int, str]:
    """Object names, checked: ``names`` is a JSON file ``{"9": "duck", ...}`` (a path) or such a
    mapping (ids as whole numbers or their strings). Ids must be whole numbers >= 1 and names
    non-empty strings (``unique``: no two alike); anything else is one :class:`UserError` naming
    ``where`` (default: the file, or --names)."""
    if isinstance(names, (str, os.PathLike)):
        path = Path(names)
        where = where or str(path)
        if not path.is_file():
            raise UserError(f"{where}: no such names file (expected JSON like {{\"9\": \"duck\"}})")
        try:
            names = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise UserError(f"{where}: not valid JSON ({str(e).splitlines()[0][:80]}); expected "
                            f"{{\"9\": \"duck\", ...}}") from None
    where = where or "--names"
    if not isinstance(names, dict):
        raise UserError(f"{where}: expected a JSON object of object ids to names, like {{\"9\": \"duck\"}}")
    out = {}
    for k, v in names.items():
        oid = k if isinstance(k, int) and not isinstance(k, bool) else (
            int(k) if isinstance(k, str) and k.strip().isascii() and k.strip().isdigit() else None)
        if oid is None or oid < 1:
            raise UserError(f"{where}: {k!r} is not an object id (a whole number >= 1, like \"9\")")
        if not isinstance(v, str) or not v.strip():
            raise UserError(f"{where}: the name of object {oid} must be a non-empty string, not {v!r}")
        if oid in out:
            raise UserError(f"{where}: object {oid} is named twice")
        out[oid] = v.strip()
    twice = sorted({n for n in out.values() if list(out.values()).count(n) > 1})
    if twice and unique:
        raise UserError(f"{where}: two objects named {twice[0]!r}; give each its own name")
    return dict(sorted(out.items()))


def _given_names(src, names, ids) -> dict[int, str]:
    """The names that beat the file names: ``names`` (a file or mapping) when given, else a
    ``names.json`` beside the meshes ({} without one); checked against the meshes' ids
    (``ids``: {file: id}) and the names the others keep from their files."""
    if names is None:
        beside = Path(src) / NAMES
        if not beside.is_file():
            return {}
        names, where = beside, str(beside)
    else:
        where = str(names) if isinstance(names, (str, os.PathLike)) else "--names"
    given = read_names(names, where)
    unknown = sorted(set(given) - set(ids.values()))
    if unknown:
        raise UserError(f"{where}: names for object(s) {', '.join(map(str, unknown))}, which no mesh of {src} has "
                        f"(its ids: {', '.join(map(str, sorted(ids.values())))})")
    taken = {_file_name(p): oid for p, oid in ids.items() if oid not in given}
    clash = [(oid, n) for oid, n in given.items() if n in taken]
    if clash:
        raise UserError(f"{where}: object {clash[0][0]} named {clash[0][1]!r}, the name object {taken[clash[0][1]]} "
                        f"has from its file; give each its own name")
    return given


def _file_name(p: Path) -> str:
    """An object's name from its file: ``NAME`` of ``obj_NNNNNN_NAME``, ``obj_N``, or the file name."""
    m = BOP_NAME.match(p.stem)
    return (m.group(2) or f"obj_{int(m.group(1))}") if m else p.stem


def prepare_models(src, out, units: str = "auto", symmetries: bool = True, log=print,
                   names=None) -> dict[int, dict]:
    """Write ``out``/obj_NNNNNN.ply, models_info.json and names.json from the meshes in ``src``.
    Files named ``obj_NNNNNN.*`` or ``obj_NNNNNN_NAME.*`` keep their id; the others are numbered 1, 2, ... in name
    order (after the kept ids). An object's name is ``names``' (a JSON file ``{"9": "duck"}`` or
    a mapping, :func:`read_names`; None: ``src``/names.json when there is one), else its file's
    (``NAME`` above, the file name, or ``obj_N``). Returns {obj_id: {"name", "source",
    "diameter_mm", "scale"}}."""
    from tracker.core.bop import save_models_info
    from tracker.core.meshes import compute_models_info, diameter, load_mesh
    if units not in UNITS:
        raise UserError(f"--units must be one of {', '.join(UNITS)}, not '{units}'")
    files = mesh_files(src)
    ids, taken = {}, set()
    for p in files:
        m = BOP_NAME.match(p.stem)
        if m:
            if int(m.group(1)) < 1:
                raise UserError(f"{p}: object ids start at 1 (BOP); rename it, e.g. obj_000001{p.suffix}")
            if int(m.group(1)) in taken:
                raise UserError(f"{src}: two meshes for object {int(m.group(1))}")
            ids[p] = int(m.group(1))
            taken.add(ids[p])
    nxt = 1
    for p in files:
        if p not in ids:
            while nxt in taken:
                nxt += 1
            ids[p] = nxt
            taken.add(nxt)
    given = _given_names(src, names, ids)  # a bad names file fails before any mesh is read
    out = Path(out)
    from tracker.core.meshes import model_files
    stale = sorted(set(model_files(out)) - set(ids.values()))
    if stale:  # jobs read every obj_*.ply of the folder: an old one would be trained on too
        raise UserError(f"--out {out} already holds obj_{stale[0]:06d}.ply, not one of these meshes; "
                        f"give an empty folder or remove the old meshes first")
    out.mkdir(parents=True, exist_ok=True)
    report = {}
    for p in files:
        mesh = _load_any(p)
        d = diameter(np.asarray(mesh.vertices))
        scale = UNITS[units]
        if scale is None:
            if d < METRES_BELOW:
                raise UserError(f"{p.name}: diameter {d:.3g} looks like metres (meshes here are in millimetres); "
                                f"pass --units m to convert it (or --units mm if it really is {d:.3g} mm across)")
            scale = 1.0
        if d * scale > LARGEST_MM:
            raise UserError(f"{p.name}: {d * scale:.3g} mm across; pass the units it is in (--units m, cm, mm ...)")
        far = float(np.abs(mesh.vertices).max()) / d if d > 0 else 0.0
        if far > FARTHEST:  # a PLY stores float32: the shape would be lost in the offset
            raise UserError(f"{p.name}: the mesh lies {far:.3g} times its size from its origin (world or map "
                            f"coordinates?); move it to the origin (BOP: the bounding-box centre) first")
        if scale != 1.0:
            mesh.apply_scale(scale)
        if getattr(mesh.visual, "kind", None) != "vertex":
            import trimesh
            from tracker.core.meshes import GREY
            warnings.warn(f"{p.name}: no vertex colours or texture; the object is rendered grey, which "
                          f"hides what the encoder could learn of its look", stacklevel=2)
            mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile(GREY, (len(mesh.vertices), 1)))
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        if np.any(lo > 0) or np.any(hi < 0):
            warnings.warn(f"{p.name}: its origin lies outside the object (poses are of that origin; BOP "
                          f"meshes have it at the bounding-box centre)", stacklevel=2)
        oid = ids[p]
        dst = out / f"obj_{oid:06d}.ply"
        mesh.export(dst, encoding="binary")
        load_mesh(dst, oid)  # what the other jobs will read
        name = given.get(oid) or _file_name(p)
        report[oid] = {"name": name, "source": str(p), "diameter_mm": round(d * scale, 3), "scale": scale}
        log(f"{p.name} -> {dst.name}: '{name}', diameter {d * scale:.1f} mm" + (f" (x {scale:g})" if scale != 1 else ""))
    from tracker.core.meshes import load_models
    save_models_info(out / "models_info.json", compute_models_info(load_models(out, sorted(report)), symmetries))
    (out / "names.json").write_text(json.dumps({str(k): v["name"] for k, v in sorted(report.items())}, indent=1))
    return report


def object_names(models_dir) -> dict[int, str]:
    """The names a prepared models folder gives its objects ({} without names.json)."""
    p = Path(models_dir) / NAMES
    return read_names(p, unique=False) if p.is_file() else {}  # file names may repeat, as before


def set_object_names(bundle_dir, names, log=print, command: str | None = None):
    """Rename a bundle's objects in place (``names``: a names file or mapping, :func:`read_names`;
    objects it does not name keep theirs): only the manifest changes, through the staged writer
    (:func:`tracker.core.bundle.update_manifest`), which records the change under
    ``object_names``. Returns the new manifest."""
    from tracker.core.bundle import update_manifest
    where = str(names) if isinstance(names, (str, os.PathLike)) else "--names"
    given = read_names(names, where)
    renamed = {}

    def change(manifest, folder):
        unknown = sorted(set(given) - set(manifest.obj_ids))
        if unknown:
            raise UserError(f"{where}: names for object(s) {', '.join(map(str, unknown))}, which {bundle_dir} "
                            f"does not have (its ids: {', '.join(map(str, manifest.obj_ids))})")
        for o in manifest.objects:
            if o.id in given and o.name != given[o.id]:
                renamed[o.id] = (o.name, given[o.id])
                o.name = given[o.id]
        final = [o.name for o in manifest.objects]
        twice = sorted({n for n in final if final.count(n) > 1})
        if twice:
            raise UserError(f"{where}: {bundle_dir} would have two objects named {twice[0]!r}")
        if renamed:
            manifest.extra["object_names"] = {
                "renamed": {str(k): {"from": a, "to": b} for k, (a, b) in renamed.items()},
                "command": command or "app.py " + " ".join(sys.argv[1:]),
                "created": time.strftime("%Y-%m-%d %H:%M:%S")}
    manifest = update_manifest(bundle_dir, change)
    log(f"bundle {bundle_dir}: " + (", ".join(f"{k} {a} -> {b}" for k, (a, b) in renamed.items())
                                    if renamed else "names unchanged"))
    return manifest
