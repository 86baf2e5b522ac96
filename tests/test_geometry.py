import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from tracker.core import geometry as G

finite = st.floats(-1.0, 1.0, allow_nan=False)
quat = arrays(np.float64, 4, elements=finite).filter(lambda q: np.linalg.norm(q) > 1e-3)


def rot(q):
    return G.matrix_from_quat(q)


@given(quat)
def test_6d_round_trip(q):
    R = rot(q)
    assert np.allclose(G.matrix_from_rot6d(G.rot6d_from_matrix(R)), R, atol=1e-9)


@given(arrays(np.float64, 6, elements=st.floats(-10, 10, allow_nan=False)))
def test_gram_schmidt_gives_a_rotation(d6):
    a, b = d6[:3], d6[3:]
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    # only non-degenerate inputs: both vectors present and not parallel
    if na < 1e-3 or nb < 1e-3 or np.linalg.norm(np.cross(a / na, b / nb)) < 1e-3:
        return
    R = G.matrix_from_rot6d(d6)
    assert G.is_rotation(R, tol=1e-8)
    assert np.allclose(R[:, 0], a / na)  # first column keeps the first vector's direction


@given(quat)
def test_quaternion_round_trip(q):
    R = rot(q)
    q2 = G.quat_from_matrix(R)
    assert q2[0] >= 0
    assert np.isclose(np.linalg.norm(q2), 1.0)
    qn = q / np.linalg.norm(q)
    assert np.allclose(q2, qn, atol=1e-7) or np.allclose(q2, -qn, atol=1e-7)
    assert np.allclose(G.matrix_from_quat(q2), R, atol=1e-9)


@given(quat)
def test_axis_angle_round_trip(q):
    R = rot(q)
    rv = G.axis_angle_from_matrix(R)
    assert np.linalg.norm(rv) <= np.pi + 1e-9
    assert np.allclose(G.matrix_from_axis_angle(rv), R, atol=1e-9)


@given(quat, st.floats(0.0, 179.0))
def test_rotation_error_is_the_angle_between(q, angle):
    R = rot(q)
    axis = np.array([0.3, -0.5, 0.8])
    D = G.matrix_from_axis_angle(axis / np.linalg.norm(axis) * np.radians(angle))
    assert np.isclose(G.rotation_error_deg(D @ R, R), angle, atol=1e-4)


def test_translation_error():
    assert G.translation_error([1, 2, 3], [1, 2, 13]) == pytest.approx(10.0)


def K_strategy():
    return st.tuples(st.floats(200, 2000), st.floats(200, 2000), st.floats(100, 900), st.floats(100, 700)).map(
        lambda p: np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]]))


@given(K_strategy(), st.floats(-300, 300), st.floats(-300, 300), st.floats(200, 3000), quat)
def test_project_then_recover_translation(K, tx, ty, tz, q):
    t = np.array([tx, ty, tz])
    centre = G.project(np.zeros((1, 3)), K, rot(q), t)[0]
    assert np.allclose(G.translation_from_centre(centre, tz, K), t, rtol=1e-9, atol=1e-6)


def test_translation_from_centre_takes_one_intrinsics_per_centre():
    rng = np.random.default_rng(1)
    Ks = np.stack([np.array([[f, 0, cx], [0, f * 1.01, cy], [0, 0, 1.0]])
                   for f, cx, cy in zip(rng.uniform(300, 900, 5), rng.uniform(100, 400, 5), rng.uniform(100, 300, 5))])
    centres, tz = rng.uniform(0, 640, (5, 2)), rng.uniform(300, 2000, 5)
    each = np.stack([G.translation_from_centre(c, z, K) for c, z, K in zip(centres, tz, Ks)])
    assert np.array_equal(G.translation_from_centre(centres, tz, Ks), each)
    assert not np.allclose(G.translation_from_centre(centres, tz, Ks[0]), each)


@given(K_strategy(), arrays(np.float64, 3, elements=st.floats(-200, 200)), st.floats(300, 2000),
       st.sampled_from([(320, 240), (1280, 960), (160, 120), (800, 600)]))
def test_scaled_intrinsics_project_to_scaled_pixels(K, p, z, size):
    P = p + np.array([0, 0, z])
    uv = G.project(P[None], K)[0]
    K2 = G.scale_intrinsics(K, (640, 480), size)
    s = np.array([size[0] / 640, size[1] / 480])
    assert np.allclose(G.project(P[None], K2)[0], (uv + 0.5) * s - 0.5, atol=1e-6)


