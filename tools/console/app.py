"""The operator console: a Textual app with the IRSS primary display's five areas and the
debug window's displays (world-model browser and keyed writes, parameters, live menus,
force displays).

Few widgets (docs/console.md, the new-dependencies notes: one widget rendering all its
values costs a tenth of many small ones): each area is one :class:`textual.widgets.Static`
whose text :mod:`tools.console.view` renders; a timer refreshes them at
:data:`REFRESH_HZ`. Keys send the Global Commands through the world model's request
protocol (:class:`tools.console.control.ControllerLink`), and the debug window's edits
are keyed user writes through the same ring ``pfma wm set`` uses; nothing else is written.
"""

from __future__ import annotations

import asyncio
import math
import signal
import sys
import time
from typing import Callable

from rich.cells import cell_len
from rich.segment import Segment
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Grid, Horizontal, Vertical, VerticalScroll
from textual.geometry import Region
from textual.screen import ModalScreen
from textual.strip import Strip
from textual.widget import Widget
from textual.widgets import Footer, Input, Static

from controller.routes import MONITORS, route_request_arg
from tools.console.recording import ConsoleRecording
from tools.console import debug, view
from tools.console.control import Answer, ControlError, ControllerLink, Request, Response, parse_move

#: refresh rate of the areas (the issue's 10 Hz)
REFRESH_HZ = 10.0
#: frames one capital-S single step runs
BIG_STEP = 10
#: requests the console follows to their final answers at once (the newest; System Up/Down
#: queues at most controller.layers.QUEUE_SLOTS, and a few more are answered at once)
PENDING_FOLLOWED = 16


