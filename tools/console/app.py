"""The operator console: a Textual app with the IRSS primary display's five areas.

Few widgets (docs/console.md, the new-dependencies notes: one widget rendering all its
values costs a tenth of many small ones): each area is one :class:`textual.widgets.Static`
whose text :mod:`tools.console.view` renders; a timer refreshes them at
:data:`REFRESH_HZ`. Keys send the Global Commands through the world model's request
protocol (:class:`tools.console.control.ControllerLink`); nothing else is written.
"""

from __future__ import annotations

import time
from typing import Callable

from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Grid
from textual.screen import ModalScreen
from textual.widgets import Footer, Static

from drivers.pio.routes import MONITORS, route_request_arg
from tools.console import view
from tools.console.control import Answer, ControlError, ControllerLink, Request, Response

#: refresh rate of the areas (the issue's 10 Hz)
REFRESH_HZ = 10.0
#: frames one capital-S single step runs
BIG_STEP = 10


class MessagesScreen(ModalScreen):
    """The last 100 messages of every source, time-ordered (``m`` or Escape closes)."""

    BINDINGS = [Binding("escape,m,q", "app.pop_screen", "close")]

    def __init__(self, text: str) -> None:
        super().__init__()
        self.text = text

    def compose(self) -> ComposeResult:
        yield Static(self.text, id="all-messages", markup=False)


class BrowserScreen(ModalScreen):
    """The world model by area, live and read-only (issue 18 item 2's browser; modifying
    needs ``pfma wm set`` with the key). Left/right: area, pgup/pgdn: page."""

    BINDINGS = [Binding("escape,w,q", "app.pop_screen", "close"),
                Binding("left", "area(-1)", "area"), Binding("right", "area(1)", "area"),
                Binding("pageup", "page(-1)", "page"), Binding("pagedown", "page(1)", "page")]

    def __init__(self, wm) -> None:
        super().__init__()
        self.wm = wm
        self.area = 0
        self.page = 0

    def compose(self) -> ComposeResult:
        yield Static("", id="browser", markup=False)

    def on_mount(self) -> None:
        self.redraw()

    def redraw(self) -> None:
        self.query_one("#browser", Static).update(view.wm_browser(self.wm, self.area, self.page))

    def text(self) -> str:
        return str(self.query_one("#browser", Static).render())

    def action_area(self, d: int) -> None:
        self.area, self.page = self.area + d, 0
        self.redraw()

    def action_page(self, d: int) -> None:
        self.page += d
        self.redraw()


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


