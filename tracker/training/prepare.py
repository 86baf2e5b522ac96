"""A user's meshes -> a BOP models folder that every other job reads.

Any mesh trimesh reads (PLY, OBJ, STL, GLB/glTF, OFF) becomes ``obj_NNNNNN.ply`` in
millimetres with vertex colours (a texture is sampled at the vertices; a mesh without colour
gets a grey one, with a warning), plus ``models_info.json`` (diameter, bounding box, discrete
symmetries) and ``names.json`` (the object names: the file names). Units are checked: BOP
meshes are in millimetres, and a mesh whose diameter is under :data:`METRES_BELOW` units looks
like metres, so it is refused unless ``units`` says which it is (``m`` converts to mm)."""
from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np

from tracker.core.errors import UserError

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".gltf", ".off")
METRES_BELOW = 5.0  # a diameter under 5 units: metres (a 5 m object), not a 5 mm one
UNITS = {"auto": None, "mm": 1.0, "cm": 10.0, "m": 1000.0}
BOP_NAME = re.compile(r"^obj_(\d{6})(?:[_-](.+))?$")  # obj_000009 or obj_000009_duck: id 9 (named duck)


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


def prepare_models(src, out, units: str = "auto", symmetries: bool = True, log=print) -> dict[int, dict]:
    """Write ``out``/obj_NNNNNN.ply, models_info.json and names.json from the meshes in ``src``.
    Files named ``obj_NNNNNN.*`` or ``obj_NNNNNN_NAME.*`` keep their id; the others are numbered 1, 2, ... in name
    order (after the kept ids). Returns {obj_id: {"name", "source", "diameter_mm", "scale"}}."""
    from tracker.core.bop import save_models_info
    from tracker.core.meshes import compute_models_info, diameter, load_mesh
    if units not in UNITS:
        raise UserError(f"--units must be one of {', '.join(UNITS)}, not '{units}'")
    files = mesh_files(src)
    ids, taken = {}, set()
    for p in files:
        m = BOP_NAME.match(p.stem)
        if m:
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
    out = Path(out)
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
        m = BOP_NAME.match(p.stem)
        name = (m.group(2) or f"obj_{int(m.group(1))}") if m else p.stem
        report[oid] = {"name": name, "source": str(p), "diameter_mm": round(d * scale, 3), "scale": scale}
        log(f"{p.name} -> {dst.name}: '{name}', diameter {d * scale:.1f} mm" + (f" (x {scale:g})" if scale != 1 else ""))
    from tracker.core.meshes import load_models
    save_models_info(out / "models_info.json", compute_models_info(load_models(out, sorted(report)), symmetries))
    (out / "names.json").write_text(json.dumps({str(k): v["name"] for k, v in sorted(report.items())}, indent=1))
    return report


def object_names(models_dir) -> dict[int, str]:
    """The names a prepared models folder gives its objects ({} without names.json)."""
    p = Path(models_dir) / "names.json"
    if not p.is_file():
        return {}
    try:
        return {int(k): str(v) for k, v in json.loads(p.read_text()).items()}
    except (ValueError, AttributeError):
        raise UserError(f"{p}: unreadable (expected {{\"1\": \"name\", ...}})") from None
