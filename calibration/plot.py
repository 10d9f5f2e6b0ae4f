"""Calibration plots people can read: matplotlib (Agg, no display needed).

A plot is a stack of :class:`Panel` s (top to bottom), typically the measured points with
the fitted line, then the residuals. Every panel has a title and axis labels with units;
every labelled series appears in the panel's legend; a residual panel draws its zero line.
The figure is a PNG of ``width`` x ``height_per_panel * panels`` pixels.

matplotlib is imported when a plot is drawn (a procedure that saves no plot, and every
other ``pfma`` verb, never pays its import).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

#: the procedures' colour names -> matplotlib colours (the tab10 palette)
COLOURS = {"black": "black", "blue": "tab:blue", "red": "tab:red", "green": "tab:green",
           "orange": "tab:orange", "grey": "tab:gray", "purple": "tab:purple"}
DPI = 100


@dataclass
class Series:
    x: Any
    y: Any
    style: str = "points"  #: "points" or "line"
    colour: str = "blue"
    label: str = ""  #: legend entry ("" = none)


@dataclass
class Panel:
    series: Sequence[Series]
    title: str
    xlabel: str  #: quantity and units, e.g. "reference (V)"
    ylabel: str
    zero_line: bool = False  #: draw y = 0 (residual panels)
    notes: list[str] = field(default_factory=list)  #: lines written in the panel's corner


def residual_panel(series: Sequence[Series], what: str, units: str, xlabel: str) -> Panel:
    """The residuals of a fit, with their scale in the title (largest |residual|)."""
    worst = max((float(np.nanmax(np.abs(np.asarray(s.y, float)))) for s in series
                 if np.asarray(s.y).size), default=0.0)
    return Panel(series, f"{what} residuals (largest {worst:.3g} {units})", xlabel,
                 f"residual ({units})", zero_line=True)


def figure(panels: Sequence[Panel], title: str, width: int = 640, height_per_panel: int = 240):
    """The matplotlib Figure of ``panels`` (for tests and for :func:`plot_fit`)."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display

    fig = Figure(figsize=(width / DPI, height_per_panel * max(1, len(panels)) / DPI), dpi=DPI)
    fig.suptitle(title, fontsize=10)
    axes = fig.subplots(max(1, len(panels)), 1, squeeze=False)[:, 0]
    for ax, panel in zip(axes, panels):
        for s in panel.series:
            x, y = np.asarray(s.x, float).ravel(), np.asarray(s.y, float).ravel()
            colour = COLOURS.get(s.colour, s.colour)
            if s.style == "line":
                order = np.argsort(x)
                ax.plot(x[order], y[order], "-", color=colour, lw=1.2, label=s.label or None)
            else:
                ax.plot(x, y, "o", color=colour, ms=3.5, label=s.label or None)
        if panel.zero_line:
            ax.axhline(0.0, color="0.6", lw=0.8)
        ax.set_title(panel.title, fontsize=9)
        ax.set_xlabel(panel.xlabel, fontsize=8)
        ax.set_ylabel(panel.ylabel, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, lw=0.3, alpha=0.5)
        if any(s.label for s in panel.series):
            ax.legend(fontsize=7, loc="best")
        if panel.notes:
            ax.text(0.01, 0.97, "\n".join(panel.notes), transform=ax.transAxes, va="top", fontsize=7)
    fig.tight_layout()
    return fig


def plot_fit(path: str | Path, panels: Sequence[Panel], title: str, width: int = 640,
             height_per_panel: int = 240) -> Path:
    """Write a PNG of ``panels`` (top to bottom) under ``title``; returns its path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig = figure(panels, title, width, height_per_panel)
    fig.savefig(p, dpi=DPI, format="png")
    return p


def read_png_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR (for tests)."""
    import struct
    data = Path(path).read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG")
    return struct.unpack(">II", data[16:24])
