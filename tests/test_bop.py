import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tracker.core import bop
from tracker.core.errors import UserError
from tracker.core.geometry import matrix_from_axis_angle, project


def test_load_dev_scene(lmo_dev):
    assert len(lmo_dev.im_ids) == 50
    assert lmo_dev.im_ids[0] == 3
    img = lmo_dev.read_rgb(3)
    assert img.shape == (480, 640, 3) and img.dtype == np.uint8
    assert np.allclose(lmo_dev.K(3)[0], [572.4114, 0, 325.2611])
    ids = {g.obj_id for gts in lmo_dev.gt.values() for g in gts}
    assert ids == {1, 5, 6, 8, 9, 10, 11, 12}


def test_scene_round_trip(lmo_dev, tmp_path):
    bop.save_scene_camera(tmp_path / "scene_camera.json", lmo_dev.cameras)
    bop.save_scene_gt(tmp_path / "scene_gt.json", lmo_dev.gt)
    cams = bop.load_scene_camera(tmp_path / "scene_camera.json")
    gt = bop.load_scene_gt(tmp_path / "scene_gt.json")
    assert set(cams) == set(lmo_dev.cameras) and np.allclose(cams[8]["K"], lmo_dev.K(8))
    for k in lmo_dev.gt:
        for a, b in zip(gt[k], lmo_dev.gt[k]):
            assert a.obj_id == b.obj_id and np.allclose(a.R, b.R) and np.allclose(a.t, b.t)


def test_scene_gt_info_is_attached(tmp_path, lmo_dev):
    insts = [bop.GtInstance(g.obj_id, g.R, g.t, {"bbox_obj": [1, 2, 3, 4], "visib_fract": 0.5})
             for g in lmo_dev.gt[3]]
    bop.save_scene_gt(tmp_path / "scene_gt.json", {3: insts})
    bop.save_scene_gt_info(tmp_path / "scene_gt_info.json", {3: insts})
    back = bop.load_scene_gt(tmp_path / "scene_gt.json", tmp_path / "scene_gt_info.json")
    assert back[3][0].info == {"bbox_obj": [1, 2, 3, 4], "visib_fract": 0.5}


def _dev_copy(tmp_path, data_dir):
    """A copy of the dev scene to break."""
    return Path(shutil.copytree(data_dir / "lmo" / "dev", tmp_path / "scene"))


@pytest.mark.parametrize("remove", ["rgb", "scene_camera.json"])
def test_broken_scene_folders(tmp_path, data_dir, remove):
    dst = _dev_copy(tmp_path, data_dir)
    p = dst / remove
    shutil.rmtree(p) if p.is_dir() else p.unlink()
    with pytest.raises(UserError):
        bop.load_scene(dst)


def _mutate(path, change):
    d = json.loads(path.read_text())
    path.write_text(json.dumps(change(d)))


@pytest.mark.parametrize("file, change, match", [
    ("scene_camera.json", lambda d: {**d, "3": {**d["3"], "cam_K": [-572.4] + d["3"]["cam_K"][1:]}}, "focal lengths must be positive"),
    ("scene_camera.json", lambda d: {**d, "3": {**d["3"], "cam_K": [0] * 9}}, "focal lengths must be positive"),
    ("scene_camera.json", lambda d: {**d, "abc": d["3"]}, "'abc' is not an image id"),
    ("scene_camera.json", lambda d: list(d.values()), "expected an object keyed by image id"),
    ("scene_gt.json", lambda d: {**d, "3": [{**d["3"][0], "cam_R_m2c": [0] * 9}] + d["3"][1:]}, "not a rotation"),
    ("scene_gt.json", lambda d: {**d, "3": [{**d["3"][0], "cam_t_m2c": [0, float("nan"), 900]}] + d["3"][1:]},
     "not finite"),
    ("scene_gt.json", lambda d: {**d, "3": 5}, "expected a list"),
    ("scene_gt_info.json", lambda d: {"3": 5}, "expected a list"),
    ("scene_gt_info.json", lambda d: {"3": [{"bbox_visib": [1, 2, 3]}]}, "'bbox_visib' must be x, y, width, height"),
    ("scene_gt_info.json", lambda d: {"3": [{"bbox_obj": [1, 2, -3, 4]}]}, "'bbox_obj' must be"),
    ("scene_gt_info.json", lambda d: {"3": [{"visib_fract": float("nan")}]}, "'visib_fract' must be a number in"),
    ("scene_gt_info.json", lambda d: {"3": [{"visib_fract": "high"}]}, "'visib_fract' must be a number in"),
    ("scene_gt_info.json", lambda d: {"3": [{"px_count_visib": -1}]}, "'px_count_visib' must be a pixel count"),
])
def test_malformed_scene_files_are_refused(tmp_path, data_dir, file, change, match):
    dst = _dev_copy(tmp_path, data_dir)
    if file == "scene_gt_info.json":
        (dst / file).write_text("{}")
    _mutate(dst / file, change)
    with pytest.raises(UserError, match=match):
        bop.load_scene(dst)


