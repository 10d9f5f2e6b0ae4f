"""``pfma console``: the operator console (IRSS primary display) over the live system.

Examples::

    pfma console                         # the service on buffer pfma, the controller's pfma_wm
    pfma console --buffer pfma --wm pfma_wm
    pfma console --sim                   # the whole simulated system in this process (make run),
                                         # on buffer pfma and world model pfma_wm unless in use
    pfma console --sim --menu examples/console-menu.toml    # with live menus (key l)

Five areas (Local Status, World Status, Messages, Local Commands, Global Commands),
refreshed at 10 Hz; keys send power up/down, error reset, halt, single step, re-arm and
resume to System Up/Down through the world model's request protocol. docs/console.md.
"""

from __future__ import annotations

import sys

from tools.cli.args import add_sim_errors


def add_parser(sub):
    p = sub.add_parser("console", help="the operator console: five areas over the live system, "
                                       "power up/down, halt/step/resume",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--buffer", default=None,
                   help="Bit3 shared-memory name of the service (default pfma), or zenoh://HOST:PORT/NAME "
                        "through a pfma bridge (docs/bridge.md; the world model --wm stays on this host); "
                        "--sim: the name the simulated system takes")
    p.add_argument("--wm", "--name", dest="wm", default=None, metavar="NAME",
                   help="the controller's world-model name (default pfma_wm)")
    p.add_argument("--key", default=None, help="world-model access key (default $PFMA_WM_KEY or the default key)")
    p.add_argument("--sim", action="store_true",
                   help="run the whole simulated system here (simulated rack, service, controller powered up "
                        "flying a demo path) and show it; q or Ctrl-C stops everything, outputs 0 V. On buffer "
                        "pfma and world model pfma_wm, so every tool reaches it with its defaults; while another "
                        "system uses either, on a private pair, named in one line"),
    p.add_argument("--no-demo", action="store_true", help="--sim: power up but fly no demo path")
    add_sim_errors(p)
    p.add_argument("--menu", metavar="FILE.toml", default=None,
                   help="live menus (key l): named pages of world-model variables with a format each and a refresh "
                        "rate (examples/console-menu.toml); a mistake is named with file, line and field, exit 2")
    return p


def _load_menu(args):
    """The --menu file read and checked (not yet against the model); None without --menu.
    :raises MenuError: the file's mistake (the caller prints it, exit 2)"""
    if not args.menu:
        return None
    from tools.console.menu import load
    return load(args.menu)


def run(args) -> int:
    from tools.console.menu import MenuError
    try:
        menu = _load_menu(args)
    except MenuError as err:
        print(f"pfma console: {err}", file=sys.stderr)
        return 2
    if args.sim:
        return _run_sim(args, menu)
    from tools.runnames import DEFAULT_BUFFER, DEFAULT_WM
    args.buffer, args.wm = args.buffer or DEFAULT_BUFFER, args.wm or DEFAULT_WM
    from tools.attach import attach_reader, no_service
    from tools.console.control import ControlError, ControllerLink
    from tools.console.view import Sources
    why = no_service(args.buffer)
    if why is not None:
        print(f"pfma console: {why}", file=sys.stderr)
        return 1
    try:
        link = ControllerLink.attach(args.wm, args.key)
    except ControlError as err:
        print(f"pfma console: {err}; start the controller (`pfma controller --buffer {args.buffer} "
              f"--wm {args.wm}`)", file=sys.stderr)
        return 1
    try:  # shared memory, or zenoh://HOST:PORT/NAME through a bridge (the world model stays local)
        client = attach_reader(args.buffer)
    except Exception as err:  # noqa: BLE001 - one clear message, never a traceback
        link.close()
        print(f"pfma console: cannot read buffer {args.buffer!r}: {err}", file=sys.stderr)
        return 1
    try:
        if menu is not None:
            menu.check(link.wm)
        # simulated or not: what the service's buffer says (its SIMULATED flag), every refresh
        sources = Sources(client, link.wm)
        sources.names = f"buffer {args.buffer}, world model {args.wm}"
        app = _app(sources, link, menu=menu)
        try:
            app.run()
        finally:
            app.stop_recording()
    except MenuError as err:
        print(f"pfma console: {err}", file=sys.stderr)
        return 2
    finally:
        client.close()
        link.close()
    return 0


def _app(sources, link, on_tick=None, menu=None):
    from tools.console.app import ConsoleApp
    return ConsoleApp(sources, link, on_tick=on_tick, menu=menu)


def _run_sim(args, menu=None) -> int:
    from bit3.client import Client
    from tools.console.control import ControllerLink
    from tools.console.simrun import SimulatedSystem
    from tools.console.view import Sources
    from tools.console.menu import MenuError
    from tools.runnames import DEFAULT_BUFFER, DEFAULT_WM, claim
    from pfma.errors import PfmaError
    if args.buffer is not None and "://" in args.buffer:
        print(f"pfma console: --sim runs the simulated system here, on a shared-memory buffer: --buffer takes its "
              f"name, not {args.buffer}", file=sys.stderr)
        return 2
    try:  # the defaults unless another system runs on them (then a private pair, said); a name given: as given
        names = claim(args.buffer or DEFAULT_BUFFER, args.wm or DEFAULT_WM,
                      fallback=args.buffer is None and args.wm is None)
        system = SimulatedSystem(demo=not args.no_demo, buffer=names.buffer, wm=names.wm,
                                 sim_errors=getattr(args, "sim_errors", 0))
    except PfmaError as err:  # in use (or taken since the check): one line
        print(f"pfma console: {err}", file=sys.stderr)
        return 1
    # said before the console covers the terminal (seen after it), and in its Messages
    for note in (names.note, system.fault_note):
        if note:
            print(f"pfma console: {note}", file=sys.stderr, flush=True)
    if menu is not None:
        try:
            menu.check(system.sim.rt.wm)
        except MenuError as err:
            system.close()
            print(f"pfma console: {err}", file=sys.stderr)
            return 2
    client = Client.attach(system.name, layout=system.sim.rig.layout)
    sources = Sources(client, system.sim.rt.wm, rack="simulated")
    sources.speed = lambda: system.speed
    sources.names = f"buffer {names.buffer}, world model {names.wm}"
    for note in (names.note, system.fault_note):
        if note:
            sources.note(0.0, "WARNING", note)
    app = _app(sources, ControllerLink(system.sim.rt.wm, args.key), menu=menu)
    system.start()
    try:
        app.run()
    except KeyboardInterrupt:
        pass
    finally:
        app.stop_recording()  # before the service it records stops
        volts = system.stop()
        client.close()
        system.close()
    top = float(abs(volts).max()) if len(volts) else 0.0
    print(f"pfma console: simulated system stopped; DAC outputs {top:.3f} V max (service stopped, outputs "
          f"disconnected); buffer {names.buffer} and world model {names.wm} removed")
    return 0
