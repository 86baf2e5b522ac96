"""IMU comparison (thesis Appendix B): does the tracked rotation agree with an IMU that is
rigidly fixed to the object?

Inputs: a tracking run folder (``poses.csv`` in the BOP results format and ``timings.csv``
with ``im_id,t_capture``) and an IMU log (CSV ``t,qw,qx,qy,qz`` with optional
``gx,gy,gz`` in rad/s), see ``CONVENTIONS.md``.

Conventions
-----------
* Quaternions are scalar-first ``(w, x, y, z)`` as everywhere in :mod:`tracker.core.geometry`.
* The IMU quaternion at time t is read as ``R_world_imu(t)``: it maps IMU-body coordinates
  to the IMU's world (earth) frame ("body to world", the usual AHRS output). Some devices
  log the inverse; :func:`compare` detects that by default (``imu_convention="auto"``) and
  reports which one fitted (``imu_quat_convention``).
* The tracked rotation is BOP's ``cam_R_m2c`` = ``R_cam_obj(t)`` (object to camera).
* Clocks: ``time_offset_s`` = IMU clock minus camera clock, i.e. the frame captured at camera
  time ``t_capture`` is paired with the IMU orientation at IMU time ``t_capture + time_offset_s``
  (slerped between the two neighbouring IMU samples).
* Model ("full" mode), with a static camera and the IMU rigidly mounted on the object::

      R_cam_obj(t) = A . R_world_imu(t + offset) . B

  ``A = R_cam_world`` (world-to-camera, reported as ``world_to_cam_quat_wxyz``) and
  ``B = R_imu_obj`` (object-to-IMU-body mounting rotation, ``mounting_quat_wxyz``) are
  constant and estimated from the data; RE per pair is ``angle(R_cam_obj . (A R_world_imu B)^T)``.
* "simple" mode (the thesis): both rotations relative to their first paired sample,
  expressed in the body frame::

      R_cam_rel(i) = R_cam_obj(0)^T R_cam_obj(i)       (object motion in object axes)
      R_imu_rel(i) = R_world_imu(0)^T R_world_imu(i)   (IMU motion in IMU axes)

  RE(i) = angle(R_cam_rel(i) R_imu_rel(i)^T) for every pair after the reference one (which
  would be 0 by construction). This is independent of A but assumes the IMU axes are
  aligned with the object axes (B = I); the estimated mounting angle is reported so a large
  misalignment shows.

Estimation
----------
1. Clock offset: angular speed of both tracks on a common grid (the IMU's from ``|gyro|`` when
   the log has gyro columns, else from its differentiated quaternions; the camera's from the
   rotation between t - h/2 and t + h/2 over a baseline h of about 0.1 s, the same smoothing
   applied to the gyro), normalised cross-correlation over +- ``max_offset_s``, parabolic
   peak; then refined by minimising the (robust) rotation residual of the full model over
   about +- one frame period around the peak (bounded Brent).
2. A and B: hand-eye initialisation from relative motions (``rotvec(R_cam_i^T R_cam_j) =
   B^T rotvec(R_imu_i^T R_imu_j)``, Kabsch via ``Rotation.align_vectors``), A by Kabsch
   given B, then ``scipy.optimize.least_squares`` on the 6 rotation parameters with
   residuals ``rotvec(R_cam^T A R_imu B)`` (plain, then Huber loss so tracking outliers do
   not pull the fit).
"""
from __future__ import annotations

import csv
import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares, minimize_scalar
from scipy.spatial.transform import Rotation, RotationSpline, Slerp

from tracker.core.bop import csv_rows, read_results
from tracker.core.errors import UserError
from tracker.core.files import write_whole
from tracker.core.geometry import quat_from_matrix, rotation_error_deg

REQUIRED_COLUMNS = ("t", "qw", "qx", "qy", "qz")
GYRO_COLUMNS = ("gx", "gy", "gz")
REPORT_KEYS = ("n_pairs", "time_offset_s", "re_mean_deg", "re_median_deg", "re_p90_deg", "re_max_deg")
DEFAULT_MAX_GAP_S = 0.25


# --------------------------------------------------------------------------- rotations


def _rot(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.roll(np.asarray(q_wxyz, dtype=np.float64), -1, axis=-1))


def _as_matrix(r) -> np.ndarray:
    """A rotation given as a scipy Rotation, a 3x3 matrix or a (w, x, y, z) quaternion."""
    if r is None:
        return np.eye(3)
    if isinstance(r, Rotation):
        return r.as_matrix()
    a = np.asarray(r, dtype=np.float64)
    if a.shape == (3, 3):
        return a
    if a.shape == (4,):
        return _rot(a).as_matrix()
    raise ValueError(f"expected a Rotation, 3x3 matrix or wxyz quaternion, got shape {a.shape}")


def _continuous(q: np.ndarray) -> np.ndarray:
    """Flip quaternion signs so consecutive samples lie in the same hemisphere."""
    q = np.array(q, dtype=np.float64)
    if len(q) < 2:
        return q
    s = np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0)
    return q * np.concatenate([[1.0], np.cumprod(s)])[:, None]


