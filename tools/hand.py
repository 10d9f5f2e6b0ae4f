"""A hand controller's live state, and the simulated CAE stick held by hand: the logic of
``pfma hand`` (:mod:`tools.cli.hand`, whose help says what each source is).

A source (:data:`SOURCES`) opens the CAE rate controller on the A/D board, the CRL master on
a serial port or a SpaceMouse, each on a fake when asked (a simulated stick or puck that
moves gently); :func:`state_lines` polls it at the CRL frame rate and yields its lines.
:func:`parse_deflection` and :func:`hold_stick` deflect the running simulated rack's stick.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

POLL_S = 0.02  # the drivers are polled at the CRL frame rate (50 Hz)


def parse_deflection(text: str) -> list[float]:
    """``x=0.4,z=-0.2`` -> the six CAE axis voltages (``CAE_AXES`` order, +-10 V full).

    :raises ValueError: a name not in AXES (the closest named), a value not a number in -1..1
    """
    from drivers.crl.cae import CAE_AXES, FULL_SCALE_V
    from drivers.crl.state import AXES
    from pfma.errors import did_you_mean
    frac = dict.fromkeys(AXES, 0.0)
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        name, eq, value = part.partition("=")
        name = name.strip()
        if name not in frac:
            raise ValueError(f"no axis {name!r} (axes: {' '.join(AXES)})" + did_you_mean(name, AXES, n=1))
        try:
            v = float(value) if eq else float("nan")
        except ValueError:
            v = float("nan")
        if not -1.0 <= v <= 1.0:
            raise ValueError(f"{part!r}: give NAME=VALUE with VALUE in -1..1 (of full deflection)")
        frac[name] = v
    return [sign * frac[axis] * FULL_SCALE_V + 0.0 for _, axis, sign in CAE_AXES]  # + 0.0: no -0.0


def hold_stick(buffer: str, volts: list[float], deadman: bool, for_s: float) -> dict:
    """Ask service ``buffer`` to hold its simulated CAE stick at ``volts`` for ``for_s``
    seconds (deadman pressed or not); the service's reply.

    :raises tools.faultctl.NoEndpoint: the service runs a real rack (or there is none)
    """
    from tools.faultctl import request
    return request(buffer, {"op": "hand", "source": "cae", "volts": volts, "deadman": bool(deadman),
                            "for_s": for_s})


def _wave(t_s: float, k: int, amp: float = 0.6) -> float:
    return amp * math.sin(2 * math.pi * t_s / (4.0 + 1.3 * k))


class _Source:
    """poll() -> state; extra() -> text after the state; close(). ``header`` is the line
    above the states; ``notes`` what the verb says on stderr about how it was opened."""

    header = ""
    notes: tuple[str, ...] = ()

    def poll(self):
        raise NotImplementedError

    def extra(self) -> str:
        return ""

    def close(self) -> None:
        pass


class _Cae(_Source):
    def __init__(self, bus: str | None, rack: str, clock) -> None:
        from drivers.adc import Dvme611
        from drivers.crl.cae import CAE_AXES, CAE_DISCRETES, CaeHandController
        from pfma.rack import load_rack

        rack = load_rack(rack)
        board = rack.board(rack.channel("cae_up_down").board)
        port = bus or "fake"
        self.fake_adc = None
        if port in ("fake", "fake://"):
            from fakes.rack import FakeRack

            self.bus = FakeRack.from_config(rack)
            self.fake_adc = self.bus[board.name]
            self.header = f"CAE on a fake rack: {board.name} @0x{board.base:04X}, simulated stick"
        else:
            from tools.regs import open_cli_bus

            self.bus = open_cli_bus(port, rack)
            self.header = f"CAE on {port}: {board.name} @0x{board.base:04X}"
        self.adc = Dvme611(self.bus, board.base, name=board.name)
        self.cae = CaeHandController(rack=rack, clock=clock)
        self.axis_channels = [rack.channel(s).channel for s, _, _ in CAE_AXES]
        self.deadman_channel = rack.channel(CAE_DISCRETES[0][0]).channel
        self.clock, self.t0 = clock, clock.now()

    def poll(self):
        if self.fake_adc is not None:
            t = self.clock.now() - self.t0
            for k, ch in enumerate(self.axis_channels):
                self.fake_adc.set_input_volts(ch, 10.0 * _wave(t, k))
            self.fake_adc.set_input_volts(self.deadman_channel, 5.0 if t > 0.5 else 0.0)
        return self.cae.read(self.adc.read_volts)

    def close(self) -> None:
        from tools.regs import close_bus

        close_bus(self.bus)


class _Crl(_Source):
    def __init__(self, bus: str | None, rack: str, clock) -> None:
        from drivers.crl import CrlHandController

        port = bus or "fake"
        self.fake = self.pty = None
        self.clock, self.t0 = clock, clock.now()
        if port == "fake":
            from fakes.crl import FakeCrlMaster, gentle_axes
            from fakes.pty import PtyDevice

            self.fake = FakeCrlMaster(axes_fn=gentle_axes)
            self.pty = PtyDevice(self.fake).start()
            port = self.pty.port_name
            self.header = f"CRL: fake master on pty {port} (placeholder framing), spring force sent back"
        else:
            self.header = f"CRL on {port} (placeholder framing), zero force frames sent"
        self.drv = CrlHandController.open(port, clock)

    def poll(self):
        if self.fake is not None:
            self.fake.deadman = self.clock.now() - self.t0 > 0.5
        st = self.drv.update()
        if self.fake is not None:  # a soft spring towards the centre, only on the fake
            self.drv.send_force(tuple(-20.0 * a for a in st.axes[:3]), tuple(-1.0 * a for a in st.axes[3:]))
        else:
            self.drv.send_force((0.0,) * 3, (0.0,) * 3, enable=False)
        return st

    def extra(self) -> str:
        s = self.drv.link_stats()
        txt = f" | ok {s['frames_ok']} bad {s['frames_bad']} lost {s['frames_lost']} trips {s['watchdog_trips']}"
        if self.fake is not None:
            f = self.fake.displayed_force_n
            txt += f" | display F=({f[0]:+5.1f},{f[1]:+5.1f},{f[2]:+5.1f}) N"
        return txt

    def close(self) -> None:
        self.drv.close()
        if self.pty is not None:
            self.pty.stop()


class _Hid(_Source):
    def __init__(self, bus: str | None, rack: str, clock) -> None:
        from drivers.crl import HidSpaceMouse

        port = bus or "auto"
        self.fake = None
        self.clock, self.t0 = clock, clock.now()
        if port == "auto":
            try:
                self.sm = HidSpaceMouse(clock=clock)
                found = self.sm.enumerate()
            except (ImportError, OSError) as err:
                self.notes += (f"hidapi unavailable ({err})",)
                found = []
            if found:
                self.header = f"SpaceMouse {found[0].get('product_string') or ''} at {found[0].get('path')!r}"
                return
            self.notes += ("no SpaceMouse found; using a FAKE device (fakes.hid.FakeHidDevice)",)
            port = "fake"
        if port == "fake":
            from fakes.hid import FakeHidDevice

            self.fake = FakeHidDevice()
            self.sm = HidSpaceMouse(opener=self.fake, clock=clock)
            self.header = "SpaceMouse: FAKE device (no hardware), simulated puck"
        else:
            self.sm = HidSpaceMouse(path=port, clock=clock)
            self.header = f"SpaceMouse at {port}"

    def poll(self):
        if self.fake is not None:
            t = self.clock.now() - self.t0
            w = [int(350 * _wave(t, k)) for k in range(6)]
            self.fake.set_axes(w[:3], w[3:])
            self.fake.set_buttons(1 if t > 0.5 else 0)
        return self.sm.update()

    def close(self) -> None:
        self.sm.close()


#: ``--source`` -> its reader
SOURCES = {"cae": _Cae, "crl": _Crl, "hid": _Hid}


def state_lines(source: _Source, clock, *, count: int | None, duration: float | None, rate_hz: float,
                as_json: bool):
    """Poll ``source`` every :data:`POLL_S` and yield a line ``rate_hz`` times a second (a
    JSON object with ``as_json``), until ``count`` lines or ``duration`` seconds."""
    t0 = clock.now()
    next_poll = next_print = t0
    lines = 0
    while True:
        now = clock.now()
        if duration is not None and now - t0 >= duration:
            break
        state = source.poll()
        if now >= next_print:
            # shown as seconds since this command started (the driver stamps its clock's
            # time: on the host's monotonic clock that is the machine's uptime)
            state = replace(state, t_s=state.t_s - t0)
            yield json.dumps(state.as_dict()) if as_json else state.format() + source.extra()
            lines += 1
            next_print += 1.0 / rate_hz
            if count is not None and lines >= count:
                break
        next_poll += POLL_S
        clock.sleep_until(next_poll)
