"""Render assets from Debian packages, for `synth --backgrounds` and `synth --occluders`
(issues 57 item 5, 58 item 1): table-top textures from `openarena-081-textures` and textured
household meshes from `sweethome3d-furniture`. Optional inputs of the renderer, never needed
by it; `scripts/debian_assets.py` fetches the pinned packages and calls these.

A `.deb` is an `ar` archive whose `data.tar.*` holds the files; read here with the standard
library (no dpkg needed)."""
from __future__ import annotations

import io
import re
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import trimesh

from tracker.core.errors import UserError
from tracker.training.synth.randomise import vertex_coloured


def deb_files(deb: bytes, suffix: str) -> dict[str, bytes]:
    """The files of a Debian package's data archive whose names end with ``suffix``."""
    if not deb.startswith(b"!<arch>\n"):
        raise UserError("not a Debian package (no ar signature)")
    pos, out = 8, {}
    while pos + 60 <= len(deb):
        name = deb[pos:pos + 16].decode().strip().rstrip("/")
        size = int(deb[pos + 48:pos + 58].decode().strip())
        body = deb[pos + 60:pos + 60 + size]
        pos += 60 + size + (size & 1)
        if name.startswith("data.tar"):
            with tarfile.open(fileobj=io.BytesIO(body)) as tar:
                for m in tar.getmembers():
                    if m.isfile() and m.name.endswith(suffix):
                        out[m.name.removeprefix("./")] = tar.extractfile(m).read()
            return out
    raise UserError("Debian package without a data archive")


# texture folders of the game that are not surfaces: effects, skies, lights, liquids, flares
NOT_SURFACES = ("sfx", "skies", "nebulae", "liquids", "flares", "common", "light", "effects", "cosmo_sfx")


def textures_from_pk3(pk3: bytes, out_dir, min_side: int = 128) -> list[Path]:
    """The surface textures of a Quake III-style .pk3 (a zip) as JPEGs in ``out_dir`` (named
    folder_file.jpg): at least ``min_side`` pixels a side, opaque, not an effect."""
    from PIL import Image  # Pillow comes with pyrender
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    with zipfile.ZipFile(io.BytesIO(pk3)) as z:
        for name in sorted(z.namelist()):
            parts = name.lower().split("/")
            if len(parts) < 3 or parts[0] != "textures" or not parts[-1].endswith((".jpg", ".tga")):
                continue
            if any(s in parts[1] for s in NOT_SURFACES):
                continue
            img = Image.open(io.BytesIO(z.read(name)))
            if min(img.size) < min_side:
                continue
            if img.mode in ("RGBA", "LA", "P"):
                a = np.asarray(img.convert("RGBA"))[..., 3]
                if (a < 250).mean() > 0.01:  # a decal or a grate: see-through, not a surface
                    continue
            dest = out_dir / f"{parts[1]}_{Path(parts[-1]).stem}.jpg"
            img.convert("RGB").save(dest, quality=92)
            written.append(dest)
    return written


def _properties(text: str) -> dict[int, dict[str, str]]:
    """A Sweet Home 3D furniture catalog: {index: {key: value}} from `key#index=value` lines."""
    items: dict[int, dict[str, str]] = {}
    for line in text.splitlines():
        m = re.match(r"^([A-Za-z]+)#(\d+)=(.*)$", line.strip())
        if m:
            items.setdefault(int(m.group(2)), {})[m.group(1)] = m.group(3).strip()
    return items


def furniture_from_sh3f(sh3f: bytes, out_dir, max_cm: float = 80.0, max_faces: int = 3000,
                        prefix: str = "") -> list[Path]:
    """The small pieces (largest side at most ``max_cm``) of a Sweet Home 3D catalog (.sh3f, a
    zip of OBJ + MTL + textures) as PLY meshes in ``out_dir``: millimetres, z up, centred,
    the texture sampled into vertex colours (the renderer colours by vertex), decimated to about
    ``max_faces``. Returns the files written."""
    import tempfile

    from tracker.training.decimate import decimate_mesh
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    with zipfile.ZipFile(io.BytesIO(sh3f)) as z, tempfile.TemporaryDirectory() as tmp:
        items = _properties(z.read("PluginFurnitureCatalog.properties").decode("latin-1"))
        z.extractall(tmp)
        for idx, it in sorted(items.items()):
            size = [float(it.get(k, "nan")) for k in ("width", "depth", "height")]
            if "model" not in it or not np.all(np.isfinite(size)) or max(size) > max_cm:
                continue
            if it.get("doorOrWindow") == "true":
                continue
            try:
                scene = trimesh.load(Path(tmp) / it["model"].lstrip("/"), force="scene")
                mesh = _coloured(scene)
            except Exception:  # noqa: BLE001 - a model trimesh cannot read is skipped, not fatal
                continue
            if mesh is None or len(mesh.faces) < 4:
                continue
            # Sweet Home 3D models are y up; its catalog may rotate them further
            rot = np.eye(4)
            if "modelRotation" in it:
                rot[:3, :3] = np.array([float(v) for v in it["modelRotation"].split()]).reshape(3, 3)
            y_up_to_z_up = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
            mesh.apply_transform(y_up_to_z_up @ rot)
            ext = mesh.extents
            mesh.apply_scale(np.array([size[0], size[1], size[2]]) * 10.0 / np.maximum(ext, 1e-9))
            mesh.apply_translation(-mesh.bounds.mean(0))
            if len(mesh.faces) > max_faces:
                mesh = decimate_mesh(mesh, max_faces)
            name = re.sub(r"[^a-z0-9]+", "_", f"{prefix}{it.get('name', idx)}_{idx}".lower()).strip("_")
            dest = out_dir / f"{name}.ply"
            mesh.export(dest)
            written.append(dest)
    return written


def _coloured(scene) -> trimesh.Trimesh | None:
    """One mesh of a scene's parts, each part's texture or material colour sampled into
    vertex colours (:func:`vertex_coloured`)."""
    parts = [vertex_coloured(g.copy()) for g in scene.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    return trimesh.util.concatenate(parts) if parts else None
