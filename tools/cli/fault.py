"""``pfma fault``: inject and clear faults in a running simulated rack.

``pfma serve`` on the simulated rack (``--rack fake``) opens a control endpoint beside
its Bit3 buffer: the Unix-domain stream socket ``/dev/shm/NAME.faults`` (mode 0600, as
the buffer; removed when the service stops; a stale one, left by a killed service, is
recognised and replaced). ``pfma fault`` talks to it with one line of JSON each way::

    pfma fault inject resolver-los:shoulder_pitch_angle     # --buffer NAME (default pfma)
    pfma fault list --active [--json]
    pfma fault clear resolver-los:shoulder_pitch_angle      # or: pfma fault clear all
    pfma fault list                                          # every kind, no service needed

The service applies a request between two frames, in its loop's thread (the only thread
that touches the fakes), and posts every fault it injects or clears in its message queue
(codes 180 and 181), so ``pfma monitor`` and ``pfma stats`` show that a fault is
simulated. A service on a real rack has no endpoint: ``pfma fault`` then says so and
exits 1. A bad spec exits 2 with the closest names. Specs: ``pfma fault list``,
docs/faults.md.

For ``pfma serve``: :func:`add_serve_fault_args` adds ``--fault SPEC`` (repeatable) and
``--scenario FILE``; :func:`install_serve_faults` applies them and opens the endpoint.
"""

from __future__ import annotations

import argparse
import atexit
import json
import sys
from typing import Any

from pfma.errors import ConfigError, PfmaError

from tools.faultctl import (
    FaultController, FaultEndpoint, NoEndpoint, request, socket_path)