class LinesView(Widget):
    """Lines of plain text drawn through Textual's line API: :meth:`show` repaints only the
    lines whose text changed, without the parsing, wrapping and layout a ``Static`` does on
    every update (the force display's vector view: about 2 ms per drawing instead of 5-6;
    docs/console.md "Force displays"). Longer lines are cut at the widget's width."""

    DEFAULT_CSS = "LinesView { height: auto; }"

    def __init__(self, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.lines: list[str] = []
        self._strips: dict[tuple[int, int], Strip] = {}  # (line, width) -> strip of the text shown

    def show(self, text: str) -> None:
        new = text.split("\n")
        old, self.lines = self.lines, new
        if len(new) != len(old):
            self._strips.clear()
            self.refresh(layout=True)
            return
        width = self.size.width
        for y, (a, b) in enumerate(zip(old, new)):
            if a != b:
                self._strips.pop((y, width), None)
                self.refresh(Region(0, y, width, 1))

    def get_content_height(self, container, viewport, width: int) -> int:
        return len(self.lines)

    def render_line(self, y: int) -> Strip:
        width = self.size.width
        style = self.rich_style
        if y >= len(self.lines):
            return Strip.blank(width, style)
        strip = self._strips.get((y, width))
        if strip is None:
            text = self.lines[y]
            strip = Strip([Segment(text, style)], cell_len(text)).crop_extend(0, width, style)
            if len(self._strips) > 4 * max(1, len(self.lines)):
                self._strips.clear()  # widths that are no longer shown
            self._strips[(y, width)] = strip
        return strip

    def text(self) -> str:
        return "\n".join(self.lines)


class DebugDisplay(ModalScreen):
    """A debug-window display: it covers the five areas, which are not redrawn while it is
    open (their cost would double the refresh's), and are redrawn when it closes."""

    def on_unmount(self) -> None:
        app = self.app
        if isinstance(app, ConsoleApp) and app.is_running:
            app.call_later(app.refresh_areas)


class Area(VerticalScroll, inherit_bindings=False):
    """One area of the primary display: its text in a scrollable box. Tab focuses the next
    area; pgup/pgdn/home/end scroll the focused one (the arrows stay the layer keys)."""

    BINDINGS = [Binding("pageup", "page_up", "scroll", show=False), Binding("pagedown", "page_down", "scroll"),
                Binding("home", "scroll_home", "top", show=False), Binding("end", "scroll_end", "end", show=False)]


class MessagesScreen(ModalScreen):
    """Every message the console keeps (:data:`view.MESSAGES_KEPT`), newest first, live:
    ``s`` cycles the source shown, ``l`` the lowest level shown; pgdn/pgup/home/end
    scroll (pgdn: older); ``m`` or Escape closes."""

    BINDINGS = [Binding("escape,m,q", "app.pop_screen", "close"),
                Binding("s", "source", "source"), Binding("l", "level", "level"),
                Binding("pagedown", "scroll('page_down')", "older"), Binding("pageup", "scroll('page_up')", "newer"),
                Binding("down", "scroll('scroll_down')", "older", show=False),
                Binding("up", "scroll('scroll_up')", "newer", show=False),
                Binding("home", "scroll('scroll_home')", "newest", show=False),
                Binding("end", "scroll('scroll_end')", "oldest", show=False)]
    CSS = """
    MessagesScreen { background: $surface; }
    MessagesScreen #messages-head { height: 1; padding: 0 1; text-style: bold; }
    MessagesScreen VerticalScroll { height: 1fr; }
    MessagesScreen #all-messages { padding: 0 1; text-wrap: nowrap; text-overflow: ellipsis; }
    """

    def __init__(self, msgs) -> None:
        super().__init__()
        self.msgs = msgs
        self.source: str | None = None  #: the source shown (None: all)
        self.level: str | None = None  #: the lowest level shown (None: all)
        self._text = ""

    def compose(self) -> ComposeResult:
        yield Static("", id="messages-head", markup=False)
        with VerticalScroll(id="messages-scroll", can_focus=False):  # the keys are the screen's (footer)
            yield Static("", id="all-messages", markup=False)
        yield Footer()

    def on_mount(self) -> None:
        self.redraw()

    def redraw(self) -> None:
        """Redraw when the text changed (the app's refresh calls it while open)."""
        head, _, body = view.messages_screen(self.msgs, self.source, self.level).partition("\n")
        if head + body == self._text:
            return
        self._text = head + body
        self.query_one("#messages-head", Static).update(head)
        self.query_one("#all-messages", Static).update(body)

    def text(self) -> str:
        return str(self.query_one("#messages-head", Static).render()) + "\n" + str(
            self.query_one("#all-messages", Static).render())

    def action_source(self) -> None:
        sources = [None, *view.message_sources(self.msgs)]
        self.source = sources[(sources.index(self.source) + 1) % len(sources) if self.source in sources else 0]
        self.redraw()
        self.query_one(VerticalScroll).scroll_home(animate=False)

    def action_level(self) -> None:
        levels: list[str | None] = [None, *view.LEVELS[1:]]
        self.level = levels[(levels.index(self.level) + 1) % len(levels)]
        self.redraw()
        self.query_one(VerticalScroll).scroll_home(animate=False)

    def action_scroll(self, how: str) -> None:
        getattr(self.query_one(VerticalScroll), f"action_{how}")()


class BrowserScreen(DebugDisplay):
    """The world model by area, live (issue 18 item 2's browser). Left/right: area,
    pgup/pgdn: page, up/down: variable, Enter/``e``: modify it where the ownership rules
    let a user (the code path of ``pfma wm set``, with the console's access key)."""

    BINDINGS = [Binding("escape,w,q", "app.pop_screen", "close"),
                Binding("left", "area(-1)", "area"), Binding("right", "area(1)", "area"),
                Binding("up", "row(-1)", "variable"), Binding("down", "row(1)", "variable"),
                Binding("pageup", "page(-1)", "page"), Binding("pagedown", "page(1)", "page"),
                Binding("enter,e", "edit", "modify")]

    def __init__(self, wm) -> None:
        super().__init__()
        self.wm = wm
        self.area = 0
        self.page = 0
        self.row = 0

    def compose(self) -> ComposeResult:
        yield Static("", id="browser", markup=False)

    def on_mount(self) -> None:
        self.redraw()

    def on_screen_resume(self) -> None:  # back from the editor: its outcome or refusal
        self.redraw()

    def _rows(self) -> int:
        from controller.worldmodel.spec import AREAS as WM_AREAS
        names = view.browser_names(self.wm, WM_AREAS[self.area % len(WM_AREAS)])
        pages = max(1, -(-len(names) // view.BROWSER_ROWS))
        return max(1, len(names[(self.page % pages) * view.BROWSER_ROWS:][:view.BROWSER_ROWS]))

    def redraw(self) -> None:
        self.row %= self._rows()
        status = self.app.write_status if isinstance(self.app, ConsoleApp) else ""
        self.query_one("#browser", Static).update(view.wm_browser(self.wm, self.area, self.page, self.row, status))

    def text(self) -> str:
        return str(self.query_one("#browser", Static).render())

    def selected(self) -> str | None:
        return view.browser_selected(self.wm, self.area, self.page, self.row)

    def action_area(self, d: int) -> None:
        self.area, self.page, self.row = self.area + d, 0, 0
        self.redraw()

    def action_page(self, d: int) -> None:
        self.page, self.row = self.page + d, 0
        self.redraw()

    def action_row(self, d: int) -> None:
        self.row = (self.row + d) % self._rows()
        self.redraw()

    def action_edit(self) -> None:
        name = self.selected()
        app = self.app
        if name is not None and isinstance(app, ConsoleApp):
            app.begin_edit(name)
        self.redraw()


class ParamScreen(DebugDisplay):
    """The parameter-modification display: the servo compensators and limits (every
    world-model variable users may set only while powered down) by joint, live. Enter/``e``
    edits the selected value through the same write path as the browser; while powered up
    the ownership rule refuses it and the reason is shown."""

    BINDINGS = [Binding("escape,p,q", "app.pop_screen", "close"),
                Binding("up", "row(-1)", "parameter"), Binding("down", "row(1)", "parameter"),
                Binding("left", "col(-1)", "joint"), Binding("right", "col(1)", "joint"),
                Binding("enter,e", "edit", "edit")]

    def __init__(self, wm, select: str | None = None) -> None:
        super().__init__()
        self.wm = wm
        self.names = debug.param_names(wm)
        self.row = self.names.index(select) if select in self.names else 0
        self.col = 0

    def compose(self) -> ComposeResult:
        yield Static("", id="params", markup=False)

    def on_mount(self) -> None:
        self.redraw()

    def on_screen_resume(self) -> None:
        self.redraw()

    def redraw(self) -> None:
        status = self.app.write_status if isinstance(self.app, ConsoleApp) else ""
        self.query_one("#params", Static).update(debug.params_display(self.wm, self.row, self.col, status))

    def text(self) -> str:
        return str(self.query_one("#params", Static).render())

    def selected(self) -> tuple[str, int | None] | None:
        if not self.names:
            return None
        n = self.names[self.row]
        return n, (self.col if self.wm.spec(n).shape else None)

    def action_row(self, d: int) -> None:
        if self.names:
            self.row = (self.row + d) % len(self.names)
            self.col = min(self.col, debug.param_columns(self.wm, self.names[self.row]) - 1)
        self.redraw()

    def action_col(self, d: int) -> None:
        if self.names:
            self.col = (self.col + d) % debug.param_columns(self.wm, self.names[self.row])
        self.redraw()

    def action_edit(self) -> None:
        sel = self.selected()
        app = self.app
        if sel is not None and isinstance(app, ConsoleApp):
            app.begin_edit(*sel)
        self.redraw()


class MenuScreen(DebugDisplay):
    """The user's live menus (``pfma console --menu FILE.toml``): one page at a time, each
    refreshed at its own rate (every :meth:`MenuPage.every`-th console refresh). Up/down
    select a variable, Enter/``e`` modifies it where the ownership rules let a user: the
    browser's write path (:meth:`ConsoleApp.begin_edit`: the rule's check, the editor, the
    keyed write), its refusals and outcomes shown on the page as in the browser."""

    BINDINGS = [Binding("escape,l,q", "app.pop_screen", "close"),
                Binding("left", "page(-1)", "page"), Binding("right,tab", "page(1)", "page"),
                Binding("up", "row(-1)", "variable"), Binding("down", "row(1)", "variable"),
                Binding("enter,e", "edit", "modify")]

    def __init__(self, menu, wm) -> None:
        super().__init__()
        self.menu = menu
        self.wm = wm
        self.index = 0
        self.row = 0  #: the variable under the cursor on the page shown
        self.ticks = 0
        self.draws = 0  #: page redraws (tests: the refresh rate)
        self._names: tuple[str, ...] = ()
        self._status = ""  # the write status the page shows
        self._lines = -1  # the number of lines drawn last

    def compose(self) -> ComposeResult:
        yield Static("", id="menu", markup=False)

    def on_mount(self) -> None:
        self.redraw()

    def on_screen_resume(self) -> None:  # back from the editor: its outcome or refusal
        self.redraw()

    def _app_status(self) -> str:
        return self.app.write_status if isinstance(self.app, ConsoleApp) else ""

    def tick(self) -> None:
        """One console refresh: redraw the page when its rate says so, or at once when a
        write's outcome or refusal arrived."""
        self.ticks += 1
        if self.ticks % self.menu.pages[self.index].every(REFRESH_HZ) == 0 or self._app_status() != self._status:
            self.redraw()

    def redraw(self) -> None:
        from tools.console.menu import page_text
        page = self.menu.pages[self.index]
        if len(self._names) != len(page.vars) or self._names[0] != page.vars[0].name:
            self._names = tuple(v.name for v in page.vars)  # one tuple per page: the model caches its plan
        self.draws += 1
        self._status = self._app_status()
        text = page_text(self.menu, self.index, self.wm.get_task_inputs(self._names), self.wm, self.row, self._status)
        lines = text.count("\n")  # a layout pass only when the number of lines changed (a page, a status)
        self.query_one("#menu", Static).update(text, layout=lines != self._lines)
        self._lines = lines

    def text(self) -> str:
        return str(self.query_one("#menu", Static).render())

    def selected(self) -> str:
        """The variable under the cursor."""
        page = self.menu.pages[self.index]
        return page.vars[self.row % len(page.vars)].name

    def action_page(self, d: int) -> None:
        self.index = (self.index + d) % len(self.menu.pages)
        self._names, self.ticks, self.row = (), 0, 0
        self.redraw()

    def action_row(self, d: int) -> None:
        self.row = (self.row + d) % len(self.menu.pages[self.index].vars)
        self.redraw()

    def action_edit(self) -> None:
        app = self.app
        if isinstance(app, ConsoleApp):
            app.begin_edit(self.selected())
        self.redraw()


class ForceScreen(DebugDisplay):
    """The force displays: a time plot of the F/T force and torque (textual-plotext) and a
    pseudo-3D view of the force vector, from the service's inputs area (Bit3), live."""

    BINDINGS = [Binding("escape,f,q", "app.pop_screen", "close")]
    CSS = """
    ForceScreen Horizontal { height: 1fr; }
    ForceScreen #ft-plots { width: 1fr; }
    ForceScreen #ft-vector { width: 68; height: 100%; border: round $accent; padding: 0 1; }
    ForceScreen #ft-help { height: 2; }
    """

    def __init__(self, history: "debug.FtHistory") -> None:
        super().__init__()
        self.history = history
        self.series: dict[str, list[float]] = {}  #: what the plots were last given (tests)
        self._seen = -1  # the record the plots show
        self._drawn = -1  # the newest record redraw() has seen
        self._ticks = 0  # refreshes that brought a new record

    def compose(self) -> ComposeResult:
        from textual_plotext import PlotextPlot
        with Horizontal():
            with Vertical(id="ft-plots"):
                yield PlotextPlot(id="ft-force")
                yield PlotextPlot(id="ft-torque")
            yield LinesView(id="ft-vector")
        yield Static("", id="ft-help", markup=False)

    def on_mount(self) -> None:
        self.redraw()

    def redraw(self) -> None:
        """At a console refresh: nothing without a new F/T record; with one, the vector view
        every ``FT_VECTOR_EVERY``-th time (the lines whose text changed), the force plot
        every ``FT_PLOT_EVERY``-th and the torque plot half a period later (one plotext
        drawing at a time); everything at once when the display opens."""
        from textual_plotext import PlotextPlot
        h = self.history
        if h.count == self._drawn:
            return  # no new F/T record since the last drawing
        self._drawn = h.count
        first = self._seen < 0
        self._ticks += 1
        if first or self._ticks % debug.FT_VECTOR_EVERY == 0:
            f, m = (h.f[-1], h.m[-1]) if h.f else ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            self.query_one("#ft-vector", LinesView).show(debug.vector_view(f, m, h.full_scale_n()))
        phase = self._ticks % debug.FT_PLOT_EVERY
        plots = (("#ft-force", h.f, ("Fx", "Fy", "Fz"), "N"), ("#ft-torque", h.m, ("Tx", "Ty", "Tz"), "N*m"))
        if not first:
            if phase not in (0, debug.FT_PLOT_EVERY // 2):
                return  # plotext is the expensive part
            plots = plots[:1] if phase == 0 else plots[1:]
        self._seen = h.count
        t_now = h.t[-1] if h.t else 0.0
        t = [x - t_now for x in h.t]
        self.series = {**self.series, "t": t}  # a new dict per drawing (tests: was anything drawn)
        for wid, vals, names, unit in plots:
            plot = self.query_one(wid, PlotextPlot)
            plt = plot.plt
            plt.clear_data()
            plt.clear_figure()
            plt.title(f"{'force' if unit == 'N' else 'torque'} ({unit}), the last {debug.FT_HISTORY_S:g} s")
            plt.xlabel("s (0: now)")
            for k, name in enumerate(names):
                ys = [v[k] for v in vals]
                self.series[name] = ys
                if ys:
                    plt.plot(t, ys, label=name, marker="braille")
            plt.xlim(-debug.FT_HISTORY_S, 0.0)
            plot.refresh()
        self.query_one("#ft-help", Static).update(
            f"F/T from the service's inputs (ft_force_n, ft_torque_nm), sampled at the console's refresh: "
            f"{len(h.t)} samples; each plot redrawn at {REFRESH_HZ / debug.FT_PLOT_EVERY:g} Hz, the vector at "
            f"{REFRESH_HZ / debug.FT_VECTOR_EVERY:g} Hz   Escape/f close", layout=False)

    def text(self) -> str:
        return self.query_one("#ft-vector", LinesView).text()


class EditScreen(ModalScreen):
    """Type a value for one variable (or one element of a vector), Enter to check it,
    Enter again to confirm and send it; Escape cancels. The value is read as ``pfma wm
    set`` reads VALUE (JSON, numbers separated by commas/spaces, or a name of an enumerated
    variable's values); a value outside the enumeration is refused here, nothing sent."""

    BINDINGS = [Binding("escape", "cancel", "cancel")]
    CSS = "EditScreen { align: center middle; } #edit { width: 100; height: auto; border: round $accent; }"

    def __init__(self, name: str, spec, current, index: int | None = None) -> None:
        super().__init__()
        self.var = name
        self.spec = spec
        self.current = current
        self.index = index
        self.confirm: str | None = None  # the text checked and shown for confirmation

    def compose(self) -> ComposeResult:
        from tools.wmtext import format_value, value_text
        now = self.current if self.index is None else self.current[self.index]
        with Vertical(id="edit"):
            yield Static(self._info(value_text(self.spec, self.current)), id="edit-info", markup=False)
            yield Input(value=format_value(now), id="edit-value")
            yield Static("Enter: check the value   Escape: cancel", id="edit-status", markup=False)

    def _info(self, now: str) -> str:
        s = self.spec
        what = f"{self.var}[{self.index}]" if self.index is not None else self.var
        when = "any time" if s.user == "always" else "only while powered down"
        return (f"modify {what}  ({s.type_text}{' ' + s.units if s.units else ''}; written by {s.writer}; "
                f"users may set it {when})\nnow: {now}\n{s.doc}"
                + (f"\nvalues: {s.values_text()}" if s.enum or s.choices else ""))

    def full_text(self, text: str) -> str:
        """The value to send: the typed text, or the vector with the element replaced."""
        if self.index is None:
            return text
        import json

        from tools.wmtext import parse_value
        v = parse_value(text, self.spec)
        vec = [x.item() if hasattr(x, "item") else x for x in list(self.current)]
        vec[self.index] = v
        return json.dumps(vec)

    def on_input_submitted(self, event: Input.Submitted) -> None:
        from controller.worldmodel import WorldModelError, coerce_user
        from tools.wmtext import parse_value, value_text
        text = event.value.strip()
        status = self.query_one("#edit-status", Static)
        app = self.app
        assert isinstance(app, ConsoleApp)
        if self.confirm is not None and text == self.confirm:
            app.user_write(self.var, self.full_text(text))
            self.app.pop_screen()
            return
        try:
            value = coerce_user(self.spec, parse_value(self.full_text(text), self.spec))
        except WorldModelError as err:  # the value check of pfma wm set: shown here, nothing sent
            self.confirm = None
            status.update(f"not sent: {err}")
            return
        self.confirm = text
        status.update(f"set {self.var} = {value_text(self.spec, value)}?  Enter: confirm and send   Escape: cancel")

    def action_cancel(self) -> None:
        self.app.pop_screen()


class PowerUpScreen(ModalScreen):
    """POWER UP asks first (issue 30 item 2): the shoulder roll is indexed by hand and has no
    sensor, so the operator confirms the index the kinematics will take
    (``joint.shoulder_roll_deg``, docs/console.md "Power-up and the shoulder-roll index").
    ``y``/Enter sends POWER UP, ``p`` opens the parameters to change the index, ``n``/Escape
    cancels; nothing is sent but on ``y``."""

    BINDINGS = [Binding("y,enter", "confirm", "yes: power up"), Binding("p", "change", "no: change it"),
                Binding("n,escape", "cancel", "cancel")]
    CSS = "PowerUpScreen { align: center middle; } #power-up { width: 84; height: auto; border: heavy $warning; }"

    def __init__(self, deg: float) -> None:
        super().__init__()
        self.deg = deg

    def compose(self) -> ComposeResult:
        yield Static(view.power_up_question(self.deg), id="power-up", markup=False)

    def text(self) -> str:
        return str(self.query_one("#power-up", Static).render())

    def action_confirm(self) -> None:
        app = self.app
        self.app.pop_screen()
        if isinstance(app, ConsoleApp):
            app.power_up_confirmed(self.deg)

    def action_change(self) -> None:
        app = self.app
        self.app.pop_screen()
        if isinstance(app, ConsoleApp):
            app._note("INFO", "POWER UP not sent: change the shoulder-roll index (joint.shoulder_roll_deg) here, "
                              "then u again")
            app.push_screen(ParamScreen(app.sources.wm, select="joint.shoulder_roll_deg"))

    def action_cancel(self) -> None:
        app = self.app
        self.app.pop_screen()
        if isinstance(app, ConsoleApp):
            app._note("INFO", "POWER UP cancelled (the shoulder-roll index was not confirmed)")
            app.refresh_areas()


class CameraScreen(ModalScreen):
    """Camera routes (docs/cameras.md): ``1`` ``2`` ``3`` put that camera on the selected
    monitor, ``0`` blanks it, up/down/tab select the monitor; each key sends one CAMERA
    ROUTE request (Data Acquisition applies it). Live at the console's refresh."""

    BINDINGS = [Binding("escape,v,q", "app.pop_screen", "close"),
                Binding("up", "monitor(-1)", "monitor"), Binding("down,tab", "monitor(1)", "monitor"),
                Binding("1", "camera(1)", "camera 1"), Binding("2", "camera(2)", "camera 2"),
                Binding("3", "camera(3)", "camera 3"), Binding("0", "camera(0)", "blank")]

    def __init__(self) -> None:
        super().__init__()
        self.monitor = MONITORS[0]

    def compose(self) -> ComposeResult:
        yield Static("", id="cameras", markup=False)

    def on_mount(self) -> None:
        self.redraw()

    def redraw(self) -> None:
        app = self.app
        assert isinstance(app, ConsoleApp)
        self.query_one("#cameras", Static).update(view.camera_screen(app.reading, self.monitor, app.last_answer))

    def text(self) -> str:
        return str(self.query_one("#cameras", Static).render())

    def action_monitor(self, d: int) -> None:
        self.monitor = MONITORS[(MONITORS.index(self.monitor) + d) % len(MONITORS)]
        self.redraw()

    def action_camera(self, camera: int) -> None:
        app = self.app
        assert isinstance(app, ConsoleApp)
        app._send(Request.ROUTE, route_request_arg(self.monitor, camera))
        self.redraw()


class MoveScreen(ModalScreen):
    """Move to (docs/console.md "Move to"): type a pose, joint angles or ``stop``; Enter
    checks the text and shows the move, Enter again sends it as a move-to request
    (:meth:`ControllerLink.move_pose` / ``move_joints`` / ``stop_move``; a pose move sets
    cart.mode 2 TRAJECTORY first if it is not). The controller checks the motion before it
    starts; its answer (a refusal naming the point and the reason, OK, FAILED with the worst
    tracking error) shows here and in Messages. Live at the console's refresh."""

    BINDINGS = [Binding("escape", "app.pop_screen", "close")]
    CSS = "MoveScreen { align: center middle; } #move { width: 110; height: auto; border: round $accent; }"

    def __init__(self) -> None:
        super().__init__()
        self.confirm: str | None = None  # the text checked and shown for confirmation
        self.status = ""

    def compose(self) -> ComposeResult:
        with Vertical(id="move"):
            yield Static("", id="move-info", markup=False)
            yield Input(value="", placeholder="pose 1.55,0,-0.33", id="move-text")

    def on_mount(self) -> None:
        self.redraw()

    def redraw(self) -> None:
        app = self.app
        assert isinstance(app, ConsoleApp)
        self.query_one("#move-info", Static).update(view.move_screen(app.sources.wm, self.status))

    def text(self) -> str:
        return str(self.query_one("#move-info", Static).render())

    def on_input_submitted(self, event: Input.Submitted) -> None:
        app = self.app
        assert isinstance(app, ConsoleApp)
        text = event.value.strip()
        try:
            kind, nums, turn = parse_move(text)
        except ControlError as err:
            self.confirm = None
            self.status = f"not sent: {err}"
            self.redraw()
            return
        if self.confirm != text:
            self.confirm = text
            what = {"stop": "stop the running move or playback",
                    "pose": f"move the tool to {text[4:].strip()}",
                    "joints": f"move the joints to {text[6:].strip()} deg"}[kind]
            self.status = f"{what}?  Enter: confirm and send   Escape: close"
            self.redraw()
            return
        self.confirm = None
        self.status = app.send_move(kind, nums, turn)
        self.redraw()


#: the debug-window displays that cover the five areas (not redrawn while one is open)
COVERING = (BrowserScreen, ParamScreen, MenuScreen, ForceScreen)


#: signals that end the console as ``q`` does (Textual restores the terminal, the caller's
#: clean-up runs: a simulated system stops with its outputs at 0 V): a process manager's
#: SIGTERM, and SIGHUP when the terminal goes away. Before, either killed it at once, the
#: terminal left in the alternate screen and a --sim system's buffer left in /dev/shm.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


def _exit_on_signals(app: "App") -> list[int]:
    """Install ``app.exit`` on :data:`STOP_SIGNALS` in the running event loop; the signals
    installed (none where the loop cannot take them: not the main thread)."""
    try:
        loop = asyncio.get_running_loop()
    except RuntimeError:
        return []
    done = []
    for sig in STOP_SIGNALS:
        try:
            loop.add_signal_handler(sig, app.exit)
        except (NotImplementedError, RuntimeError, ValueError):
            continue
        done.append(sig)
    return done


def _restore_signals(sigs: list[int]) -> None:
    try:
        loop = asyncio.get_running_loop()
    except RuntimeError:
        return
    for sig in sigs:
        loop.remove_signal_handler(sig)


class ConsoleApp(App):
    """The primary display over the live system.

    :param sources: where to read (:class:`tools.console.view.Sources`)
    :param link: requests to the controller (None: read-only, the commands say so)
    :param auto_refresh: refresh on a timer (False in tests: :meth:`refresh_areas` by hand)
    :param on_tick: called before each timed refresh (``make run`` paces nothing here; a
        hook for a caller that wants it)
    """

    # Sizes (docs/console.md): from 120 columns two columns (Local Status and World Status
    # left, the commands right, Messages under both); below, one column, each area with a
    # title line and no side borders. Every area scrolls (tab, pgup/pgdn); no line wraps
    # (a line longer than its area ends in an ellipsis).
    HORIZONTAL_BREAKPOINTS = [(0, "-narrow"), (120, "-wide")]
    CSS = """
    Grid { grid-size: 2 3; grid-columns: 2fr 1fr; grid-rows: 15fr 17fr 7fr; }
    Area { border: round $accent; padding: 0 1; height: 100%; scrollbar-size-vertical: 1; }
    Area:focus { border: round $secondary; }
    Area > Static { text-wrap: nowrap; text-overflow: ellipsis; }
    #messages-area { column-span: 2; }
    Screen.-narrow Grid { grid-size: 1 5; grid-columns: 1fr; grid-rows: 6fr 3fr 7fr 2fr 5fr; }
    Screen.-narrow Area { border: none; border-top: round $accent; padding: 0 1; }
    Screen.-narrow Area:focus { border-top: round $secondary; }
    Screen.-narrow #messages-area { column-span: 1; }
    #banner { dock: top; height: auto; padding: 0 1; background: red; color: white; text-style: bold;
              border: heavy yellow; display: none; }
    """
    TITLE = "PFMA operator console"
    BINDINGS = [
        Binding("left", "layer(-1)", "layer", show=False), Binding("right", "layer(1)", "layer", show=False),
        Binding("up", "tree(-1)", "tree", show=False), Binding("down", "tree(1)", "tree", show=False),
        Binding("u", "power_up", "power up"),
        Binding("d", "request('POWER_DOWN')", "power down"),
        Binding("e", "request('ERROR_RESET')", "error reset"),
        Binding("h", "request('HALT')", "halt"),
        Binding("s", "step(1)", "step"), Binding("S", "step(10)", "10 steps", show=False),
        Binding("a", "rearm", "re-arm"),
        Binding("r", "resume", "resume"),
        Binding("c", "record", "record"), Binding("v", "cameras", "cameras"),
        Binding("o", "gripper('OPEN')", "open", show=False), Binding("g", "gripper('CLOSE')", "grip", show=False),
        Binding("x", "gripper('STOP')", "gripper stop", show=False),
        Binding("plus", "grip_force(1)", "force+", show=False), Binding("minus", "grip_force(-1)", "force-", show=False),
        Binding("t", "move", "move to"),
        Binding("m", "messages", "messages"),
        Binding("w", "browser", "world model"),
        Binding("p", "params", "parameters"),
        Binding("l", "menu", "menus"),
        Binding("f", "force", "force"),
        Binding("q", "quit", "quit"),
        Binding("ctrl+c", "quit", "quit", show=False, priority=True),
    ]

    def __init__(self, sources: view.Sources, link: ControllerLink | None, *, auto_refresh: bool = True,
                 on_tick: Callable[[], None] | None = None, clock: Callable[[], float] = time.monotonic,
                 menu=None) -> None:
        super().__init__()
        self._stop_signals: list[int] = []  # STOP_SIGNALS installed in on_mount
        self.menu = menu  #: the live menus (tools.console.menu.Menu, checked against the model) or None
        self.sources = sources
        self.link = link
        self.auto = auto_refresh
        self.on_tick = on_tick
        self.clock = clock
        self.status_layer = 0  #: the layer Local Status details (left/right), index into view.LAYERS
        self.command_layer = 0  #: the layer Local Commands shows (up/down through the tree): its own selection
        self.rearm = False
        self.last_answer = ""
        self.pending: list[int] = []  # requests waiting for their final answers, oldest first (queued requests)
        self.gripper_pending: int | None = None  # gripper request waiting for its final answer
        self.reading: view.Reading | None = None
        self.read_error = ""
        self.refreshes = 0
        self._shown: dict[str, str] = {}  # the text each area shows
        self.ft = debug.FtHistory()  # the F/T values seen: the force displays' history
        self.writes: dict[int, str] = {}  # user writes waiting for the owner's verdict: id -> variable
        self.write_status = ""  # the last write's outcome or refusal (the browser and parameters show it)
        self.recording: ConsoleRecording | None = None  # ``c``: a pfma record process, made at the first press
        self.pending_move: int | None = None  # the move-to request whose answer is awaited

    def compose(self) -> ComposeResult:
        # issue 28 item 5: shown only while the service reports its outputs NOT known safe
        yield Static("", id="banner", markup=False)
        titles = dict(zip(("local", "world", "messages", "commands", "global"), view.AREAS))
        with Grid():
            for key in ("local", "global", "world", "commands", "messages"):  # the grid's order (CSS)
                with Area(id=f"{key}-area", classes="area") as area:
                    area.border_title = titles[key] + (f" ({self.sources.names})" if key == "world" and
                                                       self.sources.names else "")
                    yield Static("", id=key, markup=False)
        yield Footer()

    def on_mount(self) -> None:
        self.refresh_areas()
        if self.auto:
            self.set_interval(1.0 / REFRESH_HZ, self._timed)
        self._stop_signals = _exit_on_signals(self)

    def on_unmount(self) -> None:
        _restore_signals(self._stop_signals)

    def _timed(self) -> None:
        if self.on_tick is not None:
            self.on_tick()
        self.refresh_areas()

    # --- reading and drawing ------------------------------------------------------------
    def refresh_areas(self) -> None:
        """Read the system once and redraw the five areas (the 10 Hz tick)."""
        self.refreshes += 1
        self._follow_writes()
        scr = self.screen
        # a display pushed but not mounted yet (the timer can come between) draws itself in on_mount
        ready = scr.is_mounted
        if ready and isinstance(scr, (BrowserScreen, ParamScreen)):  # the world model is live there too (10 Hz)
            scr.redraw()
        elif ready and isinstance(scr, MenuScreen):  # at the page's own rate
            scr.tick()
        try:
            r = self.reading = self.sources.read()
            self.read_error = ""
        except Exception as err:  # noqa: BLE001 - the display says what it cannot read, it does not die
            self.read_error = f"cannot read the system: {type(err).__name__}: {err}"
            self._set("world", self.read_error)
            return
        self._follow_answer()
        self._follow_gripper()
        self._show_banner(view.outputs_banner(r))
        self.ft.add(r.inputs)
        if ready and isinstance(scr, ForceScreen):
            scr.redraw()
        if isinstance(scr, COVERING):  # a debug display covers the areas: redrawn when it closes
            return
        self._set("local", view.local_status(r, self.status_layer))
        speed = self.sources.speed() if self.sources.speed is not None else None
        self._set("world", view.world_status(r, self.sources.rack, speed))
        self._set("messages", view.messages_area(self.sources.messages), follow=True)
        self._set("commands", view.local_commands(r, self.command_layer, self.sources.wm))
        self._set("global", view.global_commands(r, self.rearm, self.last_answer))
        self._follow_move()
        if isinstance(self.screen, (CameraScreen, MessagesScreen, MoveScreen)) and self.screen.is_mounted:  # live too
            self.screen.redraw()

    def _show_banner(self, text: str) -> None:
        """The banner above the areas (and under any screen pushed over them: it is the main
        screen's): shown with ``text``, hidden when ``text`` is ""."""
        if self._shown.get("banner") == text:
            return
        self._shown["banner"] = text
        banner = self.query_one("#banner", Static)
        banner.update(text)
        banner.display = bool(text)

    @property
    def banner_text(self) -> str:
        """The banner's text while it is shown, "" while hidden."""
        banner = self.query_one("#banner", Static)
        return str(banner.render()) if banner.display else ""

    def _set(self, key: str, text: str, follow: bool = False) -> None:
        """Redraw an area only when its text changed; a layout pass only when its number of
        lines changed (the grid fixes the area's size, its scroll range follows the text).
        ``follow``: an area that showed its end keeps showing it (Messages: the newest)."""
        old = self._shown.get(key)
        if old == text:
            return
        self._shown[key] = text
        lines = old is None or old.count("\n") != text.count("\n")
        self.query_one(f"#{key}", Static).update(text, layout=lines)
        if follow:
            area = self.query_one(f"#{key}-area", Area)
            if area.scroll_y >= area.max_scroll_y:
                self.call_after_refresh(area.scroll_end, animate=False, immediate=True)

    def area_text(self, key: str) -> str:
        """The text an area shows now (``local``, ``world``, ``messages``, ``commands``, ``global``)."""
        return str(self.query_one(f"#{key}", Static).render())

    def _follow_answer(self) -> None:
        if not self.pending or self.link is None:
            return
        for seq in list(self.pending):  # each request sent is followed to its final answer
            a = self.link.answer(seq)
            if a is None:
                continue
            self._show_answer(a)
            if a.done:
                self.pending.remove(seq)
                if a.ok and "SINGLE STEP" in a.text:
                    for line in self.link.step_trace().splitlines()[-3:]:
                        self._note("INFO", "trace " + line.strip())

    def _show_answer(self, a: Answer) -> None:
        line = a.line()
        if line != self.last_answer:
            self.last_answer = line
            self._note("WARNING" if a.code in (Response.REFUSED, Response.FAILED) else "INFO", line)

    def _note(self, level: str, text: str) -> None:
        t = float(self.reading.t_s) if self.reading is not None else 0.0
        self.sources.note(t, level, text)

    # --- keyed user writes (the debug window) ---------------------------------------------
    def begin_edit(self, name: str, index: int | None = None) -> bool:
        """Open the editor for ``name`` (element ``index`` of a vector) if the ownership rules
        let a user set it now; else say why in Messages and the screen. True if opened."""
        from pfma.errors import PfmaError
        if self.link is None:
            return self._refuse(name, "read-only console: no controller to send writes to")
        try:
            spec = self.link.may_set(name)  # the rule `pfma wm set` applies
            current = self.link.wm.get(name)
        except PfmaError as err:
            return self._refuse(name, str(err))
        self.push_screen(EditScreen(name, spec, current, index))
        return True

    def _refuse(self, name: str, why: str) -> bool:
        self.write_status = f"{name}: refused: {why}"
        self._note("WARNING", self.write_status)
        return False

    def user_write(self, name: str, text: str) -> int | None:
        """Send one keyed user write (:meth:`ControllerLink.write`); the outcome follows at
        the refresh (Messages and :attr:`write_status`)."""
        from pfma.errors import PfmaError
        if self.link is None:
            self._refuse(name, "read-only console: no controller to send writes to")
            return None
        try:
            rid = self.link.write(name, text)
        except PfmaError as err:
            self._refuse(name, str(err))
            return None
        self.writes[rid] = name
        self.write_status = f"{name}: write #{rid} = {text} sent; the controller applies it at its next frame"
        self._note("INFO", self.write_status)
        return rid

    def _follow_writes(self) -> None:
        if not self.writes or self.link is None:
            return
        for rid in list(self.writes):
            o = self.link.outcome(rid)
            if o is None:
                continue
            name = self.writes.pop(rid)
            if o.applied:
                from tools.wmtext import value_text
                self.write_status = (f"{name} = {value_text(self.link.wm.spec(name), self.link.wm.get(name))} "
                                     f"(write #{rid}, {o.result})")
                self._note("INFO", self.write_status)
            else:
                self._refuse(name, f"write #{rid} rejected by the controller: {o.result}")

    # --- actions ------------------------------------------------------------------------
    def action_layer(self, d: int) -> None:
        """Left/right: the layer Local Status details (Local Commands keeps its own)."""
        self.status_layer = (self.status_layer + d) % len(view.LAYERS)
        self.refresh_areas()
        # the selected layer's row in view (Local Status scrolls on a short terminal; row 0 is the header)
        area = self.query_one("#local-area", Area)
        self.call_after_refresh(area.scroll_to_region, Region(0, self.status_layer + 1, 1, 1), animate=False,
                                immediate=True)

    def action_tree(self, d: int) -> None:
        """Up/down: the layer Local Commands shows, up or down the layer tree (Local Status
        keeps its own; report 2.2.8: the two areas move independently)."""
        self.command_layer = (self.command_layer + d) % len(view.LAYERS)
        self.refresh_areas()
        area = self.query_one("#commands-area", Area)  # its first line names the layer: in view
        self.call_after_refresh(area.scroll_home, animate=False, immediate=True)

    def _send(self, kind: int, arg: int = 0) -> None:
        if self.link is None:
            self._note("WARNING", "read-only console: no controller to send requests to")
            return
        try:
            seq = self.link.submit(kind, arg)
        except ControlError as err:
            self._note("ERROR", str(err))
            return
        self.pending.append(seq)
        del self.pending[:-PENDING_FOLLOWED]  # the oldest unanswered stop being followed (never more than these)
        self._note("INFO", f"request {seq}: {Request.NAMES[kind]} sent")
        self.refresh_areas()

    def action_request(self, name: str) -> None:
        self._send(getattr(Request, name))

    def action_power_up(self) -> None:
        """``u``: POWER UP, once the operator has confirmed the shoulder-roll index (no sensor;
        :class:`PowerUpScreen`). A world model without the index sends it at once."""
        wm = self.sources.wm
        if self.link is None or "joint.shoulder_roll_deg" not in wm.names():
            self._send(Request.POWER_UP)
            return
        self.push_screen(PowerUpScreen(float(wm.get("joint.shoulder_roll_deg"))))

    def power_up_confirmed(self, deg: float) -> None:
        """The operator confirmed the index ``deg``: POWER UP (unless it changed meanwhile)."""
        from controller.params import shoulder_roll_text
        now = float(self.sources.wm.get("joint.shoulder_roll_deg"))
        if now != deg:
            self._note("WARNING", f"POWER UP not sent: the shoulder-roll index changed to {shoulder_roll_text(now)} "
                                  f"while the question showed {shoulder_roll_text(deg)}; u again")
            self.refresh_areas()
            return
        self._note("INFO", f"shoulder-roll index {shoulder_roll_text(deg)} confirmed by the operator")
        self._send(Request.POWER_UP)

    # --- the gripper (Global Commands o g x + -; controller/gripper.py) ---------------------------
    def action_gripper(self, name: str, force_n: float = 0.0) -> None:
        from pfma.gripper import GripperRequest
        if self.link is None:
            self._note("WARNING", "read-only console: no controller to send gripper requests to")
            return
        try:
            self.gripper_pending = self.link.submit_gripper(int(GripperRequest[name]), force_n)
        except ControlError as err:
            self._note("ERROR", str(err))
            return
        self._note("INFO", f"gripper request {self.gripper_pending}: {name}"
                           + (f" {force_n:g} N" if force_n else "") + " sent")
        self.refresh_areas()

    def action_grip_force(self, sign: int) -> None:
        """``+``/``-``: the grip force in force plus or minus view.GRIP_FORCE_STEP_N (the controller
        refuses one outside its range, naming it)."""
        now = float(self.reading.wm.get("gripper.force_n", 0.0)) if self.reading is not None else 0.0
        self.action_gripper("FORCE", max(0.0, now + sign * view.GRIP_FORCE_STEP_N))

    def _follow_gripper(self) -> None:
        if self.gripper_pending is None or self.link is None:
            return
        a = self.link.gripper_answer(self.gripper_pending)
        if a is None:
            return
        self._show_answer(a)
        if a.done:
            self.gripper_pending = None

    def action_step(self, n: int) -> None:
        self._send(Request.STEP, n)

    def action_rearm(self) -> None:
        self.rearm = not self.rearm
        self._note("INFO", "re-arm given: the next resume re-arms the outputs" if self.rearm else "re-arm withdrawn")
        self.refresh_areas()

    def action_resume(self) -> None:
        self._send(Request.RESUME, 1 if self.rearm else 0)
        self.rearm = False  # one re-arm, one resume

    def action_not_yet(self, key: str) -> None:
        self._note("INFO", view.NOT_YET[key])
        self.refresh_areas()

    def action_record(self) -> None:
        """``c``: start or stop a ``pfma record`` of this system (tools/console/recording.py)."""
        if self.recording is None:
            buffer = getattr(getattr(self.sources.client, "buffer", None), "name", None)
            if not buffer:
                self._note("WARNING", "record: this console's buffer has no name a recorder can attach")
                self.refresh_areas()
                return
            self.recording = ConsoleRecording(buffer, getattr(self.sources.wm, "name", None))
        rec = self.recording
        self._note("INFO", rec.stop() if rec.active else rec.start())
        self.refresh_areas()

    def stop_recording(self) -> None:
        """End a recording the console started (the console is closing)."""
        if self.recording is not None and self.recording.active:
            print(f"pfma console: {self.recording.stop()}", file=sys.stderr)

    def action_cameras(self) -> None:
        if self.link is None:
            self._note("WARNING", "read-only console: no controller to route the cameras")
        self.push_screen(CameraScreen())

    def action_move(self) -> None:
        if self.link is None:
            self._note("WARNING", "read-only console: no controller to send moves to")
        self.push_screen(MoveScreen())

    def send_move(self, kind: str, nums: list[float], turn: float | None) -> str:
        """Send one move-to request (the move screen); the answer follows at the refresh."""
        if self.link is None:
            self._note("WARNING", "read-only console: no controller to send moves to")
            return "not sent: read-only console"
        try:
            if kind == "stop":
                seq = self.link.stop_move()
            elif kind == "pose":
                change = self.link.trajectory_mode()
                if change:
                    self._note("INFO", f"{change} (a pose move follows the Trajectory Planner)")
                seq = self.link.move_pose(nums[:3], nums[3:] if len(nums) == 7 else None, turn)
            else:
                seq = self.link.move_joints(nums, turn)
        except ControlError as err:
            self._note("ERROR", str(err))
            return f"not sent: {err}"
        self.pending_move = seq
        line = f"move {seq} sent: {kind} " + (" ".join(f"{x:g}" for x in nums) if kind == "pose" else
                                            " ".join(f"{math.degrees(x):g}" for x in nums))
        self._note("INFO", line.rstrip())
        return line.rstrip() + "; the controller checks it before it starts"

    def _follow_move(self) -> None:
        if self.pending_move is None or self.link is None:
            return
        a = self.link.move_answer(self.pending_move)
        if a is None:
            return
        self.pending_move = None
        self.last_answer = a.line()
        self._note("INFO" if a.ok else "WARNING", a.line())

    def action_browser(self) -> None:
        self.push_screen(BrowserScreen(self.sources.wm))

    def action_params(self) -> None:
        self.push_screen(ParamScreen(self.sources.wm))

    def action_menu(self) -> None:
        if self.menu is None:
            self._note("INFO", "no live menus: start the console with --menu FILE.toml (examples/console-menu.toml)")
            self.refresh_areas()
            return
        self.push_screen(MenuScreen(self.menu, self.sources.wm))

    def action_force(self) -> None:
        self.push_screen(ForceScreen(self.ft))

    def action_messages(self) -> None:
        self.push_screen(MessagesScreen(self.sources.messages))
