import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from tracker.core.errors import UserError
from tracker.core.meshes import compute_models_info, diameter, find_discrete_symmetries, load_mesh

# BOP's published models_info.json for LM-O (diameters, mm): an independent reference
BOP_DIAMETERS = {1: 102.099, 5: 201.404, 6: 154.546, 8: 261.472, 9: 108.999, 10: 164.628,
                 11: 175.889, 12: 145.543}


@pytest.fixture(scope="module")
def lmo_info(lmo_models):
    return compute_models_info(lmo_models)


def test_diameter_matches_brute_force_and_bop(lmo_models, lmo_info):
    ape = lmo_models[1].vertices
    assert diameter(ape) == pytest.approx(pdist(ape).max(), rel=1e-12)
    for k, d in BOP_DIAMETERS.items():
        assert lmo_info[k]["diameter"] == pytest.approx(d, rel=1e-3)


def test_bounding_boxes(lmo_models, lmo_info):
    for k, m in lmo_models.items():
        v = m.vertices
        i = lmo_info[k]
        assert i["min_x"] == pytest.approx(v[:, 0].min()) and i["size_z"] == pytest.approx(np.ptp(v[:, 2]))


def test_only_eggbox_and_glue_are_symmetric(lmo_models, lmo_info):
    symmetric = {k for k, i in lmo_info.items() if i.get("symmetries_discrete")}
    assert symmetric == {10, 11}
    for k in (10, 11):
        (T,) = [np.array(s).reshape(4, 4) for s in lmo_info[k]["symmetries_discrete"]]
        rv = Rotation.from_matrix(T[:3, :3]).as_rotvec()
        assert np.degrees(np.linalg.norm(rv)) == pytest.approx(180, abs=3)  # a half turn ...
        assert abs(rv[2]) / np.linalg.norm(rv) > 0.99                       # ... about model z
        v = lmo_models[k].vertices
        moved = v @ T[:3, :3].T + T[:3, 3]
        # the turned model covers the model: mean nearest-vertex distance < 1 % of the diameter
        from scipy.spatial import cKDTree
        assert cKDTree(v).query(moved)[0].mean() < 0.01 * lmo_info[k]["diameter"]


def test_a_box_is_symmetric_about_every_axis_and_a_wedge_is_not():
    box = trimesh.creation.box(extents=(100, 60, 40)).subdivide().subdivide().subdivide()
    assert {s["axis"] for s in find_discrete_symmetries(box.vertices, diameter(box.vertices))} == {"x", "y", "z"}
    wedge = box.vertices.copy()
    wedge[:, 2] += 0.6 * wedge[:, 0]  # shear: no longer symmetric about x or z
    axes = {s["axis"] for s in find_discrete_symmetries(wedge, diameter(wedge))}
    assert "x" not in axes and "z" not in axes


def test_mesh_without_colours_is_grey_with_a_warning(tmp_path):
    p = tmp_path / "obj_000042.ply"
    trimesh.creation.icosphere(subdivisions=2, radius=30).export(p)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        m = load_mesh(p)
    assert m.obj_id == 42 and not m.has_colours
    assert any("no vertex colours" in str(x.message) for x in w)
    assert np.all(m.mesh.visual.vertex_colors[:, :3] == 160)


@pytest.mark.parametrize("content", [b"ply\nformat ascii 1.0\nelement vertex 3\ngarbage", b"\x00" * 100, b""])
def test_unreadable_meshes(tmp_path, content):
    p = tmp_path / "obj_000001.ply"
    p.write_bytes(content)
    with pytest.raises(UserError):
        load_mesh(p)


def _ascii_ply(path, vertices, faces):
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    path.write_text(head + "".join(f"{x} {y} {z}\n" for x, y, z in vertices)
                    + "".join(f"3 {a} {b} {c}\n" for a, b, c in faces))
    return path


def test_meshes_with_broken_faces_or_no_area_are_refused(tmp_path):
    from tracker.core.meshes import read_mesh
    quad = [(0, 0, 0), (10, 0, 0), (0, 10, 0), (0, 0, 10)]
    assert read_mesh(_ascii_ply(tmp_path / "ok.ply", quad, [(0, 1, 2), (0, 1, 3)])).area > 0
    with pytest.raises(UserError, match="a face names vertex 99 of 4"):
        read_mesh(_ascii_ply(tmp_path / "idx.ply", quad, [(0, 1, 2), (0, 1, 99)]))
    line = [(0, 0, 0), (10, 0, 0), (20, 0, 0), (30, 0, 0)]
    with pytest.raises(UserError, match="triangles have no area"):
        read_mesh(_ascii_ply(tmp_path / "line.ply", line, [(0, 1, 2), (1, 2, 3)]))


def test_a_bop_folder_with_object_id_0_is_refused(tmp_path):
    from tracker.core.meshes import model_files
    (tmp_path / "obj_000000.ply").write_text("ply")
    with pytest.raises(UserError, match="object ids start at 1"):
        model_files(tmp_path)


