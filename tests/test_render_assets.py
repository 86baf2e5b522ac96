"""Render assets from Debian packages (scripts/debian_assets.py, synth --occluders): hand-made
packages, textures and furniture catalogs, so nothing is downloaded."""
import io
import subprocess
import sys
import tarfile
import zipfile
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from tracker.core.bop import load_scene
from tracker.core.errors import UserError
from tracker.training.synth.assets import deb_files, furniture_from_sh3f, textures_from_pk3
from tracker.training.synth.engine import DISTRACTOR_BASE, SynthConfig, generate

ROOT = Path(__file__).resolve().parents[1]


def _deb(files: dict[str, bytes]) -> bytes:
    """An ar archive as dpkg writes it: debian-binary, control.tar.xz, data.tar.xz."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:xz") as tar:
        for name, data in files.items():
            info = tarfile.TarInfo("./" + name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    out = b"!<arch>\n"
    for name, body in (("debian-binary", b"2.0\n"), ("control.tar.xz", b"x" * 3), ("data.tar.xz", buf.getvalue())):
        out += f"{name:<16}{0:<12}{0:<6}{0:<6}{100644:<8}{len(body):<10}`\n".encode() + body + b"\n" * (len(body) & 1)
    return out


def _image(fmt: str, side: int, alpha_holes: bool = False) -> bytes:
    from PIL import Image
    rng = np.random.default_rng(side)
    a = rng.integers(0, 255, (side, side, 4), dtype=np.uint8)
    a[..., 3] = 255
    if alpha_holes:
        a[: side // 2, :, 3] = 0
    buf = io.BytesIO()
    img = Image.fromarray(a, "RGBA")
    (img.convert("RGB") if fmt == "JPEG" else img).save(buf, fmt)
    return buf.getvalue()


def test_a_debian_package_is_read_without_dpkg():
    deb = _deb({"usr/share/a/x.pk3": b"PK-data", "usr/share/doc/a/copyright": b"CC0"})
    assert deb_files(deb, ".pk3") == {"usr/share/a/x.pk3": b"PK-data"}
    assert deb_files(deb, "/copyright") == {"usr/share/doc/a/copyright": b"CC0"}
    with pytest.raises(UserError, match="not a Debian package"):
        deb_files(b"PK\x03\x04", ".pk3")


def test_textures_keep_opaque_surfaces_of_useful_size(tmp_path):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("textures/base_floor/tile.jpg", _image("JPEG", 256))
        z.writestr("textures/base_wall/panel.tga", _image("TGA", 128))
        z.writestr("textures/base_wall/grate.tga", _image("TGA", 256, alpha_holes=True))  # see-through
        z.writestr("textures/base_floor/tiny.jpg", _image("JPEG", 64))  # too small
        z.writestr("textures/sfx/flame.jpg", _image("JPEG", 256))  # an effect
        z.writestr("models/mapobjects/thing.jpg", _image("JPEG", 256))  # not a texture
    written = textures_from_pk3(buf.getvalue(), tmp_path)
    assert sorted(p.name for p in written) == ["base_floor_tile.jpg", "base_wall_panel.jpg"]
    for p in written:
        assert cv2.imread(str(p)).shape[2] == 3  # synth reads them as backgrounds


CATALOG = """id=Test#catalog
name=Test catalog
id#1=Test#mug
name#1=Red mug
category#1=Kitchen
model#1=/test/mug/mug.obj
width#1=10.0
depth#1=8.0
height#1=12.0
doorOrWindow#1=false
id#2=Test#sofa
name#2=Sofa
model#2=/test/sofa/sofa.obj
width#2=200.0
depth#2=90.0
height#2=80.0
"""


def _box_obj(extents, kd) -> tuple[str, str]:
    """An OBJ box (y up, as Sweet Home 3D's models) with a material of colour ``kd``."""
    m = trimesh.creation.box(extents=extents)
    lines = ["mtllib m.mtl", "usemtl paint"] + [f"v {x} {y} {z}" for x, y, z in m.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    return "\n".join(lines) + "\n", f"newmtl paint\nKd {kd[0]} {kd[1]} {kd[2]}\n"


def _sh3f(models: dict) -> bytes:
    """A catalog (CATALOG) with the given models: {name: (obj, mtl)} at test/NAME/NAME.obj."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("PluginFurnitureCatalog.properties", CATALOG)
        for name, (obj, mtl) in models.items():
            z.writestr(f"test/{name}/{name}.obj", obj)
            z.writestr(f"test/{name}/m.mtl", mtl)
    return buf.getvalue()


def test_small_furniture_becomes_coloured_meshes_in_mm_z_up(tmp_path):
    # the model's own units and axes differ from the catalog's: width x (10), height y (12), depth z (8)
    sh3f = _sh3f({"mug": _box_obj([1.0, 1.2, 0.8], (0.8, 0.1, 0.1)), "sofa": _box_obj([2.0, 0.8, 0.9], (0.1, 0.1, 0.8))})
    written = furniture_from_sh3f(sh3f, tmp_path, max_cm=80.0, prefix="t_")
    assert [p.name for p in written] == ["t_red_mug_1.ply"]  # the sofa is too big
    mesh = trimesh.load(written[0], force="mesh")
    assert np.allclose(mesh.extents, [100.0, 80.0, 120.0], atol=0.5)  # mm; the catalog's height on z
    assert np.allclose(mesh.bounds.mean(0), 0.0, atol=0.5)
    rgb = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(int)
    assert (rgb[:, 0] > 150).all() and (rgb[:, 1:] < 60).all()  # the material's red


def test_the_script_refuses_a_package_that_is_not_the_pinned_one(tmp_path):
    fake = tmp_path / "openarena.deb"
    fake.write_bytes(_deb({"usr/share/x.pk3": b""}))
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "debian_assets.py"), "textures", "--out",
                        str(tmp_path / "t"), "--deb", str(fake)], capture_output=True, text=True)
    assert r.returncode == 1 and "not the pinned package" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "t").exists()


def _occluder_folder(folder: Path) -> Path:
    folder.mkdir()
    for i, (shape, colour) in enumerate([(trimesh.creation.box(extents=[3, 2, 1]), (200, 30, 30, 255)),
                                         (trimesh.creation.icosphere(radius=2), (30, 200, 30, 255)),
                                         (trimesh.creation.cylinder(radius=1, height=4), (30, 30, 200, 255))]):
        shape.visual = trimesh.visual.ColorVisuals(shape, vertex_colors=np.tile(colour, (len(shape.vertices), 1)))
        shape.export(folder / f"piece_{i}.ply")
    (folder / "COPYRIGHT").write_text("CC0")  # not a mesh: skipped
    return folder


def test_synth_draws_distractors_from_an_occluder_folder_in_their_own_colours(data_dir, tmp_path):
    from tracker.training.synth import engine
    occ = _occluder_folder(tmp_path / "occ")
    cfg = SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                      obj_ids=[1, 5], seed=2, occluders_dir=str(occ), distractors="hard")
    engine._init_worker(asdict(cfg))
    try:
        assert engine._W["n_dis"] == 3 and not engine._W["tint"]
        for i in range(3):
            v = engine._W["verts"][DISTRACTOR_BASE + i]
            assert 40.0 - 1e-6 <= np.ptp(v, axis=0).max() <= 250.0 + 1e-6  # household sizes, mm
        drawn = set()
        for k in range(20):
            inst, _, _, _ = engine._sample_instances(np.random.default_rng([2, k]), cfg)
            drawn |= {i for i, _, _ in inst if i >= DISTRACTOR_BASE}
        assert drawn == {DISTRACTOR_BASE + i for i in range(3)}
    finally:
        for k in ("scene", "crop"):
            engine._W.pop(k).close()
    generate(cfg, tmp_path / "split", 2, workers=1, progress=False)
    scene = load_scene(tmp_path / "split" / "000000", require_gt=True)
    assert scene.im_ids == [0, 1] and {g.obj_id for i in scene.im_ids for g in scene.gt[i]} <= {1, 5}


def test_bad_occluder_folders_are_one_line_each(data_dir, tmp_path):
    def cfg(folder):
        return SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                           obj_ids=[1], occluders_dir=str(folder))
    with pytest.raises(UserError, match="occluders folder not found"):
        generate(cfg(tmp_path / "missing"), tmp_path / "a", 1, workers=1, progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="no .ply/.obj"):
        generate(cfg(tmp_path / "empty"), tmp_path / "b", 1, workers=1, progress=False)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "broken.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\ngarbage")
    from tracker.training.synth.randomise import list_occluders, occluder_meshes
    with pytest.raises(UserError, match="broken.ply"):
        occluder_meshes(list_occluders(tmp_path / "bad"), np.random.default_rng(0))
    r = subprocess.run([sys.executable, str(ROOT / "app.py"), "synth", "--models", str(data_dir / "lmo" / "models"),
                        "--out", str(tmp_path / "c"), "--images", "1", "--occluders", str(tmp_path / "empty")],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode != 0 and "no .ply/.obj" in r.stderr and "Traceback" not in r.stderr


def test_occluders_keep_face_colours_and_grey_only_what_has_none(tmp_path):
    from tracker.training.synth.randomise import occluder_meshes
    faces = trimesh.creation.box(extents=[1, 2, 3])
    faces.visual.face_colors = np.tile([10, 200, 30, 255], (len(faces.faces), 1))
    faces.export(tmp_path / "a_faces.obj")
    trimesh.creation.icosphere(radius=1).export(tmp_path / "b_plain.stl")  # no colour at all
    a, b = occluder_meshes([tmp_path / "a_faces.obj", tmp_path / "b_plain.stl"], np.random.default_rng(0))
    assert np.array_equal(np.unique(np.asarray(a.visual.vertex_colors)[:, :3], axis=0), [[10, 200, 30]])
    assert len(np.unique(np.asarray(b.visual.vertex_colors)[:, :3], axis=0)) == 1  # one flat colour


def test_the_script_writes_the_furniture_and_its_copyright_from_a_package(tmp_path, monkeypatch, capsys):
    import hashlib
    import importlib.util
    spec = importlib.util.spec_from_file_location("debian_assets", ROOT / "scripts" / "debian_assets.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    deb = _deb({"usr/share/sweethome3d/furniture/Kitchen.sh3f": _sh3f({"mug": _box_obj([1.0, 1.2, 0.8], (0.1, 0.7, 0.2))}),
                "usr/share/doc/sweethome3d-furniture/copyright": b"Files: *\nLicense: CC0\n"})
    (tmp_path / "f.deb").write_bytes(deb)
    name, version, _ = script.PACKAGES["furniture"]
    monkeypatch.setitem(script.PACKAGES, "furniture", (name, version, hashlib.sha256(deb).hexdigest()))
    assert script.main(["furniture", "--out", str(tmp_path / "out"), "--deb", str(tmp_path / "f.deb")]) == 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["COPYRIGHT", "kitchen_red_mug_1.ply"]
    assert (tmp_path / "out" / "COPYRIGHT").read_text().endswith("License: CC0\n")
    assert "wrote 1 file to" in capsys.readouterr().out
