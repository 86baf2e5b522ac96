"""A user's meshes -> a BOP models folder: formats, units, names, ids."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tracker.training.prepare import object_names, prepare_models
from tracker.core.errors import UserError
from tracker.core.meshes import load_models

FIX = Path(__file__).parent / "fixtures" / "models"


def _box_in_metres(path, colour=True):
    m = trimesh.creation.box(extents=[0.06, 0.04, 0.02])  # 60 x 40 x 20 mm, given in metres
    if colour:
        m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=np.tile([200, 30, 30, 255], (len(m.vertices), 1)))
    m.export(path)


@pytest.mark.parametrize("suffix", [".obj", ".glb", ".ply"])
def test_metres_are_refused_unless_said_and_then_converted(tmp_path, suffix):
    src = tmp_path / "src"
    src.mkdir()
    _box_in_metres(src / f"duck{suffix}")
    with pytest.raises(UserError, match=rf"duck{suffix}: diameter 0.0748 looks like metres.*--units m"):
        prepare_models(src, tmp_path / "out", log=lambda *a: None)
    rep = prepare_models(src, tmp_path / "out", units="m", log=lambda *a: None)
    assert rep[1]["name"] == "duck" and rep[1]["diameter_mm"] == pytest.approx(74.833, abs=1e-3)
    m = load_models(tmp_path / "out")[1]
    assert np.allclose(m.vertices.max(0) - m.vertices.min(0), [60, 40, 20])
    assert m.has_colours and tuple(np.asarray(m.mesh.visual.vertex_colors)[0][:3]) == (200, 30, 30)
    info = json.loads((tmp_path / "out" / "models_info.json").read_text())
    assert info["1"]["diameter"] == pytest.approx(74.833, abs=1e-3) and len(info["1"]["symmetries_discrete"]) == 3
    assert object_names(tmp_path / "out") == {1: "duck"}


def test_bop_ids_are_kept_and_other_files_numbered_around_them(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(FIX / "obj_000001.ply", src / "obj_000001.ply")
    trimesh.load(FIX / "obj_000002.ply", process=False).export(src / "mug.stl")  # STL: no colours
    shutil.copy(FIX / "obj_000001.ply", src / "obj_000007_duck.ply")
    with pytest.warns(UserWarning, match="mug.stl: no vertex colours or texture"):
        rep = prepare_models(src, tmp_path / "out", symmetries=False, log=lambda *a: None)
    assert {k: v["name"] for k, v in rep.items()} == {1: "obj_1", 2: "mug", 7: "duck"}
    assert sorted(load_models(tmp_path / "out")) == [1, 2, 7]


def test_a_folder_without_meshes_is_one_clear_error(tmp_path):
    with pytest.raises(UserError, match="no meshes"):
        prepare_models(tmp_path, tmp_path / "out", log=lambda *a: None)
    (tmp_path / "bad.ply").write_text("ply\nnot really")
    with pytest.raises(UserError, match="bad.ply"):
        prepare_models(tmp_path, tmp_path / "out", log=lambda *a: None)


def _sphere(path, radius_mm=50.0, at=(0.0, 0.0, 0.0)):
    m = trimesh.creation.icosphere(subdivisions=2, radius=radius_mm)
    m.apply_translation(at)
    m.export(path)


@pytest.mark.parametrize("name, radius, at, units, match", [
    ("obj_000000.ply", 50.0, (0, 0, 0), "auto", "object ids start at 1"),
    # a scan in map coordinates: float32 would keep its position and lose its shape
    ("scan.ply", 0.075, (500000.0, 5000000.0, 100.0), "m", "lies 3.07e\\+07 times its size from its origin"),
    ("big.ply", 1e20, (0, 0, 0), "auto", "mm across; pass the units"),
])
def test_meshes_that_would_be_lost_or_misread_are_refused(tmp_path, name, radius, at, units, match):
    src = tmp_path / "src"
    src.mkdir()
    _sphere(src / name, radius, at)
    with pytest.raises(UserError, match=match):
        prepare_models(src, tmp_path / "out", units=units, log=lambda *a: None)
    assert not list((tmp_path / "out").glob("obj_*.ply"))


def test_an_output_folder_holding_other_meshes_is_refused(tmp_path):
    """Every obj_*.ply of a models folder is trained on: an old mesh left there would be too."""
    src = tmp_path / "src"
    src.mkdir()
    _sphere(src / "a.ply")
    _sphere(src / "b.ply", 30.0)
    prepare_models(src, tmp_path / "out", symmetries=False, log=lambda *a: None)
    (src / "b.ply").unlink()
    with pytest.raises(UserError, match="already holds obj_000002.ply"):
        prepare_models(src, tmp_path / "out", symmetries=False, log=lambda *a: None)
    prepare_models(src, tmp_path / "again", symmetries=False, log=lambda *a: None)  # a new folder: fine
    assert sorted(load_models(tmp_path / "again")) == [1]


def _two_meshes(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(FIX / "obj_000001.ply", src / "obj_000001.ply")
    shutil.copy(FIX / "obj_000001.ply", src / "obj_000007_duck.ply")
    return src


def test_names_come_from_a_names_file_beside_the_meshes_or_a_given_one_that_wins(tmp_path):
    from tracker.training.prepare import read_names
    src = _two_meshes(tmp_path)
    quiet = {"symmetries": False, "log": lambda *a: None}
    (src / "names.json").write_text(json.dumps({"1": "ape"}))  # beside the meshes: read when no file is given
    rep = prepare_models(src, tmp_path / "a", **quiet)
    assert {k: v["name"] for k, v in rep.items()} == {1: "ape", 7: "duck"}  # 7 unnamed: its file's name
    assert object_names(tmp_path / "a") == {1: "ape", 7: "duck"}
    given = tmp_path / "mine.json"
    given.write_text(json.dumps({"7": "goose"}))  # given: it wins over the file beside the meshes
    rep = prepare_models(src, tmp_path / "b", names=given, **quiet)
    assert {k: v["name"] for k, v in rep.items()} == {1: "obj_1", 7: "goose"}
    rep = prepare_models(src, tmp_path / "c", names={1: "ape", "7": "goose"}, **quiet)  # or a mapping
    assert object_names(tmp_path / "c") == {1: "ape", 7: "goose"}
    assert read_names(given) == {7: "goose"}


@pytest.mark.parametrize("text, match", [
    ('{"1": "ape",', r"bad\.json: not valid JSON"),
    ('["ape"]', r"bad\.json: expected a JSON object of object ids to names"),
    ('{"one": "ape"}', r"bad\.json: 'one' is not an object id"),
    ('{"0": "ape"}', r"bad\.json: '0' is not an object id"),
    ('{"1": 5}', r"bad\.json: the name of object 1 must be a non-empty string, not 5"),
    ('{"1": ""}', r"bad\.json: the name of object 1 must be a non-empty string"),
    ('{"1": "ape", "7": "ape"}', r"bad\.json: two objects named 'ape'"),
    ('{"9": "duck"}', r"bad\.json: names for object\(s\) 9, which no mesh of .* has \(its ids: 1, 7\)"),
    ('{"1": "duck"}', r"bad\.json: object 1 named 'duck', the name object 7 has from its file"),
])
def test_a_bad_names_file_is_one_line_error_before_any_mesh_is_written(tmp_path, text, match):
    src = _two_meshes(tmp_path)
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    with pytest.raises(UserError, match=match) as e:
        prepare_models(src, tmp_path / "out", names=bad, log=lambda *a: None)
    assert "\n" not in str(e.value) and not (tmp_path / "out").exists()
    shutil.copy(bad, src / "names.json")  # the same checks for the file beside the meshes
    with pytest.raises(UserError, match=match.replace(r"bad\.json", r"names\.json")):
        prepare_models(src, tmp_path / "out", log=lambda *a: None)
    with pytest.raises(UserError, match="no such names file"):
        prepare_models(src, tmp_path / "out", names=tmp_path / "none.json", log=lambda *a: None)


def test_a_bundles_objects_are_renamed_through_the_staged_writer(tmp_path):
    from tests.conftest import REPO
    from tracker.core.bundle import open_bundle, sha256
    from tracker.training.prepare import set_object_names
    b = tmp_path / "lmo"
    shutil.copytree(REPO / "models" / "lmo", b)
    files = {p.name: sha256(p) for p in b.rglob("*") if p.is_file() and p.name != "manifest.json"}
    with pytest.raises(UserError, match="names for object.*2, which .* does not have"):
        set_object_names(b, {2: "bench"}, log=lambda *a: None)
    m = set_object_names(b, {12: "punch", 1: "monkey"}, log=lambda *a: None, command="test")
    after = open_bundle(b).manifest  # every hash verified
    assert after.object(12).name == "punch" and after.object(1).name == "monkey" and after.object(9).name == "duck"
    assert after.extra["object_names"]["renamed"]["12"] == {"from": "holepuncher", "to": "punch"}
    assert m.to_dict() == after.to_dict()
    assert {p.name: sha256(p) for p in b.rglob("*") if p.is_file() and p.name != "manifest.json"} == files
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lmo"]
