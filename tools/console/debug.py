"""The debug window's displays (issue 18 item 2, docs/console.md "The debug window"), as
plain text like every area: the parameter-modification display and the force displays.
The Textual screens that show them are in :mod:`tools.console.app`."""

from __future__ import annotations

import math
from collections import deque
from typing import Sequence

from controller.params import JOINT_NAMES

# --- the parameter-modification display (p) ----------------------------------------------------
#: the servo compensator's parameters (the rest of servo.* are limits)
COMPENSATORS = ("servo.kp_per_s", "servo.tau_z_s", "servo.tau_p_s")
#: the element names of a per-joint vector: the six joints, then the gripper (servo.current_limit_a)
ELEMENTS = tuple(JOINT_NAMES) + ("gripper",)
#: width of one value column
CELL = 14


def param_group(name: str) -> str:
    """The heading a parameter is shown under."""
    if name in COMPENSATORS:
        return "servo compensators"
    if name.startswith("servo."):
        return "servo limits"
    if name.startswith("traj."):
        return "trajectory limits"
    return name.split(".")[0] + " parameters"


def param_names(wm) -> tuple[str, ...]:
    """The parameters: every world-model variable a user may set only while powered down
    (``VarSpec.user == "powered_down"``: the control-law parameters and limits), the servo
    compensators first, then the servo limits, then the rest, each group in the model's order."""
    names = [s.name for s in wm.specs if s.user == "powered_down"]
    order = ["servo compensators", "servo limits", "trajectory limits"]
    return tuple(sorted(names, key=lambda n: (order.index(param_group(n)) if param_group(n) in order else 99,
                                              param_group(n))))


def param_columns(wm, name: str) -> int:
    """Editable cells of a parameter: its elements (1 for a scalar)."""
    return wm.spec(name).count


def _cell(v: float) -> str:
    return f"{float(v):.6g}"


def params_display(wm, row: int, col: int, status: str = "") -> str:
    """Every parameter by joint, the selected cell in brackets, and whether it can be edited
    now (only while powered down; the ownership rule decides, this only says it)."""
    names = param_names(wm)
    values = wm.get_task_inputs(names) if names else {}
    up = bool(wm.powered_up)
    lines = ["Parameters: the servo compensators and limits (world-model control flags, user=powered_down)",
             ("LOCKED: the system is powered up; power down (d) to edit them" if up else
              "EDITABLE: the system is powered down; Enter/e edits the selected value"),
             f"  {'PARAMETER':<24} {'UNITS':<8}" + "".join(f"{e[:CELL - 1]:>{CELL}}" for e in ELEMENTS)]
    group = ""
    for r, n in enumerate(names):
        g = param_group(n)
        if g != group:
            lines.append(g)
            group = g
        s = wm.spec(n)
        vals = [values[n]] if s.shape == () else list(values[n].ravel())
        cells = []
        for c, v in enumerate(vals):
            t = _cell(v)
            cells.append(f"[{t}]".rjust(CELL) if (r == row and c == col) else f"{t} ".rjust(CELL))
        mark = ">" if r == row else " "
        lines.append(f"{mark} {n:<24} {s.units or '-':<8}" + "".join(cells))
    lines += ["", "up/down parameter  left/right joint  Enter/e edit  Escape/p close", status]
    return "\n".join(lines)


# --- the force displays (f) ----------------------------------------------------------------------
#: seconds of F/T history the time plot shows
FT_HISTORY_S = 30.0
#: samples kept (the console samples at its 10 Hz refresh: 30 s)
FT_HISTORY = 300
#: each time plot is redrawn every this many console refreshes that brought a new F/T
#: record (0.5 Hz), the torque plot half a period after the force plot: plotext's drawing of
#: one plot costs ~35 ms with a full history, most of the force displays' cost
#: (docs/console.md "Cost of the debug window")
FT_PLOT_EVERY = 20
#: the vector view is redrawn every this many such refreshes (10 Hz), only its changed lines
FT_VECTOR_EVERY = 1
#: the smallest axis length of the vector view (a sensor at rest shows its noise small)
FT_MIN_SCALE_N = 10.0


class FtHistory:
    """The F/T values the console saw, one per refresh with a new F/T record (``ft_t_s``
    changed): the time plot's data. Sampled at the console's refresh, not at the sensor's
    rate (docs/console.md)."""

    def __init__(self, n: int = FT_HISTORY) -> None:
        self.t: deque[float] = deque(maxlen=n)
        self.f: deque[tuple[float, float, float]] = deque(maxlen=n)
        self.m: deque[tuple[float, float, float]] = deque(maxlen=n)
        self._last = math.nan
        self.count = 0  #: records added so far

    def full_scale_n(self) -> float:
        """The vector view's axis length: the largest |F| in the history, rounded up to 1, 2
        or 5 times a power of ten, at least :data:`FT_MIN_SCALE_N` (auto-scaled, docs/console.md)."""
        top = max((math.sqrt(x * x + y * y + z * z) for x, y, z in self.f), default=0.0)
        top = max(top, FT_MIN_SCALE_N)
        e = 10.0 ** math.floor(math.log10(top))
        return next(k * e for k in (1.0, 2.0, 5.0, 10.0) if k * e >= top)

    def add(self, inputs) -> bool:
        """Note the inputs' F/T record if it is new; True if it was."""
        t = float(inputs.ft_t_s)
        if t == self._last:
            return False
        self._last = t
        f, m = inputs.ft_force_n, inputs.ft_torque_nm
        self.t.append(t)
        self.f.append((float(f[0]), float(f[1]), float(f[2])))
        self.m.append((float(m[0]), float(m[1]), float(m[2])))
        self.count += 1
        return True


