"""Issue 32 item 5: plots a person reads at a glance. Every calibration procedure, run in
the bring-up order on a simulated rack with a real rack's errors (simulated time), draws
figures in which, by matplotlib's own bounding boxes after a draw:

- no legend overlaps an axes other than its own (a figure legend: any axes);
- no legend covers a plotted data point, nor a drawn line between two points;
- no two entries of one legend share a colour, and no legend has more entries than the
  palette's distinct colours (more channels go to small multiples, one panel each);
- no legend covers a title (the figure's or a panel's), no two titles overlap (small
  panels' titles are narrow), no axis's offset text or multiplier ("1e-5") overlaps a title,
  and every title lies inside the figure.

The checkout (tools/checkout) draws no plots: nothing of it to check here.
"""

from __future__ import annotations


import numpy as np
import pytest

import calibration.plot as plot
from sim.errors import seeded
from tests.calibration.conftest import BRINGUP_ORDER, bringup_run

ORDER = BRINGUP_ORDER
SEED = 7  # a rack with every error drawn (README's example); the plots then show real scatter
MAX_ENTRIES = 6  #: ASSUMED: more entries than this cannot be told apart at a glance
STEPS_PER_SEGMENT = 20  #: points sampled along each drawn line segment


@pytest.fixture(scope="module")
def figures(tmp_path_factory):
    """procedure name -> the matplotlib Figures it drew (plot.figure wrapped to keep them)."""
    d = tmp_path_factory.mktemp("legible")
    drawn: dict[str, list] = {}
    current: list[str] = [""]
    real = plot.figure

    def keep(*a, **kw):
        fig = real(*a, **kw)
        drawn.setdefault(current[0], []).append(fig)
        return fig

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plot, "figure", keep)
        with bringup_run(seeded(SEED), d, before=lambda name: current.__setitem__(0, name)):
            pass
    yield drawn


def _drawn(fig):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return canvas.get_renderer()


def _legends(fig):
    """(the legend's own axes or None for a figure legend, the legend)."""
    return [(ax, ax.get_legend()) for ax in fig.axes if ax.get_legend() is not None] + \
        [(None, leg) for leg in fig.legends]


def _display_points(ax) -> np.ndarray:
    """Every plotted point of ``ax`` in display coordinates, lines sampled between points;
    only what lies inside the axes (the rest is clipped, not drawn)."""
    pts = []
    for line in ax.get_lines():
        xy = line.get_transform().transform(np.asarray(line.get_xydata(), float))
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        if line.get_linestyle() not in ("None", "", " ", "none") and len(xy) > 1:
            t = np.linspace(0.0, 1.0, STEPS_PER_SEGMENT)[:, None]
            xy = np.concatenate([a + t * (b - a) for a, b in zip(xy[:-1], xy[1:])])
        pts.append(xy)
    if not pts:
        return np.empty((0, 2))
    xy = np.concatenate(pts)
    box = ax.get_window_extent()
    inside = (xy[:, 0] >= box.x0) & (xy[:, 0] <= box.x1) & (xy[:, 1] >= box.y0) & (xy[:, 1] <= box.y1)
    return xy[inside]


def _handle_colour(h) -> tuple:
    from matplotlib.colors import to_rgba

    if h.get_linestyle() in ("None", "", " ", "none"):
        return to_rgba(h.get_markerfacecolor())
    return to_rgba(h.get_color())


def _titles(fig, renderer):
    """(text, display box) of the figure's title and every non-empty panel title."""
    texts = [fig._suptitle] if fig._suptitle is not None else []
    texts += [t for ax in fig.axes for t in (ax.title, ax._left_title, ax._right_title)]
    return [(t.get_text(), t.get_window_extent(renderer)) for t in texts if t.get_text()]


def _title_faults(fig, renderer) -> list[str]:
    titles = _titles(fig, renderer)
    page = fig.bbox
    faults = [f"titles {a!r} and {b!r} overlap" for k, (a, box_a) in enumerate(titles)
              for b, box_b in titles[k + 1:] if box_a.overlaps(box_b)]
    faults += [f"the title {a!r} runs off the figure" for a, box in titles
               if box.x0 < page.x0 or box.x1 > page.x1 or box.y0 < page.y0 or box.y1 > page.y1]
    offsets = [(ax, t) for ax in fig.axes for t in (ax.xaxis.get_offset_text(), ax.yaxis.get_offset_text())
               if t.get_visible() and t.get_text()]
    faults += [f"the offset text {t.get_text()!r} of {ax.get_title()!r} overlaps the title {a!r}"
               for ax, t in offsets for a, box in titles if t.get_window_extent(renderer).overlaps(box)]
    return faults


