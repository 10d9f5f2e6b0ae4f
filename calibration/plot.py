"""Calibration plots people can read at a glance: matplotlib (Agg, no display needed).

A plot is a grid of :class:`Panel` s, ``columns`` wide, filled row by row (one column:
a stack, top to bottom), typically the measured points with the fitted line, then the
residuals. Every panel has a title and axis labels with units; a residual panel draws its
zero line. Many channels go to small multiples (:func:`fit_grid`: one small panel per
channel, titled with its name) rather than one panel with a long legend.

Legends never cover data: in a one-column plot each panel's legend sits outside its axes,
on the right; in a grid one legend for the whole figure sits below the panels (the same
series roles in every small panel: one legend says them once). The layout (matplotlib's
constrained layout) makes room for both. The figure is a PNG of ``width`` x
``height_per_panel * rows`` pixels.

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
    xticks: Sequence[str] = ()  #: names of the categories at x = 0, 1, ... (e.g. one per joint)


@dataclass
class Fit:
    """One channel's fit, for :func:`fit_grid`."""
    name: str  #: the channel or joint (its small panels' title)
    x: Any
    measured: Any
    fitted: Any  #: the fit at ``x``
    residuals: Any
    note: str = ""  #: what the fit found, after the name in the title (e.g. "gain 1.0021")


def residual_panel(series: Sequence[Series], what: str, units: str, xlabel: str, sep: str = " ") -> Panel:
    """The residuals of a fit, with their scale in the title (largest |residual|); ``sep``
    "\\n" puts the scale on a second line (a small panel's title is narrow)."""
    worst = max((float(np.nanmax(np.abs(np.asarray(s.y, float)))) for s in series
                 if np.asarray(s.y).size), default=0.0)
    return Panel(series, f"{what} residuals{sep}(largest {worst:.3g} {units})", xlabel,
                 f"residual ({units})", zero_line=True)


def fit_grid(fits: Sequence[Fit], xlabel: str, ylabel: str, units: str, columns: int = 4,
             measured: str = "measured", fitted: str = "fit") -> list[Panel | None]:
    """Small multiples of ``fits``: per ``columns`` of them a row of fit panels (points
    ``measured``, line ``fitted``) above the row of their residual panels (in ``units``), so
    each channel's residuals sit under its fit. ``None`` fills a short last row (no panel).
    Draw with ``columns=columns``: the series roles are said once, in the figure's legend."""
    panels: list[Panel | None] = []
    for k in range(0, len(fits), columns):
        chunk = list(fits[k:k + columns])
        pad: list[Panel | None] = [None] * (columns - len(chunk))
        panels += [Panel([Series(f.x, f.measured, "points", "blue", measured),
                          Series(f.x, f.fitted, "line", "red", fitted)],
                         f"{f.name}\n{f.note}" if f.note else f.name, xlabel, ylabel) for f in chunk] + pad
        panels += [residual_panel([Series(f.x, f.residuals, "points", "blue")], f.name, units, xlabel, "\n")
                   for f in chunk] + pad
    return panels


def _whole_numbers():
    """A tick formatter writing each tick's whole value with the digits its spacing needs
    (1.0002 beside 1.0001; 5e-14 beside 1e-13), and 0 as 0."""
    from matplotlib.ticker import Formatter

    class WholeNumbers(Formatter):
        digits, step = 3, 0.0

        def set_locs(self, locs):
            v = np.sort(np.abs(np.asarray(locs, float)))
            steps = np.diff(np.sort(np.asarray(locs, float)))
            self.step = float(steps.min()) if steps.size else 0.0
            if self.step > 0 and v.size and v[-1] > 0:
                # the largest tick's leading digit down to the spacing's, and one more
                self.digits = max(2, int(np.floor(np.log10(v[-1])) - np.floor(np.log10(self.step))) + 2)

        def __call__(self, x, pos=None):
            if abs(x) <= 1e-9 * self.step:  # a tick at zero, computed a rounding error away
                return "0"
            return f"{x:.{self.digits}g}"

    return WholeNumbers()


def _draw_panel(ax, panel: Panel, small: bool) -> None:
    for s in panel.series:
        x, y = np.asarray(s.x, float).ravel(), np.asarray(s.y, float).ravel()
        colour = COLOURS.get(s.colour, s.colour)
        if s.style == "line":
            order = np.argsort(x)
            ax.plot(x[order], y[order], "-", color=colour, lw=1.2, label=s.label or None)
        else:
            ax.plot(x, y, "o", color=colour, ms=3 if small else 3.5, label=s.label or None)
    if panel.zero_line:
        ax.axhline(0.0, color="0.6", lw=0.8)
    # each tick says its whole number: an offset or a "1e-5" multiplier over the axes is
    # read late or not at all, and it sits where the title is
    ax.xaxis.set_major_formatter(_whole_numbers())
    ax.yaxis.set_major_formatter(_whole_numbers())
    if panel.xticks:
        ax.set_xticks(range(len(panel.xticks)), list(panel.xticks), rotation=30, ha="right")
        ax.set_xlim(-0.5, len(panel.xticks) - 0.5)
    ax.set_title(panel.title, fontsize=8 if small else 9)
    ax.set_xlabel(panel.xlabel, fontsize=7 if small else 8)
    ax.set_ylabel(panel.ylabel, fontsize=7 if small else 8)
    ax.tick_params(labelsize=6 if small else 7)
    ax.grid(True, lw=0.3, alpha=0.5)
    if panel.notes:
        ax.text(0.01, 0.97, "\n".join(panel.notes), transform=ax.transAxes, va="top", fontsize=7)


def _figure_legend(fig, axes) -> None:
    """One legend below the grid (above it, matplotlib puts it over the suptitle): each label once (its first series), as the small panels
    draw the same roles in the same colours."""
    seen: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(label, handle)
    if seen:
        fig.legend(list(seen.values()), list(seen), loc="outside lower center", ncols=len(seen), fontsize=7)


def figure(panels: Sequence[Panel | None], title: str, width: int = 640, height_per_panel: int = 240,
           columns: int = 1):
    """The matplotlib Figure of ``panels`` in a grid ``columns`` wide, filled row by row
    (``None``: an empty cell); for tests and for :func:`plot_fit`."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display

    rows = max(1, -(-len(panels) // columns))
    fig = Figure(figsize=(width / DPI, height_per_panel * rows / DPI), dpi=DPI, layout="constrained")
    fig.suptitle(title, fontsize=10)
    grid = fig.subplots(rows, columns, squeeze=False)
    cells = list(grid.ravel())
    drawn = []
    for k, ax in enumerate(cells):
        panel = panels[k] if k < len(panels) else None
        if panel is None:
            ax.remove()
            continue
        _draw_panel(ax, panel, small=columns > 1)
        drawn.append(ax)
        if columns == 1 and any(s.label for s in panel.series):
            # outside the axes, on the right: a legend never covers the data
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    if columns > 1:
        _figure_legend(fig, drawn)
    return fig


def plot_fit(path: str | Path, panels: Sequence[Panel | None], title: str, width: int = 640,
             height_per_panel: int = 240, columns: int = 1) -> Path:
    """Write a PNG of ``panels`` (a grid ``columns`` wide, row by row) under ``title``; returns its path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig = figure(panels, title, width, height_per_panel, columns)
    fig.savefig(p, dpi=DPI, format="png")
    return p


def read_png_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR (for tests)."""
    import struct
    data = Path(path).read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG")
    return struct.unpack(">II", data[16:24])
