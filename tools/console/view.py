"""What the console shows: one reading of the live system and the text of each area.

The console reads only, outside every loop: the service's Bit3 buffer as a reader (no
claim) and the controller's world model (attached read-only, or the simulator's own
model); it writes nothing but user requests into the world model's request ring
(:mod:`tools.console.control`). Every area is rendered here as plain text, so the Textual
app has one widget per area (docs/console.md) and the text can be tested without a
terminal.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from bit3.layout import DEVICE_GROUPS, FAULT_CODE_NAMES, FAULT_DAC_UNREACHABLE, HAND_CONTROLLERS, ServiceState, Severity
from controller.cartesian import CartesianLayer
from controller.daq_layer import FAULT_NAMES, DataAcquisitionLayer
from controller.decision import Command, status_text
from controller.layers import TASK_NAMES, JointPlannerLayer, UpDownLayer
from controller.params import JOINT_NAMES, shoulder_roll_text
from controller.paths import MultiSegmentLayer
from controller.servo import ServoLayer
from controller.trajectory import TrajectoryLayer
from drivers.pio.registers import decode_matrix_route
from controller.routes import MONITORS, camera_name, route_text
from pfma.show import flag_names, name_of, named, wrap_angle
from tools.wmview import GRIPPER_VARS  # the gripper's world-model variables (controller/gripper.py)

#: the seven IRSS layers, highest first: (world-model key, the report's title)
_LAYER_CLASSES = (UpDownLayer, MultiSegmentLayer, TrajectoryLayer, CartesianLayer, JointPlannerLayer, ServoLayer,
                  DataAcquisitionLayer)
LAYERS: tuple[tuple[str, str], ...] = tuple((c.key, c.title) for c in _LAYER_CLASSES)
#: each layer's ``<key>.error`` codes by name (its class's ``error_names``)
_ERROR_NAMES: dict[str, dict[int, str]] = {c.key: c.error_names for c in _LAYER_CLASSES}
#: the five areas of the primary display, titled as the IRSS report names them (2.2.8)
AREAS = ("Local Status", "World Status", "Messages", "Local Commands", "Global Commands")
#: messages kept by the console (the Messages screen shows them all, newest first, filtered)
MESSAGES_KEPT = 1000
#: messages in the main screen's Messages area: the newest, in time order (newest at the bottom)
MAIN_MESSAGES = 50
#: the levels the Messages screen filters by (``l`` cycles): at least this severe
LEVELS = ("INFO", "WARNING", "ERROR", "FATAL")
#: what one press of + or - changes the grip force by (the console's step; assumed)
GRIP_FORCE_STEP_N = 10.0
#: the Global Commands, their keys and what each sends (None: not yet built)
GLOBAL_COMMANDS: tuple[tuple[str, str, str | None], ...] = (
    ("u", "power up", "POWER UP"),
    ("d", "power down", "POWER DOWN"),
    ("e", "error reset", "ERROR RESET"),
    ("h", "halt", "HALT"),
    ("s", "single step (1 frame; S: 10)", "SINGLE STEP"),
    ("a", "re-arm (for the next resume)", None),
    ("r", "resume (needs a first)", "RESUME"),
    ("c", "record start/stop", None),
    ("v", "camera routes", "CAMERA ROUTE"),  # v and t open their screens (one line: the
    ("t", "move to", None),                   # area fits the 120x40 split, docs/console.md "Sizes")
    ("o g x", "gripper open, grip, stop", "GRIPPER OPEN / CLOSE / STOP"),
    ("+ -", f"grip force +-{GRIP_FORCE_STEP_N:g} N", "GRIPPER FORCE"),
)
NOT_YET: dict[str, str] = {}  #: keys whose command is not built yet: their text


@dataclass
class ConsoleMessage:
    t_s: float
    source: str
    level: str
    text: str


@dataclass
class Reading:
    """One reading of the live system (everything the areas show)."""

    service_state: str = "?"
    frame: int = 0
    t_s: float = 0.0
    inputs: Any = None  #: the service's input snapshot
    stats: Any = None  #: the service's statistics snapshot
    wm: dict = field(default_factory=dict)  #: world-model values by name
    controller_alive: bool = False
    controller_owner: str = ""


class Sources:
    """Where the console reads: a Bit3 reader client, the world model, and what the rack is.

    :param client: a :class:`bit3.client.Client` (a reader; never a writer)
    :param wm: the controller's world model (attached, or the simulator's own)
    :param rack: "simulated" (the boards are fakes: said on every screen), "real" (a
        hardware bus), "unknown"; None (default): what the buffer says, read at every
        refresh (the service's SIMULATED flag, :func:`rack_kind`)
    """

    def __init__(self, client, wm, rack: str | None = None) -> None:
        self.client = client
        self.wm = wm
        self.rack = rack or "unknown"
        self._rack_from_buffer = rack is None
        self.layout = client.layout
        names = set(wm.names())
        self.layer_vars = tuple(f"{k}.{f}" for k, _ in LAYERS for f in ("command", "status", "row", "task", "error")
                                if f"{k}.{f}" in names)
        extra = ("runtime.halted", "runtime.steps_left", "runtime.step_frames", "runtime.frames", "runtime.rate_hz",
                 "runtime.missed_frames", "daq.fault_bits", "daq.joint_angle_rad", "daq.joint_rate_rad_s", "daq.camera_route",
                 "ui.response_seq", "ui.response", "ui.response_text", "runtime.first_cause",
                 "joint.shoulder_roll_deg", "servo.brake_state")
        extra += GRIPPER_VARS
        self.wm_vars = self.layer_vars + tuple(n for n in extra if n in names)
        self.messages: deque[ConsoleMessage] = deque(maxlen=MESSAGES_KEPT)
        #: simulated seconds per wall second (``pfma console --sim``), or None (a live system)
        self.speed: Callable[[], float] | None = None
        #: the names read, shown in World Status's title ("buffer pfma, world model pfma_wm"; "": none)
        self.names = ""
        self._seq = {"service": 0, "controller": 0}

    def read(self) -> Reading:
        c = self.client
        if self._rack_from_buffer:
            self.rack = rack_kind(c)
        snap = c.read_inputs()
        r = Reading(inputs=snap, stats=c.read_stats())
        st = int(snap.service_state)
        r.service_state = ServiceState(st).name if st in ServiceState._value2member_map_ else str(st)
        r.frame, r.t_s = int(snap.frame), float(snap.t_s)
        r.wm = dict(self.wm.get_task_inputs(self.wm_vars))
        info = self.wm.info()
        r.controller_alive, r.controller_owner = bool(info.owner_alive), info.owner
        self._read_messages()
        return r

    def _read_messages(self) -> None:
        for q in ("service", "controller"):
            for m in self.client.messages(self._seq[q], q):
                self._seq[q] = max(self._seq[q], int(m.seq))
                sev = Severity(int(m.severity)).name if int(m.severity) in Severity._value2member_map_ else "?"
                src, text = ("service", m.text) if q == "service" else _split_source(m.text)
                self.messages.append(ConsoleMessage(float(m.t_s), src, sev, text))

    def note(self, t_s: float, level: str, text: str) -> None:
        """A message of the console itself (request answers, refusals, 'not yet')."""
        self.messages.append(ConsoleMessage(t_s, "console", level, text))


def _split_source(text: str) -> tuple[str, str]:
    """The controller forwards ``"<layer>: <text>"`` (whole: a long text takes several queue entries)."""
    src, sep, rest = text.partition(": ")
    return (src, rest) if sep and " " not in src else ("controller", text)


# --- the areas' text ---------------------------------------------------------------------------
def _enum(enum_cls, v: int) -> str:
    return name_of(v, enum_cls)


def rack_kind(client) -> str:
    """"simulated", "real" or "unknown": the SIMULATED flag the service publishes in its
    owner slots of the Bit3 header (``HeaderInfo.rack_kind``; unknown when the header
    cannot be read or has no owners, as over the Zenoh bridge)."""
    try:
        return str(client.header().rack_kind)
    except Exception:  # noqa: BLE001 - a display: what cannot be read is unknown
        return "unknown"


def rack_line(rack: str) -> str:
    return {"simulated": "SIMULATED RACK: the boards, the arm and the sensors are fakes",
            "real": "rack: real (the service's register bus is hardware, not simulated)"
            }.get(rack, "rack: unknown (the buffer does not say if its boards are simulated)")


def local_status(r: Reading, selected: int) -> str:
    """One line per layer (state, command; a layer's subordinate is the row under it), the
    selected one (left/right; Local Commands has its own selection) marked and detailed.
    Lines fit 76 columns (docs/console.md "Sizes")."""
    lines = [f"  {'LAYER':<26} {'STATE':<31} COMMAND"]
    w = r.wm
    for i, (k, title) in enumerate(LAYERS):
        st = int(w.get(f"{k}.status", -1))
        cmd = int(w.get(f"{k}.command", 0))
        mark = ">" if i == selected else " "
        lines.append(f"{mark} {title:<26} {status_text(st):<31} {_enum(Command, cmd)}")
    k, title = LAYERS[selected]
    task = int(w.get(f"{k}.task", 0))
    err = int(w.get(f"{k}.error", 0))
    lines.append(f"{title}: row {int(w.get(f'{k}.row', 0))}, task {name_of(task, TASK_NAMES).lower()}, "
                 f"last error {named(err, _ERROR_NAMES[k]) if err else 'none'}")
    if k == "daq":
        bits = int(w.get("daq.fault_bits", 0))
        lines.append("hardware checks: " + flag_names(bits, FAULT_NAMES, clear="clear").replace("|", ", "))
    lines.append("<- -> layer")
    return "\n".join(lines)


def world_status(r: Reading, rack: str, speed: float | None = None) -> str:
    s, st = r.inputs, r.stats
    lay = s.layout
    halted = bool(r.wm.get("runtime.halted", False))
    outputs_word = "NOT KNOWN SAFE" if outputs_unknown(r) else "LIVE" if int(s.outputs_enabled) else "safe (0 V)"
    lines = [rack_line(rack) + ("" if speed is None else f"; time x{speed:.2f}"),
             f"service {r.service_state:<8} frame {r.frame:<9} t {r.t_s:9.3f} s  "
             f"{float(st.rate_hz):6.1f} Hz  fault {name_of(s.fault_code, FAULT_CODE_NAMES)}",
             f"outputs {outputs_word}  {brake_summary(r, s)}  watchdog "
             f"{'TRIPPED' if int(s.watchdog_tripped) else 'ok'} (command age {float(s.command_age_s) * 1e3:.1f} ms)"]
    ctl = (f"controller ({r.controller_owner or '?'}): "
           + ("NOT RUNNING" if not r.controller_alive else
              ("HALTED" + (f", {int(r.wm.get('runtime.steps_left', 0))} step(s) to run" if
                           int(r.wm.get('runtime.steps_left', 0)) else "") if halted else "running"))
           + f"  {float(r.wm.get('runtime.rate_hz', 0.0)):.0f} Hz  frames {int(r.wm.get('runtime.frames', 0))}"
           + f"  missed {int(r.wm.get('runtime.missed_frames', 0))}")
    lines.append(ctl)
    lines += shoulder_roll_lines(r)
    lines += first_cause_lines(r)
    if halted:
        lines.append("HALTED: the motion below is measured, the outputs as the service holds them")
    joints = joint_lines(s)
    lines += joints[:1] + brake_row(r, s) + joints[1:]
    f, t = s.ft_force_n, s.ft_torque_nm
    lines.append(f"F/T  F ({float(f[0]):+7.2f}, {float(f[1]):+7.2f}, {float(f[2]):+7.2f}) N  "
                 f"T ({float(t[0]):+6.3f}, {float(t[1]):+6.3f}, {float(t[2]):+6.3f}) N*m")
    hc = "  ".join(f"{n} {'DEADMAN' if bool(s.hc_deadman[i]) else 'released'}"
                   for i, n in enumerate(HAND_CONTROLLERS))
    lines.append(f"hand controllers: {hc}")
    lines.append(camera_routes_line(r))
    lines.append(gripper_status_line(r))
    lines.append("device rates: " + "  ".join(f"{g} {float(st.device_rate_hz[lay.slot('device', g)]):.0f}"
                                              for g in DEVICE_GROUPS) + " Hz")
    return "\n".join(lines)


def shoulder_roll_lines(r: Reading) -> list[str]:
    """The shoulder-roll index (issue 30 item 2): the operator's parameter
    ``joint.shoulder_roll_deg`` (indexed by hand, no sensor). While powered up it is the one
    the kinematics use (power-up takes it, and it cannot change until power-down). Fits 76
    columns."""
    deg = r.wm.get("joint.shoulder_roll_deg")
    if deg is None or not r.controller_alive:
        return []
    return [f"shoulder roll {shoulder_roll_text(float(deg))} (indexed by hand, no sensor)"]


def power_up_question(deg: float) -> str:
    """What the console asks before POWER UP (:class:`tools.console.app.PowerUpScreen`)."""
    t = shoulder_roll_text(deg)
    return "\n".join([
        "POWER UP: confirm the shoulder-roll index",
        "",
        "The shoulder roll is indexed by hand and has no sensor: every Cartesian mode",
        "(teleoperation, paths, impedance) and the F/T gravity compensation will take it",
        f"as {t} (joint.shoulder_roll_deg).",
        "",
        f"Check the joint's index pin: is the shoulder roll pinned at {t}?",
        "",
        "The power-up then tests every brake (servo.brake_test): each joint moves a",
        "little out and back (about a degree) before START UP COMPLETE. Keep clear.",
        "",
        "y / Enter    yes: power up",
        "p            no: change the index (the parameters, powered down), then u again",
        "n / Escape   cancel"])


def first_cause_lines(r: Reading) -> list[str]:
    """The root of the current episode, while there is one (issue 29 item 3): the service's
    first trip or refusal since the last arm (Bit3 ``inputs.first_trip_*``) and the
    controller's ERROR episode's first cause (``runtime.first_cause``), not the cascade after."""
    out = []
    s = r.inputs
    if s is not None and int(s.first_trip_code):
        out.append(f"service first trip: {s.text('first_trip_text')}")
    raw = r.wm.get("runtime.first_cause")
    if raw is not None and r.controller_alive:
        text = bytes(np.asarray(raw, dtype=np.uint8)).rstrip(b"\0").decode(errors="replace")
        if text:
            out.append(f"controller first cause: {text}")
    return out


def gripper_status_line(r: Reading) -> str:
    """The gripper: its state, the grip force set and the motor's, the jaw estimate (not
    sensed: estimated from the tach once an open reached the stop)."""
    w = r.wm
    if "gripper.state" not in w:
        return "gripper: this controller has none"
    if not r.controller_alive:
        return "gripper: controller not running"
    from pfma.gripper import describe
    return describe(int(w["gripper.state"]), float(w["gripper.force_n"]), float(w["gripper.motor_force_n"]),
                    float(w["gripper.jaw_m"]) if bool(w.get("gripper.jaw_known", False)) else None)


def _short(joint: str) -> str:
    """A joint's name in 10 columns: ``shoulder_pitch`` -> ``sh pitch``."""
    first, _, rest = joint.partition("_")
    return (f"{_SHORT.get(first, first)} {rest}" if rest else first)[:10]


_SHORT = {"shoulder": "sh", "elbow": "elb", "wrist": "wr"}
_JOINT_SLOTS: dict[int, tuple[tuple[str, ...], list[int], list[int], list[int]]] = {}


#: ``servo.brake_state`` as World Status shows it (controller.supervision.BRAKE_STATE_NAMES)
_BRAKE_WORDS = {0: "SET", 1: "unproven", 2: "released"}


def _sensed_brakes(r: Reading) -> dict[str, int] | None:
    """Each joint's ``servo.brake_state`` by joint name; None while no controller runs or it
    is halted (the last state it posted would be old) or it posts none."""
    states = r.wm.get("servo.brake_state")
    if states is None or not r.controller_alive or bool(r.wm.get("runtime.halted", False)):
        return None  # halted: the controller senses nothing (its world model is frozen)
    return {n: int(v) for n, v in zip(JOINT_NAMES, states)}


def brake_summary(r: Reading, s) -> str:
    """The brakes on World Status's outputs line: as the sensors showed them (the
    controller's ``servo.brake_state``, issue 30 item 3) when every joint's is the same;
    ``mixed`` with a row per joint under the joint names (:func:`brake_row`) when not; the
    service's commanded state (its current limits, not proof) while no controller runs or it
    is halted."""
    sensed = _sensed_brakes(r)
    if sensed is None:
        return f"brakes {'released' if int(s.brakes_released) else 'set'} (commanded)"
    words = {_BRAKE_WORDS.get(v, "?") for v in sensed.values()}
    return f"brakes {words.pop()} (sensed)" if len(words) == 1 else "brakes mixed (sensed, by joint below)"


def brake_row(r: Reading, s) -> list[str]:
    """Each joint's brake as the sensors showed it, under the joint names of
    :func:`joint_lines`, when they differ (:func:`brake_summary` says it in one word else)."""
    sensed = _sensed_brakes(r)
    if sensed is None or len(set(sensed.values())) == 1:
        return []
    try:
        names = tuple(s.layout.joint_names)
    except (AttributeError, LookupError, ValueError):
        return []
    return ["brake      " + " ".join(f"{_BRAKE_WORDS.get(sensed.get(n, -1), '?'):>10}" for n in names)]


def joint_lines(s) -> list[str]:
    """The joints as the service measured them at its latest frame (Bit3 inputs, not the
    world model: while the controller is halted its ``daq.*`` copy is frozen at its last
    frame, so a rate read there would be old motion shown as now): the resolver angle in
    (-pi, pi], the tach rate, and the rate command the DAC holds (V). Fits 74 columns."""
    lay = s.layout
    slots = _JOINT_SLOTS.get(id(lay))
    if slots is None:
        try:
            names = tuple(lay.joint_names)
            slots = (names, [lay.joint_entry("rtd", j, "angle").slot for j in names],
                     [lay.joint_entry("adc", j, "rate").slot for j in names],
                     [lay.joint_entry("dac", j, "rate_command").slot for j in names])
        except (KeyError, LookupError, ValueError, AttributeError):
            slots = ((), [], [], [])
        _JOINT_SLOTS[id(lay)] = slots
    names, rtd, tach, dac = slots
    if not names:
        return ["joints: this layout names no joint channels"]
    ang, rate, volts = s.rtd_angle_rad, s.adc_value, s.dac_volts
    return ["joint      " + " ".join(f"{_short(n):>10}" for n in names),
            "rad        " + " ".join(f"{wrap_angle(float(ang[k])):>+10.4f}" for k in rtd),
            "rad/s tach " + " ".join(f"{float(rate[k]):>+10.4f}" for k in tach),
            "V out      " + " ".join(f"{float(volts[k]):>+10.3f}" for k in dac)]


def outputs_unknown(r: Reading) -> bool:
    """The service says its outputs are NOT known safe: its DAC board does not answer
    (``inputs.fault_code`` FAULT_DAC_UNREACHABLE, issue 28 item 5)."""
    return r.inputs is not None and int(r.inputs.fault_code) == FAULT_DAC_UNREACHABLE


def outputs_banner(r: Reading) -> str:
    """The banner the console shows above every area while :func:`outputs_unknown` ("" when
    not): what is known (the values last written, as the service published them), what it
    means and what the operator must do."""
    if not outputs_unknown(r):
        return ""
    s = r.inputs
    held = [(float(s.dac_volts[c.slot]), c.name) for c in s.layout.channels
            if c.kind == "dac" and c.area == "inputs" and abs(float(s.dac_volts[c.slot])) >= 0.005]
    last = ", ".join(f"{v:+.2f} V {name}" for v, name in held) or "0 V on every channel"
    return ("OUTPUTS NOT KNOWN SAFE: the DAC board is not answering; its outputs may hold their last "
            f"values ({last}).\n"
            "PRESS THE HARDWARE E-STOP if the arm moves. Software cannot stop it through the DAC: the "
            "service keeps writing 0 V every frame and has stopped the amplifier-enable charge pump if "
            "the rack has one; without one only the E-stop stops the arm.")


def camera_routes_line(r: Reading) -> str:
    """The route the service has applied to the matrix switcher, by name, and the one the
    controller asks for when it differs (not yet applied, or the switcher did not answer)."""
    applied = int(r.inputs.matrix_route)
    line = f"camera routes: {route_text(applied)}"
    asked = r.wm.get("daq.camera_route")
    if asked is not None and r.controller_alive and int(asked) != applied:
        line += f"  (controller asks {route_text(int(asked))})"
    return line


def camera_screen(r: Reading | None, monitor: int, last: str) -> str:
    """The camera-routes screen (``v``): the applied route per monitor, the selected one."""
    lines = ["Camera routes: the user I/F box's switches or the keys here (docs/cameras.md)", ""]
    cams = decode_matrix_route(int(r.inputs.matrix_route)) if r is not None else (None,) * len(MONITORS)
    for m, cam in zip(MONITORS, cams):
        lines.append(f"{'>' if m == monitor else ' '} monitor {m}: {'?' if cam is None else camera_name(cam)}")
    if r is not None:
        lines += ["", camera_routes_line(r)]
    lines += ["", "1 2 3  that camera on the selected monitor   0  blank it",
              "up/down, tab  select the monitor   v, Escape  close", f"last answer: {last or '-'}"]
    return "\n".join(lines)


def messages_area(msgs, n: int = MAIN_MESSAGES) -> str:
    """The ``n`` newest messages of every source in time order, the newest at the bottom
    (the area keeps its end in view; ``m`` shows them all, newest first)."""
    ordered = sorted(list(msgs)[-4 * n:], key=lambda m: m.t_s)[-n:]  # the newest received: not all kept
    return "\n".join(_msg_line(m) for m in ordered) if ordered else "(no messages yet)"


def message_sources(msgs) -> list[str]:
    """The sources the messages come from, the console's and the service's first."""
    return sorted({m.source for m in msgs}, key=lambda s: (s != "console", s != "service", s))


def filter_messages(msgs, source: str | None = None, level: str | None = None) -> list[ConsoleMessage]:
    """The messages of ``source`` (None: all) at least as severe as ``level`` (None: all),
    newest first (equal times: the later received first)."""
    floor = LEVELS.index(level) if level in LEVELS else -1
    keep = [m for m in msgs if (source is None or m.source == source)
            and (floor < 0 or (m.level in LEVELS and LEVELS.index(m.level) >= floor))]
    return [m for _, m in sorted(enumerate(keep), key=lambda km: (km[1].t_s, km[0]), reverse=True)]


def messages_screen(msgs, source: str | None = None, level: str | None = None) -> str:
    """The messages the console keeps, newest first, of one source and from one level up."""
    shown = filter_messages(msgs, source, level)
    head = (f"{len(shown)} of {len(msgs)} messages, newest first   source: {source or 'all'} (s)   "
            f"level: {level + ' and above' if level else 'all'} (l)")
    return "\n".join([head] + [_msg_line(m) for m in shown] if shown else [head, "(no messages)"])


def _msg_line(m: ConsoleMessage) -> str:
    return f"{m.t_s:10.3f} {m.source:<11} {m.level:<7} {m.text}"


def local_commands(r: Reading, selected: int, wm) -> str:
    """The command of the layer selected here (up/down through the layer tree; its own
    selection, not Local Status's) and the variables a user may set in it (read-only here;
    ``w``, ``p`` and the live menus modify). Lines fit 36 columns (docs/console.md "Sizes")."""
    k, title = LAYERS[selected]
    lines = [f"{title}: command {_enum(Command, int(r.wm.get(f'{k}.command', 0)))}",
             f"  sent by {'the user requests' if k == 'updown' else LAYERS[selected - 1][1]}"]
    settable = [s for s in wm.specs if s.name.startswith(f"{k}.") and s.user != "never"]
    if settable:
        lines.append("settable (*: powered down only)")
    for s in settable[:8]:
        lines.append(f"  {s.name}{'' if s.user == 'always' else ' *'}  {s.type_text}")
    if len(settable) > 8:
        lines.append(f"  ... {len(settable) - 8} more (pfma wm list)")
    if not settable:
        lines.append("  (no user-settable variables)")
    lines.append("w  world model (Enter: modify)")
    lines.append("p  parameters (powered down)")
    lines.append("up/down: layer tree")
    return "\n".join(lines)


def global_commands(r: Reading, rearm: bool, last: str) -> str:
    """The last answer first (the newest), then the Global Commands, short ones paired
    (lines fit 36 columns: docs/console.md "Sizes")."""
    items = []
    for key, what, _ in GLOBAL_COMMANDS:
        extra = ""
        if key == "a":
            extra = "  [RE-ARM GIVEN]" if rearm else ""
        elif key in NOT_YET:
            extra = "  (not yet)"
        items.append(f"{key}  {what}{extra}")
    lines = [f"last answer: {last or '-'}"]
    line = ""
    for it in items:
        if line and len(line) + 3 + len(it) > 36:
            lines.append(line)
            line = ""
        line = f"{line}   {it}" if line else it
    lines += [line, "m  messages   w  world model", "p  parameters  l  menus  f  force", "q  quit   tab, pgup/pgdn: scroll"]
    return "\n".join(lines)


# --- the world-model browser (issue 18 item 2) --------------------------------------
#: rows of the browser per page
BROWSER_ROWS = 30


def browser_names(wm, area: str) -> tuple[str, ...]:
    """The world-model variables of one area (report 2.3.6), in the model's order."""
    return tuple(s.name for s in wm.specs if s.area == area)


def _value_text(spec, v, width: int = 70) -> str:
    import numpy as np
    a = np.asarray(v)
    if spec.value_text(v) is not None and a.ndim == 0:  # an enumeration or a bit set: by name (pfma/show.py)
        out = spec.value_text(v)
    elif spec.dtype == "u1" and a.ndim == 1 and a.size > 16:  # a text field (zero-padded UTF-8)
        text = bytes(a).rstrip(b"\0").decode(errors="replace").replace("\n", " | ")
        out = repr(text)
    elif a.ndim == 0:
        out = f"{a.item():.6g}" if spec.dtype.startswith("f") else str(a.item())
    else:
        out = np.array2string(a, precision=4, separator=" ", max_line_width=10_000, threshold=24,
                              suppress_small=True).replace("\n", "")
    return out if len(out) <= width else out[:width - 3] + "..."


def wm_browser(wm, area_index: int, page: int, cursor: int = 0, status: str = "") -> str:
    """One page of one world-model area, live values, who writes each and who may set it;
    ``>`` marks the variable under the cursor (Enter/``e`` modifies it), ``status`` is the
    last write's outcome or refusal."""
    from controller.worldmodel.spec import AREAS as WM_AREAS
    area = WM_AREAS[area_index % len(WM_AREAS)]
    names = browser_names(wm, area)
    pages = max(1, -(-len(names) // BROWSER_ROWS))
    page = page % pages
    shown = names[page * BROWSER_ROWS:(page + 1) * BROWSER_ROWS]
    values = wm.get_task_inputs(shown) if shown else {}
    tabs = "  ".join(f"[{a}]" if a == area else a for a in WM_AREAS)
    power = "powered up" if wm.powered_up else "powered down"
    lines = [f"world model {wm.name or '(private)'} ({power}): {tabs}",
             f"area {area}: {len(names)} variables, page {page + 1}/{pages}   <- -> area  pgup/pgdn page  "
             f"up/down select  Enter/e modify (USER rule, access key)  Escape/w close",
             f"  {'NAME':<30} {'TYPE':<9} {'WRITER':<18} {'USER':<13} VALUE"]
    for k, n in enumerate(shown):
        s = wm.spec(n)
        mark = ">" if k == cursor else " "
        lines.append(f"{mark} {n:<30} {s.type_text:<9} {s.writer:<18} {s.user:<13} {_value_text(s, values[n])}")
    if not shown:
        lines.append("(no variables in this area)")
    lines.append(status or "")
    return "\n".join(lines)


def browser_selected(wm, area_index: int, page: int, cursor: int) -> str | None:
    """The variable under the browser's cursor (None on an empty area)."""
    from controller.worldmodel.spec import AREAS as WM_AREAS
    names = browser_names(wm, WM_AREAS[area_index % len(WM_AREAS)])
    pages = max(1, -(-len(names) // BROWSER_ROWS))
    shown = names[(page % pages) * BROWSER_ROWS:(page % pages + 1) * BROWSER_ROWS]
    return shown[cursor % len(shown)] if shown else None


# --- the move-to screen (issue 30 item 5, docs/console.md "Move to") -------------------------
MOVE_HELP = ("type  pose X,Y,Z  (m, world; the tool keeps its orientation)\n"
             "      pose X,Y,Z,QW,QX,QY,QZ   joints D,D,D,D,D,D  (degrees, command order)   stop\n"
             "      add  turn DEG  to allow a larger tool rotation than msp.max_turn_rad\n"
             "Enter: check it   Enter again: send   Escape: close")


def move_screen(wm, status: str) -> str:
    """The move-to screen: where the tool is, the last move's answer, how to type a move."""
    import numpy as np
    from controller.paths import MspMode
    from controller.params import JOINT_NAMES
    names = ("joint.tool_pos_m", "joint.tool_quat", "daq.joint_angle_rad", "cart.mode", "msp.state",
             "msp.move_seq", "msp.move_done_seq", "msp.result_text", "msp.max_turn_rad", "msp.track_err_m",
             "msp.track_err_rad")
    if wm is None:
        return "MOVE TO: no controller world model (start the console with the controller's --wm)"
    try:
        v = wm.get_task_inputs(names)
    except Exception as err:  # noqa: BLE001 - a controller without moves: say so, do not die
        return f"MOVE TO: cannot read the controller's world model: {type(err).__name__}: {err}"
    p, q = v["joint.tool_pos_m"], v["joint.tool_quat"]
    j = v["daq.joint_angle_rad"]
    last = bytes(np.asarray(v["msp.result_text"], dtype=np.uint8)).rstrip(b"\0").decode(errors="replace")
    state = MspMode.NAMES.get(int(v["msp.state"]), "?")
    lines = [f"MOVE TO   tool ({float(p[0]):+.4f}, {float(p[1]):+.4f}, {float(p[2]):+.4f}) m  "
             f"q ({float(q[0]):+.4f}, {float(q[1]):+.4f}, {float(q[2]):+.4f}, {float(q[3]):+.4f})",
             "joints   " + "  ".join(f"{n} {math.degrees(float(a)):+.1f}" for n, a in zip(JOINT_NAMES, j)) + " deg",
             f"path planner {state}  move {int(v['msp.move_seq'])} (answered {int(v['msp.move_done_seq'])})  "
             f"cart.mode {int(v['cart.mode'])}  largest tool rotation {math.degrees(float(v['msp.max_turn_rad'])):.0f} "
             f"deg  tracking {float(v['msp.track_err_m']) * 1e3:.1f} mm / "
             f"{math.degrees(float(v['msp.track_err_rad'])):.2f} deg",
             f"last: {last or '-'}", "", MOVE_HELP]
    if status:
        lines += ["", status]
    return "\n".join(lines)
