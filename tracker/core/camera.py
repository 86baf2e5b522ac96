"""Camera model: intrinsics, distortion, camera files and undistortion.

Reads OpenCV FileStorage YAML (``camera_matrix``, ``distortion_coefficients``,
``image_width``, ``image_height``) and ROS ``camera_info`` YAML; writes the OpenCV form.
A camera is tied to a resolution; :meth:`Camera.at_size` rescales it for frames of
another size with the same aspect ratio.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from tracker.core.errors import UserError
from tracker.core.geometry import intrinsics_problem, scale_intrinsics

# LM-O / Linemod Kinect camera (BOP), 640x480
LMO_K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])


@dataclass
class Camera:
    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.dist = np.asarray(self.dist, dtype=np.float64).ravel()
        self.width, self.height = int(self.width), int(self.height)
        check_camera(self)

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def at_size(self, width: int, height: int, tol: float = 0.01) -> "Camera":
        """The same camera read out at ``width`` x ``height`` (aspect ratio must match)."""
        if (width, height) == self.size:
            return self
        a0, a1 = self.width / self.height, width / height
        if abs(a0 - a1) / a0 > tol:
            raise UserError(
                f"frames are {width}x{height} but the calibration is {self.width}x{self.height} "
                f"with another aspect ratio; calibrate the camera at this resolution")
        K = scale_intrinsics(self.K, self.size, (width, height))
        return Camera(K, width, height, self.dist.copy())


def check_camera(cam: Camera) -> None:
    problem = intrinsics_problem(cam.K)
    if problem:
        raise UserError(f"camera_matrix: {problem}")
    if not np.all(np.isfinite(cam.dist)):
        raise UserError("distortion_coefficients hold non-finite numbers")
    if cam.width <= 0 or cam.height <= 0:
        raise UserError(f"camera image size must be positive, got {cam.width}x{cam.height}")
    cx, cy = cam.K[0, 2], cam.K[1, 2]
    if not (0 < cx < cam.width and 0 < cy < cam.height):
        raise UserError(f"the principal point ({cx:g}, {cy:g}) lies outside the {cam.width}x{cam.height} "
                        f"image; the camera matrix's cx, cy are pixels (about half the width and height)")
    if cam.dist.size not in (4, 5, 8, 12, 14):
        raise UserError(f"distortion must have 4, 5, 8, 12 or 14 coefficients, got {cam.dist.size}")


# --------------------------------------------------------------------------- files


def _matrix(node, name: str, path: Path) -> np.ndarray:
    """A matrix from a ROS-style ``{rows, cols, data}`` mapping or a plain list."""
    if isinstance(node, dict):
        data = node.get("data")
        rows, cols = node.get("rows"), node.get("cols")
    else:
        data, rows, cols = node, None, None
    if data is None:
        hint = " (or leave it out for a camera without distortion)" if name == "distortion_coefficients" else ""
        raise UserError(f"{path}: '{name}' is empty; give its numbers{hint}")
    try:
        a = np.asarray(data, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise UserError(f"{path}: '{name}' is not a list of numbers") from None
    if rows is not None or cols is not None:
        try:
            rows, cols = int(rows), int(cols)
        except (TypeError, ValueError):
            raise UserError(f"{path}: '{name}' needs whole numbers for rows and cols, got {rows!r} and {cols!r}") from None
        if a.size != rows * cols:
            raise UserError(f"{path}: '{name}' has {a.size} values, expected {rows}x{cols}")
    return a


def _read_opencv_yaml(path: Path) -> Camera:
    fs = None
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        if not fs.isOpened():
            raise UserError(f"{path}: not a readable OpenCV FileStorage file")
        K = fs.getNode("camera_matrix").mat()
        d = fs.getNode("distortion_coefficients").mat()
        w = fs.getNode("image_width").real()
        h = fs.getNode("image_height").real()
    except (cv2.error, SystemError) as e:  # cv2 raises SystemError for some parse errors
        msg = str(e.__cause__ or e).strip().splitlines() or [e.__class__.__name__]
        raise UserError(f"{path}: garbled OpenCV camera file ({msg[-1][:100]})") from None
    finally:
        if fs is not None:
            fs.release()
    if K is None or K.size != 9:
        raise UserError(f"{path}: no 3x3 'camera_matrix'")
    if not w or not h or not np.isfinite([w, h]).all():
        raise UserError(f"{path}: missing or non-finite 'image_width' / 'image_height'")
    return Camera(K, int(w), int(h), np.zeros(5) if d is None else d.ravel())


def _read_ros_yaml(path: Path, text: str) -> Camera:
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise UserError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise UserError(f"{path}: not a camera file (expected a YAML mapping)")
    missing = [k for k in ("camera_matrix", "image_width", "image_height") if k not in doc]
    if missing:
        raise UserError(f"{path}: camera file lacks {', '.join(missing)}")
    K = _matrix(doc["camera_matrix"], "camera_matrix", path)
    if K.size != 9:
        raise UserError(f"{path}: 'camera_matrix' must have 9 values, has {K.size}")
    d = _matrix(doc.get("distortion_coefficients", [0, 0, 0, 0, 0]), "distortion_coefficients", path)
    model = doc.get("distortion_model", "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial"):
        raise UserError(f"{path}: distortion_model '{model}' is not supported (plumb_bob, rational_polynomial)")
    try:
        w, h = int(doc["image_width"]), int(doc["image_height"])
    except (TypeError, ValueError, OverflowError):
        raise UserError(f"{path}: image_width / image_height must be integers") from None
    return Camera(K, w, h, d)


def read_camera(path) -> Camera:
    """Read an OpenCV FileStorage YAML or a ROS camera_info YAML camera file."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"camera file not found: {path}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: cannot read camera file ({e.__class__.__name__})") from None
    try:
        if text.lstrip().startswith("%YAML:1.0") or "!!opencv-matrix" in text:
            return _read_opencv_yaml(path)
        return _read_ros_yaml(path, text)
    except UserError as e:  # the camera's own checks: name the file
        raise UserError(str(e) if str(e).startswith(str(path)) else f"{path}: {e}") from None


