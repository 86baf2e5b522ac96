"""BOP file formats: scene_camera / scene_gt / scene_gt_info / models_info JSON and the
results CSV (``scene_id,im_id,obj_id,score,R,t,time``).

Formats: https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md
Everything that reads user files raises :class:`UserError` with the file (and line) at fault.
"""
from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from tracker.core.errors import UserError
from tracker.core.files import write_whole
from tracker.core.geometry import intrinsics_problem, is_rotation

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
SCENE_VIDEOS = ("rgb.avi", "rgb.mp4", "rgb.mkv")  # a scene's frames as one video, im_ids in order


# --------------------------------------------------------------------------- JSON helpers


def _load_json(path: Path):
    if not path.is_file():
        raise UserError(f"missing file: {path}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: not valid JSON ({e})") from None


def check_output_file(path, what: str = "output") -> Path:
    """A file about to be written: refused at once if it is a folder (before any long work)."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{what} {path} is a folder; name a file")
    return path


def write_json(path: Path, obj) -> Path:
    path = check_output_file(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_whole(path, lambda tmp: tmp.write_text(json.dumps(obj, indent=1, default=_json_default)))


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"cannot serialise {type(o).__name__}")


# --------------------------------------------------------------------------- records


@dataclass
class GtInstance:
    obj_id: int
    R: np.ndarray  # 3x3 model -> camera
    t: np.ndarray  # (3,) mm
    info: dict = field(default_factory=dict)  # scene_gt_info entry when present


def _by_image(path: Path, raw, kind=dict) -> dict:
    """A BOP per-image JSON: an object keyed by image ids (digits), each entry a ``kind``."""
    if not isinstance(raw, dict):
        raise UserError(f"{path}: expected an object keyed by image id, not a {type(raw).__name__}")
    for k, v in raw.items():
        if not str(k).isdigit():
            raise UserError(f"{path}: '{k}' is not an image id (digits)")
        if not isinstance(v, kind):
            raise UserError(f"{path}: image {k}: expected a{'n object' if kind is dict else ' list'}, "
                            f"not a {type(v).__name__}")
    return raw


def load_scene_camera(path) -> dict[int, dict]:
    """{im_id: {"K": 3x3, "depth_scale": float, ...}} from scene_camera.json."""
    path = Path(path)
    raw = _by_image(path, _load_json(path))
    out = {}
    for k, v in raw.items():
        try:
            K = np.asarray(v["cam_K"], dtype=np.float64).reshape(3, 3)
        except (KeyError, ValueError, TypeError):
            raise UserError(f"{path}: image {k} has no valid 'cam_K' (9 numbers)") from None
        problem = intrinsics_problem(K)
        if problem:
            raise UserError(f"{path}: image {k}'s cam_K: {problem}")
        entry = dict(v)
        entry["K"] = K
        out[int(k)] = entry
    return out


def save_scene_camera(path, cameras: dict[int, dict]) -> Path:
    obj = {}
    for im_id in sorted(cameras):
        c = cameras[im_id]
        e = {"cam_K": np.asarray(c["K"], dtype=float).ravel().tolist(),
             "depth_scale": float(c.get("depth_scale", 1.0))}
        for k in ("cam_R_w2c", "cam_t_w2c"):
            if k in c:
                e[k] = np.asarray(c[k], dtype=float).ravel().tolist()
        obj[str(im_id)] = e
    return write_json(path, obj)


def load_scene_gt(path, info_path=None) -> dict[int, list[GtInstance]]:
    path = Path(path)
    raw = _by_image(path, _load_json(path), list)
    info = {}
    if info_path is not None and Path(info_path).is_file():
        info = _by_image(Path(info_path), _load_json(Path(info_path)), list)
        if not all(isinstance(e, dict) for v in info.values() for e in v):
            raise UserError(f"{info_path}: each image must list one object per instance (bbox_visib, visib_fract, ...)")
    out = {}
    for k, insts in raw.items():
        lst = []
        infos = info.get(k, [])
        for j, g in enumerate(insts):
            try:
                R = np.asarray(g["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
                t = np.asarray(g["cam_t_m2c"], dtype=np.float64).reshape(3)
                oid = int(g["obj_id"])
            except (KeyError, ValueError, TypeError):
                raise UserError(f"{path}: image {k} instance {j} lacks a valid cam_R_m2c / cam_t_m2c / obj_id") from None
            if not is_rotation(R, tol=0.05) or not np.all(np.isfinite(t)):  # (LM-O: within 0.003)
                raise UserError(f"{path}: image {k} instance {j}: cam_R_m2c is not a rotation or cam_t_m2c "
                                f"is not finite")
            entry = dict(infos[j]) if j < len(infos) else {}
            problem = gt_info_problem(entry)
            if problem:
                raise UserError(f"{info_path}: image {k} instance {j}: {problem}")
            lst.append(GtInstance(oid, R, t, entry))
        out[int(k)] = lst
    return out


def gt_info_problem(entry: dict) -> str | None:
    """What is wrong with a ``scene_gt_info`` entry (None: nothing): boxes are four finite
    numbers with a size >= 0 (or BOP's ``[-1, -1, -1, -1]``: nothing visible), the visible
    fraction is a number in [0, 1], pixel counts are >= 0."""
    for key in ("bbox_obj", "bbox_visib"):
        if key in entry:
            try:
                b = np.asarray(entry[key], dtype=np.float64)
            except (TypeError, ValueError):
                b = None
            empty = b is not None and b.shape == (4,) and np.all(b == -1)  # BOP's box of nothing
            if not empty and (b is None or b.shape != (4,) or not np.all(np.isfinite(b)) or b[2] < 0 or b[3] < 0):
                return (f"'{key}' must be x, y, width, height (four finite numbers, sizes >= 0; -1 four times "
                        f"for none), not {entry[key]!r}")
    v = entry.get("visib_fract", 1.0)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 1.0:  # NaN fails too
        return f"'visib_fract' must be a number in [0, 1], not {v!r}"
    for key in ("px_count_all", "px_count_valid", "px_count_visib"):
        c = entry.get(key, 0)
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not c >= 0:
            return f"'{key}' must be a pixel count >= 0, not {c!r}"
    return None


def save_scene_gt(path, gt: dict[int, list[GtInstance]]) -> Path:
    obj = {str(k): [{"cam_R_m2c": g.R.ravel().tolist(), "cam_t_m2c": g.t.ravel().tolist(),
                     "obj_id": int(g.obj_id)} for g in gt[k]] for k in sorted(gt)}
    return write_json(path, obj)


def save_scene_gt_info(path, gt: dict[int, list[GtInstance]]) -> Path:
    keys = ("bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract")
    obj = {str(k): [{kk: g.info[kk] for kk in keys if kk in g.info} for g in gt[k]] for k in sorted(gt)}
    return write_json(path, obj)


# --------------------------------------------------------------------------- scenes


class VideoFrames:
    """Random access to the frames of a video file (sequential reads are cheap; a jump seeks)."""

    def __init__(self, path: Path):
        self.path = path
        self.cap = cv2.VideoCapture(str(path))
        if not self.cap.isOpened():
            raise UserError(f"{path}: cannot open the video (corrupt, or a codec OpenCV lacks)")
        self.count = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.next = 0

    def read(self, index: int) -> np.ndarray:
        if index != self.next:
            self.cap.set(cv2.CAP_PROP_POS_FRAMES, index)
        ok, bgr = self.cap.read()
        if not ok:
            raise UserError(f"{self.path}: frame {index} is missing (truncated video?)")
        self.next = index + 1
        return bgr

    def close(self):
        self.cap.release()


@dataclass
class Scene:
    """A BOP scene folder: ``rgb/`` (or the frames as one video, ``rgb.avi``, in im_id order),
    ``scene_camera.json`` and, when present, ground truth."""

    root: Path
    cameras: dict[int, dict]
    gt: dict[int, list[GtInstance]] | None
    images: dict[int, Path | int]  # image file, or frame index in ``video``
    video: VideoFrames | None = None

    @property
    def im_ids(self) -> list[int]:
        return sorted(self.images)

    def K(self, im_id: int) -> np.ndarray:
        return self.cameras[im_id]["K"]

    def read_rgb(self, im_id: int) -> np.ndarray:
        """The image as RGB uint8."""
        p = self.images[im_id]
        if self.video is not None:
            bgr = self.video.read(p)
        else:
            bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if bgr is None:
                raise UserError(f"unreadable image: {p}")
        K = self.cameras[im_id]["K"]
        h, w = bgr.shape[:2]
        if not (0 < K[0, 2] < w and 0 < K[1, 2] < h):  # a camera for another resolution
            raise UserError(f"{self.root}: image {im_id} is {w}x{h} but its cam_K puts the principal point at "
                            f"({K[0, 2]:.1f}, {K[1, 2]:.1f}): the images were resized or the camera is another's")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def close(self):
        if self.video is not None:
            self.video.close()

    def image_size(self, im_id: int) -> tuple[int, int]:
        """(width, height) of an image, from its header (no decoding: ``frame_size`` asks it of
        every frame; Pillow comes with pyrender)."""
        if self.video is None:
            from PIL import Image, UnidentifiedImageError
            try:
                with Image.open(self.images[im_id]) as im:
                    return im.size
            except (OSError, UnidentifiedImageError):
                raise UserError(f"unreadable image: {self.images[im_id]}") from None
        return self.read_rgb(im_id).shape[1::-1]

    def frame_size(self, im_ids) -> tuple[int, int]:
        """(width, height) shared by the frames ``im_ids``; an error names a frame of another size
        (a scene is one camera: its visibility and scores are computed at one size)."""
        im_ids = list(im_ids)
        size = self.image_size(im_ids[0])
        if self.video is None:  # a video's frames share one size
            for i in im_ids[1:]:
                other = self.image_size(i)
                if other != size:
                    raise UserError(f"{self.images[i]} is {other[0]}x{other[1]}, image {im_ids[0]} "
                                    f"{size[0]}x{size[1]}: a scene's frames must share one size (one camera); "
                                    f"'app.py lab resize-scene' reads a scene out at one size")
        return size

    @property
    def has_depth(self) -> bool:
        d = self.root / "depth"
        return d.is_dir() and all((d / f"{i:06d}.png").is_file() for i in self.images)

    def read_depth(self, im_id: int) -> np.ndarray:
        """The depth image in mm (float; 0 = no reading): depth/NNNNNN.png x depth_scale."""
        p = self.root / "depth" / f"{im_id:06d}.png"
        raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.ndim != 2:
            raise UserError(f"unreadable depth image (expected a one-channel PNG): {p}")
        return raw.astype(np.float64) * float(self.cameras[im_id].get("depth_scale", 1.0))

    @property
    def has_gt_info(self) -> bool:
        return (self.root / "scene_gt_info.json").is_file()

    def only(self, obj_ids) -> "Scene":
        """The same scene with the ground truth of ``obj_ids`` alone (as if the others were absent)."""
        import dataclasses
        keep = {int(o) for o in obj_ids}
        gt = None if self.gt is None else {i: [g for g in lst if g.obj_id in keep] for i, lst in self.gt.items()}
        return dataclasses.replace(self, gt=gt)


def is_scene_dir(root) -> bool:
    """A BOP scene: scene_camera.json beside rgb/ or the frames as one video."""
    root = Path(root)
    return (root / "scene_camera.json").is_file() and (
        (root / "rgb").is_dir() or any((root / v).is_file() for v in SCENE_VIDEOS))


def load_scene(root, require_gt: bool = False) -> Scene:
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"BOP scene folder not found: {root}")
    rgb = root / "rgb"
    videos = [root / v for v in SCENE_VIDEOS if (root / v).is_file()]
    if not rgb.is_dir() and not videos:
        raise UserError(f"{root}: not a BOP scene (no rgb/ folder or {SCENE_VIDEOS[0]})")
    cameras = load_scene_camera(root / "scene_camera.json")
    images, video = {}, None
    if rgb.is_dir():
        for p in sorted(rgb.iterdir()):
            if p.suffix.lower() in IMAGE_EXTS and p.stem.isdigit():
                images[int(p.stem)] = p
        if not images:
            raise UserError(f"{rgb}: no NNNNNN.png / .jpg images")
    else:
        video = VideoFrames(videos[0])
        if video.count < len(cameras):
            raise UserError(f"{videos[0]}: {video.count} frames, scene_camera.json lists {len(cameras)} images "
                            f"(truncated video?)")
        images = {im_id: k for k, im_id in enumerate(sorted(cameras))}
    missing = sorted(set(images) - set(cameras))
    if missing:
        raise UserError(f"{root}/scene_camera.json has no camera for image(s) {missing[:5]}")
    gt = None
    gt_path = root / "scene_gt.json"
    if gt_path.is_file():
        gt = load_scene_gt(gt_path, root / "scene_gt_info.json")
        frameless = sorted(set(gt) - set(images))
        if frameless:
            raise UserError(f"{gt_path} has ground truth for image(s) {frameless[:5]} with no frame in "
                            f"{'rgb/' if video is None else video.path.name}: add the frames or remove their entries")
    elif require_gt:
        raise UserError(f"{root}: missing scene_gt.json (ground truth is needed here)")
    return Scene(root, cameras, gt, images, video)


# --------------------------------------------------------------------------- models_info


def positive_number(x) -> bool:
    """A JSON number (not a bool) that is finite and above 0: a diameter in mm."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        return math.isfinite(float(x)) and x > 0
    except OverflowError:  # an integer too large for a float
        return False


def _is_vector(v, nonzero: bool = False) -> bool:
    """Three finite numbers (not all zero, with ``nonzero``)."""
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return a.shape == (3,) and bool(np.all(np.isfinite(a))) and (not nonzero or bool(np.any(a != 0)))


def load_models_info(path) -> dict[int, dict]:
    path = Path(path)
    raw = _load_json(path)
    if not isinstance(raw, dict):
        raise UserError(f"{path}: expected an object of objects keyed by id (BOP models_info), not a {type(raw).__name__}")
    out = {}
    for k, v in raw.items():
        where = f"{path}: object {k}"
        if not str(k).isdigit() or not isinstance(v, dict):
            raise UserError(f"{where}: expected an object id (digits) mapped to its entry")
        if "diameter" not in v:
            raise UserError(f"{where} has no 'diameter'")
        d = v["diameter"]
        if not positive_number(d):
            raise UserError(f"{where}: 'diameter' must be a positive number of mm, not {d!r}")
        syms = v.get("symmetries_discrete", [])
        if not isinstance(syms, list) or any(np.asarray(t, dtype=object).size != 16 for t in syms):
            raise UserError(f"{where}: 'symmetries_discrete' must be a list of 4x4 transforms, each 16 numbers")
        try:
            T = np.asarray(syms, dtype=np.float64).reshape(-1, 4, 4)
        except (TypeError, ValueError):
            raise UserError(f"{where}: 'symmetries_discrete' holds something that is not a number") from None
        if not all(is_rotation(t[:3, :3], tol=1e-3) and np.all(np.isfinite(t)) for t in T):
            raise UserError(f"{where}: a 'symmetries_discrete' transform is not a rotation (a reflection, or not orthonormal)")
        conts = v.get("symmetries_continuous", [])
        if not isinstance(conts, list) or not all(
                isinstance(c, dict) and _is_vector(c.get("axis"), nonzero=True) and _is_vector(c.get("offset", [0, 0, 0]))
                for c in conts):
            raise UserError(f"{where}: 'symmetries_continuous' must be a list of {{'axis': [x, y, z], 'offset': ...}}")
        out[int(k)] = v
    return out


def save_models_info(path, info: dict[int, dict]) -> Path:
    return write_json(path, {str(k): info[k] for k in sorted(info)})


# bop_toolkit's max_sym_disc_step (0.01: the vertex farthest from the axis travels at most 1 % of
# the diameter between two steps) gives ceil(pi / 0.01) = 315 steps per continuous symmetry
BOP_CONTINUOUS_STEPS = int(np.ceil(np.pi / 0.01))


def symmetry_transforms(info: dict, continuous_steps: int = BOP_CONTINUOUS_STEPS) -> np.ndarray:
    """All symmetry transforms of one object as (S, 4, 4), identity first.

    Discrete symmetries are taken as listed; continuous ones are discretised into
    ``continuous_steps`` rotations about their axis (steps 0 .. N-1 of 2 pi / N), and combined
    with the discrete ones (continuous @ discrete, discrete outer), as bop_toolkit's
    ``get_symmetry_transformations`` does with its default ``max_sym_disc_step`` of 0.01.
    """
    disc = [np.eye(4)]
    for s in info.get("symmetries_discrete", []):
        disc.append(np.asarray(s, dtype=np.float64).reshape(4, 4))
    conts = [np.eye(4)]
    from scipy.spatial.transform import Rotation
    for c in info.get("symmetries_continuous", []):
        axis = np.asarray(c["axis"], dtype=np.float64)
        offset = np.asarray(c.get("offset", [0, 0, 0]), dtype=np.float64)
        for i in range(1, continuous_steps):
            R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * 2 * np.pi * i / continuous_steps).as_matrix()
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = offset - R @ offset
            conts.append(T)
    return np.array([c @ d for d in disc for c in conts])


