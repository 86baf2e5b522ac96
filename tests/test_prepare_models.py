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