class ConsoleApp(App):
    """The primary display over the live system.

    :param sources: where to read (:class:`tools.console.view.Sources`)
    :param link: requests to the controller (None: read-only, the commands say so)
    :param auto_refresh: refresh on a timer (False in tests: :meth:`refresh_areas` by hand)
    :param on_tick: called before each timed refresh (``make run`` paces nothing here; a
        hook for a caller that wants it)
    """

    CSS = """
    Grid { grid-size: 2 3; grid-columns: 1fr 1fr; grid-rows: 1fr 1fr auto; }
    .area { border: round $accent; padding: 0 1; height: 100%; }
    #world { row-span: 1; }
    #messages { column-span: 2; }
    """
    TITLE = "PFMA operator console"
    BINDINGS = [
        Binding("left", "layer(-1)", "layer", show=False), Binding("right", "layer(1)", "layer", show=False),
        Binding("up", "layer(-1)", "tree", show=False), Binding("down", "layer(1)", "tree", show=False),
        Binding("u", "request('POWER_UP')", "power up"),
        Binding("d", "request('POWER_DOWN')", "power down"),
        Binding("e", "request('ERROR_RESET')", "error reset"),
        Binding("h", "request('HALT')", "halt"),
        Binding("s", "step(1)", "step"), Binding("S", "step(10)", "10 steps", show=False),
        Binding("a", "rearm", "re-arm"),
        Binding("r", "resume", "resume"),
        Binding("c", "not_yet('c')", "record"), Binding("v", "cameras", "cameras"),
        Binding("m", "messages", "messages"),
        Binding("w", "browser", "world model"),
        Binding("q", "quit", "quit"),
        Binding("ctrl+c", "quit", "quit", show=False, priority=True),
    ]

    def __init__(self, sources: view.Sources, link: ControllerLink | None, *, auto_refresh: bool = True,
                 on_tick: Callable[[], None] | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.sources = sources
        self.link = link
        self.auto = auto_refresh
        self.on_tick = on_tick
        self.clock = clock
        self.selected = 0
        self.rearm = False
        self.last_answer = ""
        self.pending: int | None = None  # request waiting for its final answer
        self.reading: view.Reading | None = None
        self.read_error = ""
        self.refreshes = 0
        self._shown: dict[str, str] = {}  # the text each area shows

    def compose(self) -> ComposeResult:
        with Grid():
            for key, title in zip(("local", "world", "messages", "commands", "global"), view.AREAS):
                w = Static("", id=key, classes="area", markup=False)
                w.border_title = title
                yield w
        yield Footer()

    def on_mount(self) -> None:
        self.refresh_areas()
        if self.auto:
            self.set_interval(1.0 / REFRESH_HZ, self._timed)

    def _timed(self) -> None:
        if self.on_tick is not None:
            self.on_tick()
        self.refresh_areas()

    # --- reading and drawing ------------------------------------------------------------
    def refresh_areas(self) -> None:
        """Read the system once and redraw the five areas (the 10 Hz tick)."""
        self.refreshes += 1
        if isinstance(self.screen, BrowserScreen):  # the browser is live too (10 Hz)
            self.screen.redraw()
        try:
            r = self.reading = self.sources.read()
            self.read_error = ""
        except Exception as err:  # noqa: BLE001 - the display says what it cannot read, it does not die
            self.read_error = f"cannot read the system: {type(err).__name__}: {err}"
            self._set("world", self.read_error)
            return
        self._follow_answer()
        self._set("local", view.local_status(r, self.selected))
        speed = self.sources.speed() if self.sources.speed is not None else None
        self._set("world", view.world_status(r, self.sources.rack, speed))
        self._set("messages", view.messages_area(self.sources.messages))
        self._set("commands", view.local_commands(r, self.selected, self.sources.wm))
        self._set("global", view.global_commands(r, self.rearm, self.last_answer))
        if isinstance(self.screen, CameraScreen):  # the camera routes are live too
            self.screen.redraw()

    def _set(self, key: str, text: str) -> None:
        """Redraw an area only when its text changed, without a layout pass (the grid fixes
        every area's size; its text never does)."""
        if self._shown.get(key) == text:
            return
        self._shown[key] = text
        self.query_one(f"#{key}", Static).update(text, layout=False)

    def area_text(self, key: str) -> str:
        """The text an area shows now (``local``, ``world``, ``messages``, ``commands``, ``global``)."""
        return str(self.query_one(f"#{key}", Static).render())

    def _follow_answer(self) -> None:
        if self.pending is None or self.link is None:
            return
        a = self.link.answer(self.pending)
        if a is None:
            return
        self._show_answer(a)
        if a.done:
            self.pending = None
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

    # --- actions ------------------------------------------------------------------------
    def action_layer(self, d: int) -> None:
        self.selected = (self.selected + d) % len(view.LAYERS)
        self.refresh_areas()

    def _send(self, kind: int, arg: int = 0) -> None:
        if self.link is None:
            self._note("WARNING", "read-only console: no controller to send requests to")
            return
        try:
            self.pending = self.link.submit(kind, arg)
        except ControlError as err:
            self._note("ERROR", str(err))
            return
        self._note("INFO", f"request {self.pending}: {Request.NAMES[kind]} sent")
        self.refresh_areas()

    def action_request(self, name: str) -> None:
        self._send(getattr(Request, name))

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

    def action_cameras(self) -> None:
        if self.link is None:
            self._note("WARNING", "read-only console: no controller to route the cameras")
        self.push_screen(CameraScreen())

    def action_browser(self) -> None:
        self.push_screen(BrowserScreen(self.sources.wm))

    def action_messages(self) -> None:
        self.push_screen(MessagesScreen(view.messages_screen(self.sources.messages)))