def test_the_parsed_mesh_cache_gives_the_parsed_mesh_and_survives_a_broken_cache(tmp_path, monkeypatch, data_dir):
    """A PLY read twice: the second read comes from the cache (keyed by the file's contents)
    and equals the parse; a corrupt cache file is parsed again, and an edited file is not
    served from the old entry."""
    import shutil
    cache = tmp_path / "cache"
    monkeypatch.setenv("AUTOPOSE_CACHE", str(cache))
    src = tmp_path / "obj_000001.ply"
    shutil.copy(data_dir / "lmo" / "models" / "obj_000001.ply", src)
    first = load_mesh(src)
    (entry,) = cache.glob("mesh_*.npz")
    second = load_mesh(src)
    assert second.has_colours and second.obj_id == 1
    for a, b in ((first.mesh.vertices, second.mesh.vertices), (first.mesh.faces, second.mesh.faces),
                 (first.mesh.visual.vertex_colors, second.mesh.visual.vertex_colors)):
        assert np.array_equal(a, b)
    entry.write_bytes(b"not an npz")
    third = load_mesh(src)
    assert np.array_equal(third.mesh.vertices, first.mesh.vertices)
    grey = trimesh.Trimesh(np.asarray(first.mesh.vertices) * 2.0, first.mesh.faces, process=False)
    grey.export(src)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        edited = load_mesh(src)
    assert np.allclose(edited.mesh.vertices, 2.0 * np.asarray(first.mesh.vertices), atol=1e-3)
    assert not edited.has_colours and len(list(cache.glob("mesh_*.npz"))) == 2


def test_cached_decimation_renders_the_same_pixels_and_survives_a_broken_cache(tmp_path, monkeypatch, lmo_models):
    """synth's decimated meshes come from a cache after the first run: the same arrays and the
    same rendered pixels as a fresh decimation; a damaged entry is decimated again; another
    face count is another entry."""
    from tracker.training import decimate as dec
    from tracker.runtime.render import Renderer
    monkeypatch.setenv("AUTOPOSE_CACHE", str(tmp_path / "cache"))
    mesh = lmo_models[1].mesh
    fresh = dec.decimate_mesh(mesh, 3000, cache=True)
    (entry,) = (tmp_path / "cache").glob("decimated_*.npz")
    monkeypatch.setattr(dec, "_decimate", lambda *a: pytest.fail("decimated again"))
    cached = dec.decimate_mesh(mesh, 3000, cache=True)
    for a, b in ((fresh.vertices, cached.vertices), (fresh.faces, cached.faces),
                 (fresh.visual.vertex_colors, cached.visual.vertex_colors)):
        assert np.array_equal(a, b)
    K = np.array([[572.4, 0, 64.0], [0, 573.6, 64.0], [0, 0, 1]])
    R, t = np.eye(3), np.array([0.0, 0.0, 600.0])
    with Renderer(128, 128, {1: fresh}) as r1, Renderer(128, 128, {1: cached}) as r2:
        (a, da), (b, db) = r1.render(K, [(1, R, t)]), r2.render(K, [(1, R, t)])
    assert (da > 0).sum() > 500 and np.array_equal(a, b) and np.array_equal(da, db)
    monkeypatch.undo()
    monkeypatch.setenv("AUTOPOSE_CACHE", str(tmp_path / "cache"))
    entry.write_bytes(b"not an npz")
    again = dec.decimate_mesh(mesh, 3000, cache=True)
    assert np.array_equal(again.vertices, fresh.vertices)
    dec.decimate_mesh(mesh, 2000, cache=True)
    assert len(list((tmp_path / "cache").glob("decimated_*.npz"))) == 2


def test_cached_hull_gives_the_hull_and_diameter_and_reads_them_back(lmo_models, tmp_path, monkeypatch):
    import tracker.core.meshes as meshes
    from tracker.core.meshes import cached_hull, diameter, hull_vertices
    monkeypatch.setenv("AUTOPOSE_CACHE", str(tmp_path / "cache"))
    v = np.asarray(lmo_models[8].mesh.vertices)
    hull, d = cached_hull(v)
    assert np.array_equal(hull, hull_vertices(v)) and d == diameter(v)
    assert len(list((tmp_path / "cache").glob("hull_*.npz"))) == 1

    calls = []
    real = meshes.ConvexHull
    monkeypatch.setattr(meshes, "ConvexHull", lambda *a, **k: calls.append(1) or real(*a, **k))
    again, d2 = cached_hull(v.copy())  # the same bytes: read back, not computed
    assert np.array_equal(again, hull) and d2 == d and not calls
    cached_hull(v * 1.001)  # other vertices: another entry
    assert len(calls) == 1 and len(list((tmp_path / "cache").glob("hull_*.npz"))) == 2
    for f in (tmp_path / "cache").glob("hull_*.npz"):
        f.write_bytes(b"half a file")  # damaged: computed again
    assert np.array_equal(cached_hull(v)[0], hull) and len(calls) == 2
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)  # degenerate: all vertices
    assert len(cached_hull(flat)[0]) == 4 and cached_hull(flat)[1] == pytest.approx(np.sqrt(2))
