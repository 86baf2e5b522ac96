#!/usr/bin/env python3
"""Check a run's rerun recording in a real browser (outside CI; localhost only).

Serves RECORDING.rrd with ``rerun --serve-web``, opens the web viewer in headless Chromium
(Debian's ``chromium``) driven over the DevTools protocol, waits for the viewer's WebAssembly
to load and draw, takes a screenshot and fails if it is blank or the console shows a viewer
error. A plain ``chromium --headless --screenshot`` returns before the viewer has loaded.

    .venv/bin/python scripts/check_web_viewer.py runs/demo-.../recording.rrd --png viewer.png

Without a recording, one is made first (``app.py demo --max-frames 10``). Needs
``apt install chromium`` and websocket-client (in the ``test`` extra). Exit 0: the viewer drew
the recording; 1: it did not (the reason on one line); 2: bad input.
"""
from __future__ import annotations

import argparse
import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VIEWER_ERRORS = ("panic", "error", "failed", "requires a pinhole", "uncaught")
# the viewer's calls to the internet (release check, examples, fonts, telemetry) fail offline
OFFLINE = ("ERR_NAME_NOT_RESOLVED", "ERR_INTERNET_DISCONNECTED", "ERR_CONNECTION_REFUSED (http",
           "TypeError: Failed to fetch")
