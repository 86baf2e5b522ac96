"""Path-traced colour for ``synth``'s targets: Blender's Cycles, on the CPU (``synth --renderer
cycles``; ``apt install blender``, an optional tool like ``scripts/debian_assets.py``: never
needed by the runtime, the tests of CI or a bundle).

Every scene is drawn and annotated as with the rasteriser (pyrender keeps the depth, labels,
masks, visible boxes and clean crops); only the targets' pixels of the image come from Cycles,
rendered alone with the same camera and lights (soft shading, self-shadowing, ambient
occlusion, specular light that the rasteriser does not make), so a split rendered both ways has
identical annotations and can be compared paired (docs/experiments/stop-64.md, item 13).

One Blender process per render worker (``cycles_blender.py`` runs inside it), fed the meshes
once and then one JSON request a line per image; a Blender that dies or stalls raises here, so
``synth``'s pool sees a failed worker, never a hang.
"""
from __future__ import annotations

import json
import os
import selectors
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from tracker.core.errors import UserError

SCRIPT = Path(__file__).with_name("cycles_blender.py")
SAMPLES = 16  # per pixel: 0.9-1.9 s for the targets of a 640 x 480 image on one core's share (stop 64)
ROUGHNESS, SPECULAR = 0.6, 0.3
# pyrender's light intensities and ambient -> Cycles' sun and world strengths, so that the targets
# come out about as bright as the rasteriser draws them (median ratio of their visible pixels' mean,
# 8-bit sRGB, raster / Cycles, over the objects of the same synth images: 1.50 with a factor of 1
# (27 objects), 0.92 with 2.44 (51); 2.0 interpolates in linear light)
LIGHT_SCALE = 2.0
RENDER_TIMEOUT = 600.0  # seconds for one image before Blender counts as stalled
START_TIMEOUT = 300.0


def blender_executable() -> str:
    """``AUTOPOSE_BLENDER`` or ``blender`` on the PATH; a one-line error when there is none."""
    exe = os.environ.get("AUTOPOSE_BLENDER") or shutil.which("blender")
    if not exe or not Path(exe).is_file():
        raise UserError("--renderer cycles needs Blender: install it (apt install blender) or set "
                        "AUTOPOSE_BLENDER to its executable")
    return exe


class CyclesRenderer:
    """``render(K, instances, lights, ambient)`` -> (rgb uint8 HxWx3, alpha float32 HxW in 0..1):
    the instances [(mesh id, R, t mm)] in front of nothing. ``meshes``: {id: trimesh mesh in mm
    with vertex colours}; ``threads``: Cycles' threads (one per render worker)."""

    def __init__(self, width: int, height: int, meshes: dict, threads: int = 1, samples: int = SAMPLES):
        self.width, self.height = int(width), int(height)
        self._tmp = tempfile.TemporaryDirectory(prefix="autopose-cycles-")
        tmp = Path(self._tmp.name)
        paths = {}
        for k, m in meshes.items():
            paths[str(int(k))] = str(tmp / f"mesh_{int(k)}.ply")
            m.export(paths[str(int(k))])
        self._log = open(tmp / "blender.log", "w")
        self._proc = subprocess.Popen(
            [blender_executable(), "--background", "--factory-startup", "--python", str(SCRIPT)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._proc.stdout, selectors.EVENT_READ)
        self._buf = b""  # Blender's stdout as read so far (raw reads: a buffered reader would hide lines from select)
        self._out = str(tmp / "render.png")
        self._ask({"op": "init", "meshes": paths, "width": self.width, "height": self.height, "samples": int(samples),
                   "threads": int(threads), "roughness": ROUGHNESS, "specular": SPECULAR}, START_TIMEOUT)

    def _ask(self, req: dict, timeout: float) -> None:
        try:
            self._proc.stdin.write((json.dumps(req) + "\n").encode())
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise UserError(f"Blender exited (code {self._proc.wait(timeout=30)}): {self._last_log_line()}") from None
        deadline = time.monotonic() + timeout
        fd = self._proc.stdout.fileno()
        while True:
            while b"\n" in self._buf:
                line, self._buf = self._buf.split(b"\n", 1)
                if line.startswith(b"AUTOPOSE "):
                    reply = line[len(b"AUTOPOSE "):].decode(errors="replace").strip()
                    if reply != "ok":
                        raise UserError(f"Blender: {reply}")
                    return
            left = deadline - time.monotonic()
            if left <= 0 or not self._sel.select(left):
                why = self._last_log_line()
                self.close()
                raise UserError(f"Blender gave no answer in {timeout:.0f} s: {why}")
            chunk = os.read(fd, 65536)
            if not chunk:
                raise UserError(f"Blender exited (code {self._proc.wait()}): {self._last_log_line()}")
            self._buf += chunk

    def _last_log_line(self) -> str:
        """The last line Blender wrote to its log (its error, usually)."""
        if not self._log.closed:
            self._log.flush()
        lines = [x.strip() for x in Path(self._log.name).read_text(errors="replace").splitlines() if x.strip()]
        return lines[-1] if lines else "(its log is empty)"

    def render(self, K, instances, lights, ambient) -> tuple[np.ndarray, np.ndarray]:
        amb = float(np.mean(ambient)) * LIGHT_SCALE
        req = {"op": "render", "K": np.asarray(K, np.float64).ravel().tolist(), "out": self._out, "ambient": amb,
               "instances": [[int(k), np.asarray(R, np.float64).ravel().tolist(),
                              np.asarray(t, np.float64).ravel().tolist()] for k, R, t in instances],
               "lights": [[np.asarray(d, np.float64).tolist(), np.asarray(c, np.float64).tolist(), float(i) * LIGHT_SCALE]
                          for d, c, i in lights]}
        self._ask(req, RENDER_TIMEOUT)
        img = cv2.imread(self._out, cv2.IMREAD_UNCHANGED)
        if img is None or img.shape != (self.height, self.width, 4):
            raise UserError(f"Blender wrote no {self.width}x{self.height} RGBA image to {self._out}")
        return cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB), img[..., 3].astype(np.float32) / 255.0

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        self._log.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
