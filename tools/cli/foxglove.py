"""``pfma foxglove``: a running service's live channels in the Foxglove app.

    pfma foxglove [--buffer NAME | zenoh://HOST:PORT/NAME] [--port 8765] [--rate 30] [--host 127.0.0.1]

Serves the channels of an MCAP recording (``/pfma/inputs_raw``, ``/pfma/joints``,
``/pfma/adc``, ``/pfma/status``, ...: same names and schemas, so a layout made for
recordings shows the live system) over the foxglove-sdk WebSocket server. A reader in its
own process, outside the service's frame loop, at ``--rate`` 20-60 Hz (default 30): the
newest frame each tick, device groups when their sample time changed. Bound to
127.0.0.1 unless ``--host`` says otherwise. In the Foxglove app: Open connection ->
Foxglove WebSocket -> ws://127.0.0.1:8765. docs/bridge.md.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time

from tools.cli.args import float_in, positive_float


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= v < 65536:
        raise argparse.ArgumentTypeError(f"{text} outside 0..65535 (0: any free port)")
    return v


def add_parser(sub):
    from tools.foxglove import DEFAULT_HOST, DEFAULT_PORT, DEFAULT_RATE_HZ, RATE_MAX_HZ, RATE_MIN_HZ
    p = sub.add_parser("foxglove", help="serve the live channels to the Foxglove app (WebSocket, 20-60 Hz)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--buffer", default="pfma",
                   help="Bit3 shared-memory name (default pfma), or zenoh://HOST:PORT/NAME through a "
                        "pfma bridge (docs/bridge.md)")
    p.add_argument("--rack", default=None, help="rack TOML the service runs (default: the IRSS rack)")
    p.add_argument("--port", type=_port, default=DEFAULT_PORT, help=f"WebSocket port (default {DEFAULT_PORT})")
    p.add_argument("--host", default=DEFAULT_HOST,
                   help=f"address to bind (default {DEFAULT_HOST}: this host only)")
    p.add_argument("--rate", type=float_in(RATE_MIN_HZ, RATE_MAX_HZ, "Hz"), default=DEFAULT_RATE_HZ,
                   help=f"ticks per second, {RATE_MIN_HZ:g}-{RATE_MAX_HZ:g} (default {DEFAULT_RATE_HZ:g})")
    p.add_argument("--duration", type=positive_float, default=None, help="seconds to serve (default: until Ctrl-C)")
    return p


def run(args) -> int:
    from pfma.errors import PfmaError
    from tools.attach import attach_reader
    try:
        import foxglove  # noqa: F401
    except ImportError:
        raise PfmaError("the foxglove-sdk package is not installed (pip install 'foxglove-sdk>=0.30,<0.31')") \
            from None
    from tools.foxglove import serve
    client = attach_reader(args.buffer, args.rack)  # no live service / bridge: one line, exit 1
    stop = {"flag": False}
    old = {s: signal.signal(s, lambda *_: stop.__setitem__("flag", True)) for s in (signal.SIGINT, signal.SIGTERM)}
    t_end = None if args.duration is None else time.monotonic() + args.duration
    say = lambda s: print(f"pfma foxglove: {s}", file=sys.stderr, flush=True)  # noqa: E731
    try:
        live = serve(client, host=args.host, port=args.port, rate_hz=args.rate, say=say,
                     done=lambda: stop["flag"] or (t_end is not None and time.monotonic() >= t_end))
    except RuntimeError as err:  # the server could not bind (port in use, bad address)
        raise PfmaError(f"cannot serve on {args.host}:{args.port}: {err}") from None
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        client.close()
    say(f"stopped after {live.ticks} ticks; {sum(live.sent.values())} messages on {len(live.sent)} channels")
    return 0