class _Track:
    """Rotations sampled at increasing times; slerp between neighbours no further apart
    than ``max_gap`` and never across a longer gap or outside the samples."""

    def __init__(self, t: np.ndarray, rot: Rotation, max_gap: float):
        self.t = np.asarray(t, dtype=np.float64)
        self.rot = rot
        self.max_gap = float(max_gap)
        self._slerp = Slerp(self.t, rot) if len(self.t) >= 2 else None

    def valid(self, times) -> np.ndarray:
        times = np.asarray(times, dtype=np.float64)
        t = self.t
        if len(t) < 2:
            return np.isclose(times, t[0], rtol=0, atol=1e-9) if len(t) else np.zeros(times.shape, bool)
        k = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
        ok = (times >= t[0]) & (times <= t[-1]) & ((t[k + 1] - t[k]) <= self.max_gap)
        # a time exactly on a sample is valid even next to a gap
        j = np.clip(np.searchsorted(t, times), 0, len(t) - 1)
        return ok | np.isclose(times, t[j], rtol=0, atol=1e-9)

    def at(self, times) -> tuple[Rotation, np.ndarray]:
        times = np.asarray(times, dtype=np.float64)
        valid = self.valid(times)
        if self._slerp is None:
            return Rotation.concatenate([self.rot] * max(len(times), 1))[: len(times)], valid
        return self._slerp(np.clip(times, self.t[0], self.t[-1])), valid


# --------------------------------------------------------------------------- IMU log


@dataclass
class ImuLog:
    """An IMU log, sorted by time, duplicates dropped, quaternion signs continuous.

    ``q``: (N, 4) unit quaternions (w, x, y, z) = R_world_imu; ``gyro``: (N, 3) rad/s in the
    IMU body frame, or None. Samples further apart than ``max_gap_s`` are never interpolated
    between.
    """

    t: np.ndarray
    q: np.ndarray
    gyro: np.ndarray | None = None
    max_gap_s: float = DEFAULT_MAX_GAP_S
    source: str = ""

    def __len__(self) -> int:
        return len(self.t)

    @property
    def rotations(self) -> Rotation:
        return _rot(self.q)

    @property
    def gaps(self) -> list[tuple[float, float]]:
        """(start, end) of every gap longer than max_gap_s (IMU clock)."""
        d = np.diff(self.t)
        return [(float(self.t[i]), float(self.t[i + 1])) for i in np.flatnonzero(d > self.max_gap_s)]

    def _track(self, inverted: bool = False) -> _Track:
        r = self.rotations
        return _Track(self.t, r.inv() if inverted else r, self.max_gap_s)

    def at(self, times) -> tuple[np.ndarray, np.ndarray]:
        """Slerped R_world_imu at IMU-clock ``times`` as (M, 3, 3), and a validity mask
        (False outside the log and inside gaps)."""
        r, valid = self._track().at(times)
        return r.as_matrix().reshape(-1, 3, 3), valid


def imu_log_from_arrays(t, q_wxyz, gyro=None, max_gap_s: float = DEFAULT_MAX_GAP_S,
                        source: str = "IMU log") -> ImuLog:
    """Build an :class:`ImuLog`: normalise, sort (warning), drop duplicate timestamps
    (warning, first kept) and make quaternion signs continuous."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    q = np.asarray(q_wxyz, dtype=np.float64).reshape(-1, 4)
    g = None if gyro is None else np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
    if len(t) != len(q) or (g is not None and len(g) != len(t)):
        raise ValueError("t, q and gyro must have the same length")
    norms = np.linalg.norm(q, axis=1)
    if np.any(norms < 1e-6):
        raise UserError(f"{source}: zero-norm quaternion at sample {int(np.argmax(norms < 1e-6))}")
    q = q / norms[:, None]
    if np.any(np.diff(t) < 0):
        warnings.warn(f"{source}: timestamps are not sorted; sorting them", stacklevel=2)
        order = np.argsort(t, kind="stable")
        t, q = t[order], q[order]
        g = None if g is None else g[order]
    dup = np.concatenate([[False], np.diff(t) == 0])
    if dup.any():
        warnings.warn(f"{source}: {int(dup.sum())} duplicate timestamp(s); keeping the first sample "
                      "of each", stacklevel=2)
        t, q = t[~dup], q[~dup]
        g = None if g is None else g[~dup]
    if len(t) < 2:
        raise UserError(f"{source}: needs at least 2 samples with distinct timestamps, got {len(t)}")
    return ImuLog(t, _continuous(q), g, float(max_gap_s), source)


def read_imu_log(path, max_gap_s: float = DEFAULT_MAX_GAP_S) -> ImuLog:
    """Read an IMU log CSV (``t,qw,qx,qy,qz[,gx,gy,gz]``, any column order, extra columns
    ignored). Problems are reported as ``UserError("FILE:LINE: ...")``."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"IMU log not found: {path}")
    ts, qs, gs = [], [], []
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # past a spreadsheet's byte-order mark
            rows = csv.reader(f)
            header = None
            for line, row in enumerate(rows, start=1):
                if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
                    continue
                if header is None:
                    header = [h.strip().lower() for h in row]
                    hline = line
                    missing = [c for c in REQUIRED_COLUMNS if c not in header]
                    if missing:
                        raise UserError(f"{path}:{line}: missing column(s) {', '.join(missing)} "
                                        f"(expected header t,qw,qx,qy,qz[,gx,gy,gz])")
                    have_g = [c for c in GYRO_COLUMNS if c in header]
                    if have_g and len(have_g) != 3:
                        raise UserError(f"{path}:{line}: gyro columns must be all of gx,gy,gz "
                                        f"(found only {', '.join(have_g)})")
                    qcols = [header.index(c) for c in ("qw", "qx", "qy", "qz")]
                    tcol = header.index("t")
                    gcols = [header.index(c) for c in GYRO_COLUMNS] if have_g else None
                    continue
                if len(row) != len(header):
                    raise UserError(f"{path}:{line}: {len(row)} fields, expected {len(header)} "
                                    f"(header on line {hline})")
                try:
                    tv = float(row[tcol])
                    qv = [float(row[c]) for c in qcols]
                    gv = [float(row[c]) for c in gcols] if gcols else None
                except ValueError as e:
                    raise UserError(f"{path}:{line}: not a number ({e})") from None
                if not (math.isfinite(tv) and all(map(math.isfinite, qv))
                        and (gv is None or all(map(math.isfinite, gv)))):
                    raise UserError(f"{path}:{line}: non-finite value")
                if math.sqrt(sum(v * v for v in qv)) < 1e-6:
                    raise UserError(f"{path}:{line}: zero-norm quaternion")
                ts.append(tv)
                qs.append(qv)
                if gv is not None:
                    gs.append(gv)
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text CSV file") from None
    if header is None:
        raise UserError(f"{path}: empty file (expected header t,qw,qx,qy,qz[,gx,gy,gz])")
    return imu_log_from_arrays(ts, np.array(qs).reshape(-1, 4), np.array(gs) if gs else None,
                               max_gap_s=max_gap_s, source=str(path))


