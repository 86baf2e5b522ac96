"""The annotated frames as a person would share them: a video file (``--video-out``) and/or
numbered PNGs (``--frames-out``), written while the loop runs."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tracker.core.errors import UserError

CODECS = {".mp4": "mp4v", ".avi": "MJPG", ".mkv": "MJPG"}


def check_video_path(path) -> Path:
    """Refuse, before the run starts, a video path this writer cannot produce."""
    p = Path(path)
    if p.suffix.lower() not in CODECS:
        raise UserError(f"--video-out {p}: give a .mp4, .avi or .mkv file")
    if p.is_dir():
        raise UserError(f"--video-out {p} is a folder; give a file, e.g. {p / 'run.mp4'}")
    if not p.parent.is_dir():
        raise UserError(f"--video-out {p}: folder {p.parent} does not exist")
    return p


def check_frames_dir(path) -> Path:
    """Refuse, before the run starts, a --frames-out that is a file."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"--frames-out {p} is a file; give a folder")
    return p


class FrameWriter:
    """Writes RGB frames to ``video`` (at ``fps``) and/or as ``frames_dir/NNNNNN.png``; a
    context manager (leaving it closes the video)."""

    def __init__(self, video=None, frames_dir=None, fps: float = 30.0):
        self.video = check_video_path(video) if video else None
        self.frames_dir = check_frames_dir(frames_dir) if frames_dir else None
        if self.frames_dir is not None:
            self.frames_dir.mkdir(parents=True, exist_ok=True)
        self.fps = float(fps) if fps and fps > 0 else 30.0
        self._vw = None
        self._size = None
        self.frames = 0

    @property
    def active(self) -> bool:
        return self.video is not None or self.frames_dir is not None

    def write(self, index: int, rgb: np.ndarray) -> None:
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        if self.video is not None:
            h, w = bgr.shape[:2]
            if self._vw is None:
                self._vw = cv2.VideoWriter(str(self.video), cv2.VideoWriter_fourcc(*CODECS[self.video.suffix.lower()]),
                                           self.fps, (w, h))
                if not self._vw.isOpened():
                    self._vw = None
                    raise UserError(f"--video-out {self.video}: OpenCV cannot write this video here")
                self._size = (w, h)
            if (w, h) != self._size:  # a source that changes size mid-run: keep the file's size
                bgr = cv2.resize(bgr, self._size, interpolation=cv2.INTER_AREA)
            self._vw.write(bgr)
        if self.frames_dir is not None:
            cv2.imwrite(str(self.frames_dir / f"{int(index):06d}.png"), bgr)
        self.frames += 1

    def close(self) -> None:
        if self._vw is not None:
            self._vw.release()
            self._vw = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
