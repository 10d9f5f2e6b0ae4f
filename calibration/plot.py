"""A tiny PNG plotter (zlib + struct, no matplotlib): scatter points and lines on axes.

Enough for a calibration record: the measured points, the fitted line and the
residuals panel, each series in its own colour, with a zero line and a frame. No text
is drawn; the procedure's report names the axes and series.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

COLOURS = {"black": (0, 0, 0), "blue": (31, 119, 180), "red": (214, 39, 40), "green": (44, 160, 44),
           "orange": (255, 127, 14), "grey": (190, 190, 190), "purple": (148, 103, 189)}


@dataclass
class Series:
    x: np.ndarray
    y: np.ndarray
    style: str = "points"  #: "points" or "line"
    colour: str = "blue"


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an (h, w, 3) uint8 array as an 8-bit RGB PNG."""
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[r].astype(np.uint8).tobytes() for r in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(png)
    return p


class Canvas:
    """Pixel canvas with one or more panels stacked vertically."""

    def __init__(self, width: int = 640, height: int = 480) -> None:
        self.w, self.h = width, height
        self.img = np.full((height, width, 3), 255, dtype=np.uint8)

    def _set(self, x: int, y: int, c) -> None:
        if 0 <= x < self.w and 0 <= y < self.h:
            self.img[y, x] = c

    def line(self, x0: int, y0: int, x1: int, y1: int, c) -> None:
        """Bresenham line."""
        dx, dy = abs(x1 - x0), -abs(y1 - y0)
        sx, sy = (1 if x0 < x1 else -1), (1 if y0 < y1 else -1)
        err = dx + dy
        for _ in range(4 * (self.w + self.h)):
            self._set(x0, y0, c)
            if x0 == x1 and y0 == y1:
                return
            e2 = 2 * err
            if e2 >= dy:
                err += dy
                x0 += sx
            if e2 <= dx:
                err += dx
                y0 += sy

    def marker(self, x: int, y: int, c, r: int = 2) -> None:
        self.img[max(0, y - r):max(0, y + r + 1), max(0, x - r):max(0, x + r + 1)] = c

    def panel(self, top: int, bottom: int, series: list[Series], margin: int = 30) -> None:
        """Draw ``series`` into the band ``top..bottom`` with a frame and a y = 0 line."""
        left, right = margin, self.w - margin // 2
        top, bottom = top + margin // 2, bottom - margin // 2
        xs = np.concatenate([np.asarray(s.x, float).ravel() for s in series]) if series else np.zeros(1)
        ys = np.concatenate([np.asarray(s.y, float).ravel() for s in series]) if series else np.zeros(1)
        xs, ys = xs[np.isfinite(xs)], ys[np.isfinite(ys)]
        x0, x1 = (float(xs.min()), float(xs.max())) if xs.size else (0.0, 1.0)
        y0, y1 = (float(ys.min()), float(ys.max())) if ys.size else (0.0, 1.0)
        if x1 - x0 < 1e-12:
            x0, x1 = x0 - 1, x1 + 1
        if y1 - y0 < 1e-12:
            y0, y1 = y0 - 1, y1 + 1
        pad = 0.05 * (y1 - y0)
        y0, y1 = y0 - pad, y1 + pad

        def px(x):
            return int(round(left + (x - x0) / (x1 - x0) * (right - left)))

        def py(y):
            return int(round(bottom - (y - y0) / (y1 - y0) * (bottom - top)))

        grey, black = COLOURS["grey"], COLOURS["black"]
        if y0 < 0 < y1:
            self.line(left, py(0.0), right, py(0.0), grey)
        if x0 < 0 < x1:
            self.line(px(0.0), top, px(0.0), bottom, grey)
        for a, b, c, d in ((left, top, right, top), (right, top, right, bottom),
                           (right, bottom, left, bottom), (left, bottom, left, top)):
            self.line(a, b, c, d, black)
        for s in series:
            c = COLOURS.get(s.colour, COLOURS["blue"])
            x, y = np.asarray(s.x, float).ravel(), np.asarray(s.y, float).ravel()
            ok = np.isfinite(x) & np.isfinite(y)
            x, y = x[ok], y[ok]
            if s.style == "line":
                order = np.argsort(x)
                for i in range(len(order) - 1):
                    a, b = order[i], order[i + 1]
                    self.line(px(x[a]), py(y[a]), px(x[b]), py(y[b]), c)
            else:
                for xi, yi in zip(x, y):
                    self.marker(px(xi), py(yi), c)


def plot_fit(path: str | Path, panels: list[list[Series]], width: int = 640, height_per_panel: int = 240) -> Path:
    """Write a PNG with one panel per entry of ``panels`` (top to bottom)."""
    cv = Canvas(width, height_per_panel * max(1, len(panels)))
    for i, series in enumerate(panels):
        cv.panel(i * height_per_panel, (i + 1) * height_per_panel, series)
    return write_png(path, cv.img)


def read_png_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR (for tests)."""
    data = Path(path).read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG")
    return struct.unpack(">II", data[16:24])
