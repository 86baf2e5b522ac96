"""Frame sources: a V4L2 camera (threaded, newest frame wins), a video file, an image folder
or a BOP scene. Every source yields :class:`Frame` objects with RGB pixels and a capture time
on the monotonic clock."""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from tracker.core.bop import IMAGE_EXTS, GtInstance, is_scene_dir, load_scene
from tracker.core.errors import UserError
from tracker.core.files import require_utf8


@dataclass
class Frame:
    index: int            # im_id for BOP scenes, else the frame counter
    t_capture: float      # time.monotonic() when the frame was read
    rgb: np.ndarray
    K: np.ndarray | None = None           # per-frame intrinsics (BOP scenes)
    gt: list[GtInstance] = field(default_factory=list)


class Source:
    """A source is a context manager: leaving the ``with`` closes it (a camera's thread ends)."""
    kind = "source"
    fps: float | None = None
    dropped = 0

    def __iter__(self):
        raise NotImplementedError

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class BopSceneSource(Source):
    kind = "bop"

    def __init__(self, root, max_frames=None, realtime=False):
        self.scene = load_scene(root)
        self.ids = self.scene.im_ids[:max_frames] if max_frames else self.scene.im_ids
        self.realtime = realtime
        self.fps = 30.0
        if self.scene.video is not None:
            self.fps = float(self.scene.video.cap.get(cv2.CAP_PROP_FPS)) or 30.0

    def __iter__(self):
        t0 = time.monotonic()
        for n, im_id in enumerate(self.ids):
            if self.realtime:
                _sleep_until(t0 + n / self.fps)
            rgb = self.scene.read_rgb(im_id)
            gt = self.scene.gt.get(im_id, []) if self.scene.gt else []
            yield Frame(im_id, time.monotonic(), rgb, self.scene.K(im_id), gt)

    def close(self):
        self.scene.close()


class ImageFolderSource(Source):
    kind = "images"

    def __init__(self, root, max_frames=None, realtime=False, fps=30.0):
        self.paths = sorted(require_utf8(p, "image") for p in Path(root).iterdir() if p.suffix.lower() in IMAGE_EXTS)
        if not self.paths:
            raise UserError(f"{root}: no .png/.jpg images")
        self.paths = self.paths[:max_frames] if max_frames else self.paths
        self.realtime, self.fps = realtime, fps

    def __iter__(self):
        t0 = time.monotonic()
        for n, p in enumerate(self.paths):
            if self.realtime:
                _sleep_until(t0 + n / self.fps)
            bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if bgr is None:
                raise UserError(f"unreadable image: {p}")
            yield Frame(n, time.monotonic(), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))