def legibility_faults(fig) -> list[str]:
    """What makes ``fig`` hard to read at a glance (empty: nothing)."""
    renderer = _drawn(fig)
    faults = _title_faults(fig, renderer)
    for own, leg in _legends(fig):
        box = leg.get_window_extent(renderer)
        where = f"legend of {own.get_title()!r}" if own is not None else "figure legend"
        for ax in fig.axes:
            if ax is not own and box.overlaps(ax.get_window_extent(renderer)):
                faults.append(f"{where} overlaps the axes {ax.get_title()!r}")
            xy = _display_points(ax)
            covered = int(np.sum((xy[:, 0] > box.x0) & (xy[:, 0] < box.x1)
                                 & (xy[:, 1] > box.y0) & (xy[:, 1] < box.y1)))
            if covered:
                faults.append(f"{where} covers {covered} plotted points of {ax.get_title()!r}")
        faults += [f"{where} covers the title {text!r}" for text, tb in _titles(fig, renderer) if box.overlaps(tb)]
        labels = [t.get_text() for t in leg.get_texts()]
        colours = [_handle_colour(h) for h in leg.legend_handles]
        if len(set(colours)) < len(colours):
            faults.append(f"{where} repeats a colour among its {len(labels)} entries {labels}")
        if len(labels) > MAX_ENTRIES:
            faults.append(f"{where} has {len(labels)} entries (more than {MAX_ENTRIES})")
    return faults


@pytest.mark.parametrize("name", ORDER)
def test_every_procedure_plot_reads_at_a_glance(figures, name):
    assert figures.get(name), f"{name} drew no figure"
    for fig in figures[name]:
        faults = legibility_faults(fig)
        assert not faults, f"{fig.get_suptitle()}:\n" + "\n".join(faults)


def test_the_checker_sees_a_crowded_legend():
    """The check itself: today's crowded plot (one panel, a legend inside, colours cycling)
    is caught; the same data as small multiples is not."""
    x = np.linspace(-9, 9, 5)
    colours = ("blue", "red", "green", "orange", "purple", "black")
    crowded = [plot.Series(x, x * (1 + 0.01 * i), "points", colours[i % 6], f"ch{i}") for i in range(8)]
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 2.4))
    ax = fig.subplots()
    for s in crowded:
        ax.plot(s.x, s.y, "o", color=plot.COLOURS[s.colour], label=s.label)
    ax.legend(loc="center")
    faults = legibility_faults(fig)
    assert any("repeats a colour" in f for f in faults) and any("covers" in f for f in faults)
    assert any("entries (more than" in f for f in faults)


def test_fit_grid_puts_each_channel_residuals_under_its_fit_and_says_the_roles_once():
    x = np.linspace(-9, 9, 5)
    fits = [plot.Fit(f"ch{i}", x, x, x, 1e-13 * x, f"gain {1 + i / 1e4:.4f}") for i in range(5)]
    fig = plot.figure(plot.fit_grid(fits, "reference (V)", "reading (V)", "V", 3), "ADC", 720, 180, 3)
    assert len(fig.axes) == 10  # 5 fits + 5 residuals; the short last row's empty cells are gone
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[:3] == ["ch0\ngain 1.0000", "ch1\ngain 1.0001", "ch2\ngain 1.0002"]
    assert titles[3].startswith("ch0 residuals\n(largest")
    by_title = {ax.get_title().split("\n")[0]: ax for ax in fig.axes}
    _drawn(fig)
    fit_box, res_box = by_title["ch1"].get_window_extent(), by_title["ch1 residuals"].get_window_extent()
    assert res_box.y1 < fit_box.y0 and abs(res_box.x0 - fit_box.x0) < 1  # right under its fit
    assert all(ax.get_legend() is None for ax in fig.axes)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["measured", "fit"]
    assert legibility_faults(fig) == []
    # each tick its whole value, no "1e-13" multiplier over the axes
    res = by_title["ch0 residuals"]
    assert res.yaxis.get_offset_text().get_text() == ""
    assert any("e-13" in t.get_text() for t in res.get_yticklabels())