MAIN_VIEW_STD = 25.0  # pixel spread of the image view once it shows a frame (blank or spinner: < 5)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop_group(p: subprocess.Popen) -> None:
    """Terminate ``p`` and every process it started (its own session), killing what lingers."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            return
        try:
            p.wait(10)
            time.sleep(0.5)  # the group's other members exit after its leader
        except subprocess.TimeoutExpired:
            pass


def wait_http(url: str, timeout: float) -> bytes:
    end = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                return r.read()
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.3)


class DevTools:
    """The few DevTools-protocol calls needed, over one page's websocket."""

    def __init__(self, ws_url: str):
        import websocket  # websocket-client
        self.ws = websocket.create_connection(ws_url, timeout=60, suppress_origin=True)
        self.n = 0
        self.console: list[str] = []

    def call(self, method: str, **params) -> dict:
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.n:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self._event(msg)

    def pump(self, seconds: float) -> None:
        """Collect console events for ``seconds``."""
        end = time.monotonic() + seconds
        self.ws.settimeout(1.0)
        import websocket
        while time.monotonic() < end:
            try:
                self._event(json.loads(self.ws.recv()))
            except websocket.WebSocketTimeoutException:
                pass
        self.ws.settimeout(60)

    def _event(self, msg: dict) -> None:
        m, p = msg.get("method"), msg.get("params", {})
        if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            self.console.append(" ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
        elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            e = p["entry"]
            self.console.append(e.get("text", "") + (f" ({e['url']})" if e.get("url") else ""))
        elif m == "Runtime.exceptionThrown":
            self.console.append(p.get("exceptionDetails", {}).get("text", "exception"))


def analyse(png: bytes) -> dict:
    """How much the screenshot shows: distinct colours and the spread of its pixels."""
    import cv2
    import numpy as np
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    h, w = img.shape[:2]
    small = (img[::4, ::4] // 8).reshape(-1, 3)
    main = img[int(0.1 * h):int(0.7 * h), int(0.05 * w):int(0.55 * w)]  # the blueprint's large image view
    return {"width": int(w), "height": int(h), "std": float(img.std()), "main_std": float(main.std()),
            "colours": int(len(np.unique(small, axis=0)))}


def make_recording(tmp: Path) -> Path:
    out = tmp / "demo"
    subprocess.run([sys.executable, str(REPO / "app.py"), "demo", "--max-frames", "10", "--out", str(out)],
                   check=True, cwd=REPO, stdout=subprocess.DEVNULL)
    return out / "recording.rrd"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", nargs="?", help="a run's recording.rrd (default: make one with the demo)")
    ap.add_argument("--png", default="viewer.png", help="where to write the screenshot")
    ap.add_argument("--wait", type=float, default=90.0,
                    help="at most this many seconds for the viewer to load and draw (looked at from 30 s on)")
    ap.add_argument("--size", default="1600,1000", help="browser window W,H")
    args = ap.parse_args(argv)
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        print("error: no chromium here; install Debian's: apt install chromium", file=sys.stderr)
        return 2
    try:
        import websocket  # noqa: F401
    except ImportError:
        print("error: needs websocket-client: .venv/bin/pip install -e '.[test]'", file=sys.stderr)
        return 2
    rerun = Path(sys.executable).parent / "rerun"
    procs = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rrd = Path(args.recording) if args.recording else make_recording(tmp)
        if not rrd.is_file():
            print(f"error: {rrd}: no such recording", file=sys.stderr)
            return 2
        web, grpc, dbg = free_port(), free_port(), free_port()
        try:
            procs.append(subprocess.Popen([str(rerun), "--serve-web", str(rrd), "--bind", "127.0.0.1",
                                           "--web-viewer-port", str(web), "--port", str(grpc)],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                          start_new_session=True))
            wait_http(f"http://127.0.0.1:{web}/", 60)
            procs.append(subprocess.Popen([chromium, "--headless=new", "--no-sandbox", "--disable-gpu-sandbox",
                                           "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                                           f"--window-size={args.size}", f"--remote-debugging-port={dbg}",
                                           "--remote-debugging-address=127.0.0.1", f"--user-data-dir={tmp / 'profile'}",
                                           "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                          start_new_session=True))
            wait_http(f"http://127.0.0.1:{dbg}/json/version", 60)
            pages = json.loads(wait_http(f"http://127.0.0.1:{dbg}/json/list", 10))
            page = next(p for p in pages if p.get("type") == "page")
            dt = DevTools(page["webSocketDebuggerUrl"])
            for domain in ("Page", "Runtime", "Log"):
                dt.call(f"{domain}.enable")
            url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy"
            dt.call("Page.navigate", url=url)
            t0 = time.monotonic()
            dt.pump(min(30.0, args.wait))
            while True:  # the frame's JPEGs decode last: look again until the main view shows one
                png = base64.b64decode(dt.call("Page.captureScreenshot", format="png")["data"])
                if analyse(png)["main_std"] >= MAIN_VIEW_STD or time.monotonic() - t0 >= args.wait:
                    break
                dt.pump(5.0)
            Path(args.png).write_bytes(png)
            waited = time.monotonic() - t0
        finally:  # whole process groups: .venv/bin/rerun is a wrapper that starts the real server
            for p in procs:
                stop_group(p)
    a = analyse(png)
    offline = [c for c in dt.console if any(k in c for k in OFFLINE) and "(http://127.0.0.1" not in c
               or c.startswith("TypeError: Failed to fetch")]  # the JS side of those calls (its URL is logged apart)
    errors = [c for c in dt.console if c not in offline and any(k in c.lower() for k in VIEWER_ERRORS)]
    print(f"screenshot {args.png} after {waited:.0f} s: {a['width']}x{a['height']}, {a['colours']} colours, "
          f"pixel std {a['std']:.1f} (image view {a['main_std']:.1f}); {len(errors)} console error(s), "
          f"{len(offline)} failed call(s) to the internet (offline here)")
    for c in errors[:10]:
        print(f"  console: {c[:200]}")
    if a["colours"] < 50 or a["std"] < 10 or a["main_std"] < MAIN_VIEW_STD:
        print("FAIL: the screenshot is (nearly) blank or the image view shows no frame: the viewer did not draw",
              file=sys.stderr)
        return 1
    if errors:
        print(f"FAIL: the viewer reported an error: {errors[0][:200]}", file=sys.stderr)
        return 1
    print("ok: the viewer drew the recording")
    return 0


if __name__ == "__main__":
    sys.exit(main())