def test_an_image_smaller_than_its_camera_is_refused(tmp_path, data_dir):
    import cv2
    dst = _dev_copy(tmp_path, data_dir)
    p = dst / "rgb" / "000003.png"
    cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (320, 240)))
    scene = bop.load_scene(dst)
    assert scene.read_rgb(8).shape == (480, 640, 3)
    with pytest.raises(UserError, match="image 3 is 320x240 but its cam_K puts the principal point at"):
        scene.read_rgb(3)


def test_bop_s_box_of_nothing_is_a_valid_info_entry(tmp_path, data_dir):
    dst = _dev_copy(tmp_path, data_dir)
    (dst / "scene_gt_info.json").write_text(json.dumps({"3": [{"bbox_visib": [-1, -1, -1, -1], "visib_fract": 0.0}]}))
    assert bop.load_scene(dst).gt[3][0].info["bbox_visib"] == [-1, -1, -1, -1]


def test_ground_truth_of_a_missing_frame_is_refused(tmp_path, data_dir):
    dst = _dev_copy(tmp_path, data_dir)
    (dst / "rgb" / "000003.png").unlink()
    cams = json.loads((dst / "scene_camera.json").read_text())
    del cams["3"]
    (dst / "scene_camera.json").write_text(json.dumps(cams))
    with pytest.raises(UserError, match=r"ground truth for image\(s\) \[3\] with no frame in rgb/"):
        bop.load_scene(dst)


def test_frames_of_two_sizes_are_named(tmp_path, data_dir):
    import cv2

    from tracker.core.geometry import scale_intrinsics
    dst = _dev_copy(tmp_path, data_dir)
    p = dst / "rgb" / "000008.png"
    cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (1280, 960)))
    cams = json.loads((dst / "scene_camera.json").read_text())
    K = scale_intrinsics(np.reshape(cams["8"]["cam_K"], (3, 3)), (640, 480), (1280, 960))
    cams["8"]["cam_K"] = K.ravel().tolist()
    (dst / "scene_camera.json").write_text(json.dumps(cams))
    scene = bop.load_scene(dst)
    assert scene.frame_size([3, 17]) == (640, 480)
    with pytest.raises(UserError, match="000008.png is 1280x960, image 3 640x480: a scene's frames must share one size"):
        scene.frame_size(scene.im_ids)


def test_scene_without_gt_when_gt_is_required(tmp_path, data_dir):
    dst = _dev_copy(tmp_path, data_dir)
    (dst / "scene_gt.json").unlink()
    assert bop.load_scene(dst).gt is None
    with pytest.raises(UserError, match="scene_gt.json"):
        bop.load_scene(dst, require_gt=True)


def test_corrupt_json_names_the_file(tmp_path):
    (tmp_path / "scene_camera.json").write_text("{ nope")
    with pytest.raises(UserError, match="scene_camera.json"):
        bop.load_scene_camera(tmp_path / "scene_camera.json")


def _est(im_id=3, obj_id=1, t=(1.0, 2.0, 900.0), time=0.02):
    R = matrix_from_axis_angle([0.1, 0.2, 0.3])
    return bop.Estimate(2, im_id, obj_id, 0.9, R, np.array(t), time)


def test_results_csv_round_trip(tmp_path):
    ests = [_est(3, 1), _est(3, 5, (5, 6, 700)), _est(8, 1, time=0.05)]
    p = bop.write_results(tmp_path / "r.csv", ests)
    assert p.read_text().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"
    back = bop.read_results(p, known_obj_ids={1, 5})
    assert len(back) == 3
    for a, b in zip(back, ests):
        assert (a.scene_id, a.im_id, a.obj_id) == (b.scene_id, b.im_id, b.obj_id)
        assert np.allclose(a.R, b.R, atol=1e-7) and np.allclose(a.t, b.t, atol=1e-5)
    bom = tmp_path / "bom.csv"  # saved by a spreadsheet as "CSV UTF-8": a byte-order mark first
    bom.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    assert len(bop.read_results(bom, known_obj_ids={1, 5})) == 3


@pytest.mark.parametrize("mutate,match", [
    (lambda lines: ["scene_id,im_id,obj_id,score,R,t"] + [ln.rsplit(",", 1)[0] for ln in lines[1:]], "missing column"),
    (lambda lines: lines[:2] + [lines[2].replace("0.9000", "abc")], ":3: unparsable"),
    (lambda lines: lines[:1] + [lines[1].replace(lines[1].split(",")[4], " ".join(["1"] * 9))] + lines[2:], ":2: R is not a rotation"),
    (lambda lines: lines[:2] + [lines[2].replace(",0.020000", ",0.030000")], ":3: time"),
    (lambda lines: lines[:1] + [lines[1].replace("2,3,1,", "2,3,77,", 1)] + lines[2:], ":2: unknown obj_id 77"),
    (lambda lines: lines[:2] + [lines[2].replace(",0.900000,", ",nan,")], ":3: score is not finite"),
])
def test_bad_results_csv_names_the_line(tmp_path, mutate, match):
    p = bop.write_results(tmp_path / "r.csv", [_est(3, 1), _est(3, 5)])
    lines = p.read_text().splitlines()
    p.write_text("\n".join(mutate(lines)) + "\n")
    with pytest.raises(UserError, match=match):
        bop.read_results(p, known_obj_ids={1, 5})


