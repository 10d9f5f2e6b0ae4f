"""A distributed controller (issue 19 item 3; docs/controller.md "Distributing the layers"):
``pfma controller --distribute FILE --process NAME`` runs one process of it (assembled by
:class:`tools.stacks.controller.ControllerStack`); with ``--sim``, all of them in the
distributed simulator."""

from __future__ import annotations

import signal
import sys
import time

from tools.cli.controller.common import first_cause_line, log, no_wm, refuse, stack_options, summary
from tools.stacks.controller import PROG, ControllerStack, Distribution, DistributedDriver

#: live seconds a process with --power-up waits for every other process's section before it
#: gives up (assumed: long enough to start the processes by hand one after the other)
DISTRIBUTED_WAIT_S = 10.0
PROG_DISTRIBUTE = f"{PROG} --distribute"


def _unsupported(args) -> list[str]:
    """Flags a distributed controller does not take (halt and single step stay with one
    process; the motion and path flags set world-model variables: pfma wm set --name BASE.PROCESS)."""
    flags = [("--halt", args.halt), ("--step", args.step is not None), ("--record", args.record is not None),
             ("--play", args.play is not None), ("--teleop", args.teleop is not None),
             ("--impedance", args.impedance is not None), ("--delay", args.delay is not None),
             ("--jitter", args.jitter is not None), ("--vernier", args.vernier), ("--demo-stick", args.demo_stick),
             ("--demo-wall", args.demo_wall is not None), ("--tables", args.tables),
             ("--hc-frame", args.hc_frame != "world"), ("--shoulder-roll", args.shoulder_roll is not None)]
    return [f for f, on in flags if on]


def _load(args):
    """The --distribute file, or the exit code after saying why it is refused."""
    from controller.distributed import DistributedConfigError, load_config
    if args.action is not None:
        return refuse("not for a distributed controller (halt, step, resume and route need one process's "
                      "controller)", f"{PROG} {args.action}")
    if args.distribute is None:
        return refuse("--process needs --distribute FILE (the file that assigns the layers to processes)")
    try:
        config = load_config(args.distribute)
    except DistributedConfigError as e:
        for problem in e.problems:
            refuse(f"{e.source}: {problem}")
        return 2
    bad = _unsupported(args)
    if bad:
        return refuse(f"{', '.join(bad)} not with a distributed controller (set world-model variables with `pfma wm "
                      f"set --name BASE.PROCESS`; halt and single step need one process)", PROG_DISTRIBUTE)
    return config


def _process(args, config, base: str):
    """This process's Distribution, or the exit code after saying why it is refused."""
    from controller.distributed import DistributedConfigError
    from tools.attach import remote_target
    if args.process is None:
        return refuse(f"which process is this? --process NAME (processes in {config.source}: "
                      f"{', '.join(config.names)}); --sim runs all of them simulated", PROG_DISTRIBUTE)
    try:
        spec = config.process(args.process)
    except DistributedConfigError as e:
        return refuse(e.problems[0])
    if args.power_up and "updown" not in spec.layers:
        return refuse(f"--power-up goes to the process that runs updown (System Up/Down): "
                      f"{config.process_of('updown')}, not {spec.name}")
    if "daq" in spec.layers and remote_target(args.buffer) is not None:
        return refuse(f"process {spec.name} runs daq, the one writer of the Bit3 command area: it needs the "
                      f"service's shared memory (--buffer NAME on the rack's host), not {args.buffer}")
    return Distribution(config, spec.name, base)


def run(args) -> int:
    """``pfma controller --distribute FILE --process NAME``: one process of a distributed
    controller (or, with --sim, all of them in the distributed simulator)."""
    config = _load(args)
    if isinstance(config, int):
        return config
    if args.sim:  # --wm none: private memory (no `pfma wm` view)
        return _run_sim(args, config, None if no_wm(args) else args.wm or config.wm or "pfma_wm")
    if no_wm(args):
        return refuse("the processes find each other's world models by name: give --wm BASE (not none)",
                      PROG_DISTRIBUTE)
    where = _process(args, config, args.wm or config.wm or "pfma_wm")
    if isinstance(where, int):
        return where
    try:
        stack = ControllerStack(stack_options(args, where)).open()
    except FileNotFoundError as e:
        return refuse(f"no service buffer {args.buffer!r} ({e}); start `pfma serve`", code=1)
    except Exception as e:  # noqa: BLE001 - a PfmaError (no service, no bridge, world model in use): one line
        from pfma.errors import PfmaError
        if not isinstance(e, PfmaError):
            raise
        return refuse(str(e), code=1)
    with stack:
        assert isinstance(stack.driver, DistributedDriver)
        # SIGINT and SIGTERM acted on between frames, as for one process: a KeyboardInterrupt
        # inside a frame could leave the world model mid-write and the power-down hung
        stack.stop_on_signals()
        return _run_process(stack.driver, args)


