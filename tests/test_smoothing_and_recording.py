"""Temporal pose smoothing and scenes packed as a video."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tracker.core.errors import UserError
from tracker.core.geometry import rotation_error_deg
from tracker.runtime.smoothing import PoseSmoother


def test_smoother_moves_part_of_the_way_and_resets():
    R0, R1 = np.eye(3), Rotation.from_euler("z", 40, degrees=True).as_matrix()
    s = PoseSmoother(alpha=0.25)
    s(1, R0, [0, 0, 500], 0)
    R, t = s(1, R1, [0, 0, 600], 1)
    assert rotation_error_deg(R, R0) == pytest.approx(10.0, abs=1e-6)
    np.testing.assert_allclose(t, [0, 0, 525])
    R, t = s(1, R1, [0, 0, 600], 20)  # unseen for 19 frames: restart from the new estimate
    assert rotation_error_deg(R, R1) < 1e-6
    R, t = s(2, R0, [0, 0, 500], 21)  # objects are independent
    assert rotation_error_deg(R, R0) < 1e-6
    s = PoseSmoother(alpha=0.25, reset_deg=90.0)
    s(1, R0, [0, 0, 500], 0)
    R2 = Rotation.from_euler("z", 120, degrees=True).as_matrix()
    R, t = s(1, R2, [0, 0, 500], 1)  # a jump beyond reset_deg restarts, no averaging across it
    assert rotation_error_deg(R, R2) < 1e-6
    R, t = s(1, R2, [0, 0, 900], 2)  # so does a translation jump beyond reset_mm
    np.testing.assert_allclose(t, [0, 0, 900])
    R, t = PoseSmoother(alpha=1.0)(1, R1, [1, 2, 3], 0)
    assert rotation_error_deg(R, R1) < 1e-6
    with pytest.raises(UserError):
        PoseSmoother(alpha=0.0)


def test_scene_as_video_reads_like_the_scene(data_dir, tmp_path):
    import json
    import shutil

    from tracker.core.bop import load_scene
    from tracker.runtime.recording import write_scene_video
    src = tmp_path / "src"
    (src / "rgb").mkdir(parents=True)
    dev = data_dir / "lmo" / "dev"
    cams = json.loads((dev / "scene_camera.json").read_text())
    gts = json.loads((dev / "scene_gt.json").read_text())
    ids = sorted(cams, key=int)[:4]
    for i in ids:
        shutil.copy(dev / "rgb" / f"{int(i):06d}.png", src / "rgb")
    (src / "scene_camera.json").write_text(json.dumps({i: cams[i] for i in ids}))
    (src / "scene_gt.json").write_text(json.dumps({i: gts[i] for i in ids}))
    r = write_scene_video(src, tmp_path / "rec")
    assert r["frames"] == 4 and r["psnr_min"] > 33
    low = write_scene_video(src, tmp_path / "low", quality=30)  # the quality reaches the encoder
    assert low["bytes"] < 0.7 * r["bytes"] and low["psnr_min"] < r["psnr_min"]
    a, b = load_scene(src), load_scene(tmp_path / "rec")
    assert b.im_ids == a.im_ids and b.video is not None
    for i in reversed(b.im_ids):  # random access (seeks) returns the right frame
        assert np.abs(a.read_rgb(i).astype(int) - b.read_rgb(i).astype(int)).mean() < 4
    assert len(b.gt[b.im_ids[0]]) == len(a.gt[a.im_ids[0]])
    cams["999999"] = cams[ids[0]]
    (tmp_path / "rec" / "scene_camera.json").write_text(json.dumps({i: cams[i] for i in ids + ["999999"]}))
    with pytest.raises(UserError, match="truncated"):
        load_scene(tmp_path / "rec")