def write_imu_log(path, log: ImuLog, with_gyro: bool = True) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    g = log.gyro if with_gyro else None
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(list(REQUIRED_COLUMNS) + (list(GYRO_COLUMNS) if g is not None else []))
        for i in range(len(log.t)):
            row = [f"{log.t[i]:.6f}"] + [f"{v:.9f}" for v in log.q[i]]
            if g is not None:
                row += [f"{v:.7f}" for v in g[i]]
            w.writerow(row)
    return path


# --------------------------------------------------------------------------- tracking run


@dataclass
class Run:
    """One object's tracked rotations with their capture times (camera clock), sorted."""

    im_ids: np.ndarray
    t: np.ndarray
    R: np.ndarray  # (n, 3, 3) R_cam_obj
    obj_id: int
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    source: str = ""

    def __len__(self) -> int:
        return len(self.t)


def read_timings(path) -> dict[int, float]:
    """``{im_id: t_capture}`` from a run's timings.csv."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"timings file not found: {path} (the run's per-frame capture times)")
    out: dict[int, float] = {}
    first_line: dict[int, int] = {}
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            col, rows = csv_rows(f, path, ("im_id", "t_capture"))
            ci, ct = col["im_id"], col["t_capture"]
            for line, row in rows:
                try:
                    im_id, tc = int(row[ci]), float(row[ct])
                except ValueError as e:
                    raise UserError(f"{path}:{line}: unparsable value ({e})") from None
                if not math.isfinite(tc):
                    raise UserError(f"{path}:{line}: t_capture is not finite")
                if im_id in out:
                    raise UserError(f"{path}:{line}: im_id {im_id} already on line {first_line[im_id]}")
                out[im_id] = tc
                first_line[im_id] = line
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text CSV (expected a run's timings.csv)") from None
    return out


def read_run(run_dir, obj_id: int | None = None) -> Run:
    """Times and camera rotations of one object from RUN_DIR/poses.csv + RUN_DIR/timings.csv.

    Several estimates of the object in one frame: the highest score is kept. Frames
    without a capture time are dropped with a warning.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(f"run folder not found: {run_dir}")
    poses_path = run_dir / "poses.csv"
    ests = read_results(poses_path)
    if not ests:
        raise UserError(f"{poses_path}: no poses")
    scenes = sorted({e.scene_id for e in ests})
    if len(scenes) > 1:
        raise UserError(f"{poses_path}: poses of several scenes {scenes}; expected one video/camera run")
    objs = sorted({e.obj_id for e in ests})
    if obj_id is None:
        if len(objs) > 1:
            raise UserError(f"{poses_path}: poses of several objects {objs}; choose one with --obj-id")
        obj_id = objs[0]
    elif obj_id not in objs:
        raise UserError(f"{poses_path}: no poses of obj_id {obj_id} (objects in the run: {objs})")
    best = {}
    for e in ests:
        if e.obj_id == obj_id and (e.im_id not in best or e.score > best[e.im_id].score):
            best[e.im_id] = e
    timings = read_timings(run_dir / "timings.csv")
    no_time = sorted(set(best) - set(timings))
    if no_time:
        if len(no_time) == len(best):
            raise UserError(f"{run_dir / 'timings.csv'}: none of the frames with poses has a capture time "
                            f"(im_id {no_time[:5]}...)")
        warnings.warn(f"{run_dir}: {len(no_time)} frame(s) with poses have no row in timings.csv "
                      f"(im_id {no_time[:5]}); skipped", stacklevel=2)
    ids = np.array(sorted(set(best) & set(timings)), dtype=np.int64)
    t = np.array([timings[i] for i in ids], dtype=np.float64)
    order = np.argsort(t, kind="stable")
    ids, t = ids[order], t[order]
    dup = np.concatenate([[False], np.diff(t) == 0])
    if dup.any():
        warnings.warn(f"{run_dir}: {int(dup.sum())} frame(s) share a capture time with the previous "
                      "frame; dropped", stacklevel=2)
        ids, t = ids[~dup], t[~dup]
    R = np.stack([best[i].R for i in ids])
    # re-orthonormalise the 8-decimal CSV values
    R = Rotation.from_matrix(R).as_matrix()
    scores = np.array([best[i].score for i in ids])
    return Run(ids, t, R, int(obj_id), scores, str(run_dir))


# --------------------------------------------------------------------------- clock offset


