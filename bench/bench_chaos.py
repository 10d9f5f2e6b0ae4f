"""The kill matrix (issue 20 item 1): every process of the stack SIGKILLed or SIGSTOPped at a
random point of its life, and what must hold afterwards checked in every trial.

Process kinds (:data:`KINDS`) and the stack each trial runs (every process a subprocess of
this venv's python, on a buffer named ``pfma-chaos-...``, unique per session):

=========== =================================================================================
service     ``pfma serve --rack fake --modbus 127.0.0.1:0`` + ``pfma controller --power-up
            --play`` + ``pfma record``; the victim is the service
controller  a service and a recorder; the victim is a controller flying a path
recorder    a service and a controller; the victim is ``pfma record``
console     a service and a controller; the victim is ``pfma console`` (the Textual console;
            its output goes to a file, so nothing is a terminal)
bridge      a service, ``pfma bridge --commands`` on tcp/127.0.0.1 and a controller runtime in
            another process on a RemoteClient through it; the victim is the bridge (the
            controller's link)
gateway     ``pfma gateway`` (the simulated rack behind Modbus TCP), ``pfma serve --bus
            modbus://...`` on it and a controller ``--no-ft``; the victim is the gateway
export      ``pfma serve --modbus`` (its Modbus export runs in its own process) and a
            controller; the victim is the export process
=========== =================================================================================

A trial (:class:`Trial`) is a kind, a phase of the victim's life (``start-up``: at a random
time after its launch; ``running``: the stack up and the arm flying; ``shutting down``: after
the victim was asked to stop with SIGINT, or SIGTERM for the export), an action (SIGKILL;
SIGSTOP, then SIGCONT after a random hold; SIGSTOP, then SIGKILL) and its random times.
:func:`plan` draws them from ``random.Random(f"{seed}/{kind}")``: trial *i* of a kind is the
same whatever ``--trials`` and whatever other kinds run, so a failure is replayed by its seed.

Checks (:class:`Outcome`, a name -> passed, detail):

``outputs_safe``   (a) controller, bridge: when the service was ARMED when the victim went,
                   the DAC outputs are 0 V (every channel, FAULT) within the watchdog plus one
                   frame of the last heartbeat the service saw, measured on the service's own
                   clock: the trip's time (its message's ``t_s``) minus the last heartbeat's
                   (``t_s - command_age_s`` of the frame that published the trip, a bound
                   that can only make the age look longer); every frame is read back from the
                   service's frame ring, none is sampled. When it was not ARMED: 0 V and not
                   ARMED in every frame after. For the gateway: FAULT and 0 V published
                   within the watchdog plus one frame of the kill.
``loss_reported``  (b) service: the controller says the service stopped publishing and
                   commands 0 (rates, current limits, no arm request) in the lost segment
``takeover``       (b) a new ``pfma serve`` on the same buffer name starts, and while the old
                   controller goes on writing to its old segment the new service is never
                   ARMED, nobody holds its command area and its outputs stay at 0 V (no
                   second writer obeyed); for the gateway, a new gateway and service
``export_gone``    (b) the killed service's Modbus export process exits with it
``reattach``       (c) the recorder goes on as a new session on the new service and ``pfma
                   read`` reads it; a new controller (recorder, console, bridge, export)
                   attaches where the victim was and works (the controller re-arms the
                   service, the recorder records frames, the console draws, the export
                   answers a Modbus read, the remote controller arms through a new bridge)
``unaffected``     killing a reader (recorder, console, export) does not trip the service
``recoverable``    (e) a killed recorder's file: ``pfma record recover`` rewrites it and
                   names the frames and gaps it recovered; the data lost is the time between
                   the last recovered frame and the kill (docs/recording.md: less than the
                   0.25 s flush period, plus what the recorder had not yet written)
``resumed``        a stopped and continued process goes on (the recorder lossless when the
                   hold was shorter than its frame ring)
``no_leftovers``   (d) after every process stopped in order, /dev/shm holds no file of the
                   session but the buffer and the world model a stopped service and
                   controller leave for tools by design (the bench removes those), and no
                   file any of the session's processes had mapped (zenoh's shared memory)
``clean_exits``    no traceback in any process's output; every process stops on SIGINT

Figures: trials, passes and failures (each with its cause) per kind; the trip ages and the
kill-to-0 V times; the recorder's lost seconds.

``pfma bench chaos [--trials N] [--seed S] [--kinds a,b]``: :data:`DEFAULT_TRIALS` trials
per kind by default (a few minutes); ``--trials 100`` for the issue's full matrix (hours).
Figures, never an assert (tests/chaos asserts).

Assumptions (named once here): a process's start-up lasts at most :data:`START_WINDOW_S`
(the start-up kill falls in that window after its launch; on a loaded host it may fall after
the start-up is over, and the trial says what the victim had reached); the service's ring
holds 256 frames (0.8 s at 320 Hz), read back :data:`SETTLE_S` after the kill.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import random
import re
import signal
import socket
import sys
import tempfile
import textwrap
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from pfma.process import Child, children, cmdline, free_port, host_timing_cause, listen_port, pid_alive, until

#: prefix of every buffer, world model and file this benchmark makes in /dev/shm
PREFIX = "pfma-chaos-"
KINDS = ("service", "controller", "recorder", "console", "bridge", "gateway", "export")
PHASES = ("start-up", "running", "shutting down")
ACTIONS = ("SIGKILL", "SIGSTOP+SIGCONT", "SIGSTOP+SIGKILL")
#: how often each action is drawn (SIGKILL twice as often as each SIGSTOP variant)
ACTION_WEIGHTS = (2, 1, 1)
#: start-up phase: the kill falls this long at most after the victim's launch (s; assumed:
#: a python process of this project imports and attaches in 1-3 s on the 2-vCPU VM)
START_WINDOW_S = {"service": 3.0, "controller": 3.0, "recorder": 2.0, "console": 3.0,
                  "bridge": 2.5, "gateway": 2.0, "export": 2.0}
#: running phase: the kill falls this long after the stack is up (s)
RUN_WINDOW_S = (0.1, 2.0)
#: shutting-down phase: the kill falls this long after the stop request (s)
STOP_WINDOW_S = (0.0, 0.4)
#: SIGSTOP: held this long before the SIGCONT or SIGKILL (s); the longest is past the
#: recorder's frame ring (0.8 s)
HOLD_S = (0.005, 1.5)
DEFAULT_TRIALS = 3
DEFAULT_SEED = 20
#: the service's command watchdog and frame rate (pfma serve's defaults, given explicitly)
WATCHDOG_S = 0.015
FRAME_RATE_HZ = 320.0
#: the bridge kind's service: a command watchdog and input age sized for a remote controller's
#: round trip through the bridge (``pfma serve --watchdog-ms 30 --max-input-age 9``, docs/bridge.md
#: "Sizing the command checks for the link"). With the defaults (15 ms, 4 frames) the far end's
#: Data Acquisition layer faulted on a stale command every second or two on a loaded 2-core
#: host (ages measured: 2-3 frames median, 5 and more in a few per cent of frames), so a far
#: end was rarely still flying when the kill came
LINK_WATCHDOG_S = 0.030
LINK_MAX_INPUT_AGE = 9
#: what the recorder may lose when killed: its flush period (docs/recording.md, "Crash
#: safety": less than --flush-s 0.25 s), plus the frames it had taken but not yet written,
#: which the frame ring lets lag by at most 255 frames (0.8 s)
RECORDER_FLUSH_S = 0.25
RING_S = 255 / FRAME_RATE_HZ
#: the gateway kind's service: a schedule the Modbus round trips on a loaded host can keep
#: (``pfma serve`` refuses 320 Hz over the gateway when the bus is measured too slow)
GATEWAY_SCHEDULE = ("--schedule", "slow")
#: what ``pfma read`` reads in the reattach check (a rack channel of the default rack)
READ_SIGNAL = "elbow_pitch_angle"
#: a gateway silent this long stops the service (ioservice.service.BUS_LOST_S)
BUS_LOST_S = 0.5
#: after a kill: the frames are judged this long after it (s)
SETTLE_S = 0.35
#: the ring watch reads the service's frame ring this often (s), and keeps this many frames
WATCH_POLL_S = 0.05
WATCH_KEEP = 20 * 320
#: waits for a state (a service publishing, a controller arming) give up after this (s)
WAIT_S = 30.0
#: each process must exit this long after SIGINT (then SIGKILL, and the trial says so)
STOP_TIMEOUT_S = 15.0
ARMED, FAULT, STOPPED = 2, 3, 4  # bit3.layout.ServiceState (imported lazily)
#: the service's command age limit (rack [commands] max_input_age_frames, default 4)
MAX_INPUT_AGE_FRAMES = 4
#: the service's watchdog trip message code (ioservice.safety.OutputGuard.trip(code=1))
TRIP_CODE = 1


@dataclass(frozen=True)
class Trial:
    """One kill: which process, when in its life, how (all drawn by :func:`plan`)."""

    kind: str
    index: int
    phase: str
    action: str
    at_s: float  #: the kill this long into the phase (s)
    hold_s: float  #: SIGSTOP actions: the hold before SIGCONT/SIGKILL (s)

    def describe(self) -> str:
        hold = f", held {self.hold_s * 1e3:.0f} ms" if self.action != "SIGKILL" else ""
        return f"{self.kind} #{self.index}: {self.action} {self.phase} +{self.at_s:.3f} s{hold}"


def plan(seed: int, trials: int, kinds: tuple[str, ...] = KINDS) -> list[Trial]:
    """The trials, reproducibly: trial i of a kind is drawn from ``Random(f"{seed}/{kind}")``
    after trials 0..i-1, so it does not depend on ``trials`` or on the other kinds."""
    out = []
    for kind in kinds:
        rng = random.Random(f"{seed}/{kind}")
        for i in range(trials):
            phase = rng.choice(PHASES)
            action = rng.choices(ACTIONS, weights=ACTION_WEIGHTS)[0]
            if phase == "start-up":
                at = rng.uniform(0.0, START_WINDOW_S[kind])
            elif phase == "running":
                at = rng.uniform(*RUN_WINDOW_S)
            else:
                at = rng.uniform(*STOP_WINDOW_S)
            hold = rng.uniform(*HOLD_S)
            out.append(Trial(kind, i, phase, action, round(at, 4), round(hold, 4)))
    return out


@dataclass
class Outcome:
    """What one trial found: checks (name -> (passed, detail)), figures, notes."""

    trial: Trial
    checks: dict[str, tuple[bool, str]] = field(default_factory=dict)
    figures: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def check(self, name: str, ok: bool, detail: str = "") -> bool:
        prev = self.checks.get(name)
        if prev is not None and not prev[0]:  # a failed check stays failed, with its first cause
            return ok
        self.checks[name] = (bool(ok), detail)
        return ok

    @property
    def passed(self) -> bool:
        return all(ok for ok, _ in self.checks.values())

    def failures(self) -> list[str]:
        return [f"{name}: {detail}" for name, (ok, detail) in self.checks.items() if not ok]

    def as_dict(self) -> dict:
        return {"trial": self.trial.describe(), "kind": self.trial.kind, "index": self.trial.index,
                "phase": self.trial.phase, "action": self.trial.action, "at_s": self.trial.at_s,
                "hold_s": self.trial.hold_s, "passed": self.passed,
                "checks": {k: {"ok": ok, "detail": d} for k, (ok, d) in self.checks.items()},
                "figures": self.figures, "notes": self.notes, "seconds": round(self.seconds, 2)}


# --------------------------------------------------------------------------- the frames


def frame_rows(ring, dtype, since: int = 0, rate_slots: list[int] | None = None) -> tuple[list[dict], int, int]:
    """The frames still whole in a service's frame ring from its ``since``-th publish on, as
    dicts of the fields the checks read; the number of publishes already overwritten (lost to
    us); the ring's publish count (the next ``since``).

    :param rate_slots: the DAC slots of the rate channels (``rate_vmax``: their largest volts)
    """
    import numpy as np
    n = ring.count()
    first = max(since, n - (ring.n_slots - 1))
    rows = []
    for k in range(first, n):
        data = ring.read(k)
        if data is None:
            continue
        r = np.ndarray((), dtype, buffer=data)
        rows.append({"frame": int(r["frame"]), "t_s": float(r["t_s"]), "state": int(r["service_state"]),
                     "fault": int(r["fault_code"]), "hb": int(r["command_heartbeat"]),
                     "age_s": float(r["command_age_s"]), "vmax": float(np.abs(r["dac_volts"]).max()),
                     "in_frame": int(r["command_inputs_frame"]),
                     "rate_vmax": float(np.abs(r["dac_volts"][rate_slots]).max()) if rate_slots else math.nan})
    return rows, max(0, first - since), n


def judge_outputs(rows: list[dict], messages: list, t_gone: float, *, watchdog_s: float = WATCHDOG_S,
                  period_s: float = 1.0 / FRAME_RATE_HZ, writer_returns: bool = False) -> tuple[bool, str, dict]:
    """Check (a) on the frames around the moment ``t_gone`` a command writer went (killed or
    stopped; the service's CLOCK_MONOTONIC, the host's).

    ARMED at that moment: the first frame published after it that is not ARMED must have
    every DAC channel at 0 V (FAULT by the watchdog, or SAFE when the writer's last command
    disarmed); the time the outputs went to 0 V (the service's watchdog message, else that
    frame's ``t_s``) minus the last heartbeat's time (``t_s - command_age_s`` of that frame:
    the age was taken after the frame's wake-up, so this can only make the age look longer)
    at most the watchdog plus one frame, and no frame after drives anything until the
    service is ARMED again by a new arm request (none comes from a dead writer). Not ARMED:
    every frame after is not ARMED and at 0 V; with ``writer_returns`` (SIGSTOP+SIGCONT: the
    writer, or its link, is only paused and may go on to arm with a new request) every frame
    after that is not ARMED is at 0 V. Returns (passed, detail, figures).

    :param messages: the service's messages (``bit3.buffer.Message``: ``t_s``, ``code``, ``text``)
    """
    before = [r for r in rows if r["t_s"] <= t_gone]
    after = [r for r in rows if r["t_s"] > t_gone]
    if not before or not after:
        return False, (f"the frame ring does not cover the kill ({len(before)} frames before, "
                       f"{len(after)} after)"), {}
    if before[-1]["state"] != ARMED:
        return _judge_unarmed(before[-1], after, writer_returns)
    return _judge_armed(rows, after, messages, t_gone, watchdog_s, period_s)


def _judge_unarmed(last: dict, after: list[dict], writer_returns: bool) -> tuple[bool, str, dict]:
    """:func:`judge_outputs` when the service was not ARMED at the kill (``last``: its last
    frame before): no output after (and no arming, unless the writer comes back)."""
    if writer_returns:  # a paused writer may arm once it runs again: only unarmed output is wrong
        bad = [r for r in after if r["state"] != ARMED and r["vmax"] > 0.0]
    else:
        bad = [r for r in after if r["state"] == ARMED or r["vmax"] > 0.0]
    fig = {"armed_at_kill": False}
    if bad:
        r = bad[0]
        return False, (f"not armed at the kill, yet frame {r['frame']} is "
                       f"{'ARMED' if r['state'] == ARMED else 'state %d' % r['state']} with "
                       f"{r['vmax']:.3f} V"), fig
    return True, f"not armed at the kill (state {last['state']}); 0 V in all {len(after)} frames after", fig


def _watchdog_trip(messages: list, hb_t: float, off: dict):
    """The service's last watchdog message (stale heartbeat) between the last heartbeat
    ``hb_t`` and the frame ``off`` that left ARMED, or None."""
    trip = [m for m in messages if m.code == TRIP_CODE and "stale heartbeat" in m.text
            and hb_t - 1e-3 <= m.t_s <= off["t_s"] + 1e-3]
    return trip[-1] if trip else None


def _wake_late(rows: list[dict], off: dict, period_s: float) -> float:
    """How late the service woke for the frame ``off`` (the host's, not the software's): the
    time since the frame just before it beyond one period; 0 when that frame is not in the
    ring."""
    prev = next((r for r in reversed(rows) if r["frame"] == off["frame"] - 1), None)
    late = 0.0 if prev is None else off["t_s"] - prev["t_s"] - period_s
    return late if late >= 1e-5 else 0.0  # below 10 us: on time (the clock's and float rounding)


def _judge_armed(rows: list[dict], after: list[dict], messages: list, t_gone: float, watchdog_s: float,
                 period_s: float) -> tuple[bool, str, dict]:
    """:func:`judge_outputs` when the service was ARMED at the kill: 0 V at the first frame
    that left ARMED, within the watchdog plus a frame of the last heartbeat, and nothing
    driven after.

    The bound is the software's: the first frame that finds the heartbeat older than the
    watchdog trips, and frames come every ``period_s``. A frame the host woke late (a VM's
    descheduled vCPU, even under SCHED_FIFO: CI saw 0 V 18.3 ms after the last heartbeat,
    the trip frame 0.2 ms late) adds its lateness, up to one more frame, said in the detail
    and the figures (``wake_late_ms``); later than that is a host stall and fails the trial."""
    off = next((r for r in after if r["state"] != ARMED), None)
    if off is None:
        return False, (f"still ARMED {after[-1]['t_s'] - t_gone:.3f} s after the kill "
                       f"(frame {after[-1]['frame']}, {after[-1]['vmax']:.3f} V)"), {"armed_at_kill": True}
    hb_t = off["t_s"] - off["age_s"]
    trip = _watchdog_trip(messages, hb_t, off)
    t_trip = trip.t_s if trip else off["t_s"]
    age = t_trip - hb_t
    fig = {"armed_at_kill": True, "trip_age_ms": round(age * 1e3, 2),
           "kill_to_0v_ms": round((t_trip - t_gone) * 1e3, 2)}
    late = min(_wake_late(rows, off, period_s), period_s)
    if late > 0.0:
        fig["wake_late_ms"] = round(late * 1e3, 2)
    text = trip.text if trip else "(no watchdog message)"
    return (*_trip_verdict(off, after, age, watchdog_s + period_s, text, late), fig)


def _trip_verdict(off: dict, after: list[dict], age: float, limit: float, text: str,
                  late: float = 0.0) -> tuple[bool, str]:
    """The verdict on a trip: ``off`` (the first frame not ARMED) at 0 V, no frame after it
    driving or ARMED, the outputs at 0 V ``age`` after the last heartbeat within ``limit``
    plus ``late`` (the host's lateness waking that frame); ``text``: the watchdog's message."""
    if off["vmax"] != 0.0:
        return False, (f"frame {off['frame']} left ARMED for state {off['state']} with {off['vmax']:.3f} V "
                       f"({text})")
    later = [r for r in after if r["t_s"] > off["t_s"] and (r["vmax"] > 0.0 or r["state"] == ARMED)]
    if later:
        return False, f"frame {later[0]['frame']} after the trip has {later[0]['vmax']:.3f} V"
    woke = f", the frame woke {late * 1e3:.1f} ms late" if late > 0.0 else ""
    if age > limit + late:
        why = "host stall named by the service" if "stall" in text else "late"
        return False, (f"{why}: 0 V {age * 1e3:.1f} ms after the last heartbeat > watchdog + one frame "
                       f"{limit * 1e3:.1f} ms{woke} ({text})")
    return True, f"0 V {age * 1e3:.1f} ms after the last heartbeat{woke} ({text})"


class RingWatch:
    """Every frame a service publishes, read from its frame ring by a thread every
    :data:`WATCH_POLL_S` (the ring holds 0.8 s, so none is missed while this process runs
    at least that often); the last :data:`WATCH_KEEP` frames are kept, and the time of the
    last ARMED frame."""

    def __init__(self, name: str, client) -> None:
        import collections
        import threading
        from bit3.ring import FrameRing
        self.ring = FrameRing.attach(name)
        self.dtype = _inputs_dtype(client)
        self.slots = _rate_slots(client)
        self.rows: collections.deque = collections.deque(maxlen=WATCH_KEEP)
        self.lost = 0  #: frames overwritten before this watch read them
        self.last_armed_t = -math.inf
        self._next = self.ring.count()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, name="chaos-ring-watch", daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.wait(WATCH_POLL_S):
            self.poll()

    def poll(self) -> None:
        with self._lock:
            rows, lost, self._next = frame_rows(self.ring, self.dtype, self._next, self.slots)
            self.lost += lost
            if rows:
                self.rows.extend(rows)
                armed = [r["t_s"] for r in rows if r["state"] == ARMED]
                if armed:
                    self.last_armed_t = armed[-1]

    def armed_since(self, t: float) -> bool:
        self.poll()
        return self.last_armed_t >= t

    def window(self, t0: float, t1: float) -> list[dict]:
        self.poll()
        with self._lock:
            return [r for r in self.rows if t0 <= r["t_s"] <= t1]

    def close(self) -> None:
        self._stop.set()
        self._t.join(2.0)
        self.ring.close()


# --------------------------------------------------------------------------- processes


class Proc(Child):
    """One subprocess of a trial (:class:`pfma.process.Child`): in its own process group,
    its output in a file; when it had to be killed and is a far end, it was asked first
    where it hung."""

    def __init__(self, role: str, argv: list[str], workdir: Path) -> None:
        super().__init__(role, argv, workdir)
        self.stop_t: float | None = None  #: when the trial asked it to stop (shutting-down phase)
        self.ready_t: float | None = None  #: when it was seen up (its trial's ready condition)

    def before_kill(self) -> None:
        """A far end (``REMOTE_CONTROLLER``) that did not exit: ask it to print its threads'
        stacks (faulthandler on SIGUSR1) into its output before it is killed."""
        if self.role != "remote":
            return
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGUSR1)
        time.sleep(0.5)


def hung_at(text: str) -> str:
    """Where each thread was in a faulthandler dump (``Proc.before_kill``): the innermost
    frame of each, as ``func (file:line)``; "" when ``text`` holds no dump."""
    where, want = [], False
    for line in text.splitlines():
        if line.startswith(("Thread 0x", "Current thread 0x")):
            want = True
        elif want and line.strip().startswith("File "):
            m = re.match(r'\s*File "([^"]+)", line (\d+) in (\S+)', line)
            if m:
                where.append(f"{m.group(3)} ({Path(m.group(1)).name}:{m.group(2)})")
            want = False
    return "; ".join(where)


#: the bridge trials' far ends start their rearm counter at REARM_SEED x (trial + 1), so
#: each trial's arm is its own. The session's last check runs two remote controllers that
#: do not seed it, one after the other: a RemoteCommander carries on from the command body
#: the bridge publishes (it once started at 0, and the second never armed: the service takes
#: an arm request only with a new counter)
REARM_SEED = 1000
#: far ends a bridge trial (killing the bridge while flying) and each of the final re-attach's
#: two checks start when one stops on a host-timing fault (``pfma.process.HOST_TIMING_CAUSE``:
#: missed service frames, or the service's watchdog on its late command, as CI saw once; as
#: tests/controller/_live_support.py power_up_holding does for a local controller)
REMOTE_ATTEMPTS = 3
#: a controller runtime on a RemoteClient through ``pfma bridge --commands`` (the bridge
#: kind's far end; one minor frame per inputs body received, a joint goal once started up;
#: argv: endpoint, buffer, [rearm counter seed], [--realtime])
REMOTE_CONTROLLER = textwrap.dedent("""
    import faulthandler, gc, signal, sys, time
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # the bench asks where it hangs before a SIGKILL
    stop = []
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # while connecting (blocked in zenoh): end at once
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    from controller.decision import Status
    from controller.layers import Request
    from controller.runtime import ControllerRuntime
    from pfma.clock import MonotonicClock
    from tools.bridge.remote import RemoteClient
    from tools.stacks.controller import LivePacer
    GC_EVERY_FRAMES = LivePacer.GC_EVERY_FRAMES
    from bit3.seqlock import Bit3Error
    try:  # a bridge killed or stopped in its start-up: one line, exit 1 (as a tool would)
        c = RemoteClient.connect(sys.argv[1], sys.argv[2], "chaos-remote-controller", timeout_s=30)
    except Bit3Error as err:
        print(f"remote controller: cannot connect: {err}", flush=True)
        sys.exit(1)
    if "--realtime" in sys.argv:  # as pfma controller --realtime: SCHED_FIFO on CPU 0, this
        # thread only: after the connect, so zenoh's threads (started by it) keep SCHED_OTHER
        # and every CPU (see RemoteClient)
        from ioservice.loop import realtime_setup
        realtime_setup(cpu=0)
    if len(sys.argv) > 3 and sys.argv[3].isdigit():  # the first arm request's counter - 1 (REARM_SEED)
        c.command["rearm_counter"] = int(sys.argv[3])
    try:  # the bridge gone before its first bodies: one line, exit 1
        c.remote.wait("inputs", timeout_s=30)
        rt = ControllerRuntime(c, clock=MonotonicClock())
    except Bit3Error as err:
        print(f"remote controller: no bodies from the bridge: {err}", flush=True)
        c.close()
        sys.exit(1)
    rt.request(Request.POWER_UP)
    flying = False
    signal.signal(signal.SIGTERM, lambda *a: stop.append(1))  # in the loop: finish, close the session
    signal.signal(signal.SIGINT, lambda *a: stop.append(1))
    said = None
    # the garbage collector as pfma controller keeps it (tools/stacks/controller.py): start-up's
    # objects frozen, no automatic collection inside a frame (an old-generation pass took the
    # far end's command past the service's input age), the young generations after a frame
    gc.collect()
    gc.freeze()
    gc.disable()
    ticks = 0
    while not stop:
        if not c.changed("inputs"):
            time.sleep(0.0002)
            continue
        rt.tick()
        ticks += 1
        if ticks % GC_EVERY_FRAMES == 0:
            gc.collect(1)
        if rt.first_cause is not None and rt.first_cause is not said:  # say a fault as it happens
            said = rt.first_cause
            print("fault: " + said.format(), flush=True)
        if not flying and rt.all_status(Status.START_UP_COMPLETE):
            q = [float(v) for v in rt.wm.get("daq.joint_angle_rad")]
            q[0] += 0.15
            rt.set_joint_goal(q)
            print("up", flush=True)
            flying = True
    rt.close()
    c.close()
    print("remote controller stopped", flush=True)
""")


def write_path(path_dir: Path, name: str = "chaos") -> str:
    """A small closed square (4 cm) around the simulated arm's start tool pose, for
    ``pfma controller --play``: the arm moves while a trial runs."""
    from controller.paths import PathStore, make_point
    x0, y0, z0 = 1.529, 0.0, -0.330  # the simulated arm's tool at its start pose (fk, m)
    q = (0.5, 0.5, 0.5, 0.5)
    pts = [make_point((x0 + dx, y0 + dy, z0), q, "teach")
           for dx, dy in ((0.0, 0.0), (0.02, 0.0), (0.02, 0.02), (0.0, 0.02), (0.0, 0.0))]
    store = PathStore(path_dir)
    if not store.exists(name):
        store.new(name, pts, note="pfma bench chaos/soak: a 2 cm square at the start pose")
    return name


class Session:
    """The processes of one kind's trials on one buffer name (unique), and their cleanup."""

    def __init__(self, kind: str, workdir: Path, realtime: bool = False) -> None:
        self.kind = kind
        #: the service's command watchdog and input age (the bridge kind's: the link's)
        self.watchdog_s = LINK_WATCHDOG_S if kind == "bridge" else WATCHDOG_S
        self._age: tuple[str, ...] = ("--max-input-age", str(LINK_MAX_INPUT_AGE)) if kind == "bridge" else ()
        self.realtime = realtime  #: the service and the controllers run with --realtime
        self.rt_flag: tuple[str, ...] = ("--realtime",) if realtime else ()
        self.name = f"{PREFIX}{kind[:4]}-{uuid.uuid4().hex[:6]}"
        self.wm = self.name + "-wm"
        self.workdir = workdir
        self.procs: list[Proc] = []
        self.path_dir = workdir / "paths"
        self.path = write_path(self.path_dir)
        self._client = None

    # ---- starting
    def start(self, role: str, argv: list[str]) -> Proc:
        p = Proc(role, argv, self.workdir)
        self.procs.append(p)
        return p

    def pfma(self, role: str, *args: str) -> Proc:
        return self.start(role, [sys.executable, "-m", "tools.cli", *args])

    def serve(self, *extra: str) -> Proc:
        return self.pfma("service", "serve", "--rack", "fake", "--buffer", self.name, "--watchdog-ms",
                         f"{self.watchdog_s * 1e3:g}", *self._age, *self.rt_flag, *extra)

    def controller(self, *extra: str) -> Proc:
        return self.pfma("controller", "controller", "--buffer", self.name, "--wm", self.wm, "--power-up",
                         "--play", self.path, "--path-dir", str(self.path_dir), "--messages", "0",
                         *self.rt_flag, *extra)

    def recorder(self, path: Path) -> Proc:
        return self.pfma("recorder", "record", str(path), "--buffer", self.name)

    # ---- reading the buffer
    def client(self, service: Proc | None = None, timeout_s: float = WAIT_S):
        """A read-only client of the buffer published by ``service`` (by its pid), once it
        publishes frames; None when it does not within ``timeout_s`` or exits."""
        from tools.attach import wait_for_frames
        c = self._client
        if c is not None:
            try:
                if (service is None or c.owners()["inputs"].pid == service.pid) and \
                        c.read_inputs().frame > 2 and not _replaced(c, self.name):
                    return c
            except Exception:  # noqa: BLE001 - a buffer being replaced
                pass
            c.close()
        self._client = wait_for_frames(self.name, 2, timeout_s=timeout_s, pid=None if service is None else service.pid,
                                       alive=service.alive if service is not None else lambda: True, poll_s=0.05)
        return self._client

    def ring(self):
        from bit3.ring import FrameRing
        return FrameRing.attach(self.name)

    def armed(self, c) -> bool:
        return c.read_inputs().service_state == ARMED

    # ---- the end
    def close(self, out: Outcome | None, order: tuple[str, ...]) -> None:
        """Stop every process in ``order`` of roles (then the rest), SIGINT and wait; check
        their output for tracebacks and /dev/shm for leftovers; remove what a stopped
        service and controller leave by design."""
        if self._client is not None:
            self._client.close()
            self._client = None
        for p in self.procs:
            p.note_maps()
        rank = {r: i for i, r in enumerate(order)}
        for p in sorted(self.procs, key=lambda p: rank.get(p.role, -1)):
            how = p.stop(signal.SIGTERM if p.role in ("remote", "export") else signal.SIGINT)
            if out is not None and how.startswith("needed SIGKILL") and not p.killed:
                out.check("clean_exits", False, f"{p.role} (pid {p.pid}) {how}; last output: {p.tail(3)}"
                          + (f"; it hung at: {hung_at(p.text())}" if hung_at(p.text()) else ""))
        for p in self.procs:
            p.close()
            if out is not None and "Traceback (most recent call last)" in p.text():
                tb = p.text().split("Traceback (most recent call last)", 1)[1].strip().splitlines()
                out.check("clean_exits", False, f"traceback in {p.role}'s output: {tb[-1] if tb else '?'}")
        if out is not None:
            out.check("clean_exits", True, "every process stopped, no traceback")
        self.check_leftovers(out)

    def check_leftovers(self, out: Outcome | None) -> None:
        from bit3.buffer import Bit3Buffer
        from controller.worldmodel import WorldModel
        stale = self._stale_files()
        gone_not, zenoh = self._mapped_files_left()
        if out is not None:
            _say_leftovers(out, stale, gone_not, zenoh)
        for f in stale:  # ours: remove, so the next trial starts clean
            with contextlib.suppress(OSError):
                os.unlink(f"/dev/shm/{f}")
        Bit3Buffer.unlink(self.name)
        WorldModel.remove_segment(self.wm)

    def _stale_files(self) -> list[str]:
        """The /dev/shm files of this session's name other than the buffer and the world
        model (a stopped service and controller leave those by design)."""
        mine = sorted(f for f in os.listdir("/dev/shm") if f.startswith(self.name))
        by_design = {self.name, self.wm}
        return [f for f in mine if f not in by_design]

    def _mapped_files_left(self) -> tuple[list[str], list[str]]:
        """The files of other names the processes mapped that are still there: the others
        (each with the roles that mapped it), zenoh's own ``.zenoh`` files."""
        left = {m: [p for p in self.procs if m in p.maps] for p in self.procs for m in p.maps
                if not Path(m).name.startswith(self.name) and os.path.exists(m)}
        gone_not = sorted(f"{m} (mapped by {', '.join(f'the {p.role}' for p in ps)})"
                          for m, ps in left.items() if not m.endswith(".zenoh"))
        zenoh = sorted(m for m in left if m.endswith(".zenoh"))
        return gone_not, zenoh


def _say_leftovers(out: Outcome, stale: list[str], gone_not: list[str], zenoh: list[str]) -> None:
    """The ``no_leftovers`` check of :meth:`Session.check_leftovers`, and a note for zenoh's files."""
    if zenoh:  # zenoh's own: the next zenoh session removes stale ones
        out.notes.append(f"zenoh shared-memory files still there after its processes stopped: "
                         f"{', '.join(zenoh)} (zenoh removes them when a zenoh session next starts)")
        out.figures["zenoh_files_left"] = len(zenoh)
    out.check("no_leftovers", not stale and not gone_not,
              "none" if not stale and not gone_not else
              f"left in /dev/shm: {', '.join(stale + gone_not)}")


def _replaced(client, name: str) -> bool:
    """The name now maps another segment than ``client``'s (a new service replaced it)."""
    try:
        st = os.stat(f"/dev/shm/{name}")
    except FileNotFoundError:
        return True
    try:
        return os.fstat(client.buffer.fd).st_ino != st.st_ino
    except (AttributeError, OSError):
        return False


def _signal_victim(p: Proc, trial: Trial) -> tuple[float, float]:
    """The trial's action on the victim, now: returns (time it went, time it came back or
    inf). SIGSTOP+SIGCONT: the process is continued after the hold (this call sleeps)."""
    if trial.action == "SIGKILL":
        t = p.send(signal.SIGKILL)
        p.wait_exit()
        return t, math.inf
    t = p.send(signal.SIGSTOP)
    time.sleep(trial.hold_s)
    if trial.action == "SIGSTOP+SIGCONT":
        return t, p.send(signal.SIGCONT)
    p.send(signal.SIGKILL)
    p.wait_exit()
    return t, math.inf


def _at_phase(trial: Trial, victim: Proc, ready: Callable[[], object], stop_sig: int = signal.SIGINT) -> str:
    """Wait for the trial's moment in the victim's life; returns what it had reached."""
    if trial.phase == "start-up":
        time.sleep(max(0.0, trial.at_s - (time.monotonic() - victim.t0)))
        if _safe(ready):
            victim.ready_t = time.monotonic()
            return "up"
        return "starting"
    got = until(ready, WAIT_S, must_live=(victim,))
    if not got:
        return "never up"
    victim.ready_t = time.monotonic()
    if trial.phase == "running":
        time.sleep(trial.at_s)
        return "up"
    victim.stop_t = time.monotonic()
    with contextlib.suppress(ProcessLookupError):
        os.kill(victim.pid, stop_sig)
    time.sleep(trial.at_s)
    return "stopping" if victim.alive() else "exited"


def _safe(f: Callable[[], object]) -> object:
    try:
        return f()
    except Exception:  # noqa: BLE001
        return None


def _service_messages(c) -> list:
    try:
        return c.messages(0, queue="service")
    except Exception:  # noqa: BLE001
        return []


def _outputs_check(out: Outcome, watch: RingWatch, c, t_gone: float, writer_returns: bool = False,
                   watchdog_s: float = WATCHDOG_S) -> None:
    """Check (a) on every frame from 1 s before ``t_gone`` to SETTLE_S after it."""
    time.sleep(max(0.0, t_gone + SETTLE_S - time.monotonic()))
    rows = watch.window(t_gone - 1.0, t_gone + SETTLE_S)
    ok, detail, fig = judge_outputs(rows, _service_messages(c), t_gone, writer_returns=writer_returns,
                                    watchdog_s=watchdog_s)
    out.figures.update(fig)
    out.figures["watchdog_ms"] = round(watchdog_s * 1e3, 3)
    out.check("outputs_safe", ok, detail)


def _pfma_read(name: str) -> tuple[int, str]:
    """``pfma read READ_SIGNAL --buffer NAME`` in this process: (exit code, output)."""
    from tools.cli import main
    buf_out, buf_err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(buf_out), contextlib.redirect_stderr(buf_err):
        rc = main(["read", READ_SIGNAL, "--buffer", name])
    return rc, (buf_out.getvalue() + buf_err.getvalue()).strip()


# --------------------------------------------------------------------------- the kinds


def _inputs_dtype(c):
    return c.layout.area("inputs").body_dtype


def _trial_service(trial: Trial, workdir: Path, out: Outcome, realtime: bool = False) -> None:
    """The victim is the service (with its Modbus export child); a controller flying and a
    recorder on it (running and shutting-down phases), a recorder waiting (start-up)."""
    sess = Session("service", workdir, realtime)
    rec_path = workdir / f"service-{trial.index}.mcap"
    try:
        svc = sess.serve("--modbus", "127.0.0.1:0")
        rec = sess.recorder(rec_path)
        ctl = None
        if trial.phase != "start-up":
            c = sess.client(svc)
            if c is None:
                out.check("setup", False, f"service never published: {svc.tail()}")
                return
            ctl = sess.controller()
            if not until(lambda: sess.armed(c), WAIT_S, must_live=(ctl, svc)):
                out.check("setup", False, f"never ARMED: controller {ctl.tail(3)}")
                return
        seen: list[int] = []  # the export's pid when the service was up: shutting down, it may be
        # gone before the kill (then it went with its service all the same)

        def up() -> int | None:
            k = _child_of(svc.pid)
            if k is not None:
                seen.append(k)
            return k
        reached = _at_phase(trial, svc, up)
        export = seen[-1] if seen else _child_of(svc.pid)
        out.notes.append(f"service {reached} at the {trial.action}")
        old = sess._client
        sess._client = None  # keep the old segment's client for the controller's side
        said_before = len(rec.text())  # the recorder's lines so far (about the old service)
        t_gone, t_back = _signal_victim(svc, trial)
        if trial.action == "SIGSTOP+SIGCONT":
            _service_resumed(out, sess, svc, old, t_gone, t_back, shutting_down=trial.phase == "shutting down")
            if old is not None:
                old.close()
            return
        svc2 = sess.serve()  # a new service on the same name takes over (started at once)
        # the service is dead: its export goes with it
        if export is not None:
            gone = until(lambda: not pid_alive(export), 5.0)
            out.check("export_gone", bool(gone), "the Modbus export exited with its service" if gone else
                      f"the Modbus export (pid {export}) still runs 5 s after its service died")
        if ctl is not None and old is not None:
            _controller_reports_loss(out, ctl, old)
        c2 = sess.client(svc2)
        if c2 is None:
            out.check("takeover", False, f"the new service never published: {svc2.tail()}")
            return
        _no_second_writer(out, c2, ctl)
        if old is not None:
            old.close()
        rc, text = _pfma_read(sess.name)
        out.check("reattach", rc == 0 and READ_SIGNAL in text, f"pfma read: exit {rc}: {text[-200:]}")
        said = until(lambda: re.search(r"recording continues as session \d+|recording /dev/shm",
                                        rec.text()[said_before:]), 15.0, must_live=(rec,))
        out.check("reattach", bool(said), "the recorder goes on: " + (said.group(0) if said else
                                                                         f"nothing in 15 s: {rec.tail(3)}"))
    finally:
        sess.close(out, order=("controller", "recorder", "service"))


def _child_of(pid: int) -> int | None:
    """The service ``pid``'s Modbus export process (its child), or None."""
    return next((k for k in children(pid) if "tools.modbus_export" in cmdline(k)), None)


def _controller_reports_loss(out: Outcome, ctl: Proc, old) -> None:
    """(b) The controller says the service stopped publishing and commands 0."""
    def said():
        return [m.text for m in old.messages(0, queue="controller") if "service not publishing" in m.text
                or "service STOPPED" in m.text or "fault 32" in m.text]
    got = until(said, 5.0, must_live=(ctl,))
    if not got:
        out.check("loss_reported", False, "the controller did not say the service stopped publishing within 5 s"
                  + ("" if ctl.alive() else f" (it exited: {ctl.tail(3)})"))
        return

    def zero():
        cmd = old.read_commands()
        return (not int(cmd.arm_request) and not any(float(x) for x in cmd.joint_rate_rad_s)
                and not any(float(x) for x in cmd.current_limit_a))
    z = until(zero, 2.0, must_live=(ctl,))
    out.check("loss_reported", bool(z), f"{got[0]}; commands 0" if z else
              f"{got[0]}; but its commands are not 0 (arm request, rates, current limits) 2 s later")


def _no_second_writer(out: Outcome, c2, ctl: Proc | None, watch_s: float = 1.0) -> None:
    """(b) While the old controller lives, the new service is never ARMED, its command area
    has no claim and its outputs stay at 0 V."""
    import numpy as np
    end = time.monotonic() + watch_s
    bad = None
    while time.monotonic() < end and bad is None:
        s = c2.read_inputs()
        owner = c2.owners().get("commands")
        if s.service_state == ARMED or float(np.abs(s.dac_volts).max()) > 0.0:
            bad = f"the new service is state {s.service_state} with {float(np.abs(s.dac_volts).max()):.3f} V"
        elif owner is not None and owner.pid > 0 and ctl is not None and owner.pid == ctl.pid:
            bad = f"the old controller (pid {ctl.pid}) holds the new buffer's command area"
        elif int(s.foreign_writes):
            bad = f"foreign writes {int(s.foreign_writes)} at the new service"
        time.sleep(0.01)
    alive = "" if ctl is None else (" while the old controller goes on" if ctl.alive() else
                                    " (the old controller had exited)")
    out.check("takeover", bad is None, bad or f"the new service SAFE at 0 V, command area unclaimed{alive}")


def _service_resumed(out: Outcome, sess: Session, svc: Proc, c, t_gone: float, t_back: float,
                     shutting_down: bool = False) -> None:
    """A stopped and continued service publishes again and never drives a rate from a
    command older than the age limit (its freshness rule, checked from outside). One that
    was already shutting down (SIGINT before the SIGSTOP) goes on with its shutdown instead:
    it exits 0 with its last frame STOPPED and every DAC channel at 0 V (the 100-trial matrix
    counted 6 of those as failures for not publishing again)."""
    if c is None:
        c = sess.client(svc, timeout_s=10)
    if c is None:
        out.check("resumed", False, f"no buffer to read: {svc.tail()}")
        return
    if shutting_down:
        import numpy as np
        ended = until(lambda: not svc.alive(), STOP_TIMEOUT_S)
        s = c.read_inputs()
        volts = float(np.abs(s.dac_volts).max())
        ok = bool(ended) and svc.p.returncode == 0 and int(s.service_state) == STOPPED and volts == 0.0
        out.check("resumed", ok, "its shutdown went on after a %.0f ms hold: exit 0, STOPPED, 0 V"
                  % ((t_back - t_gone) * 1e3) if ok else
                  f"the shutdown after SIGCONT: exit {svc.p.returncode if ended else 'none (still running)'}, "
                  f"state {int(s.service_state)}, DAC {volts:.3f} V max: {svc.tail()}")
        return
    k0 = c.read_inputs().frame
    moved = until(lambda: c.read_inputs().frame > k0 + 10, 10.0, must_live=(svc,))
    if not moved:
        out.check("resumed", False, f"the service did not publish again after SIGCONT: {svc.tail()}")
        return
    time.sleep(0.2)
    rows, _, _ = frame_rows(sess.ring(), _inputs_dtype(c), 0, _rate_slots(c))
    stale = [r for r in rows if r["t_s"] > t_back and r["state"] == ARMED and r["rate_vmax"] > 0.0
             and r["frame"] - r["in_frame"] > MAX_INPUT_AGE_FRAMES]
    out.check("resumed", not stale, "publishing again after a %.0f ms hold" % ((t_back - t_gone) * 1e3)
              if not stale else f"frame {stale[0]['frame']} drove a command {stale[0]['frame'] - stale[0]['in_frame']} "
                                "frames old")


def _rate_slots(c) -> list[int]:
    """The DAC slots of the joints' rate commands (the channels the freshness rule zeroes)."""
    lay = c.layout
    return [lay.joint_entry("dac", j, "rate_command").slot for j in lay.joint_names]


def _trial_controller(trial: Trial, workdir: Path, out: Outcome, sess: Session, ctx: dict) -> None:
    """The victim is a controller flying a path on a service that runs through all the
    controller trials; the next controller must arm the service again."""
    svc = ctx["service"]
    c = sess.client(svc)
    if c is None:
        out.check("setup", False, f"service not publishing: {svc.tail()}")
        return
    watch = ctx.get("watch") or ctx.setdefault("watch", RingWatch(sess.name, c))
    ctl = sess.controller()
    reached = _at_phase(trial, ctl, lambda: watch.armed_since(ctl.t0))
    out.notes.append(f"controller {reached} at the {trial.action}, service state {c.read_inputs().service_state}")
    if reached == "never up":
        out.check("reattach", False, f"the controller never armed the service: {ctl.tail(3)}")
    elif trial.index > 0 or reached == "up":
        out.check("reattach", True, "a new controller armed the service")
    t_gone, t_back = _signal_victim(ctl, trial)
    _outputs_check(out, watch, c, t_gone, writer_returns=trial.action == "SIGSTOP+SIGCONT")
    ctl.stop()


def _trial_recorder(trial: Trial, workdir: Path, out: Outcome, sess: Session, ctx: dict) -> None:
    """The victim is ``pfma record``; a service and a flying controller go on."""
    svc = ctx["service"]
    c = sess.client(svc)
    if c is None:
        out.check("setup", False, f"service not publishing: {svc.tail()}")
        return
    path = workdir / f"rec-{trial.index}.mcap"
    rec = sess.recorder(path)
    k0, t0 = c.read_inputs().frame, time.monotonic()
    reached = _at_phase(trial, rec, lambda: "recording /dev/shm" in rec.text() and path.exists()
                        and path.stat().st_size > 0)
    out.notes.append(f"recorder {reached} at the {trial.action}")
    if reached == "never up":
        out.check("reattach", False, f"the recorder never started: {rec.tail(3)}")
        return
    t_gone, t_back = _signal_victim(rec, trial)
    if trial.action == "SIGSTOP+SIGCONT":
        time.sleep(0.5)
        rec.stop()
        _recorder_summary(out, rec, path, trial)
    else:
        _recoverable(out, sess, path, t_gone, reached, rec.ready_t)
    _unaffected(out, c, k0, t0)


def _trips_since(c, t0: float) -> list[str]:
    """The service's trip messages ("outputs safe: ...", "outputs NOT known safe: ...") posted since ``t0``."""
    from ioservice.safety import TRIP_PREFIXES
    return [m.text for m in _service_messages(c) if m.t_s >= t0 and m.text.startswith(TRIP_PREFIXES)]


def _unaffected(out: Outcome, c, k0: int, t0: float) -> None:
    """Killing a reader does not stop the service; a trip meanwhile is noted with its cause
    (a reader cannot trip the service: it never writes; a loaded host can)."""
    k = c.read_inputs().frame
    trips = _trips_since(c, t0)
    out.check("unaffected", k > k0, f"the service went on (frame {k0} -> {k})")
    if trips:
        out.notes.append(f"{len(trips)} service trips during the trial (not the victim's: it never writes): "
                         f"{trips[-1]}")


def _recorder_summary(out: Outcome, rec: Proc, path: Path, trial: Trial) -> None:
    from tools.recording.reader import read_metadata
    try:
        s = read_metadata(path).get("pfma.recorder.summary", {})
    except Exception as err:  # noqa: BLE001
        out.check("resumed", False, f"the continued recorder's file has no summary: {type(err).__name__}: {err}")
        return
    missed = int(s.get("recorder_missed", -1))
    out.figures["recorder_missed"] = missed
    if trial.hold_s < RING_S - 0.2:
        out.check("resumed", missed == 0, f"held {trial.hold_s:.2f} s < its ring: recorder_missed {missed}")
    else:
        out.check("resumed", missed >= 0, f"held {trial.hold_s:.2f} s: recorder_missed {missed}, lossless "
                                          f"{s.get('lossless')} (said, not hidden)")


def _recoverable(out: Outcome, sess: Session, path: Path, t_gone: float, reached: str,
                 t_ready: float | None) -> None:
    """(e) ``pfma record recover`` on the killed recorder's file: it rewrites it and names
    the frames and gaps it recovered, or (a file cut before its first chunk) says in one
    clear message that nothing is recoverable; what was lost is at most the flush period
    plus what the recorder had taken but not written (its ring)."""
    from tools.cli import main
    bound = RECORDER_FLUSH_S + RING_S
    recorded_for = t_gone - t_ready if t_ready is not None else 0.0  # it recorded at most this long
    if not path.exists() or path.stat().st_size == 0:
        out.check("recoverable", reached != "up" or recorded_for <= bound,
                  f"killed {reached} {recorded_for:.2f} s after it started: no file written "
                  f"({'absent' if not path.exists() else 'empty'})")
        return
    fixed = path.with_name(path.stem + "-fixed.mcap")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        rc = main(["record", "recover", str(path), "-o", str(fixed)])
    text = buf.getvalue().strip()
    if "Traceback" in text:
        out.check("recoverable", False, f"recover printed a traceback: {text[-300:]}")
        return
    if rc != 0:  # a file cut before its first chunk: one clear message, exit 1
        ok = "no message recoverable" in text and recorded_for <= bound
        out.check("recoverable", ok, f"killed {reached} {recorded_for:.2f} s after it started recording: recover "
                  f"exit {rc}: {text.splitlines()[-1]}" + ("" if ok else f" (recorded for more than {bound:.2f} s)"))
        return
    m = re.search(r"recovered (\d+) messages \((\d+) frames, (\d+) frame gaps\)", text)
    if not m:
        out.check("recoverable", False, f"recover did not name what it recovered: {text[:300]}")
        return
    last_t = _last_frame_t(fixed)
    lost = t_gone - last_t if last_t is not None else recorded_for
    out.figures["recorder_lost_s"] = round(lost, 3)
    ok = lost <= bound
    out.check("recoverable", ok, f"{m.group(0)}; lost the last {lost:.3f} s before the kill"
              + ("" if ok else f" > {bound:.2f} s (flush period + ring)"))


def _last_frame_t(path: Path) -> float | None:
    """t_s of the last raw inputs frame in a (whole) recording."""
    from mcap.reader import make_reader
    from tools.recording.schema import RAW_TOPIC
    last = None
    with open(path, "rb") as f:
        for _schema, _ch, msg in make_reader(f).iter_messages(topics=[RAW_TOPIC]):
            last = msg
    if last is None:
        return None
    from tools.recording.reader import read_metadata
    try:
        off = int(read_metadata(path).get("pfma.recording", {}).get("epoch_offset_ns", 0))
    except Exception:  # noqa: BLE001
        off = 0
    return (last.log_time - off) / 1e9


def _trial_console(trial: Trial, workdir: Path, out: Outcome, sess: Session, ctx: dict) -> None:
    """The victim is ``pfma console`` (its Textual display written to a file)."""
    svc = ctx["service"]
    c = sess.client(svc)
    if c is None:
        out.check("setup", False, f"service not publishing: {svc.tail()}")
        return
    con = sess.pfma("console", "console", "--buffer", sess.name, "--wm", sess.wm)
    k0, t0 = c.read_inputs().frame, time.monotonic()
    reached = _at_phase(trial, con, lambda: "Local Status" in con.text())
    out.notes.append(f"console {reached} at the {trial.action}")
    if reached == "never up":
        out.check("reattach", False, f"the console never drew: {con.tail(2)[-300:]}")
    elif trial.index > 0 or reached == "up":
        out.check("reattach", True, "a new console drew its areas")
    _signal_victim(con, trial)
    time.sleep(0.3)
    _unaffected(out, c, k0, t0)
    con.stop()


def _trial_export(trial: Trial, workdir: Path, out: Outcome, sess: Session, ctx: dict) -> None:
    """The victim is the Modbus export process: first ``pfma serve --modbus``'s own, then
    the one this benchmark started in its place (``python -m tools.modbus_export``)."""
    svc = ctx["service"]
    c = sess.client(svc)
    if c is None:
        out.check("setup", False, f"service not publishing: {svc.tail()}")
        return
    k0, t0 = c.read_inputs().frame, time.monotonic()
    cur = ctx.get("export")
    if trial.phase == "start-up" or cur is None:
        victim = _start_export(sess)
        ready = (lambda: _modbus_port(victim) is not None)
    else:
        victim = cur
        ready = (lambda: True)
    reached = _at_phase(trial, victim, ready, stop_sig=signal.SIGTERM)
    out.notes.append(f"export {reached} at the {trial.action}")
    port = _modbus_port(victim)
    _signal_victim(victim, trial)
    if trial.action == "SIGSTOP+SIGCONT" and victim.alive():
        ans = _modbus_read(port) if port else None
        out.check("resumed", ans is not None or reached != "up",
                  "answers again after SIGCONT" if ans is not None else f"no answer after SIGCONT ({reached})")
        ctx["export"] = victim
    else:
        new = _start_export(sess)
        p = until(lambda: _modbus_port(new), 20.0, must_live=(new,))
        ans = _modbus_read(p) if p else None
        out.check("reattach", ans is not None, f"a new export answers a Modbus read (port {p})" if ans is not None
                  else f"the new export does not answer: {new.tail(3)}")
        ctx["export"] = new
    _unaffected(out, c, k0, t0)


class _Adopted(Proc):
    """A process this benchmark did not start (the service's export child), seen as a Proc."""

    def __init__(self, role: str, pid: int, port: int | None = None) -> None:  # no Popen
        self.role = role
        self.port = port
        self.argv = []
        self._pid = pid
        self.t0 = time.monotonic()
        self.stopped = self.killed = False
        self.exit_how = ""
        self.maps = set()
        self.stop_t = None
        self.ready_t = None
        self.log_path = Path("/dev/null")

    @property
    def pid(self) -> int:  # type: ignore[override]
        return self._pid

    def alive(self) -> bool:
        return pid_alive(self._pid)

    def wait_exit(self, timeout_s: float = 10.0) -> bool:
        return bool(until(lambda: not pid_alive(self._pid), timeout_s))

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = STOP_TIMEOUT_S) -> str:
        if self.alive():
            with contextlib.suppress(ProcessLookupError):
                os.kill(self._pid, signal.SIGCONT)
                os.kill(self._pid, sig)
        return "adopted"

    def text(self) -> str:
        return ""

    def close(self) -> None:
        pass


def _start_export(sess: Session) -> Proc:
    return sess.start("export", [sys.executable, "-m", "tools.modbus_export", "--buffer", sess.name,
                                 "--listen", "127.0.0.1:0"])


def _modbus_port(p: Proc) -> int | None:
    if isinstance(p, _Adopted):
        return p.port
    m = re.search(r"modbus-export listening.*:(\d+)", p.text())
    return int(m.group(1)) if m else None


def _modbus_read(port: int, timeout_s: float = 3.0) -> bytes | None:
    """One Modbus TCP read (fc 4, input register 0, count 1): the answer, or None."""
    import struct
    req = struct.pack(">HHHBBHH", 7, 0, 6, 1, 4, 0, 1)
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as s:
            s.sendall(req)
            data = s.recv(256)
    except OSError:
        return None
    return data if len(data) >= 9 and data[7] == 4 else None


def _trial_bridge(trial: Trial, workdir: Path, out: Outcome, sess: Session, ctx: dict) -> None:
    """The victim is ``pfma bridge --commands``, the link of a remote controller."""
    svc = ctx["service"]
    c = sess.client(svc)
    if c is None:
        out.check("setup", False, f"service not publishing: {svc.tail()}")
        return
    for r in [p for p in sess.procs if p.role == "remote" and p.alive()]:
        r.stop(signal.SIGTERM)  # the last trial's far end (its bridge is gone)
    watch = ctx.get("watch") or ctx.setdefault("watch", RingWatch(sess.name, c))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bridge = sess.pfma("bridge", "bridge", "--buffer", sess.name, "--listen", endpoint, "--commands")
    for attempt in range(1, REMOTE_ATTEMPTS + 1):
        # the first far end seeds its re-arm counter (its arm is its own); one started again
        # carries on from the command area's ("-"), as the service takes a counter only once
        seed = str(REARM_SEED * (trial.index + 1)) if attempt == 1 else "-"
        remote = sess.start("remote", [sys.executable, "-c", REMOTE_CONTROLLER, endpoint, sess.name, seed,
                                       *sess.rt_flag])
        reached = _at_phase(trial, bridge, lambda: watch.armed_since(remote.t0) and "up" in remote.text())
        if trial.phase != "running" or attempt == REMOTE_ATTEMPTS or not host_timing_cause(remote.text()):
            break
        # flying, the far end stopped by a host-timing fault before the kill (servo fault 12, or
        # the service's watchdog on its late command, on a loaded host, by design): the kill
        # must find the arm flying, so a new one
        out.notes.append(f"far end, attempt {attempt}: {remote.tail(1)}; started again")
        remote.stop(signal.SIGTERM)
    for p in (bridge, remote):
        p.note_maps()
    out.notes.append(f"bridge {reached} at the {trial.action}, service state {c.read_inputs().service_state}")
    if reached == "never up":
        out.check("reattach", False, f"the remote controller never armed the service: {remote.tail(3)} / "
                                     f"bridge: {bridge.tail(3)}")
    elif trial.index > 0 or reached == "up":
        out.check("reattach", True, "a new bridge and its remote controller armed the service")
    t_gone, _ = _signal_victim(bridge, trial)
    _outputs_check(out, watch, c, t_gone, writer_returns=trial.action == "SIGSTOP+SIGCONT",
                   watchdog_s=sess.watchdog_s)
    bridge.stop()


def _trial_gateway(trial: Trial, workdir: Path, out: Outcome, realtime: bool = False) -> None:
    """The victim is ``pfma gateway`` (the simulated rack behind Modbus TCP) under a service:
    the service must publish FAULT at 0 V within the watchdog plus one frame of the kill
    (latched: nothing is driven when the rack answers again until a re-arm), stop with one
    line when the bus stays silent (a gateway stopped for less than BUS_LOST_S: it rides
    through, latched safe); a new gateway and service take over. (No controller: over a
    loaded host's loopback Modbus the controller's hardware checks flap and it does not
    power up; the service's reaction to its bus is what this kind measures.)"""
    sess = Session("gateway", workdir, realtime)
    watch = None
    try:
        port = free_port()
        gw = sess.pfma("gateway", "gateway", "--listen", f"127.0.0.1:{port}")
        url = f"modbus://127.0.0.1:{port}"
        svc = None
        c = None
        if trial.phase != "start-up":
            svc, c = _gateway_service(sess, gw, url, out)
            if c is None:
                return
        watch = RingWatch(sess.name, c) if c is not None else None
        reached = _at_phase(trial, gw, lambda: "Ctrl-C stops" in gw.text())
        out.notes.append(f"gateway {reached} at the {trial.action}")
        t_gone, t_back = _signal_victim(gw, trial)
        if svc is not None and watch is not None:
            _gateway_outputs_check(trial, out, gw, c, watch, t_gone)
            watch.close()
            _gateway_service_after(trial, out, svc, c, t_gone, t_back)
        # a new gateway and service take over (the old controller is left on the old segment)
        _gateway_takeover(trial, sess, out, gw, svc, port, url)
    finally:
        if watch is not None:
            watch.close()
        sess.close(out, order=("controller", "service", "gateway"))


def _gateway_service(sess: Session, gw: Proc, url: str, out: Outcome):
    """Once the gateway is up, a service over it that publishes: (service, its client), the
    client None (a failed ``setup`` check) when either does not come."""
    if not until(lambda: "Ctrl-C stops" in gw.text(), WAIT_S, must_live=(gw,)):
        out.check("setup", False, f"gateway did not start: {gw.tail()}")
        return None, None
    svc = sess.serve("--bus", url, *GATEWAY_SCHEDULE)
    c = sess.client(svc)
    if c is None:
        out.check("setup", False, f"service over the gateway never published: {svc.tail()}")
    return svc, c


def _gateway_outputs_check(trial: Trial, out: Outcome, gw: Proc, c, watch: RingWatch, t_gone: float) -> None:
    """The ``outputs_safe`` check of a gateway trial: FAULT at 0 V published within the
    watchdog plus a frame of the kill (or of the gateway's SIGINT, when it stopped answering
    while shutting down, before the kill)."""
    time.sleep(max(0.0, t_gone + SETTLE_S - time.monotonic()))
    after = watch.window(t_gone, t_gone + SETTLE_S)
    first = next((r for r in after if r["state"] == FAULT and r["vmax"] == 0.0), None)
    period = float(_safe(lambda: c.read_stats()["period_s"]) or 1.0 / FRAME_RATE_HZ)
    limit = WATCHDOG_S + period
    early = [r for r in watch.window(gw.stop_t or t_gone, t_gone) if r["state"] == FAULT]
    if early:  # shutting down: it stopped answering after its SIGINT, before the kill
        dt = early[0]["t_s"] - (gw.stop_t or t_gone)
        out.check("outputs_safe", dt <= limit and all(r["vmax"] == 0.0 for r in early + after),
                  f"FAULT at 0 V published {dt * 1e3:.1f} ms after the gateway was asked to stop "
                  f"(before the {trial.action})")
    elif first is None:
        out.check("outputs_safe", False, f"no FAULT at 0 V published after the gateway died "
                                         f"({len(after)} frames after)")
    else:
        dt = first["t_s"] - t_gone
        out.figures["kill_to_0v_ms"] = round(dt * 1e3, 2)
        out.check("outputs_safe", dt <= limit, f"FAULT at 0 V published {dt * 1e3:.1f} ms after the kill"
                  + ("" if dt <= limit else f" > {limit * 1e3:.1f} ms"))


def _gateway_service_after(trial: Trial, out: Outcome, svc: Proc, c, t_gone: float, t_back: float) -> None:
    """What the service did after the gateway went: a short stop (SIGSTOP+SIGCONT well under
    BUS_LOST_S) ridden through latched safe (``resumed``); a gateway gone for good (or well
    over BUS_LOST_S) makes it stop saying so (``takeover``); near BUS_LOST_S neither is checked."""
    stopped_s = t_back - t_gone
    paused = trial.phase != "shutting down" and trial.action == "SIGSTOP+SIGCONT"
    if paused and stopped_s < BUS_LOST_S - 0.1:
        time.sleep(0.5)  # the bus answers again: the service rides through, latched safe
        st = _safe(lambda: c.read_inputs().service_state)
        out.check("resumed", svc.alive() and st != ARMED,
                  f"the service rode through a {stopped_s * 1e3:.0f} ms gateway stop (state {st})"
                  if svc.alive() else f"the service stopped: {svc.tail(2)}")
    elif not paused or stopped_s > BUS_LOST_S + 0.1:
        ended = until(lambda: not svc.alive(), 10.0)
        said = "stopped answering" in svc.text() or "bus lost" in svc.text()
        out.check("takeover", bool(ended) and said,
                  f"the service stopped, saying the bus stopped answering (exit {svc.p.returncode})"
                  if ended and said else
                  f"the service {'ran on' if not ended else 'stopped without saying bus lost'}: "
                  f"{svc.tail(2)}")


def _gateway_takeover(trial: Trial, sess: Session, out: Outcome, gw: Proc, svc: Proc | None,
                      port: int, url: str) -> None:
    """A new gateway (unless the old one was only paused and runs) and a new service over it
    must publish (the ``reattach`` check)."""
    if trial.action != "SIGSTOP+SIGCONT" or not gw.alive():
        gw.stop()
        gw2 = sess.pfma("gateway", "gateway", "--listen", f"127.0.0.1:{port}")
        if not until(lambda: "Ctrl-C stops" in gw2.text(), WAIT_S, must_live=(gw2,)):
            out.check("reattach", False, f"a new gateway on port {port} did not start: {gw2.tail(2)}")
            return
    if svc is not None and svc.alive():
        svc.stop()
    svc2 = sess.serve("--bus", url, *GATEWAY_SCHEDULE)
    c2 = sess.client(svc2)
    out.check("reattach", c2 is not None, "a new service publishes over the new gateway" if c2 is not None
              else f"the new service never published: {svc2.tail(2)}")


# --------------------------------------------------------------------------- sessions


#: kinds whose trials share one stack (a service, a controller) that runs through them
SHARED = {"controller": _trial_controller, "recorder": _trial_recorder, "console": _trial_console,
          "export": _trial_export, "bridge": _trial_bridge}
#: kinds whose trials each start their own stack
OWN = {"service": _trial_service, "gateway": _trial_gateway}


#: kinds whose trials share one stack, run one after another on it (readers that leave
#: the service and its controller running share one)
GROUPS: tuple[tuple[str, ...], ...] = (("controller",), ("recorder", "console", "export"), ("bridge",))


def _run_shared(kinds: tuple[str, ...], trials: list[Trial], workdir: Path, progress,
                realtime: bool = False) -> list[Outcome]:
    """The trials of ``kinds`` on one stack: a service (``--modbus`` when the export is a
    victim), a controller flying for the readers' kinds; each trial starts its victim."""
    sess = Session(kinds[0], workdir, realtime)
    ctx: dict = {}
    outs: list[Outcome] = []
    try:
        svc = sess.serve(*(("--modbus", "127.0.0.1:0") if "export" in kinds else ()))
        ctx["service"] = svc
        c = sess.client(svc)
        if c is None:
            for t in trials:
                o = Outcome(t)
                o.check("setup", False, f"the session's service never published: {svc.tail()}")
                outs.append(o)
            return outs
        if set(kinds) & {"recorder", "console", "export"}:
            ctl = sess.controller()
            if not until(lambda: sess.armed(c), WAIT_S, must_live=(ctl, svc)):
                ctx["note"] = f"the session's controller did not arm the service: {ctl.tail(2)}"
        if "export" in kinds:
            pid = until(lambda: _child_of(svc.pid), 10.0)
            if pid:
                ctx["export"] = _Adopted("export", pid, until(lambda: listen_port(pid), 10.0))
        for t in trials:
            o = Outcome(t)
            t0 = time.monotonic()
            try:
                SHARED[t.kind](t, workdir, o, sess, ctx)
            except Exception as err:  # noqa: BLE001 - the trial's failure, never a traceback out
                o.check("bench", False, f"{type(err).__name__}: {err}")
            if "note" in ctx:
                o.notes.append(ctx.pop("note"))
            o.seconds = time.monotonic() - t0
            outs.append(o)
            if progress:
                progress(o)
        for kind in ("controller", "bridge"):
            last = [o for o in outs if o.trial.kind == kind]
            if last:
                _final_reattach(kind, sess, ctx, last[-1])
    finally:
        if ctx.get("watch") is not None:
            ctx["watch"].close()
        sess.close(outs[-1] if outs else None,
                   order=("remote", "bridge", "console", "export", "recorder", "controller", "service"))
    return outs


def _final_reattach(kind: str, sess: Session, ctx: dict, out: Outcome) -> None:
    """After the last controller/bridge trial: a new one must arm the service again."""
    c = sess.client(ctx["service"])
    if c is None:
        out.check("reattach", False, "the service stopped publishing")
        return
    for r in [p for p in sess.procs if p.role == "remote" and p.alive()]:
        r.stop(signal.SIGTERM)
    watch = ctx.get("watch") or ctx.setdefault("watch", RingWatch(sess.name, c))
    if kind == "controller":
        _reattach_controller(sess, watch, out)
        return
    for i in (1, 2):  # two far ends that do not seed their rearm counter, each through a new bridge
        _reattach_far_end(i, sess, c, watch, out)


def _reattach_controller(sess: Session, watch: RingWatch, out: Outcome) -> None:
    """A new controller must arm the service after the last controller trial."""
    ctl = sess.controller()
    ok = until(lambda: watch.armed_since(ctl.t0), WAIT_S, must_live=(ctl,))
    out.check("reattach", bool(ok), "a new controller armed the service after the last trial" if ok else
              f"a new controller did not arm the service: {ctl.tail(3)}")
    ctl.stop()


def _start_far_end(i: int, sess: Session, watch: RingWatch, out: Outcome) -> tuple[Proc, Proc, bool]:
    """A new bridge and a remote controller through it that does not seed its rearm counter,
    started again (said) while it stops itself for missed frames: (bridge, remote, armed and up)."""
    for attempt in range(1, REMOTE_ATTEMPTS + 1):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        bridge = sess.pfma("bridge", "bridge", "--buffer", sess.name, "--listen", endpoint, "--commands")
        remote = sess.start("remote", [sys.executable, "-c", REMOTE_CONTROLLER, endpoint, sess.name, "-",
                                       *sess.rt_flag])
        until(lambda: (watch.armed_since(bridge.t0) and "up" in remote.text()) or "fault: " in remote.text(),
              WAIT_S / 2, must_live=(bridge, remote))
        ok = watch.armed_since(bridge.t0) and "up" in remote.text()
        if ok or not host_timing_cause(remote.text()) or attempt == REMOTE_ATTEMPTS:
            break
        # a far end descheduled past its missed-frame limit while powering up stops itself
        # (servo fault 12, by design: docs/controller.md "Missed frames"): a new one, said
        out.notes.append(f"remote controller {i} of 2, attempt {attempt}: {remote.tail(1)}; started again")
        remote.stop(signal.SIGTERM)
        bridge.stop()
    return bridge, remote, ok


def _reattach_far_end(i: int, sess: Session, c, watch: RingWatch, out: Outcome) -> None:
    """Far end ``i`` of 2 after the last bridge trial must arm the service through a new bridge."""
    before = int(c.read_commands().rearm_counter)
    bridge, remote, ok = _start_far_end(i, sess, watch, out)
    for p in (bridge, remote):
        p.note_maps()
    after = int(c.read_commands().rearm_counter)
    if ok:
        out.check("reattach", True, f"remote controller {i} of 2 (its rearm counter not seeded) armed the service")
    elif after == before:
        out.check("reattach", False, f"remote controller {i} of 2 through a new bridge never armed the service: "
                  f"its arm request carries rearm_counter {after}, the counter of the service's last arm "
                  f"(a RemoteCommander must carry on from the area's counter, tools/bridge/remote.py; the service "
                  f"takes an arm request only with a new counter)")
    else:
        armed = watch.armed_since(bridge.t0)
        out.check("reattach", False, f"remote controller {i} of 2 "
                  f"{'armed the service but was not up' if armed else 'never armed the service'} in "
                  f"{WAIT_S / 2:.0f} s (rearm counter {before} -> {after}): {remote.tail(3)} / {bridge.tail(3)}")
    remote.stop(signal.SIGTERM)
    bridge.stop()


def run_matrix(trials: int = DEFAULT_TRIALS, seed: int = DEFAULT_SEED, kinds: tuple[str, ...] = KINDS,
               progress=None, logs: Path | None = None, realtime: bool = False) -> dict:
    """Run the plan; returns the report (JSON-able): per kind trials, passes, failures with
    their causes, figures; every trial's outcome.

    :param realtime: the service and the local controllers run with ``--realtime`` (SCHED_FIFO,
        pinned CPUs), so that on a loaded host the arm is still flying when a kill comes
    :param logs: keep every process's output and the recordings in this directory (default:
        a temporary directory, removed)
    """
    t0 = time.monotonic()
    shm0 = set(os.listdir("/dev/shm"))
    outs: list[Outcome] = []
    load0 = os.getloadavg()
    with (contextlib.nullcontext(str(logs)) if logs is not None else
          tempfile.TemporaryDirectory(prefix="pfma-bench-chaos-")) as d:
        workdir = Path(d)
        workdir.mkdir(parents=True, exist_ok=True)
        for group in [(k,) for k in kinds if k in OWN] + [g for g in GROUPS]:
            mine = [t for t in plan(seed, trials, tuple(k for k in group if k in kinds))]
            if not mine:
                continue
            if group[0] in OWN:
                for t in mine:
                    o = Outcome(t)
                    t1 = time.monotonic()
                    try:
                        OWN[t.kind](t, workdir, o, realtime)
                    except Exception as err:  # noqa: BLE001
                        o.check("bench", False, f"{type(err).__name__}: {err}")
                    o.seconds = time.monotonic() - t1
                    outs.append(o)
                    if progress:
                        progress(o)
            else:
                outs += _run_shared(group, mine, workdir, progress, realtime)
    outs.sort(key=lambda o: (kinds.index(o.trial.kind), o.trial.index))
    stray = sorted(f for f in set(os.listdir("/dev/shm")) - shm0 if f.startswith(PREFIX))
    rep = report(outs, seed=seed, trials=trials, seconds=time.monotonic() - t0, stray=stray,
                 load=(load0, os.getloadavg()))
    rep["realtime"] = realtime
    return rep


def report(outs: list[Outcome], *, seed: int, trials: int, seconds: float, stray: list[str], load) -> dict:
    per: dict[str, dict] = {}
    for o in outs:
        k = per.setdefault(o.trial.kind, {"trials": 0, "passed": 0, "failures": [], "armed_at_kill": 0,
                                          "trip_age_ms": [], "kill_to_0v_ms": [], "recorder_lost_s": []})
        k["trials"] += 1
        k["passed"] += o.passed
        for f in o.failures():
            k["failures"].append({"trial": o.trial.describe(), "cause": f})
        if o.figures.get("armed_at_kill"):
            k["armed_at_kill"] += 1
        for key in ("trip_age_ms", "kill_to_0v_ms", "recorder_lost_s"):
            if o.figures.get(key) is not None:
                k[key].append(o.figures[key])
    for k in per.values():
        for key in ("trip_age_ms", "kill_to_0v_ms", "recorder_lost_s"):
            v = sorted(k.pop(key))
            k[key] = {"n": len(v), "min": v[0], "median": v[len(v) // 2], "max": v[-1]} if v else None
    return {"seed": seed, "trials_per_kind": trials, "seconds": round(seconds, 1),
            "load_avg_1min": {"start": round(load[0][0], 2), "end": round(load[1][0], 2)},
            "cpus": os.cpu_count(), "kinds": per, "stray_segments": stray,
            "passed": all(o.passed for o in outs) and not stray,
            "outcomes": [o.as_dict() for o in outs]}


def _line(o: Outcome) -> str:
    mark = "pass" if o.passed else "FAIL"
    fig = ", ".join(f"{k} {v}" for k, v in o.figures.items() if k != "armed_at_kill")
    s = f"  {mark} {o.trial.describe()} ({o.seconds:.1f} s){'; ' + fig if fig else ''}"
    for f in o.failures():
        s += f"\n       {f}"
    return s


def print_report(rep: dict) -> None:
    print(f"kill matrix, seed {rep['seed']}, {rep['trials_per_kind']} trials per kind"
          f"{', service and controllers --realtime' if rep.get('realtime') else ''}, {rep['seconds']:g} s "
          f"({rep['cpus']} CPUs, load average {rep['load_avg_1min']['start']} -> {rep['load_avg_1min']['end']})")
    print(f"  {'kind':<11}{'trials':>7}{'passed':>8}  armed at kill  trip age ms (min/med/max)  kill->0 V ms")
    for kind, k in rep["kinds"].items():
        ta, kz = k["trip_age_ms"], k["kill_to_0v_ms"]
        fmt = (lambda d: f"{d['min']}/{d['median']}/{d['max']} (n {d['n']})" if d else "-")
        print(f"  {kind:<11}{k['trials']:>7}{k['passed']:>8}  {k['armed_at_kill']:>13}  {fmt(ta):<25}  {fmt(kz)}")
        if k["recorder_lost_s"]:
            print(f"  {'':<11}recorder data lost at the kill, s (min/med/max): {fmt(k['recorder_lost_s'])}")
        for f in k["failures"]:
            print(f"    FAIL {f['trial']}: {f['cause']}")
    if rep["stray_segments"]:
        print(f"  stray /dev/shm files: {', '.join(rep['stray_segments'])}")
    print(f"  {'all passed' if rep['passed'] else 'FAILURES (above)'}")


def figures(seconds: float | None = None, trials: int = DEFAULT_TRIALS, seed: int = DEFAULT_SEED,
            kinds: tuple[str, ...] = KINDS, realtime: bool = False) -> dict:
    """The matrix's figures (the report without each trial's outcome)."""
    rep = run_matrix(trials=trials, seed=seed, kinds=kinds, realtime=realtime)
    rep.pop("outcomes")
    return rep


def run(seconds: float | None = None, trials: int | None = None, seed: int | None = None,
        kinds: tuple[str, ...] = KINDS, as_json: bool = False, realtime: bool = False) -> dict:
    """``pfma bench chaos``: the text report (or ``as_json``: the whole report)."""
    trials = DEFAULT_TRIALS if trials is None else trials
    seed = DEFAULT_SEED if seed is None else seed
    if not as_json:
        print(f"pfma bench chaos --trials {trials} --seed {seed}{' --realtime' if realtime else ''}: "
              f"{len(kinds)} kinds x {trials} trials", flush=True)
    rep = run_matrix(trials=trials, seed=seed, kinds=kinds, realtime=realtime,
                     progress=None if as_json else (lambda o: print(_line(o), flush=True)))
    if as_json:
        print(json.dumps(rep, indent=1))
    else:
        print_report(rep)
    return rep
