"""Small line charts and histograms drawn with OpenCV on a numpy canvas.

matplotlib is not a dependency of the runtime, and the reports only need a few plain
charts. Everything returns an RGB ``uint8`` image; :func:`save_png` writes one.
Series may contain NaN: a line is broken there (use it to show gaps in the data).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
# RGB colours for successive series
PALETTE = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189),
           (140, 86, 75)]
GREY = (200, 200, 200)
DARK = (40, 40, 40)


@dataclass
class Series:
    x: np.ndarray
    y: np.ndarray
    label: str = ""
    colour: tuple[int, int, int] | None = None
    thickness: int = 1


@dataclass
class Panel:
    series: list[Series]
    title: str = ""
    xlabel: str = ""
    ylabel: str = ""
    vlines: dict[str, float] = field(default_factory=dict)  # label -> x
    ylim: tuple[float, float] | None = None  # values outside are drawn on the border


def nice_ticks(lo: float, hi: float, n: int = 6) -> np.ndarray:
    """About n round tick values (steps of 1, 2 or 5 times a power of ten) covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return np.array([0.0])
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(n - 1, 1)
    p = 10.0 ** math.floor(math.log10(raw))
    step = next(m * p for m in (1, 2, 5, 10) if m * p >= raw)
    start = math.ceil(lo / step - 1e-9) * step
    ticks = np.arange(start, hi + step * 1e-6, step)
    return np.round(ticks, 12)


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.1e}"
    return f"{v:.4g}"


def _text(img, s, org, scale=0.42, colour=DARK, thickness=1, anchor="left"):
    (w, h), _ = cv2.getTextSize(s, FONT, scale, thickness)
    x, y = org
    if anchor == "centre":
        x -= w // 2
    elif anchor == "right":
        x -= w
    cv2.putText(img, s, (int(x), int(y)), FONT, scale, colour, thickness, cv2.LINE_AA)
    return w, h