@given(st.floats(300, 2000), st.floats(300, 2000), st.floats(200, 3000))
def test_depth_rescaling_keeps_apparent_size(f1, f2, z):
    size_mm = 100.0
    px = f1 * size_mm / z  # apparent size on camera 1
    z2 = G.rescale_depth(z, f1, f2)
    assert np.isclose(f2 * size_mm / z2, px)


boxes = st.tuples(st.floats(-50, 600), st.floats(-50, 400), st.floats(2, 300), st.floats(2, 300))


@given(boxes, st.sampled_from([32, 64, 128]))
def test_crop_mapping_is_invertible_and_covers_the_box(box, size):
    crop = G.square_crop(box, size)
    x, y, w, h = box
    # box corners in pixel-centre coordinates
    corners = np.array([[x - 0.5, y - 0.5], [x + w - 0.5, y + h - 0.5]])
    c = crop.to_crop(corners)
    assert np.allclose(crop.to_image(c), corners)
    # the longer side spans the whole crop, the box stays centred
    assert np.isclose(max(c[1, 0] - c[0, 0], c[1, 1] - c[0, 1]), size)
    assert np.allclose((c[0] + c[1]) / 2, (size - 1) / 2)


def test_crop_and_resize_puts_a_pixel_where_the_mapping_says():
    img = np.zeros((480, 640, 3), np.uint8)
    img[200:204, 300:304] = 255  # a 4x4 blob centred at (301.5, 201.5)
    crop = G.square_crop((280, 180, 64, 40), 128)
    out = G.crop_and_resize(img, crop, interpolation=0)  # nearest: no ringing
    ys, xs = np.nonzero(out[..., 0] > 128)
    expect = crop.to_crop([[301.5, 201.5]])[0]
    assert np.allclose([xs.mean(), ys.mean()], expect, atol=0.6)
    # out-of-image parts are filled
    crop2 = G.square_crop((-30, -30, 40, 40), 64)
    out2 = G.crop_and_resize(np.full((480, 640, 3), 200, np.uint8), crop2, fill=0)
    assert out2[0, 0].max() == 0 and out2[-1, -1].min() == 200


@given(boxes, arrays(np.float64, 2, elements=st.floats(-0.5, 0.5)))
def test_box_offset_round_trip(box, off):
    b = np.array(box)
    c = G.centre_from_box_offset(b, off)
    assert np.allclose(G.box_offset_of_centre(b, c), off, atol=1e-9)


@given(quat, st.floats(-100, 100), st.floats(-100, 100), st.floats(500, 1500))
def test_box_features_do_not_depend_on_the_camera(q, tx, ty, tz):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-50, 50, (200, 3))
    R, t = rot(q), np.array([tx, ty, tz])
    K1 = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    K2 = G.scale_intrinsics(np.array([[900.0, 0, 330], [0, 905.0, 250], [0, 0, 1]]), (640, 480), (1280, 960))
    f1 = G.box_features(G.box_from_points(G.project(pts, K1, R, t)), K1)[0]
    f2 = G.box_features(G.box_from_points(G.project(pts, K2, R, t)), K2)[0]
    # equal up to the one-pixel mask convention of box_from_points
    assert np.allclose(f1, f2, atol=2.0 / 570)


def test_is_rotation_rejects_reflections_and_garbage():
    assert G.is_rotation(np.eye(3))
    assert not G.is_rotation(np.diag([1.0, 1.0, -1.0]))
    assert not G.is_rotation(np.full((3, 3), np.nan))
    assert not G.is_rotation(np.eye(3) * 2)


def test_square_crop_rejects_empty_boxes():
    with pytest.raises(ValueError):
        G.square_crop((0, 0, 0, 10), 64)


@given(boxes, quat, st.floats(-100, 100), st.floats(-100, 100), st.floats(400, 1500))
def test_crop_intrinsics_project_into_the_crop(box, q, tx, ty, tz):
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    crop = G.square_crop(box, 128)
    pts = np.random.default_rng(1).uniform(-50, 50, (20, 3))
    R, t = rot(q), np.array([tx, ty, tz])
    assert np.allclose(G.project(pts, crop.intrinsics(K), R, t), crop.to_crop(G.project(pts, K, R, t)), atol=1e-6)


