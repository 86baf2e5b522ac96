"""``lab oracle``: each part of the poses swapped for the truth's, on hand-made poses of three dev
frames whose one wrong part is known."""
import json

import numpy as np
import pytest

from tracker.core.bop import Estimate, load_scene, write_results
from tracker.core.errors import UserError
from tracker.evaluation.oracle import SWAPS, oracle_swaps, swap_with_truth


@pytest.fixture(scope="module")
def three_frames(data_dir, tmp_path_factory):
    """The first three dev frames as a scene of their own (images linked)."""
    src = data_dir / "lmo" / "dev"
    dst = tmp_path_factory.mktemp("three") / "scene"
    (dst / "rgb").mkdir(parents=True)
    cams, gts = (json.loads((src / f).read_text()) for f in ("scene_camera.json", "scene_gt.json"))
    keep = sorted(gts, key=int)[:3]
    for f, d in (("scene_camera.json", cams), ("scene_gt.json", gts)):
        (dst / f).write_text(json.dumps({k: d[k] for k in keep}))
    for k in keep:
        (im,) = (src / "rgb").glob(f"{int(k):06d}.*")
        (dst / "rgb" / im.name).symlink_to(im)
    return dst


def _truth(scene, R_turn=None, depth=1.0):
    R_turn = np.eye(3) if R_turn is None else R_turn
    return [Estimate(0, i, g.obj_id, 1.0, np.asarray(g.R) @ R_turn, np.asarray(g.t, float).reshape(3) * depth)
            for i in scene.im_ids for g in scene.gt[i]]


def _add(r):
    return {"as": r["as_estimated"]["add_recall"], **{p: v["metrics"]["add_recall"] for p, v in r["swaps"].items()}}


def test_the_wrong_part_is_the_one_whose_truth_restores_the_poses(three_frames, data_dir, tmp_path):
    scene = load_scene(three_frames, require_gt=True)
    models = data_dir / "lmo" / "models"
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg about the model's z
    far = write_results(tmp_path / "far.csv", _truth(scene, depth=1.1))   # the right ray, 10 % too far
    turned = write_results(tmp_path / "turned.csv", _truth(scene, R_turn=turn))
    r = oracle_swaps(far, three_frames, models, n_boot=200)
    assert _add(r) == {"as": 0.0, "rotation": 0.0, "translation": 1.0, "depth": 1.0, "ray": 0.0}
    gain = r["swaps"]["depth"]["compare"]["figures"]["add_recall"]
    assert gain["diff"] == 1.0 and gain["ci"] == [1.0, 1.0]
    a = _add(oracle_swaps(turned, three_frames, models, n_boot=200))
    # the eggbox and the glue are symmetric about z by half a turn, not a quarter: all wrong, but for
    # ADI's nearest-point distance, which a quarter turn of a near-symmetric shape may pass
    assert a["rotation"] == 1.0 and a["translation"] == a["depth"] == a["ray"] == a["as"] < 0.5


def test_estimates_of_objects_not_in_their_image_are_left_alone_and_parts_are_checked(three_frames):
    scene = load_scene(three_frames, require_gt=True)
    absent = ({1, 5, 6, 8, 9, 10, 11, 12} - {g.obj_id for g in scene.gt[scene.im_ids[0]]}) or {99}
    e = Estimate(0, scene.im_ids[0], min(absent), 0.5, np.eye(3), np.array([1.0, 2.0, 900.0]))
    for part in SWAPS:
        (out,) = swap_with_truth([e], scene, part)
        assert out is e
    with pytest.raises(UserError, match="unknown part 'scale'"):
        swap_with_truth([e], scene, "scale")


def test_a_ground_truth_rotation_a_little_off_orthonormal_is_swapped_in_as_a_rotation(three_frames):
    """Scenes accept rotations up to 0.05 off orthonormal, results files 1e-2: the swap writes the
    nearest rotation, or the oracle's own results file would be refused."""
    from tracker.core.geometry import is_rotation
    scene = load_scene(three_frames, require_gt=True)
    g = scene.gt[scene.im_ids[0]][0]
    g.R = g.R * 1.02  # 2 % off, as a scanned annotation may be
    e = Estimate(0, scene.im_ids[0], g.obj_id, 0.5, np.eye(3), np.asarray(g.t, float).reshape(3))
    (out,) = swap_with_truth([e], scene, "rotation")
    assert is_rotation(out.R, tol=1e-9) and np.allclose(out.R, g.R / 1.02, atol=5e-3)  # LM-O: 3e-3 off


def test_the_cli_writes_the_table_and_its_json(three_frames, data_dir, tmp_path, capsys):
    from tracker.cli.main import main
    scene = load_scene(three_frames, require_gt=True)
    res = write_results(tmp_path / "far.csv", _truth(scene, depth=1.1))
    out = tmp_path / "oracle.json"
    assert main(["lab", "oracle", "--results", str(res), "--data", str(three_frames), "--models",
                 str(data_dir / "lmo" / "models"), "--json", str(out), "--bootstrap", "100"]) == 0
    assert set(json.loads(out.read_text())["swaps"]) == set(SWAPS)
    assert "true depth" in capsys.readouterr().out
