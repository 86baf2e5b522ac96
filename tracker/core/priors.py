"""Pose priors for synthetic scenes: where the camera is and how objects lie.

``table`` (the LM-O case): objects rest upright on a plane (model z = the plane's normal,
as LM-O models are stored), any yaw, a small tilt; the camera looks at the table from
0.6-1.5 m at an elevation of 15-85 degrees, any azimuth, a small roll. The table's pose
comes back too, so the scene can draw its surface and the objects' shadows on it.

``sphere`` (hand-held objects): every object takes a uniformly random orientation in
SO(3) at a random place in the view frustum, 0.4-1.5 m away.

Both return model-to-camera poses (R, t in mm) for the targets and the distractors.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

PRIORS = ("table", "sphere")


@dataclass(frozen=True)
class TablePrior:
    distance_mm: tuple[float, float] = (600.0, 1500.0)
    elevation_deg: tuple[float, float] = (15.0, 85.0)
    roll_deg: float = 12.0          # camera roll, uniform +-
    tilt_deg: float = 8.0           # object tilt off upright, uniform +-
    spread_mm: float = 260.0        # objects scatter this far from the look-at point
    look_jitter_mm: float = 120.0   # the look-at point moves on the table


@dataclass(frozen=True)
class SpherePrior:
    distance_mm: tuple[float, float] = (400.0, 1500.0)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera rotation of an OpenCV camera at ``eye`` looking at ``target``."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # image x right when up points up in the image (y down)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=0)


def resting_offset(vertices: np.ndarray, R_obj_w: np.ndarray) -> float:
    """Height of the model origin above the table when it rests on it rotated by R."""
    return float(-(vertices @ R_obj_w[2]).min())


def sample_table_scene(rng: np.random.Generator, vertices: list[np.ndarray], radii: list[float],
                       prior: TablePrior = TablePrior()):
    """Poses of objects standing on one table seen by one camera.

    ``vertices``/``radii``: per object to place (targets first, then distractors).
    Returns a list of (R_m2c, t_m2c) in the same order, and the table's pose in the camera
    (R_w2c, t_w2c: world z = 0 is the table's surface, z up).
    """
    el = np.radians(rng.uniform(*prior.elevation_deg))
    az = rng.uniform(0, 2 * np.pi)
    dist = rng.uniform(*prior.distance_mm)
    target = np.append(rng.normal(0, prior.look_jitter_mm / 2, 2), 0.0)
    eye = target + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    R_w2c = look_at(eye, target, np.array([0.0, 0.0, 1.0]))
    roll = Rotation.from_rotvec([0, 0, np.radians(rng.uniform(-prior.roll_deg, prior.roll_deg))]).as_matrix()
    R_w2c = roll @ R_w2c
    t_w2c = -R_w2c @ eye
    placed: list[tuple[np.ndarray, float]] = []
    poses = []
    for v, r in zip(vertices, radii):
        # scatter on the table, avoiding deep interpenetration (a few tries, then accept)
        for _ in range(20):
            xy = rng.uniform(-prior.spread_mm, prior.spread_mm, 2)
            if all(np.linalg.norm(xy - p) > 0.7 * (r + pr) for p, pr in placed):
                break
        placed.append((xy, r))
        tilt_axis = rng.normal(size=3)
        tilt_axis[2] = 0.0
        tilt_axis /= np.linalg.norm(tilt_axis) + 1e-12
        tilt = Rotation.from_rotvec(tilt_axis * np.radians(rng.uniform(-prior.tilt_deg, prior.tilt_deg)))
        yaw = Rotation.from_rotvec([0, 0, rng.uniform(0, 2 * np.pi)])
        R_ow = (tilt * yaw).as_matrix()
        t_ow = np.array([xy[0], xy[1], resting_offset(v, R_ow)])
        poses.append((R_w2c @ R_ow, R_w2c @ t_ow + t_w2c))
    return poses, (R_w2c, t_w2c)


def sample_sphere_scene(rng: np.random.Generator, radii: list[float], K: np.ndarray, size: tuple[int, int],
                        prior: SpherePrior = SpherePrior()):
    """Uniform SO(3) orientations at random places in the view (centres inside the image,
    so truncation comes from the object's extent)."""
    w, h = size
    poses = []
    for _ in radii:
        z = rng.uniform(*prior.distance_mm)
        u, v = rng.uniform(-0.05 * w, 1.05 * w), rng.uniform(-0.05 * h, 1.05 * h)
        t = np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
        poses.append((Rotation.random(random_state=rng).as_matrix(), t))
    return poses


def table_occluder_pose(rng: np.random.Generator, target_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A distractor floating between the camera and a target (a hand, a cable, a mug held up):
    these give the low visible fractions the table alone rarely produces."""
    frac = rng.uniform(0.45, 0.8)
    t = target_t * frac + rng.normal(0, 25, 3) * np.array([1, 1, 0])
    return Rotation.random(random_state=rng).as_matrix(), t


def view_elevation_deg(R: np.ndarray, t: np.ndarray) -> float:
    """Elevation of the camera above the plane the object stands on (model z up): 90 looking
    straight down, 0 level with the table, negative from below."""
    v = np.asarray(t, dtype=np.float64) / np.linalg.norm(t)
    return float(np.degrees(np.arcsin(np.clip(-np.asarray(R)[:, 2] @ v, -1.0, 1.0))))


def in_prior(prior: str, R: np.ndarray, t: np.ndarray, margin_deg: float = 10.0) -> bool:
    """Whether a pose is one the ``prior`` produces (``sphere``: any)."""
    if prior != "table":
        return True
    tp = TablePrior()
    e = view_elevation_deg(R, t)
    return tp.elevation_deg[0] - tp.tilt_deg - margin_deg <= e <= tp.elevation_deg[1] + tp.tilt_deg + margin_deg