@given(boxes, st.floats(0.6, 1.0), st.floats(-0.2, 0.2), st.floats(-0.2, 0.2))
def test_window_within_a_window_crops_the_same(box, shrink, dx, dy):
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640, 3)).astype(np.float32), (0, 0), 3)
    outer = G.square_crop(box, 256, pad=1.3)
    x, y, w, h = box
    inner = G.square_crop((x + dx * w, y + dy * h, w * shrink, h * shrink), 32)
    direct = G.crop_and_resize(img, inner, interpolation=cv2.INTER_LINEAR)
    via = G.crop_and_resize(G.crop_and_resize(img, outer, interpolation=cv2.INTER_LINEAR),
                            inner.within(outer), interpolation=cv2.INTER_LINEAR)
    # compare where the inner window lies inside the image and inside the outer window
    pts = inner.to_image(np.stack(np.meshgrid(np.arange(32), np.arange(32)), -1).reshape(-1, 2))
    ok = ((pts >= 2) & (pts < [638, 478])).all(1) & ((outer.to_crop(pts) >= 1) & (outer.to_crop(pts) < 255)).all(1)
    if ok.sum() < 50:
        return
    diff = np.abs(direct.reshape(-1, 3) - via.reshape(-1, 3))[ok]
    assert np.median(diff) < 3.0


@given(st.floats(-400, 1000), st.floats(-300, 800), quat)
def test_ray_rotation_turns_the_camera_to_look_at_the_object(u, v, q):
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    R_ray = G.ray_rotation(np.array([u, v]), K)
    assert G.is_rotation(R_ray)
    t = G.translation_from_centre(np.array([u, v]), 800.0, K)
    # in the camera turned by R_ray the object sits on the optical axis ...
    assert np.allclose(R_ray.T @ t, [0, 0, np.linalg.norm(t)], atol=1e-6)
    # ... and it is the smallest such turn: about an axis in the image plane, no roll
    assert abs(Rotation.from_matrix(R_ray).as_rotvec()[2]) < 1e-9
    # egocentric = R_ray @ allocentric, batched like the single call
    R = rot(q)
    both = G.ray_rotation(np.array([[u, v], [K[0, 2], K[1, 2]]]), np.stack([K, K]))
    assert np.allclose(both[0], R_ray) and np.allclose(both[1], np.eye(3))
    assert np.allclose(R_ray @ (R_ray.T @ R), R)


def test_mean_pose_of_equal_estimates_is_that_pose():
    R = Rotation.random(3, random_state=1).as_matrix()
    t = np.array([[10.0, -20.0, 800.0], [0.0, 5.0, 1200.0], [-40.0, 30.0, 650.0]])
    Rm, tm = G.mean_pose(np.stack([R, R, R]), np.stack([t, t, t]))
    assert np.allclose(Rm, R, atol=1e-9) and np.allclose(tm, t)


def test_chordal_mean_is_scipys_mean_for_every_object_at_once():
    R = Rotation.random(5 * 7, random_state=3).as_matrix().reshape(5, 7, 3, 3)
    R[:, 0] = R[0, 0]  # one object whose estimates agree
    want = np.stack([Rotation.from_matrix(R[:, n]).mean().as_matrix() for n in range(7)])
    assert np.allclose(G.chordal_mean(R), want, atol=1e-9)
    assert G.chordal_mean(R[:, :0]).shape == (0, 3, 3)


def test_mean_pose_halves_opposite_turns_and_averages_distance_along_the_ray():
    base = Rotation.from_euler("xyz", [30, -10, 60], degrees=True)
    turns = [Rotation.from_rotvec([0, 0, s * np.radians(20)]) for s in (1, -1)]
    R = np.stack([(base * q).as_matrix()[None] for q in turns])  # (2, 1, 3, 3)
    ray = np.array([0.1, -0.05, 1.0])
    t = np.stack([(500 * ray)[None], (2000 * ray)[None]])
    Rm, tm = G.mean_pose(R, t)
    assert G.rotation_error_deg(Rm[0], base.as_matrix()) < 1e-4  # arccos: ~1e-6 deg of rounding
    assert np.allclose(tm[0], 1000 * ray)  # the geometric mean of 500 and 2000, on the same ray
    with pytest.raises(ValueError):
        G.mean_pose(R, t[:, :, :2])
