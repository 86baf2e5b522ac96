"""synth --renderer cycles: Blender's Cycles for the targets' pixels. The failure paths run
everywhere (a stand-in 'blender'); the renders themselves only where Blender is installed
(apt install blender: an optional tool, not in CI)."""
import json
import shutil
import stat

import cv2
import numpy as np
import pytest
import trimesh

from tracker.core.errors import UserError
from tracker.training.synth import cycles
from tracker.training.synth.engine import SynthConfig, generate

OBJS = [1, 5, 9]
HAVE_BLENDER = shutil.which("blender") is not None
needs_blender = pytest.mark.skipif(not HAVE_BLENDER, reason="Blender is not installed (apt install blender)")


def _cfg(data_dir, **kw):
    return SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                       obj_ids=list(OBJS), **kw)


def _fake_blender(tmp_path, body: str) -> str:
    exe = tmp_path / "blender"
    exe.write_text("#!/bin/sh\n" + body + "\n")
    exe.chmod(exe.stat().st_mode | stat.S_IEXEC)
    return str(exe)


def _box(colour=(200, 60, 40, 255)):
    m = trimesh.creation.box(extents=(60.0, 40.0, 30.0))
    m.visual.vertex_colors = np.tile(np.array(colour, np.uint8), (len(m.vertices), 1))
    return m


def test_no_blender_is_one_line_before_any_image(tmp_path, data_dir, monkeypatch):
    monkeypatch.setenv("AUTOPOSE_BLENDER", str(tmp_path / "nowhere" / "blender"))
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(UserError, match="apt install blender") as e:
        generate(_cfg(data_dir, renderer="cycles"), tmp_path / "out", 2, workers=1, progress=False)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "out").exists()


def test_cycles_refuses_the_rasteriser_options(tmp_path, data_dir):
    with pytest.raises(UserError, match="--gloss 0"):
        generate(_cfg(data_dir, renderer="cycles", p_gloss=0.5), tmp_path / "a", 2, workers=1, progress=False)
    with pytest.raises(UserError, match="unknown renderer"):
        generate(_cfg(data_dir, renderer="povray"), tmp_path / "b", 2, workers=1, progress=False)


def test_a_blender_that_dies_is_an_error_not_a_hang(tmp_path, monkeypatch):
    monkeypatch.setenv("AUTOPOSE_BLENDER", _fake_blender(tmp_path, "echo 'Error: no GPU, no luck' >&2; exit 3"))
    with pytest.raises(UserError, match=r"Blender exited \(code 3\): Error: no GPU, no luck"):
        cycles.CyclesRenderer(64, 48, {1: _box()})


def test_a_blender_that_stalls_is_an_error_not_a_hang(tmp_path, monkeypatch):
    monkeypatch.setenv("AUTOPOSE_BLENDER", _fake_blender(tmp_path, "echo 'reading'; exec sleep 60"))
    monkeypatch.setattr(cycles, "START_TIMEOUT", 1.0)
    with pytest.raises(UserError, match="no answer in 1 s"):
        cycles.CyclesRenderer(64, 48, {1: _box()})


def test_a_blender_error_comes_back_as_its_line(tmp_path, monkeypatch):
    # answers the init, then reports an error for the render, as cycles_blender.py does
    body = "read a; echo 'AUTOPOSE ok'; read b; echo 'AUTOPOSE error KeyError: 7'; exec sleep 60"
    monkeypatch.setenv("AUTOPOSE_BLENDER", _fake_blender(tmp_path, body))
    r = cycles.CyclesRenderer(64, 48, {1: _box()})
    with pytest.raises(UserError, match="Blender: error KeyError: 7"):
        r.render(np.array([[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]]), [(7, np.eye(3), [0, 0, 500])],
                 [((0, 0, 1), (1, 1, 1), 3.0)], 0.3)
    r.close()


@needs_blender
def test_cycles_draws_where_the_rasteriser_does():
    """The camera conventions (OpenCV frame, pixel centres, principal point, fx != fy): the two
    renderers' silhouettes of the same poses agree, a second instance of one mesh included."""
    from tracker.runtime.render import Renderer
    from scipy.spatial.transform import Rotation
    W, H = 160, 120
    K = np.array([[300.0, 0, 90.3], [0, 304.0, 52.8], [0, 0, 1]])  # off-centre, non-square pixels
    meshes = {1: _box(), 2: _box((40, 90, 220, 255))}
    inst = [(1, Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix(), np.array([-40.0, 10.0, 600.0])),
            (2, Rotation.from_euler("xyz", [-30, 5, 60], degrees=True).as_matrix(), np.array([50.0, -20.0, 700.0])),
            (1, Rotation.from_euler("xyz", [0, 80, 0], degrees=True).as_matrix(), np.array([10.0, 60.0, 800.0]))]
    lights = [((0.2, 0.5, 1.0), (1.0, 1.0, 1.0), 3.0)]
    r = cycles.CyclesRenderer(W, H, meshes, threads=2, samples=4)
    rgb, alpha = r.render(K, inst, lights, 0.3)
    r.close()
    ras = Renderer(W, H, meshes)
    _, depth = ras.render(K, inst)
    a, b = alpha > 0.5, depth > 0
    assert (a & b).sum() / (a | b).sum() > 0.97
    ya, xa = np.nonzero(a)
    yb, xb = np.nonzero(b)
    assert abs(xa.mean() - xb.mean()) < 0.3 and abs(ya.mean() - yb.mean()) < 0.3
    assert rgb[a].mean() > 10 and rgb.shape == (H, W, 3)


@needs_blender
def test_a_cycles_split_has_the_rasters_annotations_and_other_targets(tmp_path, data_dir):
    ra, cy = tmp_path / "raster", tmp_path / "cycles"
    generate(_cfg(data_dir, seed=3), ra, 2, workers=1, progress=False)
    generate(_cfg(data_dir, seed=3, renderer="cycles"), cy, 2, workers=1, progress=False)
    for f in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"):
        assert json.loads((ra / "000000" / f).read_text()) == json.loads((cy / "000000" / f).read_text())
    assert json.loads((cy / "synth_config.json").read_text())["config"]["renderer"] == "cycles"
    for im in range(2):
        a = cv2.imread(str(ra / "000000" / "rgb" / f"{im:06d}.jpg")).astype(int)
        b = cv2.imread(str(cy / "000000" / "rgb" / f"{im:06d}.jpg")).astype(int)
        masks = [cv2.imread(str(p), 0) > 0 for p in sorted((ra / "000000" / "mask_visib").glob(f"{im:06d}_*.png"))]
        targets = np.any(masks, axis=0)
        near = cv2.dilate(targets.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        assert np.abs(a - b)[targets].mean() > 3  # the targets are drawn anew
        assert np.abs(a - b)[~near].mean() < 1  # the rest is the same image (JPEG aside)
