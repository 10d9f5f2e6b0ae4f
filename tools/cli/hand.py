"""``pfma hand --source cae|crl|hid``: print a hand controller's live state.

Each line is one :class:`drivers.crl.HandControllerState` (axes -1..1 in the
hand-controller frame: x forward, y left, z up; roll/pitch/yaw right-handed).

- ``cae``: the CAE rate controller on the A/D board. ``--bus fake`` (default) runs the
  driver on a fresh fake rack whose ADC inputs follow a gently moving simulated stick
  (deadman pressed after 0.5 s); any other ``--bus`` is a register bus URL
  (``modbus://HOST:PORT``, ``file:PATH``).
- ``crl``: the CRL force-reflecting master on a serial port (``--bus /dev/ttyUSB0``,
  ``socket://...``). ``--bus fake`` (default) runs ``fakes.crl.FakeCrlMaster`` behind a
  real pty, and the tool sends it a gentle spring force, so both directions are live.
  The CRL framing is a PLACEHOLDER (drivers/crl/crl_codec.py).
- ``hid``: a 3Dconnexion SpaceMouse (hidapi, hidraw backend). ``--bus auto`` (default)
  opens the first one found and falls back to a fake device, saying so; ``--bus fake``
  forces the fake; ``--bus /dev/hidrawN`` opens that node. The deadman is the left button.

Flying the simulated arm by hand (issue 30 item 6): ``--deflect AXES`` holds the simulated
CAE stick of the running ``pfma serve`` (``--buffer``, default pfma) instead of printing::

    pfma hand --source cae --deflect x=0.4 --deadman --for 2     # forward, 40 %, for 2 s

AXES are ``NAME=VALUE`` pairs in the hand-controller frame (x forward, y left, z up, roll,
pitch, yaw), each -1..1 of full deflection, mapped to the stick's voltages by the driver's
own table (``drivers.crl.cae.CAE_AXES``); the others are centred. ``--deadman`` presses
the deadman (discrete 1): without it the controller ignores the stick, as on the rack.
After ``--for`` seconds (default 1, at most 10) the stick springs back to centre and the
deadman comes up, as a hand let go does: a script renews it to keep flying, and a dead
script cannot leave the stick deflected. The controller flies it in teleoperation
(``pfma controller --power-up --teleop cae``). A real rack's service has no such
endpoint: the deflection is refused, exit 1.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
import math
import sys

from pfma.clock import MonotonicClock
from tools.cli.args import positive_float, positive_int

POLL_S = 0.02  # the drivers are polled at the CRL frame rate (50 Hz)


def add_parser(sub):
    p = sub.add_parser("hand", help="print a hand controller's live state",
                       description=__doc__.split("\n\n", 1)[1],
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", required=True, choices=("cae", "crl", "hid"), help="which controller")
    p.add_argument("--bus", default=None,
                   help="cae: register bus URL or fake (default); crl: serial URL or fake (default); "
                        "hid: auto (default), fake or a /dev/hidraw path")
    p.add_argument("--port", dest="port_alias", default=None, metavar="URL",
                   help="deprecated alias of --bus (still works; says so once on stderr)")
    p.add_argument("--count", type=positive_int, default=None, help="stop after N lines")
    p.add_argument("--duration", type=positive_float, default=None, help="stop after S seconds")
    p.add_argument("--rate-hz", type=positive_float, default=10.0, help="lines per second (default 10)")
    p.add_argument("--rack", default="fake", help="rack TOML (default: the IRSS report's tables)")
    p.add_argument("--json", action="store_true", help="one JSON object per line (JSON lines)")
    d = p.add_argument_group("flying the simulated arm (--source cae)")
    d.add_argument("--deflect", metavar="AXES", default=None,
                   help="hold the running simulated rack's CAE stick: NAME=VALUE,... (x y z roll pitch yaw, "
                        "-1..1 of full deflection)")
    d.add_argument("--deadman", action="store_true", help="with --deflect: press the deadman")
    d.add_argument("--for", dest="for_s", type=positive_float, default=1.0, metavar="S",
                   help="with --deflect: seconds before the stick springs back (default 1, at most 10)")
    d.add_argument("--buffer", default="pfma", help="with --deflect: the service's Bit3 buffer (default pfma)")
    return p


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


def _deflect(args) -> int:
    from tools.faultctl import HAND_HOLD_MAX_S, NoEndpoint, request
    if args.source != "cae":
        print(f"pfma hand: --deflect holds the simulated CAE stick (--source cae), not {args.source}",
              file=sys.stderr)
        return 2
    if args.for_s > HAND_HOLD_MAX_S:
        print(f"pfma hand: --for {args.for_s:g}: at most {HAND_HOLD_MAX_S:g} s (renew it to hold longer)",
              file=sys.stderr)
        return 2
    try:
        volts = parse_deflection(args.deflect)
    except ValueError as err:
        print(f"pfma hand: --deflect: {err}", file=sys.stderr)
        return 2
    req = {"op": "hand", "source": "cae", "volts": volts, "deadman": bool(args.deadman), "for_s": args.for_s}
    try:
        reply = request(args.buffer, req)
    except NoEndpoint:
        print(f"pfma hand: service {args.buffer} runs a real rack (or none): a stick is deflected only on the "
              f"simulated rack; on the rack, move the stick by hand", file=sys.stderr)
        return 1
    if not reply.get("ok"):
        print(f"pfma hand: {reply.get('error', 'the service refused the request')}", file=sys.stderr)
        return int(reply.get("exit", 1))
    if args.json:
        print(json.dumps(reply))
    else:
        print(f"pfma hand: {reply['text']} (then centred, deadman up)")
    return 0


def _wave(t_s: float, k: int, amp: float = 0.6) -> float:
    return amp * math.sin(2 * math.pi * t_s / (4.0 + 1.3 * k))


class _Source:
    """poll() -> state; extra() -> text after the state; close()."""

    header = ""

    def poll(self):
        raise NotImplementedError

    def extra(self) -> str:
        return ""

    def close(self) -> None:
        pass


class _Cae(_Source):
    def __init__(self, args, clock) -> None:
        from drivers.adc import Dvme611
        from drivers.crl.cae import CAE_AXES, CAE_DISCRETES, CaeHandController
        from pfma.rack import load_rack

        rack = load_rack(args.rack)
        board = rack.board(rack.channel("cae_up_down").board)
        port = args.bus or "fake"
        self.fake_adc = None
        if port in ("fake", "fake://"):
            from fakes.rack import FakeRack

            self.bus = FakeRack.from_config(rack)
            self.fake_adc = self.bus[board.name]
            self.header = f"CAE on a fake rack: {board.name} @0x{board.base:04X}, simulated stick"
        else:
            from tools.cli.reg import open_cli_bus

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
        from tools.cli.reg import close_bus

        close_bus(self.bus)


class _Crl(_Source):
    def __init__(self, args, clock) -> None:
        from drivers.crl import CrlHandController

        port = args.bus or "fake"
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
    def __init__(self, args, clock) -> None:
        from drivers.crl import HidSpaceMouse

        port = args.bus or "auto"
        self.fake = None
        self.clock, self.t0 = clock, clock.now()
        if port == "auto":
            try:
                self.sm = HidSpaceMouse(clock=clock)
                found = self.sm.enumerate()
            except (ImportError, OSError) as err:
                print(f"pfma hand: hidapi unavailable ({err})", file=sys.stderr)
                found = []
            if found:
                self.header = f"SpaceMouse {found[0].get('product_string') or ''} at {found[0].get('path')!r}"
                return
            print("pfma hand: no SpaceMouse found; using a FAKE device (fakes.hid.FakeHidDevice)",
                  file=sys.stderr)
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


SOURCES = {"cae": _Cae, "crl": _Crl, "hid": _Hid}


def run(args) -> int:
    if args.deflect is not None:
        return _deflect(args)
    if args.deadman:
        print("pfma hand: --deadman goes with --deflect", file=sys.stderr)
        return 2
    if args.rate_hz <= 0:
        print("pfma hand: --rate-hz must be positive", file=sys.stderr)
        return 2
    if args.port_alias is not None:
        if args.bus is not None and args.bus != args.port_alias:
            print(f"pfma hand: --port {args.port_alias} and --bus {args.bus} disagree; "
                  f"give --bus only", file=sys.stderr)
            return 2
        print("pfma hand: --port is deprecated; use --bus (same meaning)", file=sys.stderr)
        args.bus = args.port_alias
    clock = MonotonicClock()
    source = SOURCES[args.source](args, clock)
    try:
        if not args.json:
            print(f"# {source.header}")
        t0 = clock.now()
        next_poll = next_print = t0
        lines = 0
        while True:
            now = clock.now()
            if args.duration is not None and now - t0 >= args.duration:
                break
            state = source.poll()
            if now >= next_print:
                # shown as seconds since this command started (the driver stamps its clock's
                # time: on the host's monotonic clock that is the machine's uptime)
                state = replace(state, t_s=state.t_s - t0)
                if args.json:
                    print(json.dumps(state.as_dict()))
                else:
                    print(state.format() + source.extra())
                sys.stdout.flush()
                lines += 1
                next_print += 1.0 / args.rate_hz
                if args.count is not None and lines >= args.count:
                    break
            next_poll += POLL_S
            clock.sleep_until(next_poll)
    finally:
        source.close()
    return 0