_BRAILLE = ((0x01, 0x08), (0x02, 0x10), (0x04, 0x20), (0x40, 0x80))  # dot bits by (row % 4, col % 2)


class Braille:
    """A character grid of 2 x 4 dots per cell (Unicode braille), for lines and labels."""

    def __init__(self, cols: int, rows: int) -> None:
        self.cols, self.rows = cols, rows
        self.bits = [[0] * cols for _ in range(rows)]
        self.text: dict[tuple[int, int], str] = {}

    def dot(self, x: float, y: float) -> None:
        xi, yi = int(round(x)), int(round(y))
        if 0 <= xi < 2 * self.cols and 0 <= yi < 4 * self.rows:
            self.bits[yi // 4][xi // 2] |= _BRAILLE[yi % 4][xi % 2]

    def line(self, x0: float, y0: float, x1: float, y1: float) -> None:
        n = max(1, int(max(abs(x1 - x0), abs(y1 - y0))))
        for k in range(n + 1):
            self.dot(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n)

    def label(self, x: float, y: float, text: str) -> None:
        c, r = int(round(x)) // 2, int(round(y)) // 4
        for i, ch in enumerate(text):
            if 0 <= c + i < self.cols and 0 <= r < self.rows:
                self.text[(r, c + i)] = ch

    def render(self) -> str:
        out = []
        for r in range(self.rows):
            out.append("".join(self.text.get((r, c)) or (chr(0x2800 + b) if b else " ")
                               for c, b in enumerate(self.bits[r])))
        return "\n".join(out)


def _project(v: Sequence[float], scale: float, cx: float, cy: float) -> tuple[float, float]:
    """Cabinet projection in dots (a braille dot is about square): x to the right, y into the
    screen at half length and 30 degrees up, z up."""
    x, y, z = (float(c) for c in v)
    c30, s30 = math.cos(math.radians(30)), math.sin(math.radians(30))
    return cx + scale * (x + 0.5 * y * c30), cy - scale * (z + 0.5 * y * s30)


def _dashed(b: Braille, p0: tuple[float, float], p1: tuple[float, float], parts: int = 12) -> None:
    for k in range(0, parts, 2):
        b.line(p0[0] + (p1[0] - p0[0]) * k / parts, p0[1] + (p1[1] - p0[1]) * k / parts,
               p0[0] + (p1[0] - p0[0]) * (k + 1) / parts, p0[1] + (p1[1] - p0[1]) * (k + 1) / parts)


def vector_view(force: Sequence[float], torque: Sequence[float], full_scale_n: float,
                cols: int = 48, rows: int = 16) -> str:
    """The pseudo-3D force view: the sensor frame's axes (positive half solid, negative half
    dashed), the force vector from the origin (scaled: ``full_scale_n`` is an axis' length,
    clipped at 1.5 times that), its shadow on the x-y plane and the drop from the tip to the
    shadow (dashed: the depth cue), in a cabinet projection drawn in braille, the numbers under it."""
    b = Braille(cols, rows)
    cx, cy = cols * 1.0, rows * 2.0  # the origin in dots: the middle (the canvas is 2*cols x 4*rows dots)
    scale = min(cols * 0.9, rows * 1.6)
    o = (cx, cy)
    for axis, name in (((1, 0, 0), "x"), ((0, 1, 0), "y"), ((0, 0, 1), "z")):
        p1 = _project(axis, scale, cx, cy)
        b.line(cx, cy, *p1)
        _dashed(b, o, _project([-c for c in axis], scale, cx, cy))
        b.label(p1[0] + 2, p1[1], name)
    fs = max(full_scale_n, 1e-9)
    f = [max(-1.5, min(1.5, float(v) / fs)) for v in force]
    tip = _project(f, scale, cx, cy)
    shadow = _project((f[0], f[1], 0.0), scale, cx, cy)
    _dashed(b, o, shadow)
    _dashed(b, shadow, tip)
    for dx in (-0.5, 0.0, 0.5):  # the vector drawn bold
        b.line(cx + dx, cy, tip[0] + dx, tip[1])
    b.label(tip[0] + 2, tip[1], "F")
    mag = math.sqrt(sum(float(v) ** 2 for v in force))
    tmag = math.sqrt(sum(float(v) ** 2 for v in torque))
    return (b.render() + "\n"
            + f"F ({float(force[0]):+8.2f}, {float(force[1]):+8.2f}, {float(force[2]):+8.2f}) N   |F| {mag:7.2f} N\n"
            + f"T ({float(torque[0]):+8.3f}, {float(torque[1]):+8.3f}, {float(torque[2]):+8.3f}) N*m |T| {tmag:7.3f} N*m\n"
            + f"sensor frame; an axis is {full_scale_n:g} N\n"
            + "dashed: the negative axes, the shadow on x-y, the drop")