CAMERA_SUFFIXES = (".yaml", ".yml")


def camera_file_problem(path) -> str | None:
    """Why a camera file cannot be written at ``path`` (None: it can): camera files are YAML."""
    path = Path(path)
    if path.is_dir():
        return f"{path} is a folder; give the camera file to write, e.g. {path / 'camera.yaml'}"
    if path.suffix.lower() not in CAMERA_SUFFIXES:
        return f"{path}: camera files are written as YAML; name it .yaml or .yml"
    return None


def write_camera(path, cam: Camera, extra: dict | None = None) -> Path:
    """Write an OpenCV FileStorage YAML camera file (readable by :func:`read_camera`)."""
    problem = camera_file_problem(path)
    if problem:
        raise UserError(problem)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", cam.width)
    fs.write("image_height", cam.height)
    fs.write("camera_matrix", cam.K)
    fs.write("distortion_coefficients", cam.dist.reshape(-1, 1))
    for k, v in (extra or {}).items():
        fs.write(k, v)
    fs.release()
    return path


# --------------------------------------------------------------------------- undistortion


class Undistorter:
    """Precomputed undistortion maps (CV_16SC2) for one camera at one resolution.

    The undistorted image keeps the camera's K, so poses estimated on it use ``cam.K``.
    Frames of another size are handled by rebuilding the maps for the rescaled camera.
    """

    def __init__(self, cam: Camera):
        self.cam = cam
        self._maps: dict[tuple[int, int], tuple[Camera, tuple | None]] = {}

    def camera_for(self, width: int, height: int) -> Camera:
        return self._entry(width, height)[0]

    def _entry(self, width: int, height: int):
        key = (width, height)
        if key not in self._maps:
            cam = self.cam.at_size(width, height)
            maps = None
            if cam.has_distortion:
                maps = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, cam.K, cam.size, cv2.CV_16SC2)
            self._maps[key] = (cam, maps)
        return self._maps[key]

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        h, w = frame.shape[:2]
        _, maps = self._entry(w, h)
        if maps is None:
            return frame
        return cv2.remap(frame, maps[0], maps[1], cv2.INTER_LINEAR)