def test_a_binary_results_file_is_refused(tmp_path):
    (tmp_path / "r.csv").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(UserError, match="not a text file"):
        bop.read_results(tmp_path / "r.csv")


def test_a_json_output_that_is_a_folder_is_refused_before_writing(tmp_path):
    with pytest.raises(UserError, match="is a folder; name a file"):
        bop.save_models_info(tmp_path, {1: {"diameter": 1.0}})
    assert list(tmp_path.iterdir()) == [] and not tmp_path.with_suffix(".tmp").exists()


def test_symmetry_transforms_discretise_continuous_ones():
    info = {"diameter": 1.0, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
            "symmetries_discrete": [np.diag([1.0, -1.0, -1.0, 1.0]).ravel().tolist()]}
    T = bop.symmetry_transforms(info, continuous_steps=36)
    assert T.shape == (72, 4, 4)
    assert np.allclose(T[0], np.eye(4))
    assert all(np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3)) for t in T)


def test_continuous_symmetries_follow_bop_toolkits_default_step():
    # bop_toolkit: ceil(pi / max_sym_disc_step) with 0.01 -> 315 steps of 2 pi / 315 about the axis,
    # identity first, with the offset kept fixed: t = offset - R @ offset
    info = {"diameter": 100.0, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 10.0, 0]}]}
    T = bop.symmetry_transforms(info)
    assert T.shape == (315, 4, 4)
    step = 2 * np.pi / 315
    c, s = np.cos(step), np.sin(step)
    assert np.allclose(T[0], np.eye(4))
    assert np.allclose(T[1][:3, :3], [[c, -s, 0], [s, c, 0], [0, 0, 1]])
    assert np.allclose(T[1][:3, 3], np.array([0, 10.0, 0]) - T[1][:3, :3] @ [0, 10.0, 0])
    # a point 50 mm off the axis of a 100-mm object moves 0.997 mm a step: within 1 % of the diameter
    assert 50 * step < 0.01 * 100


def test_models_info_round_trip(tmp_path):
    info = {1: {"diameter": 102.1, "min_x": -1.0}, 10: {"diameter": 164.6}}
    bop.save_models_info(tmp_path / "models_info.json", info)
    assert json.loads((tmp_path / "models_info.json").read_text())["10"]["diameter"] == 164.6
    assert bop.load_models_info(tmp_path / "models_info.json") == info


@pytest.mark.parametrize("entry, match", [
    ({"diameter": -102.1}, "positive number"),       # a negative diameter would inflate every recall
    ({"diameter": 0}, "positive number"),
    ({"diameter": "102"}, "positive number"),
    ({"diameter": 102.1, "symmetries_discrete": [[1, 2, 3]]}, "4x4 transforms"),
    ({"diameter": 102.1, "symmetries_discrete": [[2.0] + [0.0] * 15]}, "not a rotation"),
    ({"diameter": 102.1, "symmetries_discrete": [np.diag([1.0, 1.0, -1.0, 1.0]).ravel().tolist()]}, "a reflection"),
    ({"diameter": 10 ** 400}, "positive number"),
    ({"diameter": 102.1, "symmetries_continuous": [{"axis": [0, 0, 0]}]}, "symmetries_continuous"),
    ([1, 2], "expected an object of objects"),
])
def test_bad_models_info_is_refused(tmp_path, entry, match):
    p = tmp_path / "models_info.json"
    p.write_text(json.dumps(entry if isinstance(entry, list) else {"1": entry}))
    with pytest.raises(UserError, match=match):
        bop.load_models_info(p)
    good = {"diameter": 164.6, "symmetries_discrete": [np.eye(4).ravel().tolist()],
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    p.write_text(json.dumps({"10": good}))
    assert bop.load_models_info(p)[10] == good


def test_gt_poses_project_onto_the_image(lmo_dev, lmo_models):
    """Every annotated object whose centre is in view projects to a plausible box."""
    n_in = 0
    for im_id in lmo_dev.im_ids:
        K = lmo_dev.K(im_id)
        for g in lmo_dev.gt[im_id]:
            assert 300 < g.t[2] < 2000  # table-top scene, about a metre away
            c = project(np.zeros((1, 3)), K, g.R, g.t)[0]
            if 0 <= c[0] < 640 and 0 <= c[1] < 480:
                n_in += 1
                uv = project(lmo_models[g.obj_id].vertices, K, g.R, g.t)
                # the object's own projection surrounds its centre, with a sane size
                assert (uv.min(0) <= c).all() and (uv.max(0) >= c).all()
                assert 15 < np.ptp(uv, axis=0).max() < 300
    assert n_in >= 380  # 391 instances, 7 of them with the centre outside the frame
