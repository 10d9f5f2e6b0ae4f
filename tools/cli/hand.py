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
import sys

from pfma.clock import MonotonicClock
from tools.cli.args import positive_float, positive_int
from tools.hand import SOURCES, hold_stick, parse_deflection, state_lines
from tools.regs import UsageError


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


def _deflect(args) -> int:
    from tools.faultctl import HAND_HOLD_MAX_S, NoEndpoint
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
    try:
        reply = hold_stick(args.buffer, volts, args.deadman, args.for_s)
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
    try:
        source = SOURCES[args.source](args.bus, args.rack, clock)
    except UsageError as err:  # a bus URL of the wrong shape: one line, nothing opened
        print(f"pfma hand: {err}", file=sys.stderr)
        return 2
    for note in source.notes:
        print(f"pfma hand: {note}", file=sys.stderr)
    try:
        if not args.json:
            print(f"# {source.header}")
        for line in state_lines(source, clock, count=args.count, duration=args.duration, rate_hz=args.rate_hz,
                                as_json=args.json):
            print(line)
            sys.stdout.flush()
    finally:
        source.close()
    return 0