def _draw_panel(img: np.ndarray, panel: Panel, box: tuple[int, int, int, int],
                xlim=None, ylim=None, bars=None) -> None:
    """Draw one panel into ``box`` = (x0, y0, x1, y1) of img (plot area plus margins)."""
    X0, Y0, X1, Y1 = box
    left, right, top, bottom = 70, 20, 26, 40
    px0, py0, px1, py1 = X0 + left, Y0 + top, X1 - right, Y1 - bottom

    xs = [s.x[np.isfinite(s.x) & np.isfinite(s.y)] for s in panel.series]
    ys = [s.y[np.isfinite(s.x) & np.isfinite(s.y)] for s in panel.series]
    allx = np.concatenate(xs) if xs else np.zeros(0)
    ally = np.concatenate(ys) if ys else np.zeros(0)
    if xlim is None:
        xlim = (float(allx.min()), float(allx.max())) if allx.size else (0.0, 1.0)
    if ylim is None:
        ylim = panel.ylim
    if ylim is None:
        ylim = (float(ally.min()), float(ally.max())) if ally.size else (0.0, 1.0)
    (xa, xb), (ya, yb) = xlim, ylim
    if xb <= xa:
        xa, xb = xa - 0.5, xb + 0.5
    if yb <= ya:
        ya, yb = ya - 0.5, yb + 0.5
    pad = 0.05 * (yb - ya)
    if bars is None:
        ya, yb = ya - pad, yb + pad
    else:
        yb = yb + pad

    def to_px(x, y):
        u = px0 + (np.asarray(x, float) - xa) / (xb - xa) * (px1 - px0)
        v = py1 - (np.asarray(y, float) - ya) / (yb - ya) * (py1 - py0)
        return u, v

    # grid and ticks
    for t in nice_ticks(xa, xb):
        if xa <= t <= xb:
            u, _ = to_px(t, ya)
            cv2.line(img, (int(u), py0), (int(u), py1), GREY, 1)
            _text(img, _fmt(t), (u, py1 + 15), anchor="centre")
    for t in nice_ticks(ya, yb, 5):
        if ya <= t <= yb:
            _, v = to_px(xa, t)
            cv2.line(img, (px0, int(v)), (px1, int(v)), GREY, 1)
            _text(img, _fmt(t), (px0 - 5, v + 4), anchor="right")
    cv2.rectangle(img, (px0, py0), (px1, py1), DARK, 1)
    if panel.title:
        _text(img, panel.title, ((px0 + px1) // 2, Y0 + 18), scale=0.5, anchor="centre")
    if panel.xlabel:
        _text(img, panel.xlabel, ((px0 + px1) // 2, Y1 - 6), anchor="centre")
    if panel.ylabel:
        _text(img, panel.ylabel, (X0 + 4, py0 - 6))

    if bars is not None:
        edges, counts, colour = bars
        for a, b, c in zip(edges[:-1], edges[1:], counts):
            if c <= 0:
                continue
            u0, v0 = to_px(a, 0)
            u1, v1 = to_px(b, c)
            cv2.rectangle(img, (int(u0) + 1, int(v1)), (max(int(u1) - 1, int(u0) + 1), int(v0)),
                          colour, -1)

    # series
    for k, s in enumerate(panel.series):
        colour = s.colour or PALETTE[k % len(PALETTE)]
        u, v = to_px(s.x, s.y)
        ok = np.isfinite(u) & np.isfinite(v)
        v = np.clip(v, py0, py1)
        # split into runs of finite points
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            continue
        runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
        for r in runs:
            pts = np.stack([u[r], v[r]], axis=1).round().astype(np.int32)
            if len(pts) == 1:
                cv2.circle(img, tuple(int(c) for c in pts[0]), 1, colour, -1)
            else:
                cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, colour, s.thickness, cv2.LINE_AA)

    # vertical markers
    for k, (label, x) in enumerate(panel.vlines.items()):
        if not math.isfinite(x):
            continue
        colour = PALETTE[(k + 1) % len(PALETTE)]
        u, _ = to_px(x, ya)
        cv2.line(img, (int(u), py0), (int(u), py1), colour, 1, cv2.LINE_AA)
        _text(img, f"{label} {_fmt(x)}", (u + 4, py0 + 14 + 14 * k), colour=colour)

    # legend
    y = py0 + 14
    for k, s in enumerate(panel.series):
        if not s.label:
            continue
        colour = s.colour or PALETTE[k % len(PALETTE)]
        (w, _), _ = cv2.getTextSize(s.label, FONT, 0.42, 1)
        x = px1 - w - 30
        cv2.line(img, (x, y - 4), (x + 20, y - 4), colour, 2, cv2.LINE_AA)
        _text(img, s.label, (x + 24, y))
        y += 16


def line_chart(panels: list[Panel], width: int = 900, panel_height: int = 230,
               title: str = "", share_x: bool = True) -> np.ndarray:
    """Panels stacked vertically (sharing the x range when share_x)."""
    head = 30 if title else 0
    img = np.full((head + panel_height * len(panels), width, 3), 255, np.uint8)
    if title:
        _text(img, title, (width // 2, 21), scale=0.6, anchor="centre")
    xlim = None
    if share_x:
        xs = [s.x[np.isfinite(s.x)] for p in panels for s in p.series]
        xs = np.concatenate(xs) if xs else np.zeros(0)
        if xs.size:
            xlim = (float(xs.min()), float(xs.max()))
    for i, p in enumerate(panels):
        _draw_panel(img, p, (0, head + i * panel_height, width, head + (i + 1) * panel_height), xlim=xlim)
    return img


def histogram(values, bins: int | np.ndarray | None = None, title: str = "", xlabel: str = "",
              ylabel: str = "count", vlines: dict[str, float] | None = None,
              width: int = 800, height: int = 420,
              range_: tuple[float, float] | None = None) -> np.ndarray:
    """Bar histogram of ``values``; ``vlines`` marks e.g. the median with a labelled line.
    Values outside ``range_`` are left out (say so in the title)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if range_ is not None:
        v = v[(v >= range_[0]) & (v <= range_[1])]
    if bins is None:
        bins = int(np.clip(np.sqrt(max(v.size, 1)) * 2, 10, 60))
    counts, edges = (np.histogram(v, bins=bins, range=range_) if v.size
                     else (np.zeros(1), np.array(range_ if range_ else (0.0, 1.0), float)))
    img = np.full((height, width, 3), 255, np.uint8)
    panel = Panel([], title=title, xlabel=xlabel, ylabel=ylabel, vlines=dict(vlines or {}))
    _draw_panel(img, panel, (0, 0, width, height), xlim=(float(edges[0]), float(edges[-1])),
                ylim=(0.0, float(max(counts.max(), 1))), bars=(edges, counts, PALETTE[0]))
    return img


def save_png(path, rgb: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
    return path


def scatter(xy: np.ndarray, labels, names: dict | None = None, title: str = "", width: int = 760,
            height: int = 620, radius: int = 3) -> np.ndarray:
    """2D points coloured by ``labels`` (one colour per distinct label, legend on the right)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    labels = np.asarray(labels)
    keys = sorted(set(labels.tolist()))
    names = names or {}
    colours = PALETTE + [(23, 190, 207), (188, 189, 34), (227, 119, 194), (127, 127, 127)]
    img = np.full((height, width, 3), 255, np.uint8)
    legend_w, top, pad = 170, 34 if title else 10, 12
    if title:
        _text(img, title, ((width - legend_w) // 2, 22), scale=0.55, anchor="centre")
    x0, y0, x1, y1 = pad, top, width - legend_w - pad, height - pad
    cv2.rectangle(img, (x0, y0), (x1, y1), GREY, 1)
    if len(xy):
        lo, hi = xy.min(0), xy.max(0)
        span = np.where(hi - lo > 0, hi - lo, 1.0)
        uv = (xy - lo) / span
        u = x0 + 6 + uv[:, 0] * (x1 - x0 - 12)
        v = y1 - 6 - uv[:, 1] * (y1 - y0 - 12)
        for k, key in enumerate(keys):
            col = colours[k % len(colours)]
            for a, b in zip(u[labels == key], v[labels == key]):
                cv2.circle(img, (int(round(a)), int(round(b))), radius, col, -1, cv2.LINE_AA)
    for k, key in enumerate(keys):
        yy = top + 14 + 20 * k
        cv2.circle(img, (width - legend_w + 10, yy - 4), 5, colours[k % len(colours)], -1, cv2.LINE_AA)
        _text(img, str(names.get(key, key)), (width - legend_w + 22, yy))
    return img