class VideoFileSource(Source):
    kind = "video"

    def __init__(self, path, max_frames=None, realtime=False):
        self.path = str(path)
        self.cap = cv2.VideoCapture(self.path)
        if not self.cap.isOpened():
            raise UserError(f"cannot open video '{path}' (missing, corrupt or an unknown codec)")
        ok, first = self.cap.read()
        if not ok:
            self.cap.release()
            raise UserError(f"'{path}' has no readable frame (empty or corrupt video)")
        self._first = first
        fps = self.cap.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and 1 <= fps <= 240 else 30.0
        self.max_frames, self.realtime = max_frames, realtime
        self.truncated = False

    def __iter__(self):
        t0 = time.monotonic()
        n, frame = 0, self._first
        expected = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        while frame is not None and (self.max_frames is None or n < self.max_frames):
            if self.realtime:
                _sleep_until(t0 + n / self.fps)
            yield Frame(n, time.monotonic(), cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            n += 1
            ok, frame = self.cap.read()
            if not ok:
                frame = None
        if expected and n < expected - 1 and (self.max_frames is None or n < self.max_frames):
            self.truncated = True  # the file ended early: reported, not fatal

    def close(self):
        self.cap.release()


class CameraSource(Source):
    """V4L2 camera read by a thread that keeps only the newest frame: a slow pipeline drops
    frames (counted in ``dropped``) instead of falling behind. When the camera stops
    delivering (unplugged), the thread tries to open it again for ``reconnect_s`` seconds
    (and at most ``retries`` times, None: no limit but the time), every ``retry_s`` seconds
    (counted in ``reconnects``); after that the iteration ends cleanly with ``lost`` set.

    The capture belongs to the thread: :meth:`close` asks it to stop and waits for it up to
    ``close_timeout_s`` (a live camera's read in flight returns within a frame); the thread
    releases the camera as it ends, never under a read in flight."""

    kind = "camera"

    def __init__(self, device, width=None, height=None, fps=None, max_frames=None, capture=None, timeout_s=2.0,
                 reconnect_s: float = 5.0, opener=None, retry_s: float = 0.5, retries: int | None = None,
                 close_timeout_s: float = 1.0):
        self.device = device
        self.size_fps = (width, height, fps)
        if opener is None and capture is None:
            def opener():
                return cv2.VideoCapture(device, cv2.CAP_V4L2)
        self.opener, self.reconnect_s, self.retry_s, self.retries = opener, reconnect_s, retry_s, retries
        self.close_timeout_s = close_timeout_s
        self.cap = capture if capture is not None else opener()
        if not self.cap.isOpened():
            self.cap.release()
            raise UserError(f"no camera at '{device}' (check the index or /dev/videoN and permissions)")
        self._configure(self.cap)
        self.fps = self.cap.get(cv2.CAP_PROP_FPS) or fps
        self.max_frames, self.timeout_s = max_frames, timeout_s
        self._cond = threading.Condition()
        self._latest: tuple[int, float, np.ndarray] | None = None
        self._grabbed = 0
        self._taken = -1
        self.dropped = 0
        self.reconnects = 0
        self.reconnecting = False
        self.lost = False
        self.closed = False
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _configure(self, cap):
        width, height, fps = self.size_fps
        if width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if fps:
            cap.set(cv2.CAP_PROP_FPS, fps)

    def _reopen(self) -> bool:
        if self.opener is None or self.reconnect_s <= 0:
            return False
        with self._cond:
            self.reconnecting = True
        self.cap.release()
        deadline = time.monotonic() + self.reconnect_s
        tries = 0
        try:
            while not self._stop and time.monotonic() < deadline and (self.retries is None or tries < self.retries):
                time.sleep(self.retry_s)
                tries += 1
                cap = self.opener()
                if cap.isOpened():
                    self._configure(cap)
                    self.cap = cap
                    self.reconnects += 1
                    return True
                cap.release()
            return False
        finally:
            with self._cond:
                self.reconnecting = False
                self._cond.notify_all()

    def _run(self):
        try:
            while not self._stop:
                ok, frame = self.cap.read()
                t = time.monotonic()
                if not ok:
                    if self._reopen():
                        continue
                    with self._cond:
                        self.lost = True
                        self._cond.notify_all()
                    return
                with self._cond:
                    self._latest = (self._grabbed, t, frame)
                    self._grabbed += 1
                    self._cond.notify_all()
        finally:
            self.cap.release()

    def __iter__(self):
        n = 0
        while self.max_frames is None or n < self.max_frames:
            with self._cond:
                while True:
                    ok = self._cond.wait_for(lambda: self.lost or (self._latest and self._latest[0] > self._taken),
                                             timeout=self.timeout_s)
                    if ok or not self.reconnecting:
                        break  # (while reconnecting, keep waiting)
                if not ok or (self.lost and (self._latest is None or self._latest[0] <= self._taken)):
                    self.lost = True
                    return  # unplugged or stalled: the loop ends cleanly and says so
                idx, t, frame = self._latest
                self.dropped += idx - self._taken - 1
                self._taken = idx
            yield Frame(n, t, cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            n += 1

    def close(self):
        """Stop the capture thread and wait for it (up to ``close_timeout_s``); it releases the
        camera as it ends."""
        self._stop = True
        self.closed = True
        self._thread.join(timeout=self.close_timeout_s)

    @property
    def capturing(self) -> bool:
        """Whether the capture thread still runs."""
        return self._thread.is_alive()


def _sleep_until(t):
    d = t - time.monotonic()
    if d > 0:
        time.sleep(d)


def is_camera(src) -> bool:
    """A camera index or a /dev/videoN path (anything else is a recording)."""
    s = str(src)
    return (s.isascii() and s.isdigit()) or s.startswith("/dev/video")  # "²" is a digit, not a number


def source_kind(src) -> str:
    """What ``src`` names, without opening it: camera, bop (a BOP scene folder), images (a
    folder) or video (a file); a UserError for anything else."""
    s = str(src)
    if is_camera(s):
        return CameraSource.kind
    p = Path(s)
    if p.is_dir():
        return BopSceneSource.kind if is_scene_dir(p) else ImageFolderSource.kind
    if p.is_file():
        return VideoFileSource.kind
    raise UserError(f"source '{src}' is not a camera, video file, image folder or BOP scene")


def open_source(src: str, max_frames=None, realtime=False, width=None, height=None, fps=None) -> Source:
    """Camera index or /dev/videoN, video file, image folder, or BOP scene folder."""
    s = str(src)
    kind = source_kind(s)
    if kind == CameraSource.kind:
        return CameraSource(int(s) if s.isascii() and s.isdigit() else s, width, height, fps, max_frames)
    if kind == BopSceneSource.kind:
        return BopSceneSource(Path(s), max_frames, realtime)
    if kind == ImageFolderSource.kind:
        return ImageFolderSource(Path(s), max_frames, realtime)
    return VideoFileSource(Path(s), max_frames, realtime)