def symmetry_rotations(info: dict, continuous_steps: int = 36) -> np.ndarray:
    """(S, 3, 3): the rotations of :func:`symmetry_transforms`, identity first, continuous
    symmetries in ``continuous_steps`` steps: the set the pose heads are trained and averaged with."""
    return symmetry_transforms(info, continuous_steps=continuous_steps)[:, :3, :3]


# --------------------------------------------------------------------------- results CSV

RESULT_HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
# BOP's own LM-O ground truth, written with 6 decimals, is orthonormal only to ~2e-3
ROTATION_TOL = 1e-2


@dataclass
class Estimate:
    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    time: float = -1.0


def format_result_row(e: Estimate) -> list[str]:
    return [str(int(e.scene_id)), str(int(e.im_id)), str(int(e.obj_id)), f"{e.score:.6f}",
            " ".join(f"{v:.8f}" for v in np.asarray(e.R).ravel()),
            " ".join(f"{v:.6f}" for v in np.asarray(e.t).ravel()), f"{e.time:.6f}"]


def write_results(path, estimates) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(RESULT_HEADER)
        for e in estimates:
            w.writerow(format_result_row(e))
    return path


def csv_rows(f, path, required):
    """Header check of an open CSV file: ({column: index}, iterator of (line number, row)).

    The iterator skips blank lines and rejects rows with the wrong number of fields; every
    error names the file and the line.
    """
    rows = csv.reader(f)
    header = next(rows, None)
    if header is None:
        raise UserError(f"{path}: empty file (expected header {','.join(required)},...)")
    header = [h.strip() for h in header]
    if header:  # a spreadsheet's byte-order mark ("CSV UTF-8") is not part of the first name
        header[0] = header[0].lstrip("\ufeff").strip()
    missing = [h for h in required if h not in header]
    if missing:
        raise UserError(f"{path}:1: missing column(s) {', '.join(missing)}")

    def body():
        for line, row in enumerate(rows, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise UserError(f"{path}:{line}: {len(row)} fields, expected {len(header)}")
            yield line, row
    return {h: i for i, h in enumerate(header)}, body()


def read_results(path, known_obj_ids=None) -> list[Estimate]:
    """Parse a BOP results CSV; every problem is reported with its line number."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"results file not found: {path}")
    out = []
    times: dict[tuple[int, int], tuple[float, int]] = {}
    try:
        raw = path.read_text()
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file (a BOP results CSV is expected)") from None
    with io.StringIO(raw, newline="") as f:
        col, rows = csv_rows(f, path, RESULT_HEADER)
        for line, row in rows:
            try:
                scene_id, im_id, obj_id = (int(row[col[k]]) for k in ("scene_id", "im_id", "obj_id"))
                score = float(row[col["score"]])
                R = np.array(row[col["R"]].split(), dtype=np.float64)
                t = np.array(row[col["t"]].split(), dtype=np.float64)
                tm = float(row[col["time"]])
            except ValueError as e:
                raise UserError(f"{path}:{line}: unparsable value ({e})") from None
            if R.size != 9 or t.size != 3:
                raise UserError(f"{path}:{line}: R needs 9 values and t 3, got {R.size} and {t.size}")
            R = R.reshape(3, 3)
            if not is_rotation(R, tol=ROTATION_TOL):
                raise UserError(f"{path}:{line}: R is not a rotation matrix (orthonormal, det +1)")
            if not np.all(np.isfinite(t)):
                raise UserError(f"{path}:{line}: t is not finite")
            if not np.isfinite(score):
                raise UserError(f"{path}:{line}: score is not finite")
            if known_obj_ids is not None and obj_id not in known_obj_ids:
                raise UserError(f"{path}:{line}: unknown obj_id {obj_id} (models: {sorted(known_obj_ids)})")
            key = (scene_id, im_id)
            if key in times and abs(times[key][0] - tm) > 1e-6:
                raise UserError(f"{path}:{line}: time {tm} differs from {times[key][0]} on line "
                                f"{times[key][1]} for the same image (scene {scene_id}, im {im_id})")
            times.setdefault(key, (tm, line))
            out.append(Estimate(scene_id, im_id, obj_id, score, R, t, tm))
    return out


def gt_instances_with_boxes(gts, boxes, min_visib: float = 0.0, below: bool = False) -> list[tuple]:
    """(obj_id, box, visible fraction) of the ground-truth instances of one image whose visible
    box is not empty, at least ``min_visib`` visible (or, with ``below``, less than it)."""
    out = []
    for g, (b, v) in zip(gts, boxes):
        if b[2] > 1 and b[3] > 1 and ((v < min_visib) if below else (v >= min_visib)):
            out.append((g.obj_id, b, v))
    return out
