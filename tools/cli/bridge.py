"""``pfma bridge``: the Bit3 areas of a running service on Zenoh (docs/bridge.md).

Publishes every area under ``pfma/<buffer>/<area>`` (the body bytes as in shared memory;
the layout JSON under ``pfma/<buffer>/layout``) at the rate it changes. With
``--commands`` it also claims the command area, as a controller does, and writes what
one remote writer publishes on ``pfma/<buffer>/commands/set``; the service's watchdog
and limits apply unchanged. Peer mode on explicit endpoints, no multicast scouting;
with neither --listen nor --connect it listens on tcp/127.0.0.1:7447 (loopback only).
With --users FILE (user:password lines) only peers that authenticate as one of those users
connect (Zenoh usrpwd), and Zenoh's access control lets them read while only --operator
users may command; remote tools authenticate with $PFMA_ZENOH_CREDENTIALS.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path

from pfma.errors import PfmaError
from tools.cli.args import positive_float

#: the reader loop's pause between polls, s. Assumption: 0.5 ms, well under the 3.1 ms
#: frame at 320 Hz, so an inputs body leaves within about one poll of its publication.
POLL_S = 0.0005
#: polls between two looks for the service's frame ring while the bridge has none (a
#: service still starting makes it after its buffer): about every 0.5 s
RING_LOOK_POLLS = 1000


def add_parser(sub):
    p = sub.add_parser("bridge", help="publish the Bit3 areas on Zenoh (and take remote commands)",
                       description=__doc__.split("\n\n")[1].replace("``", ""),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name (default pfma)")
    p.add_argument("--listen", action="append", metavar="tcp/HOST:PORT",
                   help="listen here (repeatable; default tcp/127.0.0.1:7447 when no --connect)")
    p.add_argument("--connect", action="append", metavar="tcp/HOST:PORT",
                   help="connect to this peer (repeatable)")
    p.add_argument("--commands", action="store_true",
                   help="claim the command area and write what one remote writer publishes")
    p.add_argument("--rack", default=None, help="rack TOML the service runs (default: the IRSS rack)")
    p.add_argument("--owner", default="pfma-bridge", help="owner name of the command claim")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--users", default=None, metavar="FILE",
                   help="user:password lines of the peers allowed to connect: Zenoh authentication "
                        "(usrpwd) and access control (every user reads; only --operator users command)")
    p.add_argument("--operator", action="append", default=[], metavar="USER",
                   help="a user of --users who may put remote commands (repeatable; with --commands)")
    return p


def run(args) -> int:
    from bit3.client import Client
    from tools.attach import no_service
    from tools.bridge.bridge import Bridge
    from tools.bridge.session import DEFAULT_LISTEN, open_session

    try:
        auth = _checked_auth(args)
    except PfmaError as err:
        print(f"pfma bridge: {err}", file=sys.stderr)
        return 2
    why = no_service(args.buffer)
    if why is not None:
        raise PfmaError(why)
    listen = args.listen or ([] if args.connect else [DEFAULT_LISTEN])
    reader = Client.attach(args.buffer, rack=args.rack)
    stop, old_handlers = _stop_on_signals()
    commander = None
    session = bridge = None
    try:
        if args.commands:
            commander = Client.attach(args.buffer, writer="commands", owner=args.owner, rack=args.rack)
        session = open_session(listen=listen, connect=args.connect, auth=auth, buffer=args.buffer,
                               operators=args.operator)
        bridge = Bridge(session, args.buffer, reader, commander=commander, now=time.monotonic,
                        ring=_ring(args.buffer, reader))
        secured = "" if auth is None else (f"; users of {args.users} only, operators: "
                                           f"{', '.join(args.operator) or 'none'}")
        print(f"pfma bridge: buffer {args.buffer} on {', '.join(listen + (args.connect or []))}"
              f"{' (remote commands on)' if commander else ' (read-only)'}{secured}", file=sys.stderr, flush=True)
        _serve(args, bridge, reader, stop)
        return 0
    finally:
        _close(bridge, session, commander, reader, old_handlers)


def _checked_auth(args):
    """The arguments checked (buffer name, endpoints, ``--operator`` with ``--users``) and
    the Zenoh authentication of ``--users`` (None without it).

    :raises PfmaError: for a bad argument or users file (``pfma bridge`` exits 2)
    """
    from tools.bridge.session import (
        CREDENTIALS_ENV, ZenohAuth, access_control, check_endpoint, check_name, read_credentials,
    )
    check_name(args.buffer)
    for e in (args.listen or []) + (args.connect or []):
        check_endpoint(e)
    if args.operator and not args.users:
        raise PfmaError("--operator needs --users (the users file it names an entry of)")
    if not args.users:
        return None
    own = ZenohAuth.from_file(os.environ[CREDENTIALS_ENV]) if os.environ.get(CREDENTIALS_ENV) else None
    auth = ZenohAuth(own.user if own else None, own.password if own else None, args.users)
    # checked here: a bad users file or an operator not in it is one line, exit 2
    access_control(args.buffer, [u for u, _ in read_credentials(Path(args.users))], args.operator)
    return auth


def _stop_on_signals() -> tuple[dict[str, int], dict]:
    """SIGTERM (a process manager) and SIGINT (also where a shell started it with SIGINT
    ignored) end the loop: the orderly close (its summary; a command claim released).
    Returns the stop flag (``{"signal": signum}``) and the handlers they replaced."""
    stop = {"signal": 0}
    old_handlers = {s: signal.signal(s, lambda signum, _f: stop.__setitem__("signal", signum))
                    for s in (signal.SIGINT, signal.SIGTERM)}
    return stop, old_handlers


def _serve(args, bridge, reader, stop: dict[str, int]) -> None:
    """Poll until ``--duration`` or a stop signal; while the bridge has no frame ring, look
    for the service's now and then."""
    ring_gone = bridge.ring is not None
    end = None if args.duration is None else time.monotonic() + args.duration
    polls = 0
    while (end is None or time.monotonic() < end) and not stop["signal"]:
        bridge.poll()
        polls += 1
        if bridge.ring is None and not polls % RING_LOOK_POLLS and not ring_gone:
            ring = _ring(args.buffer, reader)  # a service that is still starting makes it later
            if ring is not None:
                bridge.attach_ring(ring)
                ring_gone = True  # found once; a replaced ring later means a restarted service
        time.sleep(POLL_S)


def _close(bridge, session, commander, reader, old_handlers: dict) -> None:
    """The orderly close: the bridge with its summary, the session, the command claim, the
    reader; the signal handlers restored."""
    if bridge is not None:
        if bridge.ring is not None:
            bridge.ring.close()
        print(f"pfma bridge: stopped; published {bridge.published['inputs']} inputs bodies, missed "
              f"{bridge.missed} publishes of the service (polled too late){_applied(bridge)}",
              file=sys.stderr, flush=True)
        bridge.close()
    if session is not None:
        session.close()
    if commander is not None:
        commander.close()
    reader.close()
    for sig, h in old_handlers.items():
        signal.signal(sig, h)


def _applied(bridge) -> str:
    return f"; {bridge.applied} remote command bodies written" if bridge.commander is not None else ""


def _ring(buffer: str, reader):
    """The service's frame ring of this buffer and layout (``pfma serve`` keeps one), or
    None: then the bridge polls the inputs area."""
    from bit3.ring import FrameRing, RingError
    try:
        return FrameRing.attach(buffer, reader.layout.hash)
    except RingError:
        return None