def _say_process(d: DistributedDriver) -> None:
    others = [p for p in d.config.names if p != d.process]
    print(f"{PROG}: process {d.process} of {d.config.source}: layers {' '.join(d.spec.layers)}; world model "
          f"{d.dp.wm_name}; the others' sections by {'Zenoh' if d.link is not None else 'shared memory'} from "
          f"{', '.join(others)}", flush=True)


def _run_process(d: DistributedDriver, args) -> int:
    """The frames of one live process (the POWER UP, with --power-up, once every other
    process's section is seen) and the summary; the stack then leaves the arm safe."""
    from controller.layers import Request
    imp, pacer = d.dp.importer, d.pacer
    assert pacer is not None
    _say_process(d)
    d.rt.on_frame.append(d.show)
    budget = int(round(args.duration / d.period_s)) if args.duration is not None else sys.maxsize
    code = 0
    try:
        powered = not args.power_up
        wait_end = None
        for _ in range(budget):
            d.frame()
            if powered:
                continue
            # every other section seen, and this process past its first frames (imports,
            # first allocations, the collector frozen): then the request
            if imp.seen_all and pacer.frames > d.FREEZE_AFTER_FRAMES:
                d.rt.request(Request.POWER_UP)
                powered = True
            elif not imp.seen_all:
                if wait_end is None:
                    print(f"{PROG}: waiting for the sections of {', '.join(imp.missing())} before POWER UP",
                          flush=True)
                    wait_end = time.monotonic() + DISTRIBUTED_WAIT_S
                elif time.monotonic() > wait_end:
                    names = ", ".join(d.config.wm_name(d.base, p) for p in imp.missing())
                    code = refuse(f"no world-model section from {', '.join(imp.missing())} within "
                                  f"{DISTRIBUTED_WAIT_S:g} s ({names}): start those processes first; no POWER UP",
                                  code=1)
                    break
        summary(d, args)
    except KeyboardInterrupt:
        print()
        if d.stop_signal:
            log.warning(f"{signal.Signals(d.stop_signal).name}: stopping (powering down in order)")
        summary(d, args)  # Ctrl-C too: what happened, before the power-down
    return code


def _run_sim(args, config, base: str | None) -> int:
    """``--sim --distribute FILE``: every process in the distributed simulator."""
    from controller.frames import FrameConfig
    from controller.worldmodel import WorldModelError
    from sim.distributed import DistributedSimulator
    if args.process is not None:
        try:
            config.process(args.process)
        except Exception as e:  # noqa: BLE001 - DistributedConfigError
            return refuse(e.problems[0])  # type: ignore[attr-defined]
    try:
        sim = DistributedSimulator(config, frames=FrameConfig.profile(args.profile), wm_base=base,
                                   require_ft=not args.no_ft)
    except WorldModelError as e:
        return refuse(str(e), code=1)
    with sim:
        _sim_frames(sim, args, config, args.process or config.process_of("updown"))
    return 0


def _sim_frames(sim, args, config, shown: str) -> None:
    """The distributed simulator's frames, the trace of process ``shown``, the summary."""
    from controller.decision import Status
    from controller.layers import Request
    rt = sim.rt(shown)
    printed = [False]

    def show(rec) -> None:
        if not args.trace or (args.changes and not any(lt.changed for lt in rec.layers)):
            return
        if not printed[0]:
            print(f"process {shown} (layers {' '.join(config.process(shown).layers)}; the others as its "
                  f"world model sees them)")
            print(rt.header())
            printed[0] = True
        print(rt.format_frame(rec), flush=True)
    rt.on_frame.append(show)
    sim.step(10)  # the service's first frames (links open)
    if args.power_up:
        sim.top.request(Request.POWER_UP)
    budget = int(round((args.duration if args.duration is not None else 1.0) / sim.period_s))
    up_at = None
    for n in range(budget):
        sim.step(1)
        if up_at is None and sim.all_status(Status.START_UP_COMPLETE):
            up_at = n + 1
    for p in config.processes:
        line = "  ".join(f"{k}={Status(s).name}" for k, s in sim.statuses().items() if k in p.layers)
        print(f"process {p.name}: {line}")
    if args.power_up:
        print(f"power-up: {'every layer START UP COMPLETE after ' + str(up_at) + ' frames' if up_at else 'not complete'}")
    print(f"process {shown}: {first_cause_line(rt)}")
    if args.messages:
        print(f"--- last {args.messages} messages of process {shown} ---")
        print(rt.messages.format(args.messages))
