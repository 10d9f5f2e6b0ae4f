"""``pfma gateway``: the simulated rack behind a Modbus TCP gateway, as a real process.

The register-level fakes and the arm physics (``fakes.world.FakeWorld``) run on the
real-time clock; the physics is advanced every millisecond. A pymodbus server
(``fakes.modbus_gateway.ModbusGateway``) answers on ``--listen`` with the project's
mapping: **holding register N is the A16 word at 2N** (the mapping of
``drivers.bus.modbus``). So ``pfma serve --rack fake --bus modbus://127.0.0.1:5020``
runs the service over a real TCP gateway on loopback.

Serial lines do not cross a register gateway (the MVME400's 3-character FIFOs would
need a poll every 1.5 ms); the simulated F/T sensor and CRL hand controller are cabled
to the fake MVME400 but nothing drains them here.

Ctrl-C or SIGTERM stops the gateway with one line.
"""

from __future__ import annotations

import argparse
import logging
import signal
import socket
import sys
import threading

from pfma.errors import PfmaError
from tools.cli.args import positive_float

#: the listen address when none is given
DEFAULT_LISTEN = "127.0.0.1:5020"
#: the physics is advanced this often (the fake world skips steps shorter than 1 ms)
PHYSICS_TICK_S = 0.001


def add_parser(sub):
    p = sub.add_parser("gateway", help="serve the simulated rack as a Modbus TCP gateway",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rack", default="fake",
                   help="rack to simulate: fake (the IRSS report's tables, default) or a rack TOML")
    p.add_argument("--listen", default=DEFAULT_LISTEN, metavar="HOST:PORT",
                   help=f"address to answer on (default {DEFAULT_LISTEN}; port 0 = any free port)")
    p.add_argument("--duration", type=positive_float, default=None, help="seconds to run (default: until Ctrl-C)")
    return p


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); a clear PfmaError otherwise."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise PfmaError(f"--listen {text!r}: expected HOST:PORT, e.g. {DEFAULT_LISTEN}")
    try:
        number = int(port)
    except ValueError:
        raise PfmaError(f"--listen {text!r}: the port {port!r} is not a number") from None
    if not 0 <= number <= 65535:
        raise PfmaError(f"--listen {text!r}: port {number} is not 0..65535")
    return host.strip("[]"), number


def _why_not_listening(host: str, port: int) -> str:
    """The operating system's reason a listen on host:port fails (one bind attempt)."""
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
    except OSError as err:
        return err.strerror or str(err)
    return "the Modbus server did not start"


def run(args) -> int:
    from fakes.modbus_gateway import ModbusGateway
    from fakes.world import FakeWorld
    from pfma.clock import MonotonicClock
    from pfma.rack import load_rack

    # pymodbus logs a failed bind at error level; the one message below says it instead
    logging.getLogger("pymodbus").addHandler(logging.NullHandler())
    try:  # a bad --listen is a usage mistake: one line, exit 2 (as argparse's own)
        host, port = parse_listen(args.listen)
    except PfmaError as err:
        print(f"pfma gateway: {err}", file=sys.stderr)
        return 2
    rack = load_rack(args.rack)
    clock = MonotonicClock()
    world = FakeWorld(rack, clock=clock)
    gateway = ModbusGateway(world.bus, host=host, port=port, log_function_codes=False)  # runs for hours
    try:
        gateway.start()
    except RuntimeError:
        print(f"pfma gateway: cannot listen on {host}:{port}: {_why_not_listening(host, port)}",
              file=sys.stderr)
        return 1
    stop = threading.Event()

    def physics() -> None:  # the arm moves in real time, between register requests
        while not stop.wait(PHYSICS_TICK_S):
            with gateway.lock:
                world.tick(clock.now())

    def on_signal(signum, _frame) -> None:
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    mover = threading.Thread(target=physics, name="gateway-physics", daemon=True)
    mover.start()
    print(f"pfma gateway: simulated rack {rack.name} on {gateway.url} (holding register N = "
          f"A16 word 2N); Ctrl-C stops", flush=True)
    try:
        stop.wait(args.duration)
    finally:
        stop.set()
        mover.join(1.0)
        gateway.stop()
        for s, h in old.items():
            signal.signal(s, h)
    print(f"pfma gateway: stopped after {gateway.requests} requests", flush=True)
    return 0
