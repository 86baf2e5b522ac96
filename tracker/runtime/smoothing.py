"""Optional temporal smoothing of poses on SO(3) x R^3 (off by default).

An exponential moving average per object: the rotation moves a fraction ``alpha`` of the
geodesic from the smoothed rotation towards the new estimate (slerp), the translation a
fraction ``alpha`` of the straight line. ``alpha = 1`` is no smoothing; smaller is smoother
and lags more. An object unseen for more than ``max_gap`` frames, or whose new estimate
jumps further than ``reset_deg`` / ``reset_mm``, restarts from the new estimate, so a
re-detection is never dragged towards a stale pose.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from tracker.core.errors import UserError


@dataclass
class _State:
    R: np.ndarray
    t: np.ndarray
    frame: int


class PoseSmoother:
    def __init__(self, alpha: float = 0.5, max_gap: int = 5, reset_deg: float = 90.0, reset_mm: float = 150.0):
        if not 0.0 < alpha <= 1.0:
            raise UserError(f"--smooth: alpha must be in (0, 1], got {alpha}")
        self.alpha, self.max_gap, self.reset_deg, self.reset_mm = alpha, max_gap, reset_deg, reset_mm
        self.state: dict[int, _State] = {}

    def reset(self):
        self.state.clear()

    def __call__(self, obj_id: int, R: np.ndarray, t: np.ndarray, frame: int) -> tuple[np.ndarray, np.ndarray]:
        s = self.state.get(obj_id)
        R, t = np.asarray(R, float), np.asarray(t, float).reshape(3)
        if s is not None and frame - s.frame <= self.max_gap:
            delta = Rotation.from_matrix(s.R.T @ R).magnitude()
            if np.degrees(delta) <= self.reset_deg and np.linalg.norm(t - s.t) <= self.reset_mm:
                slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([s.R, R])))
                R = slerp([self.alpha]).as_matrix()[0]
                t = s.t + self.alpha * (t - s.t)
        self.state[obj_id] = _State(R, t, frame)
        return R, t
