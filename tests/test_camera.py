import shutil

import cv2
import numpy as np
import pytest

from tracker.core.calibration import calibrate, parse_board
from tracker.core.camera import Camera, Undistorter, read_camera, write_camera
from tracker.core.errors import UserError

ROS_YAML = """image_width: 640
image_height: 480
camera_name: webcam
camera_matrix:
  rows: 3
  cols: 3
  data: [600.0, 0.0, 320.0, 0.0, 610.0, 240.0, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.1, 0.01, 0.0, 0.0, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
"""


def test_read_opencv_reference_file(data_dir):
    cam = read_camera(data_dir / "calib_opencv" / "left_intrinsics.yml")
    assert cam.size == (640, 480)
    assert cam.K[0, 0] == pytest.approx(535.9157, abs=1e-3)
    assert cam.dist.size == 5 and cam.dist[0] == pytest.approx(-0.26637, abs=1e-4)


def test_write_then_read_round_trip(tmp_path):
    cam = Camera(np.array([[500.5, 0, 321.2], [0, 501.5, 239.8], [0, 0, 1]]), 640, 480,
                 np.array([-0.2, 0.05, 0.001, -0.002, 0.01]))
    p = write_camera(tmp_path / "cam.yml", cam)
    back = read_camera(p)
    assert np.allclose(back.K, cam.K) and np.allclose(back.dist, cam.dist) and back.size == cam.size


def test_read_ros_camera_info(tmp_path):
    p = tmp_path / "ros.yaml"
    p.write_text(ROS_YAML)
    cam = read_camera(p)
    assert cam.K[1, 1] == 610.0 and cam.size == (640, 480) and cam.dist[0] == -0.1


@pytest.mark.parametrize("text", [
    "%YAML:1.0\n---\ncamera_matrix: [1, 2",                 # truncated OpenCV file
    "image_width: 640\nimage_height: 480\n",                  # no camera_matrix
    "image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: [1, 2, 3]}\n",
    "image_width: 640\nimage_height: 480\ncamera_matrix: {rows: x, cols: 3, data: [600, 0, 320, 0, 600, 240, 0, 0, 1]}\n",
    "camera_matrix: [0, 0, 320, 0, 600, 240, 0, 0, 1]\nimage_width: 640\nimage_height: 480\n",  # fx = 0
    "just text, not yaml: [",
    "\x00\x01\x02 binary",
])
def test_garbled_camera_files_are_user_errors(tmp_path, text):
    p = tmp_path / "bad.yml"
    p.write_text(text)
    with pytest.raises(UserError):
        read_camera(p)


def test_a_null_distortion_is_named_as_empty(tmp_path):
    p = tmp_path / "ros.yaml"
    p.write_text("image_width: 640\nimage_height: 480\ncamera_matrix: [600, 0, 320, 0, 600, 240, 0, 0, 1]\n"
                 "distortion_coefficients: null\n")
    with pytest.raises(UserError, match="'distortion_coefficients' is empty; give its numbers .or leave it out"):
        read_camera(p)
    p.write_text("image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: null}\n")
    with pytest.raises(UserError, match="'camera_matrix' is empty; give its numbers$"):
        read_camera(p)


def test_missing_camera_file(tmp_path):
    with pytest.raises(UserError, match="not found"):
        read_camera(tmp_path / "nope.yml")


def test_camera_at_other_resolution_and_aspect_mismatch():
    cam = Camera(np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]), 640, 480)
    half = cam.at_size(320, 240)
    assert half.K[0, 0] == 300.0 and half.K[0, 2] == pytest.approx(159.5)
    with pytest.raises(UserError, match="aspect ratio"):
        cam.at_size(640, 360)


