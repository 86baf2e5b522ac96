"""IMU comparison (issue 8): clock offset, mounting, RE, simple mode, log parsing."""
import csv
import json
import warnings

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tracker.evaluation import imu
from tracker.core.bop import Estimate, write_results
from tracker.core.errors import UserError
from tracker.core.geometry import rotation_error_deg

FPS = 30.0
OFFSET = 0.137  # IMU clock minus camera clock
MOUNT = Rotation.from_euler("xyz", [30, -50, 70], degrees=True)  # R_imu_obj
WORLD = Rotation.from_euler("zyx", [10, 80, -20], degrees=True)  # R_cam_world
# dropouts on the IMU clock (the trajectory starts at camera time 100 s)
GAPS = [(103.0, 103.6), (106.0, 106.45)]


def write_run(run_dir, times, R, obj_id=1, im_ids=None, extra=()):
    """A tracking run folder: poses.csv (BOP results) and timings.csv."""
    run_dir.mkdir(parents=True, exist_ok=True)
    im_ids = np.arange(len(times)) if im_ids is None else im_ids
    ests = [Estimate(0, int(i), obj_id, 0.9, Ri, np.array([0.0, 0.0, 600.0]), 0.02)
            for i, Ri in zip(im_ids, R)]
    ests += list(extra)
    write_results(run_dir / "poses.csv", ests)
    with open(run_dir / "timings.csv", "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["im_id", "t_capture", "capture", "total"])
        for i, t in zip(im_ids, times):
            w.writerow([int(i), f"{t:.6f}", "1.0", "20.0"])
    return run_dir


def noisy(R, deg, seed):
    """Tracked rotations: truth times a random rotation of RMS angle ``deg``."""
    rng = np.random.default_rng(seed)
    return (Rotation.from_matrix(R)
            * Rotation.from_rotvec(rng.normal(0, np.radians(deg) / np.sqrt(3), (len(R), 3)))).as_matrix()


@pytest.fixture(scope="module")
def trajectory():
    return imu.synthetic_trajectory(300, FPS, seed=1, t0=100.0)


@pytest.fixture(scope="module")
def noiseless(tmp_path_factory, trajectory):
    """A noiseless log and run (files), compared once and reused."""
    times, R = trajectory
    root = tmp_path_factory.mktemp("noiseless")
    log = imu.synth_imu_log(times, R, offset_s=-0.3, mounting=MOUNT, world_to_cam=WORLD, seed=2)
    imu.write_imu_log(root / "imu.csv", log)
    write_run(root / "run", times, R)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean log raises no warning
        run, rlog = imu.read_run(root / "run"), imu.read_imu_log(root / "imu.csv")
    return root, run, rlog, imu.compare(run, rlog)


# --------------------------------------------------------------------------- alignment


@pytest.mark.parametrize("with_gyro", [True, False])
def test_recovers_offset_and_mounting(tmp_path, trajectory, with_gyro):
    times, R = trajectory
    log = imu.synth_imu_log(times, R, offset_s=OFFSET, mounting=MOUNT, world_to_cam=WORLD,
                            noise_deg=0.5, gyro_bias_drift=0.02, dropouts=GAPS, seed=3,
                            with_gyro=with_gyro)
    imu.write_imu_log(tmp_path / "imu.csv", log)
    write_run(tmp_path / "run", times, noisy(R, 2.0, seed=4))
    run = imu.read_run(tmp_path / "run")
    rlog = imu.read_imu_log(tmp_path / "imu.csv")
    assert (rlog.gyro is not None) == with_gyro and len(rlog.gaps) == 2
    rep = imu.compare(run, rlog)

    assert abs(rep["time_offset_s"] - OFFSET) < 1.0 / FPS
    assert abs(rep["time_offset_s"] - OFFSET) < 0.005  # in practice about 1 ms
    mount = imu._as_matrix(rep["mounting_quat_wxyz"])
    world = imu._as_matrix(rep["world_to_cam_quat_wxyz"])
    assert rotation_error_deg(mount, MOUNT.as_matrix()) < 1.0
    assert rotation_error_deg(world, WORLD.as_matrix()) < 1.0
    assert rep["imu_quat_convention"] == "body_to_world" and rep["mounting_observable"]
    # 2 deg RMS tracking noise + 0.5 deg IMU noise + bias drift
    assert 1.0 < rep["re_median_deg"] < 3.0

    # frames whose IMU time falls in a dropout are left unpaired, the others are paired
    t_imu = run.t + OFFSET
    in_gap = np.zeros(len(run), bool)
    near_gap = np.zeros(len(run), bool)
    for a, b in GAPS:
        in_gap |= (t_imu >= a) & (t_imu <= b)
        near_gap |= (t_imu >= a - 0.05) & (t_imu <= b + 0.05)
    paired = np.isin(run.im_ids, rep["pairs"]["im_id"])
    assert not paired[in_gap].any()
    inside = (t_imu > rlog.t[0] + 0.05) & (t_imu < rlog.t[-1] - 0.05) & ~near_gap
    assert paired[inside].all()
    assert rep["n_pairs"] == paired.sum() and rep["n_unpaired_frames"] == (~paired).sum()

    files = imu.write_report(tmp_path / "out", rep)
    js = json.loads((tmp_path / "out" / "imu_report.json").read_text())
    for k in imu.REPORT_KEYS:
        assert k in js
    assert js["n_pairs"] == rep["n_pairs"] and "pairs" not in js
    for k in ("hist", "re_time", "tracks"):
        img = cv2.imread(str(files[k]))
        assert img is not None and img.shape[0] > 100 and img.std() > 5
    with open(files["pairs"]) as f:
        assert sum(1 for _ in f) == rep["n_pairs"] + 1


def test_noiseless_log_gives_zero_error(noiseless):
    _, _, _, rep = noiseless
    assert abs(rep["time_offset_s"] - (-0.3)) < 1e-3
    assert rep["re_max_deg"] < 0.1
    assert rotation_error_deg(imu._as_matrix(rep["mounting_quat_wxyz"]), MOUNT.as_matrix()) < 0.1
    assert rotation_error_deg(imu._as_matrix(rep["world_to_cam_quat_wxyz"]), WORLD.as_matrix()) < 0.1


def test_jerky_motion_does_not_mislead_the_gyro_offset(tmp_path, trajectory):
    """Poses a tenth of a turn apart from frame to frame (a replay of sparse frames): the gyro's
    rates follow the path between them, the camera's chord speed does not; the orientation
    signal correlates better and gives the offset."""
    times, R = trajectory
    rng = np.random.default_rng(5)
    jerky = Rotation.from_matrix(R) * Rotation.from_rotvec(rng.normal(0, 0.35, (len(R), 3)))
    jerky = jerky.as_matrix()
    log = imu.synth_imu_log(times, jerky, offset_s=OFFSET, mounting=MOUNT, world_to_cam=WORLD, seed=6)
    write_run(tmp_path / "run", times, jerky)
    rep = imu.compare(imu.read_run(tmp_path / "run"), log)
    # the orientation signal wins the cross-correlation and its peak alone is on the true offset
    # (about 0.1 ms off; the gyro's peak, lower, lies 45 ms off), then refined on the residual
    assert rep["xcorr_signal"] == "orientation" and rep["xcorr_peak"] > 0.8
    assert abs(rep["offset_xcorr_s"] - OFFSET) < 0.005
    assert abs(rep["time_offset_s"] - OFFSET) < 0.002  # in practice about 0.01 ms
    # noiseless poses and IMU: what is left is the IMU's 100 Hz sampling of the jerky path (median
    # about 1.1 deg, max 3.7; 45 ms off, the gyro's offset, gives a median of about 43 deg)
    assert rep["re_median_deg"] < 2.0 and rep["re_max_deg"] < 6.0
    assert rep["n_pairs"] >= 290 and rep["n_inconsistent_frames"] == 0  # 298 of 300 frames inside the log
    assert rotation_error_deg(imu._as_matrix(rep["mounting_quat_wxyz"]), MOUNT.as_matrix()) < 0.5
    assert rotation_error_deg(imu._as_matrix(rep["world_to_cam_quat_wxyz"]), WORLD.as_matrix()) < 0.5


def test_an_offset_search_wider_than_ten_minutes_is_refused(noiseless):
    _, run, rlog, _ = noiseless
    with pytest.raises(UserError, match=r"--max-offset must lie in \(0, 600\] s"):
        imu.estimate_time_offset(run, rlog, max_offset_s=1e9)


def test_an_imu_clock_far_from_the_run_is_named_briefly(noiseless):
    _, run, rlog, _ = noiseless
    far = imu.imu_log_from_arrays(1e300 * (1 + np.arange(len(rlog.t))), rlog.q, source="far.csv")
    with pytest.raises(UserError, match=r"does not overlap") as e:
        imu.estimate_time_offset(run, far)
    assert "1e+300 s" in str(e.value) and len(str(e.value)) < 300


def test_sign_flipped_quaternions_give_the_same_result(noiseless, tmp_path):
    root, run, log, rep = noiseless
    rng = np.random.default_rng(0)
    flip = np.where(rng.random(len(log)) < 0.3, -1.0, 1.0)
    flip[0] = -1.0
    flipped = imu.ImuLog(log.t, log.q * flip[:, None], log.gyro, log.max_gap_s)
    imu.write_imu_log(tmp_path / "flipped.csv", flipped)
    back = imu.read_imu_log(tmp_path / "flipped.csv")
    # continuous again (one sign for the whole log) and the same rotations
    assert np.all(np.sum(back.q[1:] * back.q[:-1], axis=1) > 0)
    assert np.allclose(np.abs(np.sum(back.q * log.q, axis=1)), 1.0, atol=1e-8)
    rep2 = imu.compare(run, back)
    assert rep2["time_offset_s"] == pytest.approx(rep["time_offset_s"], abs=1e-6)
    for k in ("re_mean_deg", "re_median_deg", "re_max_deg"):
        assert rep2[k] == pytest.approx(rep[k], abs=1e-4)
    assert rep2["n_pairs"] == rep["n_pairs"]


def test_inverted_quaternion_convention_is_detected(noiseless):
    _, run, log, rep = noiseless
    inv = imu.ImuLog(log.t, log.q * np.array([1.0, -1.0, -1.0, -1.0]), None, log.max_gap_s)
    rep2 = imu.compare(run, inv, time_offset_s=rep["time_offset_s"])
    assert rep2["imu_quat_convention"] == "world_to_body" and rep2["re_max_deg"] < 0.1


def test_tracking_outliers_do_not_break_the_alignment(trajectory):
    times, R = trajectory
    Rn = noisy(R, 2.0, seed=5)
    bad = np.random.default_rng(6).choice(len(R), 15, replace=False)
    Rn[bad] = Rotation.random(len(bad), random_state=7).as_matrix()
    log = imu.synth_imu_log(times, R, offset_s=OFFSET, mounting=MOUNT, world_to_cam=WORLD,
                            noise_deg=0.3, seed=8, with_gyro=False)
    rep = imu.compare(imu.Run(np.arange(len(times)), times, Rn, 1), log)
    assert abs(rep["time_offset_s"] - OFFSET) < 0.005
    assert rotation_error_deg(imu._as_matrix(rep["mounting_quat_wxyz"]), MOUNT.as_matrix()) < 1.0
    assert rep["re_median_deg"] < 3.0 and rep["re_max_deg"] > 30  # the outliers still count


# --------------------------------------------------------------------------- simple mode


def test_simple_mode_is_re_of_relative_rotations(tmp_path):
    n = 12
    times = 50.0 + 0.1 * np.arange(n)
    R_cam = Rotation.from_euler("xyz", np.stack([10.0 * np.arange(n), 5.0 * np.arange(n) ** 1.2,
                                                 -7.0 * np.arange(n)], axis=1), degrees=True)
    delta = np.array([0, 1, 2, 0, 3, 0.5, 0, 4, 1, 2, 0, 5.0])  # deg, about the IMU's x axis
    # IMU fixed with axes aligned to the object's, logged at the frame times
    R_imu = WORLD.inv() * R_cam * Rotation.from_rotvec(np.radians(delta)[:, None] * [1.0, 0, 0])
    q = np.roll(R_imu.as_quat(), 1, axis=1)
    lines = ["t,qw,qx,qy,qz"] + [f"{t:.6f}," + ",".join(f"{v:.12f}" for v in qi) for t, qi in zip(times, q)]
    (tmp_path / "imu.csv").write_text("\n".join(lines) + "\n")
    write_run(tmp_path / "run", times, R_cam.as_matrix())

    run, log = imu.read_run(tmp_path / "run"), imu.read_imu_log(tmp_path / "imu.csv")
    rep = imu.compare(run, log, mode="simple", time_offset_s=0.0, imu_convention="body_to_world")
    # the angle of R_cam_rel R_imu_rel^T is the injected deviation (conjugation keeps angles)
    assert rep["n_pairs"] == n - 1 and rep["time_offset_s"] == 0.0
    assert np.allclose(rep["pairs"]["re_deg"], delta[1:], atol=1e-4)
    # and equals RE of the relative rotations computed here
    Rc, Ri = R_cam.as_matrix(), R_imu.as_matrix()
    expected = rotation_error_deg(Rc[0].T @ Rc[1:], Ri[0].T @ Ri[1:])
    assert np.allclose(rep["pairs"]["re_deg"], expected, atol=1e-4)
    assert rep["re_max_deg"] == pytest.approx(5.0, abs=1e-4)
    assert rep["re_median_deg"] == pytest.approx(np.median(delta[1:]), abs=1e-4)


# --------------------------------------------------------------------------- the log file


def _log(tmp_path, text):
    p = tmp_path / "imu.csv"
    p.write_text(text)
    return p


GOOD = ["t,qw,qx,qy,qz", "0.00,1,0,0,0", "0.01,0.9999,0.01,0,0", "0.02,0.9998,0.02,0,0",
        "0.03,0.9996,0.03,0,0"]


@pytest.mark.parametrize("lines, line_no, what", [
    (["t,qw,qx,qy"] + [r.rsplit(",", 1)[0] for r in GOOD[1:]], 1, "missing column"),
    (GOOD[:3] + ["0.02,abc,0.02,0,0"] + GOOD[4:], 4, "not a number"),
    (GOOD[:2] + ["0.01,0,0,0,0"] + GOOD[3:], 3, "zero-norm"),
    (GOOD[:4] + ["0.03,1,0,0"], 5, "fields"),
    (["t,qw,qx,qy,qz,gx,gy"] + [r + ",0,0" for r in GOOD[1:]], 1, "gx,gy,gz"),
])
def test_malformed_logs_name_the_line(tmp_path, lines, line_no, what):
    p = _log(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(UserError, match=rf"imu\.csv:{line_no}: .*{what}"):
        imu.read_imu_log(p)


def test_a_byte_order_mark_is_read_past(tmp_path):
    p = tmp_path / "imu.csv"
    p.write_bytes(b"\xef\xbb\xbf" + ("\n".join(GOOD) + "\n").encode())
    assert len(imu.read_imu_log(p)) == 4


def test_unsorted_and_duplicate_timestamps_warn(tmp_path):
    clean = imu.read_imu_log(_log(tmp_path, "\n".join(GOOD) + "\n"))
    messy = [GOOD[0], GOOD[3], GOOD[1], GOOD[2], GOOD[2].replace("0.9999", "0.5"), GOOD[4], GOOD[1]]
    with pytest.warns(UserWarning) as rec:
        log = imu.read_imu_log(_log(tmp_path, "\n".join(messy) + "\n"))
    text = " ".join(str(w.message) for w in rec)
    assert "not sorted" in text and "duplicate" in text
    assert np.array_equal(log.t, clean.t)
    assert np.allclose(log.q, clean.q)  # the first of the duplicates is kept


def test_a_gap_is_not_interpolated_across():
    t = np.concatenate([np.arange(0, 1.001, 0.01), [1.2], np.arange(2.0, 3.001, 0.01)])
    rv = np.stack([t, 0.5 * t, 0 * t], axis=1)
    q = np.roll(Rotation.from_rotvec(rv).as_quat(), 1, axis=1)
    log = imu.imu_log_from_arrays(t, q, max_gap_s=0.25)
    assert log.gaps == [(1.2, 2.0)]
    R, valid = log.at([0.5, 1.1, 1.5, 1.99, 2.0, 2.5, 3.5, -0.1])
    # 1.0 -> 1.2 (0.2 s) is bridged, 1.2 -> 2.0 (0.8 s) is not; outside the log is invalid
    assert valid.tolist() == [True, True, False, False, True, True, False, False]
    assert rotation_error_deg(R[0], Rotation.from_rotvec([0.5, 0.25, 0]).as_matrix()) < 1e-3


# --------------------------------------------------------------------------- the run folder


def test_read_run_needs_one_object(tmp_path, trajectory):
    times, R = trajectory
    other = [Estimate(0, i, 5, 0.8, np.eye(3), np.zeros(3), 0.02) for i in range(10)]
    write_run(tmp_path / "run", times[:20], R[:20], obj_id=1, extra=other)
    with pytest.raises(UserError, match=r"several objects \[1, 5\]"):
        imu.read_run(tmp_path / "run")
    run = imu.read_run(tmp_path / "run", obj_id=5)
    assert len(run) == 10 and np.allclose(run.R, np.eye(3))
    with pytest.raises(UserError, match="obj_id 7"):
        imu.read_run(tmp_path / "run", obj_id=7)
    (tmp_path / "run" / "timings.csv").unlink()
    with pytest.raises(UserError, match="timings"):
        imu.read_run(tmp_path / "run", obj_id=1)


def test_read_run_orders_frames_by_capture_time(tmp_path, trajectory):
    times, R = trajectory
    order = np.random.default_rng(0).permutation(30)
    write_run(tmp_path / "run", times[order], R[order], im_ids=order)
    run = imu.read_run(tmp_path / "run")
    assert np.array_equal(run.im_ids, np.arange(30)) and np.allclose(run.t, times[:30])
    assert np.allclose(run.R, R[:30], atol=1e-7)


def test_imu_command_line(tmp_path):
    """The CLI on a generated run: report and plots written; a malformed log is one line, exit 1."""
    import subprocess
    import sys
    from tests.conftest import REPO
    times, R = imu.synthetic_trajectory(150, fps=30, seed=3)
    run = tmp_path / "run"
    write_run(run, times, R)
    log = imu.synth_imu_log(times, R, offset_s=0.12, mounting=[0.9, 0.1, 0.3, 0.2], world_to_cam=[0.8, 0.2, -0.4, 0.3],
                        noise_deg=0.2, gyro_bias_drift=0.0, dropouts=0, seed=1)
    imu.write_imu_log(tmp_path / "imu.csv", log)
    p = subprocess.run([sys.executable, str(REPO / "app.py"), "imu", "--run", run, "--imu", tmp_path / "imu.csv",
                        "--out", tmp_path / "out"], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "out" / "imu_report.json").is_file() and (tmp_path / "out" / "imu_re_hist.png").is_file()
    (tmp_path / "bad.csv").write_text("t,qw,qx,qy\n0,1,0,0\n")
    p = subprocess.run([sys.executable, str(REPO / "app.py"), "imu", "--run", run, "--imu", tmp_path / "bad.csv",
                        "--out", tmp_path / "out2"], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert p.returncode == 1 and "Traceback" not in p.stderr and p.stderr.startswith("error:")