def _frame_period(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if d.size else 1.0 / 30


def _cam_track(run: Run, max_gap_s: float, inliers: np.ndarray | None = None) -> _Track:
    gap = max(max_gap_s, 3.5 * _frame_period(run.t))
    m = np.ones(len(run), bool) if inliers is None else np.asarray(inliers, bool)
    return _Track(run.t[m], Rotation.from_matrix(run.R[m]), gap)


def consistent_frames(R: np.ndarray, k: int = 3, min_deg: float = 15.0) -> np.ndarray:
    """Mask of tracked rotations that agree with their neighbours.

    A frame whose median angle to the k frames either side exceeds max(min_deg, 4 x the
    run's typical value) is a tracking outlier (a flip, a lost object); such frames spoil
    angular speeds and relative motions, so the clock and hand-eye initialisation skip them.
    """
    rot = Rotation.from_matrix(R)
    n = len(R)
    d = np.full((n, 2 * k), np.nan)
    col = 0
    for j in range(1, k + 1):
        if j < n:
            a = (rot[:-j].inv() * rot[j:]).magnitude()
            d[:-j, col] = a
            d[j:, col + 1] = a
        col += 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(d, axis=1)
    med = np.where(np.isfinite(med), med, 0.0)
    thr = max(math.radians(min_deg), 4.0 * float(np.median(med)))
    return med <= thr


def _rotation_speed(track: _Track, grid: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Angular speed (rad/s) as the angle between t - h/2 and t + h/2 over h."""
    ra, va = track.at(grid - h / 2)
    rb, vb = track.at(grid + h / 2)
    return (ra.inv() * rb).magnitude() / h, va & vb


def _gyro_speed(imu: ImuLog, grid: np.ndarray, h: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """|gyro| on the grid, averaged over a window of h (same smoothing as the camera's)."""
    mag = np.linalg.norm(imu.gyro, axis=1)
    s = np.interp(grid, imu.t, mag)
    v = imu._track().valid(grid)
    w = max(int(round(h / dt)), 1)
    if w > 1:
        k = np.ones(w)
        num = np.convolve(np.where(v, s, 0.0), k, mode="same")
        cnt = np.convolve(v.astype(float), k, mode="same")
        s = num / np.maximum(cnt, 1)
        v = cnt >= w - 0.5
    return s, v


MAX_SEARCH_S = 600.0  # the widest clock-offset search (10 ms steps: memory and time grow with it)


def estimate_time_offset(run: Run, imu: ImuLog, max_offset_s: float = 2.0, centre_s: float | None = None,
                         baseline_s: float | None = None, inliers: np.ndarray | None = None) -> dict:
    """Clock offset (IMU minus camera) maximising the normalised cross-correlation of the
    two angular-speed signals over ``centre_s +- max_offset_s`` (the IMU's from its orientations
    and, when the log has them, from its gyro: whichever correlates better).

    ``centre_s`` defaults to 0 when the two clocks' time ranges overlap, else to the
    difference of their start times. ``inliers``: frames to use (default: those passing
    :func:`consistent_frames`). Returns ``{"offset_s", "peak", "lags_s", "corr", "signal"}``.
    """
    if not 0 < max_offset_s <= MAX_SEARCH_S:
        raise UserError(f"--max-offset must lie in (0, {MAX_SEARCH_S:.0f}] s, not {max_offset_s:g}; for clocks "
                        f"further apart pass their offset with --time-offset")
    if inliers is None:
        inliers = consistent_frames(run.R)
    if np.count_nonzero(inliers) < 3:
        inliers = np.ones(len(run), bool)
    period = _frame_period(run.t)
    h = baseline_s if baseline_s is not None else max(0.1, 3 * period)
    dt = min(0.01, period / 2)
    grid = np.arange(run.t[0] + h / 2, run.t[-1] - h / 2, dt)
    if grid.size < 10:
        raise UserError(f"{run.source}: the run is too short ({run.t[-1] - run.t[0]:.2f} s) to align clocks")
    c, vc = _rotation_speed(_cam_track(run, imu.max_gap_s, inliers), grid, h)
    if centre_s is None:
        overlap = min(run.t[-1], imu.t[-1]) - max(run.t[0], imu.t[0])
        centre_s = 0.0 if overlap > 0.5 * (run.t[-1] - run.t[0]) else float(imu.t[0] - run.t[0])
    n_lag = int(math.ceil(max_offset_s / dt))
    lags = centre_s + dt * np.arange(-n_lag, n_lag + 1)
    igrid = grid[0] + lags[0] + dt * np.arange(grid.size + 2 * n_lag)
    # tame tracking outliers (flips give huge one-frame speeds)
    if vc.any():
        c = np.minimum(c, np.percentile(c[vc], 99))
    M = grid.size
    need = max(20, int(0.3 * vc.sum()))

    def correlation(s, vs):
        if vs.any():
            s = np.minimum(s, np.percentile(s[vs], 99.5))
        corr = np.full(lags.size, np.nan)
        for j in range(lags.size):
            m = vc & vs[j:j + M]
            if m.sum() < need:
                continue
            x, y = c[m], s[j:j + M][m]
            x = x - x.mean()
            y = y - y.mean()
            den = math.sqrt(float(x @ x) * float(y @ y))
            if den > 0:
                corr[j] = float(x @ y) / den
        return corr

    # the IMU's own orientation changes over h, measured as the camera's are; and, where the log
    # has them, the gyro's rates (free of the orientation filter's lag, but a path length where
    # the camera's is a chord: they part where the motion jerks between frames): the clearer peak
    signals = {"orientation": correlation(*_rotation_speed(imu._track(), igrid, h))}
    if imu.gyro is not None:
        signals["gyro"] = correlation(*_gyro_speed(imu, igrid, h, dt))
    peak = {k: np.nanmax(v) if np.isfinite(v).any() else -np.inf for k, v in signals.items()}
    signal = max(signals, key=lambda k: (peak[k], k == "gyro"))
    corr = signals[signal]
    if not np.isfinite(corr).any():
        raise UserError(f"{imu.source}: the IMU log does not overlap the run's {run.t[-1] - run.t[0]:.1f} s "
                        f"within +-{max_offset_s:g} s of a clock offset of {centre_s:.6g} s "
                        "(pass it with --time-offset, or widen the search with --max-offset; are both clocks in seconds?)")
    j = int(np.nanargmax(corr))
    off = float(lags[j])
    if 0 < j < lags.size - 1 and np.isfinite(corr[j - 1]) and np.isfinite(corr[j + 1]):
        a, b, cc = corr[j - 1], corr[j], corr[j + 1]
        den = a - 2 * b + cc
        if den < 0:
            off += dt * float(np.clip(0.5 * (a - cc) / den, -0.5, 0.5))
    return {"offset_s": off, "peak": float(corr[j]), "lags_s": lags, "corr": corr, "signal": signal}


# --------------------------------------------------------------------------- frames A, B


def _align(a: np.ndarray, b: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Rotation R minimising sum w ||a - R b||^2 (Kabsch, via scipy)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        r, _ = Rotation.align_vectors(a, b, weights=w)
    return r.as_matrix()


def _hand_eye_B(R_cam: np.ndarray, R_imu: np.ndarray) -> tuple[np.ndarray, float]:
    """Mounting B from relative motions: rotvec(R_cam_i^T R_cam_j) = B^T rotvec(R_imu_i^T R_imu_j).

    Also returns the spread of the motion axes (second over first singular value of the
    IMU relative rotation vectors): near 0 when the object turned about one axis only,
    where B (and A) are not observable about that axis.
    """
    n = len(R_cam)
    rc, rd = [], []
    for k in (1, 2, 4, 8, 16, 32, 64):
        if k >= n:
            break
        i = np.arange(n - k)
        rc.append(Rotation.from_matrix(R_cam[i].transpose(0, 2, 1) @ R_cam[i + k]).as_rotvec())
        rd.append(Rotation.from_matrix(R_imu[i].transpose(0, 2, 1) @ R_imu[i + k]).as_rotvec())
    if not rc:
        return np.eye(3), 0.0
    rc, rd = np.concatenate(rc), np.concatenate(rd)
    ac, ad = np.linalg.norm(rc, axis=1), np.linalg.norm(rd, axis=1)
    keep = (ad > np.radians(3)) & (ad < np.radians(150)) & (ac < np.radians(170))
    if keep.sum() < 3:
        keep = ad > np.radians(0.2)
    if keep.sum() < 2:
        return np.eye(3), 0.0
    sv = np.linalg.svd(rd[keep] / ad[keep, None], compute_uv=False)
    spread = float(sv[1] / sv[0]) if sv[0] > 0 else 0.0
    Bt = _align(rc[keep], rd[keep])
    return Bt.T, spread


def _refine(R_cam: np.ndarray, R_imu: np.ndarray, A0: np.ndarray, B0: np.ndarray,
            f_scale_deg: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Non-linear least squares on the 6 parameters of A = exp(a) A0, B = B0 exp(b), with
    residuals rotvec(R_cam^T A R_imu B) (their norm is the RE); Huber loss when f_scale_deg."""
    RcT = R_cam.transpose(0, 2, 1)

    def model(x):
        return (Rotation.from_rotvec(x[:3]).as_matrix() @ A0, B0 @ Rotation.from_rotvec(x[3:]).as_matrix())

    def fun(x):
        A, B = model(x)
        return Rotation.from_matrix(RcT @ A @ R_imu @ B).as_rotvec().ravel()

    kw = {"loss": "linear"} if f_scale_deg is None else {"loss": "huber", "f_scale": math.radians(f_scale_deg)}
    res = least_squares(fun, np.zeros(6), method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12, **kw)
    A, B = model(res.x)
    return A, B, float(res.cost)


def fit_frames(R_cam: np.ndarray, R_imu: np.ndarray, A0: np.ndarray | None = None,
               B0: np.ndarray | None = None, init_mask: np.ndarray | None = None) -> dict:
    """Estimate A = R_cam_world and B = R_imu_obj with R_cam ~ A R_imu B.

    Hand-eye initialisation of B from the pairs in ``init_mask`` (unless B0 is given), A by
    Kabsch given B, then least squares on the rotation residual with a Huber loss at twice
    the median RE (at least 0.5 deg; below it plain least squares), twice, so tracking
    outliers do not pull the fit.
    Returns ``{"A", "B", "re_deg", "f_scale_deg", "axis_spread"}``.
    """
    R_cam = np.asarray(R_cam, dtype=np.float64)
    R_imu = np.asarray(R_imu, dtype=np.float64)
    m = np.ones(len(R_cam), bool) if init_mask is None else np.asarray(init_mask, bool)
    spread = float("nan")
    if B0 is None:
        B0, spread = _hand_eye_B(R_cam[m], R_imu[m])
    if A0 is None:
        Q = R_imu[m] @ B0
        A0 = _align(R_cam[m].transpose(0, 2, 1).reshape(-1, 3), Q.transpose(0, 2, 1).reshape(-1, 3))
    A, B = A0, B0
    for _ in range(2):
        f_scale = max(2.0 * float(np.median(rotation_error_deg(R_cam, A @ R_imu @ B))), 0.5)
        A, B, _ = _refine(R_cam, R_imu, A, B, f_scale)
    re = rotation_error_deg(R_cam, A @ R_imu @ B)
    return {"A": A, "B": B, "re_deg": re, "f_scale_deg": f_scale, "axis_spread": spread}


# --------------------------------------------------------------------------- comparison


def _stats(re: np.ndarray) -> dict:
    return {"re_mean_deg": float(np.mean(re)), "re_median_deg": float(np.median(re)),
            "re_p90_deg": float(np.percentile(re, 90)), "re_max_deg": float(np.max(re))}


def compare(run: Run, imu: ImuLog, mode: str = "full", *, time_offset_s: float | None = None,
            max_offset_s: float = 2.0, offset_centre_s: float | None = None,
            imu_convention: str = "auto", min_pairs: int = 10) -> dict:
    """Compare a run's tracked rotations with an IMU log; see the module docstring.

    ``mode``: "full" (estimated world-to-camera and mounting rotations) or "simple" (both
    relative to their first paired sample). ``time_offset_s``: IMU minus camera clock; None
    estimates it. ``imu_convention``: "auto", "body_to_world" (q = R_world_imu) or
    "world_to_body" (q = R_imu_world).

    Returns a dict with the ``imu_report.json`` keys, diagnostics, and ``pairs`` (per-pair
    arrays: im_id, t_capture, t_imu, re_deg, q_cam_wxyz, q_imu_wxyz; the two quaternions
    are the compared rotations, camera and IMU, in the mode's frame).
    """
    if mode not in ("full", "simple"):
        raise UserError(f"unknown IMU comparison mode {mode!r} (full or simple)")
    if imu_convention not in ("auto", "body_to_world", "world_to_body"):
        raise UserError(f"unknown IMU quaternion convention {imu_convention!r}")
    if len(run) < 3:
        raise UserError(f"{run.source}: only {len(run)} frame(s) of obj_id {run.obj_id}; too few to compare")
    period = _frame_period(run.t)

    inliers = consistent_frames(run.R)
    xc = None
    if time_offset_s is None:
        xc = estimate_time_offset(run, imu, max_offset_s=max_offset_s, centre_s=offset_centre_s,
                                  inliers=inliers)
        off0 = xc["offset_s"]
        if xc["peak"] < 0.3:
            warnings.warn(f"clock offset poorly determined (angular-speed correlation {xc['peak']:.2f}); "
                          "does the object move enough, and does the IMU log belong to this run?",
                          stacklevel=2)
    else:
        off0 = float(time_offset_s)

    conventions = ["body_to_world", "world_to_body"] if imu_convention == "auto" else [imu_convention]
    tracks = {c: imu._track(inverted=(c == "world_to_body")) for c in conventions}

    def pairs_at(off, conv):
        r, v = tracks[conv].at(run.t + off)
        return r.as_matrix().reshape(-1, 3, 3), v

    # which convention fits (at the initial offset)
    fits = {}
    for conv in conventions:
        R_imu, v = pairs_at(off0, conv)
        if v.sum() < min_pairs:
            raise UserError(f"only {int(v.sum())} frame(s) of the run fall inside the IMU log "
                            f"(clock offset {off0:.3f} s); need {min_pairs}")
        fits[conv] = fit_frames(run.R[v], R_imu[v], init_mask=inliers[v])
    conv = min(fits, key=lambda c: float(np.median(fits[c]["re_deg"])))
    fit0 = fits[conv]

    # refine the offset on the rotation residual
    offset = off0
    if time_offset_s is None:
        r = max(period, 0.02)
        scan = off0 + np.linspace(-r, r, 9)
        mask = np.ones(len(run), bool)
        for o in scan:
            mask &= tracks[conv].valid(run.t + o)
        if mask.sum() >= min_pairs:
            A_ws, B_ws, k = fit0["A"], fit0["B"], fit0["f_scale_deg"]

            def cost(o):
                R_imu, _ = pairs_at(o, conv)
                return _refine(run.R[mask], R_imu[mask], A_ws, B_ws, k)[2]

            costs = np.array([cost(o) for o in scan])
            i = int(np.argmin(costs))
            lo, hi = scan[max(i - 1, 0)], scan[min(i + 1, len(scan) - 1)]
            res = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6})
            offset = float(res.x) if res.fun <= costs[i] else float(scan[i])

    R_imu, valid = pairs_at(offset, conv)
    if valid.sum() < min_pairs:
        raise UserError(f"only {int(valid.sum())} frame(s) of the run fall inside the IMU log; need {min_pairs}")
    fit = fit_frames(run.R[valid], R_imu[valid], A0=fit0["A"], B0=fit0["B"])
    A, B = fit["A"], fit["B"]
    spread = fit0["axis_spread"]
    observable = bool(np.isfinite(spread) and spread > 0.05)
    if not observable:
        warnings.warn("the object turned about (nearly) one axis only: the mounting and world-to-camera "
                      "rotations are not fully observable (the RE is still valid)", stacklevel=2)

    Rc = run.R[valid]
    Ri = R_imu[valid]
    ids, tc = run.im_ids[valid], run.t[valid]
    if mode == "full":
        cam_cmp, imu_cmp = Rc, A @ Ri @ B
        re = rotation_error_deg(cam_cmp, imu_cmp)
        keep = np.ones(len(re), bool)
    else:
        cam_cmp = Rc[0].T @ Rc
        imu_cmp = Ri[0].T @ Ri
        re = rotation_error_deg(cam_cmp, imu_cmp)
        keep = np.arange(len(re)) > 0  # the reference pair is 0 by construction
        if len(re) < 2:
            raise UserError("simple mode needs at least 2 pairs")
    mount_angle = float(np.degrees(Rotation.from_matrix(B).magnitude()))
    if mode == "simple" and observable and mount_angle > 5:
        warnings.warn(f"simple mode assumes the IMU axes are aligned with the object's, but the estimated "
                      f"mounting rotation is {mount_angle:.1f} deg; consider mode='full'", stacklevel=2)

    report = {
        "n_pairs": int(keep.sum()),
        "time_offset_s": float(offset),
        **_stats(re[keep]),
        "mode": mode,
        "obj_id": int(run.obj_id),
        "n_frames": int(len(run)),
        "n_imu_samples": int(len(imu)),
        "n_unpaired_frames": int((~valid).sum()),
        "n_inconsistent_frames": int((~inliers).sum()),
        "imu_gaps": len(imu.gaps),
        "offset_source": "given" if time_offset_s is not None else "estimated",
        "offset_xcorr_s": None if xc is None else float(xc["offset_s"]),
        "xcorr_peak": None if xc is None else float(xc["peak"]),
        "xcorr_signal": None if xc is None else xc["signal"],
        "imu_quat_convention": conv,
        "mounting_quat_wxyz": quat_from_matrix(B).tolist(),
        "mounting_angle_deg": mount_angle,
        "world_to_cam_quat_wxyz": quat_from_matrix(A).tolist(),
        "mounting_observable": observable,
        "full_re_median_deg": float(np.median(fit["re_deg"])),
        "conventions": ("R = R_cam_obj (BOP cam_R_m2c); IMU q = R_world_imu (body to world) unless "
                        "imu_quat_convention says otherwise; t_imu = t_capture + time_offset_s; full: "
                        "RE(R_cam_obj, A R_world_imu B) with A = R_cam_world (world_to_cam_quat_wxyz), "
                        "B = R_imu_obj (mounting_quat_wxyz); simple: RE(R_cam_obj(0)^T R_cam_obj(i), "
                        "R_world_imu(0)^T R_world_imu(i)) over pairs i >= 1"),
        "pairs": {
            "im_id": ids[keep], "t_capture": tc[keep], "t_imu": tc[keep] + offset, "re_deg": re[keep],
            "q_cam_wxyz": quat_from_matrix(cam_cmp[keep]).reshape(-1, 4),
            "q_imu_wxyz": quat_from_matrix(imu_cmp[keep]).reshape(-1, 4),
        },
    }
    return report


# --------------------------------------------------------------------------- report


def _breaks(t: np.ndarray, *ys: np.ndarray, factor: float = 3.0):
    """Insert NaN where consecutive times jump (so plotted lines break at gaps)."""
    if len(t) < 2:
        return (t, *ys)
    d = np.diff(t)
    thr = factor * float(np.median(d))
    cut = np.flatnonzero(d > thr) + 1
    t2 = np.insert(t.astype(float), cut, np.nan)
    return (t2, *[np.insert(np.asarray(y, float), cut, np.nan, axis=0) for y in ys])


def write_report(out_dir, report: dict, plots: bool = True) -> dict[str, Path]:
    """Write ``imu_report.json`` (everything but the per-pair arrays), ``imu_pairs.csv`` and
    the plots ``imu_re_hist.png``, ``imu_re_time.png``, ``imu_tracks.png``."""
    from tracker.core import cvplot

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pairs = report.get("pairs", {})
    files: dict[str, Path] = {}

    if pairs:
        p = out / "imu_pairs.csv"
        with open(p, "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(["im_id", "t_capture", "t_imu", "re_deg", "cam_qw", "cam_qx", "cam_qy", "cam_qz",
                        "imu_qw", "imu_qx", "imu_qy", "imu_qz"])
            for i in range(len(pairs["im_id"])):
                w.writerow([int(pairs["im_id"][i]), f"{pairs['t_capture'][i]:.6f}", f"{pairs['t_imu'][i]:.6f}",
                            f"{pairs['re_deg'][i]:.4f}"]
                           + [f"{v:.7f}" for v in pairs["q_cam_wxyz"][i]]
                           + [f"{v:.7f}" for v in pairs["q_imu_wxyz"][i]])
        files["pairs"] = p

    if plots and pairs and len(pairs["re_deg"]):
        re = np.asarray(pairs["re_deg"])
        t = np.asarray(pairs["t_capture"]) - float(pairs["t_capture"][0])
        mode = report.get("mode", "full")
        hi = float(re.max())
        title = f"IMU vs tracked rotation error ({mode} mode, {len(re)} pairs)"
        if hi > 3 * report["re_p90_deg"] > 0:  # keep the bulk readable; count the outliers
            hi = 3 * report["re_p90_deg"]
            title += f", {int((re > hi).sum())} above {hi:.3g} deg not shown"
        files["hist"] = cvplot.save_png(out / "imu_re_hist.png", cvplot.histogram(
            re, title=title, xlabel="RE [deg]", range_=(0.0, max(hi, 1e-6)),
            vlines={"median": report["re_median_deg"], "p90": report["re_p90_deg"]}))
        tb, reb = _breaks(t, re)
        files["re_time"] = cvplot.save_png(out / "imu_re_time.png", cvplot.line_chart(
            [cvplot.Panel([cvplot.Series(tb, reb, "RE")], title="rotation error over time",
                          xlabel="time since first pair [s]", ylabel="RE [deg]")], panel_height=300))
        rc, ri = _rot(pairs["q_cam_wxyz"]), _rot(pairs["q_imu_wxyz"])
        ec = np.degrees(np.unwrap(rc.as_euler("xyz"), axis=0))
        ei = np.degrees(np.unwrap(ri.as_euler("xyz"), axis=0))
        # keep the two tracks on the same 360-degree branch
        ei -= 360.0 * np.round((ei[0] - ec[0]) / 360.0)
        frame = "camera frame" if mode == "full" else "relative to the first pair, body frame"
        panels = []
        for k, name in enumerate("xyz"):
            tb, a, b = _breaks(t, ec[:, k], ei[:, k])
            panels.append(cvplot.Panel([cvplot.Series(tb, a, "tracked"), cvplot.Series(tb, b, "IMU")],
                                       title=f"Euler '{name}' angle (xyz), {frame}", ylabel="deg"))
        if len(t) > 1:
            dt = np.diff(t)
            sc = np.degrees((rc[:-1].inv() * rc[1:]).magnitude()) / np.maximum(dt, 1e-9)
            si = np.degrees((ri[:-1].inv() * ri[1:]).magnitude()) / np.maximum(dt, 1e-9)
            tm = 0.5 * (t[:-1] + t[1:])
            tb, a, b = _breaks(tm, sc, si)
            top = 1.5 * float(np.percentile(np.concatenate([sc, si]), 95)) if len(sc) else 1.0
            panels.append(cvplot.Panel([cvplot.Series(tb, a, "tracked"), cvplot.Series(tb, b, "IMU")],
                                       title="angular speed between consecutive pairs", ylabel="deg/s",
                                       xlabel="time since first pair [s]", ylim=(0.0, max(top, 1e-6))))
        files["tracks"] = cvplot.save_png(out / "imu_tracks.png", cvplot.line_chart(
            panels, panel_height=200, title=f"tracked vs IMU rotation (offset {report['time_offset_s']:.4f} s)"))

    js = {k: v for k, v in report.items() if k != "pairs"}
    if "pairs" in files:
        js["pairs_csv"] = files["pairs"].name
    js["plots"] = [files[k].name for k in ("hist", "re_time", "tracks") if k in files]
    p = out / "imu_report.json"
    write_whole(p, lambda tmp: tmp.write_text(json.dumps(js, indent=1)))
    files["report"] = p
    return files


# --------------------------------------------------------------------------- test data


def synthetic_trajectory(n: int, fps: float = 30.0, seed: int = 0, t0: float = 0.0,
                         amplitude_deg: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """Smooth object rotations (object in front of a camera, turned about all axes).

    Returns ``(times (n,), R_cam_obj (n, 3, 3))``: R = R0 exp(sum of sines per axis) with
    frequencies 0.15-0.9 Hz and about ``amplitude_deg`` of swing per axis.
    """
    rng = np.random.default_rng(seed)
    times = t0 + np.arange(n) / fps
    tt = times - t0
    rv = np.zeros((n, 3))
    for ax in range(3):
        for _ in range(3):
            f = rng.uniform(0.15, 0.9)
            a = np.radians(amplitude_deg) / 3 * rng.uniform(0.6, 1.4)
            rv[:, ax] += a * np.sin(2 * np.pi * f * tt + rng.uniform(0, 2 * np.pi))
    R0 = Rotation.random(random_state=rng)
    return times, (R0 * Rotation.from_rotvec(rv)).as_matrix()


def synth_imu_log(times, R_cam_obj, offset_s: float = 0.0, mounting=None, world_to_cam=None,
                  noise_deg: float = 0.0, gyro_bias_drift: float = 0.0, dropouts=(), seed: int = 0,
                  rate_hz: float = 100.0, with_gyro: bool = True,
                  max_gap_s: float = DEFAULT_MAX_GAP_S) -> ImuLog:
    """An IMU log that an IMU fixed to the object would have written during a run.

    ``times`` / ``R_cam_obj``: frame capture times (camera clock) and object-to-camera
    rotations, e.g. from :func:`read_run` or :func:`synthetic_trajectory` (interpolated with
    a cubic rotation spline). ``offset_s``: IMU clock minus camera clock. ``mounting`` =
    B = R_imu_obj and ``world_to_cam`` = A = R_cam_world (Rotation, 3x3 or wxyz; default
    identity), so R_world_imu = A^T R_cam_obj B^T. ``noise_deg``: RMS angle of independent
    orientation noise per sample. ``gyro_bias_drift``: random-walk intensity of the gyro bias
    in deg/s per sqrt(s); the orientation drifts by the integrated bias and the gyro columns
    carry it. ``dropouts``: an int (that many random gaps of 0.4-0.8 s) or (start, end)
    intervals on the IMU clock with no samples. Samples at ``rate_hz`` on the IMU clock.
    """
    rng = np.random.default_rng(seed)
    times = np.asarray(times, dtype=np.float64)
    spline = RotationSpline(times, Rotation.from_matrix(np.asarray(R_cam_obj, dtype=np.float64)))
    A, B = _as_matrix(world_to_cam), _as_matrix(mounting)
    dt = 1.0 / rate_hz
    start = times[0] + offset_s + rng.uniform(0, dt)
    t_imu = start + dt * np.arange(int(np.floor((times[-1] + offset_s - start) / dt)) + 1)
    Rc = spline(t_imu - offset_s).as_matrix()
    Rw = A.T @ Rc @ B.T
    rw = Rotation.from_matrix(Rw)
    # body angular velocity by central differences
    n = len(t_imu)
    gyro = np.zeros((n, 3))
    if n >= 3:
        gyro[1:-1] = (rw[:-2].inv() * rw[2:]).as_rotvec() / (t_imu[2:] - t_imu[:-2])[:, None]
        gyro[0] = (rw[0].inv() * rw[1]).as_rotvec() / (t_imu[1] - t_imu[0])
        gyro[-1] = (rw[-2].inv() * rw[-1]).as_rotvec() / (t_imu[-1] - t_imu[-2])
    if gyro_bias_drift > 0:
        bias = np.cumsum(rng.normal(0.0, np.radians(gyro_bias_drift) * math.sqrt(dt), (n, 3)), axis=0)
        drift = np.cumsum(bias * dt, axis=0)
        rw = rw * Rotation.from_rotvec(drift)
        gyro = gyro + bias
    if noise_deg > 0:
        rw = rw * Rotation.from_rotvec(rng.normal(0.0, np.radians(noise_deg) / math.sqrt(3), (n, 3)))
    keep = np.ones(n, bool)
    if isinstance(dropouts, (int, np.integer)):
        span = t_imu[-1] - t_imu[0]
        intervals = []
        for _ in range(int(dropouts)):
            d = rng.uniform(0.4, 0.8)
            s = t_imu[0] + rng.uniform(0.1 * span, max(0.9 * span - d, 0.1 * span))
            intervals.append((s, s + d))
    else:
        intervals = list(dropouts)
    for a, b in intervals:
        keep &= ~((t_imu > a) & (t_imu < b))
    q = quat_from_matrix(rw.as_matrix())  # canonical w >= 0: sign flips that the reader undoes
    return imu_log_from_arrays(t_imu[keep], q[keep], gyro[keep] if with_gyro else None,
                               max_gap_s=max_gap_s, source="synthetic IMU log")
