"""A scene read out at another resolution (`lab resize-scene`): the copy's intrinsics, boxes and
frames agree with the original's, and the pipeline poses the copy where it poses the original."""
import json
import shutil

import numpy as np
import pytest

from tests.test_cli import run
from tracker.core.bop import load_scene, read_results
from tracker.core.errors import UserError
from tracker.core.geometry import project
from tracker.evaluation.scene_copy import resize_scene


def _small_scene(data_dir, root, n=3):
    """The first ``n`` dev frames, with a made-up scene_gt_info entry to scale."""
    dev = data_dir / "lmo" / "dev"
    cams = json.loads((dev / "scene_camera.json").read_text())
    gts = json.loads((dev / "scene_gt.json").read_text())
    ids = sorted(cams, key=int)[:n]
    (root / "rgb").mkdir(parents=True)
    for i in ids:
        shutil.copy(dev / "rgb" / f"{int(i):06d}.png", root / "rgb")
    (root / "scene_camera.json").write_text(json.dumps({i: cams[i] for i in ids}))
    (root / "scene_gt.json").write_text(json.dumps({i: gts[i] for i in ids}))
    info = {i: [{"bbox_visib": [100, 60, 41, 81], "px_count_visib": 1000, "visib_fract": 0.5} for _ in gts[i]]
            for i in ids}
    (root / "scene_gt_info.json").write_text(json.dumps(info))
    return root


def test_a_copy_keeps_the_geometry_of_the_scene(data_dir, tmp_path):
    src = _small_scene(data_dir, tmp_path / "src")
    r = resize_scene(src, tmp_path / "small", 320, 240)
    assert r["frames"] == 3 and r["left_out"] == []
    a, b = load_scene(src), load_scene(tmp_path / "small")
    assert b.im_ids == a.im_ids
    for i in a.im_ids:
        big, small = a.read_rgb(i), b.read_rgb(i)
        assert small.shape == (240, 320, 3)
        # the same picture: each copy pixel is the mean of a 2x2 block of the original
        blocks = big.reshape(240, 2, 320, 2, 3).mean(axis=(1, 3))
        assert np.abs(blocks - small).mean() < 1.0
        for ga, gb in zip(a.gt[i], b.gt[i]):
            assert gb.obj_id == ga.obj_id and np.allclose(gb.R, ga.R) and np.allclose(gb.t, ga.t)
            # an object's centre lands on the same place of the picture (pixel centres at integers)
            pa = project(ga.t[None], a.cameras[i]["K"])[0]
            pb = project(gb.t[None], b.cameras[i]["K"])[0]
            assert np.allclose((pa + 0.5) / 2 - 0.5, pb, atol=1e-9)
            assert gb.info["bbox_visib"] == [50, 30, 20, 40] and gb.info["px_count_visib"] == 250
            assert gb.info["visib_fract"] == 0.5
    with pytest.raises(UserError, match="is the scene itself"):
        resize_scene(src, src, 320, 240)
    with pytest.raises(UserError, match="at least 16"):
        resize_scene(src, tmp_path / "tiny", 8, 6)


def test_the_pipeline_poses_a_copy_where_it_poses_the_scene(data_dir, tmp_path):
    """With the intrinsics scaled with the frames, the translations agree; a copy whose cam_K was
    left at full size would put every object twice as far."""
    src = _small_scene(data_dir, tmp_path / "src", n=2)
    p = run("lab", "resize-scene", "--data", src, "--out", tmp_path / "small", "--size", 320, 240)
    assert p.returncode == 0 and "2 frames at 320x240" in p.stdout, p.stderr
    est = {}
    for name in ("src", "small"):
        p = run("eval", "--model", "models/lmo", "--data", tmp_path / name, "--boxes", "gt",
                "--json", tmp_path / f"{name}.json", "--bop-csv", tmp_path / f"{name}.csv")
        assert p.returncode == 0, p.stderr
        est[name] = {(e.im_id, e.obj_id): e.t for e in read_results(tmp_path / f"{name}.csv")}
    assert est["src"].keys() == est["small"].keys() and len(est["src"]) >= 10
    rel = [np.linalg.norm(est["small"][k] - t) / np.linalg.norm(t) for k, t in est["src"].items()]
    assert np.median(rel) < 0.1, rel