def add_parser(sub):
    p = sub.add_parser("fault", help="inject/clear faults in a running simulated rack",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    cmds = p.add_subparsers(dest="fault_cmd", metavar="inject|clear|list", required=True)
    for name, helptext in (("inject", "inject a fault (a spec, see: pfma fault list)"),
                           ("clear", "clear an active fault (its spec) or all of them (all)"),
                           ("list", "every fault kind; with --active the faults in force")):
        c = cmds.add_parser(name, help=helptext, description=helptext)
        if name != "list":
            c.add_argument("spec", metavar="SPEC" if name == "inject" else "SPEC|all")
        else:
            c.add_argument("--active", action="store_true",
                           help="the faults in force in the service (needs a running simulated rack)")
        c.add_argument("--buffer", default="pfma", help="the service's Bit3 buffer (default pfma)")
        c.add_argument("--json", action="store_true", help="print one JSON document")
    return p


def run(args) -> int:
    from sim.faults import KINDS, parse_fault
    cmd = args.fault_cmd
    if cmd == "list" and not args.active:
        from sim.faults import fault_targets, kinds_help, targets_help
        if args.json:
            targets = fault_targets()
            _print_json([{"kind": k, "syntax": s, "meaning": m, "targets": targets[k]}
                         for k, (s, m) in KINDS.items()])
        else:
            print("\n".join(kinds_help() + targets_help()))
        return 0
    spec = getattr(args, "spec", None)
    if spec is not None and not (cmd == "clear" and spec.strip() == "all"):
        try:
            parse_fault(spec)  # the simulated rack is the default rack: check before asking
        except ConfigError as err:
            print(f"pfma fault: {err}", file=sys.stderr)
            return 2
    req: dict[str, Any] = {"op": cmd}
    if spec is not None:
        req["spec"] = spec
    try:
        reply = request(args.buffer, req)
    except NoEndpoint as err:
        print(f"pfma fault: {err}", file=sys.stderr)
        return 1
    if not reply.get("ok"):
        print(f"pfma fault: {reply.get('error', 'the service refused the request')}", file=sys.stderr)
        return int(reply.get("exit", 1))
    if args.json:
        _print_json(reply)
        return 0
    faults = reply.get("faults", [])
    if cmd == "list":
        if not faults:
            print(f"no simulated fault active in service {args.buffer}")
        for f in faults:
            print(f"{f['spec']}  (since frame {f['since']})  {f['description']}")
        for line in reply.get("rack_errors", []):  # --sim-errors SEED: the simulated rack's imperfections
            print(line)
    else:
        verb = "injected" if cmd == "inject" else "cleared"
        if not faults:
            print(f"pfma fault: no fault was active in service {args.buffer}")
        for f in faults:
            print(f"pfma fault: {verb} {f['spec']}: {f['description']}")
    return 0


def _print_json(obj) -> None:
    print(json.dumps(obj, indent=1))


# ----------------------------------------------------------------------------- pfma serve
def _spec_arg(text: str) -> str:
    """argparse type of ``--fault``: the spec checked against the simulated rack's (default) rack."""
    from sim.faults import parse_fault
    try:
        parse_fault(text)
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def _scenario_arg(path: str):
    """argparse type of ``--scenario``: the file loaded and checked (file, line, field named)."""
    from sim.scenario import load_scenario
    try:
        return load_scenario(path)
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    except OSError as err:
        raise argparse.ArgumentTypeError(f"scenario {path}: {err.strerror or err}") from None


def add_serve_fault_args(parser: argparse.ArgumentParser) -> None:
    """``--fault SPEC`` (repeatable) and ``--scenario FILE`` for ``pfma serve``; both are
    checked while the arguments are parsed (a bad one exits 2 before anything starts)."""
    parser.add_argument("--fault", action="append", default=[], metavar="SPEC", type=_spec_arg,
                        help="simulated rack only: inject this fault from the first frame "
                             "(repeatable; kinds: pfma fault list)")
    parser.add_argument("--scenario", default=None, metavar="FILE", type=_scenario_arg,
                        help="simulated rack only: run this fault scenario (TOML [[step]] at_s, "
                             "inject/clear) on the loop's frame time, e.g. scenarios/ft-unplug.toml")


def _scenario_errors(args, scenario, world) -> None:
    """A scenario's ``errors_seed``: the simulated rack's imperfections it runs on, installed
    before anything runs; a different ``--sim-errors`` seed is a mistake (exit 2)."""
    seed = getattr(scenario, "errors_seed", None)
    if seed is None:
        return
    given = getattr(args, "sim_errors", 0)
    if given and given != seed:
        print(f"pfma serve: --sim-errors {given} and the scenario's errors_seed {seed} disagree; give one",
              file=sys.stderr)
        raise SystemExit(2)
    from sim.errors import seeded
    world.sim.set_errors(seeded(seed, world.rack_config))


def install_serve_faults(args, svc, world) -> None:
    """After the service is built and before its loop runs: inject ``--fault`` specs, schedule
    the ``--scenario`` steps on the loop's frames, and open the control endpoint
    (:func:`socket_path`), removed when the service stops and at exit.

    On a real rack (``world`` None) nothing is opened; ``--fault``/``--scenario`` there
    print one message and exit 2 (``SystemExit``). An endpoint that cannot be opened (a
    buffer name too long for a socket path) is named and the service runs without it.
    """
    specs = list(getattr(args, "fault", None) or [])
    scenario = getattr(args, "scenario", None)
    if world is None:
        if specs or scenario is not None:
            print("pfma serve: --fault and --scenario need the simulated rack (--rack fake, no --bus)",
                  file=sys.stderr)
            raise SystemExit(2)
        return
    from sim.faults import parse_fault
    from sim.scenario import ScenarioRunner, load_scenario
    rack = world.rack_config
    try:
        faults = [parse_fault(s, rack) for s in specs]
        if isinstance(scenario, str):
            scenario = load_scenario(scenario, rack)
    except ConfigError as err:
        print(f"pfma serve: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as err:
        print(f"pfma serve: scenario {scenario}: {err.strerror or err}", file=sys.stderr)
        raise SystemExit(2) from None
    _scenario_errors(args, scenario, world)
    ctl = FaultController(svc, world)
    usb = getattr(getattr(getattr(svc, "hand", None), "hid", None), "opener", None)
    if hasattr(usb, "unplug") and hasattr(usb, "replug"):  # --hid fake: hand-unplugged pulls it too
        from sim.faults import attach_usb_hand_controller
        attach_usb_hand_controller(world, usb)
    for f in faults:
        try:
            ctl.inject(f.spec)
        except ConfigError as err:  # the same fault twice
            print(f"pfma serve: --fault {f.spec}: {err}", file=sys.stderr)
            raise SystemExit(2) from None
    if scenario is not None:
        ctl.scenario = ScenarioRunner(scenario, ctl.faults, svc.schedule.frame_rate_hz,
                                      say=ctl.scenario_step)
        print(f"pfma serve: scenario {scenario.name}: {len(scenario.steps)} steps"
              + (f" ({scenario.description})" if scenario.description else ""), flush=True)
    ctl.install()
    buffer = getattr(args, "buffer", None) or svc.buf.name
    endpoint = FaultEndpoint(socket_path(buffer), ctl)
    try:
        endpoint.start()
    except PfmaError as err:  # e.g. a buffer name too long for a socket path: run without it
        print(f"pfma serve: no fault control endpoint ({err}); pfma fault cannot reach this "
              f"service, --fault and --scenario still apply", file=sys.stderr)
        return
    atexit.register(endpoint.close)
    stop = svc.stop

    def stop_and_close(*a, **kw):
        try:
            return stop(*a, **kw)
        finally:
            endpoint.close()
    svc.stop = stop_and_close
    print(f"pfma serve: fault control on {endpoint.path} (pfma fault inject|clear|list "
          f"--buffer {buffer})", flush=True)