def test_undistortion_moves_points_to_their_pinhole_projection():
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    dist = np.array([-0.3, 0.1, 0.0, 0.0, 0.0])
    cam = Camera(K, 640, 480, dist)
    P = np.array([[0.5, 0.35, 1.0]])  # far off-axis: strong barrel distortion
    distorted, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)
    ideal, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, None)
    d, i = distorted.ravel(), ideal.ravel()
    assert np.linalg.norm(d - i) > 10
    img = np.zeros((480, 640, 3), np.uint8)
    cv2.circle(img, (int(round(d[0])), int(round(d[1]))), 3, (255, 255, 255), -1)
    und = Undistorter(cam)(img)
    ys, xs = np.nonzero(und[..., 0] > 100)
    assert np.hypot(xs.mean() - i[0], ys.mean() - i[1]) < 1.5
    # frames of another size use the rescaled camera
    assert Undistorter(cam).camera_for(320, 240).K[0, 0] == 250.0


def test_parse_board():
    assert parse_board("9x6") == (9, 6)
    for bad in ("2x2", "3x2", "99999999999x6"):  # OpenCV's finder wants > 2 each way; no giant grids
        with pytest.raises(UserError, match="3 to 100 inner corners"):
            parse_board(bad)
    with pytest.raises(UserError):
        parse_board("nine by six")


def test_calibration_on_real_photos_matches_opencv(data_dir):
    ref = read_camera(data_dir / "calib_opencv" / "left_intrinsics.yml")
    res = calibrate((9, 6), 25.0, images=str(data_dir / "calib_opencv" / "left*.jpg"), log=lambda m: None)
    assert res.rms_px <= 0.5
    assert len(res.used) == 13
    assert abs(res.camera.K[0, 0] / ref.K[0, 0] - 1) < 0.01
    assert abs(res.camera.K[1, 1] / ref.K[1, 1] - 1) < 0.01


def test_copies_of_one_view_count_once(data_dir, tmp_path):
    """Three copies of a photo (or a board held still before a camera) are one view: a
    calibration from them would report a small error and a focal length far off."""
    for k in range(3):
        shutil.copy(data_dir / "calib_opencv" / "left01.jpg", tmp_path / f"v{k}.jpg")
    logged = []
    with pytest.raises(UserError, match="only 1 distinct view"):
        calibrate((9, 6), 25.0, images=str(tmp_path / "v*.jpg"), log=logged.append)
    assert sum("(the same view as" in m for m in logged) == 2


def test_bad_camera_values_and_file_names_are_refused(tmp_path):
    (tmp_path / "c0.yaml").write_text(ROS_YAML.replace("320.0, 0.0, 610.0, 240.0", "0.0, 0.0, 610.0, 0.0"))
    with pytest.raises(UserError, match=r"principal point \(0, 0\) lies outside the 640x480 image"):
        read_camera(tmp_path / "c0.yaml")
    (tmp_path / "inf.yaml").write_text(ROS_YAML.replace("image_width: 640", "image_width: .inf"))
    with pytest.raises(UserError, match="must be integers"):
        read_camera(tmp_path / "inf.yaml")
    cam = Camera(np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]), 640, 480)
    for name in ("cam.xml", "cam.yaml.gz", "cam.json"):  # OpenCV would write XML, gzip, JSON: unreadable here
        with pytest.raises(UserError, match="name it .yaml or .yml"):
            write_camera(tmp_path / name, cam)
        assert not (tmp_path / name).exists()


def test_calibration_lists_skipped_views_and_needs_three(data_dir, tmp_path):
    src = data_dir / "calib_opencv"
    for name in ("left01.jpg", "left02.jpg"):
        shutil.copy(src / name, tmp_path / name)
    bg = next((data_dir / "backgrounds").glob("*.jpg"))
    img = cv2.resize(cv2.imread(str(bg)), (640, 480))
    cv2.imwrite(str(tmp_path / "left99.jpg"), img)
    (tmp_path / "left98.jpg").write_bytes(b"not an image")
    logged = []
    with pytest.raises(UserError, match="need at least 3"):
        calibrate((9, 6), 25.0, images=str(tmp_path / "left*.jpg"), log=logged.append)
    assert any("left99.jpg (board not found)" in m for m in logged)
    assert any("left98.jpg (unreadable)" in m for m in logged)
