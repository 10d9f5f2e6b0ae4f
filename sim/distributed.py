"""The distributed system simulator: a controller distributed over processes by a
configuration (controller/distributed.py), every process's runtime in this one process,
on the simulated clock, deterministic.

:class:`DistributedSimulator` is :class:`sim.system.SystemSimulator` with the seven layers
split as a distribution file says: the fake world and the real I/O service (one
:class:`sim.rig.SimRig`), and one :class:`controller.distributed.DistributedProcess` per
configured process, each with its own world model and runtime running only its layers.
The process that runs Data Acquisition holds the Bit3 command area; the others read
the service's inputs for the frame number only.

One minor frame, after each service frame, in a fixed order:

1. **imports**: every process reads the other processes' sections first, so each sees the
   others as they were at the end of the previous frame, whatever the order below. This is
   what processes woken together by the service's publish see: none has finished the new
   frame when the others import;
2. **frames**: each process's runtime runs its minor frame, in the order of the file
   (the imported sections are applied at its first communications segment);
3. :attr:`DistributedSimulator.after_step` callables (a test publishing sections over Zenoh).

A process can be stopped (:meth:`DistributedSimulator.stop`): it no longer runs frames, so
its section goes stale as a dead process's would. Two simulators built and driven the same
way give identical traces.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from bit3.client import Client
from controller.decision import Status
from controller.distributed import (
    DistributedConfig, DistributedProcess, ModelSource, SectionSource, load_config, parse_config,
)
from controller.frames import FrameConfig
from controller.layers import Request
from controller.runtime import LAYER_KEYS, ControllerRuntime
from ioservice.schedule import Schedule
from sim.rig import SimRig
from sim.system import FrameStepping


class _SimSource:
    """Another simulated process's world model, found when first read (the processes are
    built one after the other)."""

    packed = False

    def __init__(self, sim: "DistributedSimulator", process: str, signature: bytes) -> None:
        self._sim, self._process, self._sig = sim, process, signature
        self._src: ModelSource | None = None

    def read(self, into: bytearray) -> int | None:
        if self._src is None:
            self._src = ModelSource(self._sim.processes[self._process].rt.wm, self._sig)
        return self._src.read(into)

    def problem(self) -> str | None:
        return None if self._src is None else self._src.problem()

    def close(self) -> None:
        self._src = None


class DistributedSimulator(FrameStepping):
    """The whole stack, the controller distributed by ``config``, in simulated time.

    :param config: a :class:`DistributedConfig`, a distribution file, or a parsed TOML dict
    :param frames: controller frame configuration; the service runs at its frame rate
    :param profile: shortcut for ``FrameConfig.profile(profile)``
    :param name: Bit3 shared-memory name (default: a private random one)
    :param wm_base: world models ``<wm_base>.<process>`` in shared memory (for ``pfma wm``);
        None: private memory
    :param require_ft: a stale F/T link is a Data Acquisition fault
    :param links: process -> its sources (:class:`controller.distributed.SectionSource` per other
        process), for a transport other than reading the simulated processes' models (a
        test's Zenoh); default: each reads the others' world models directly
    :param world_kw: extra keyword arguments for :class:`fakes.world.FakeWorld`
    """

    def __init__(self, config: "DistributedConfig | str | Path | Mapping", *, frames: FrameConfig | None = None,
                 profile: str | None = None, name: str | None = None, wm_base: str | None = None,
                 require_ft: bool = True, trace_frames: int = 4096,
                 links: Callable[[DistributedProcess], Mapping[str, SectionSource]] | None = None,
                 **world_kw) -> None:
        if isinstance(config, Mapping):
            config = parse_config(config)
        elif not isinstance(config, DistributedConfig):
            config = load_config(config)
        self.config = config
        if frames is None:
            frames = FrameConfig.profile(profile) if profile else FrameConfig()
        self.frames = frames
        self.rig = SimRig(name=name, prefix="pfma-dsim-",
                          service_kw={"schedule": Schedule(frame_rate_hz=frames.frame_rate_hz)}, **world_kw)
        self.name, self.clock, self.world, self.svc = self.rig.name, self.rig.clock, self.rig.world, self.rig.svc
        self.processes: dict[str, DistributedProcess] = {}
        self._readers: list[Client] = []
        self.running: dict[str, bool] = {}  #: False: the process is stopped (no frames, its section stale)
        self.after_step: list[Callable[[], None]] = []  #: run after every process's frame
        self.service_frames = 0
        self.wm_base = wm_base
        try:
            for p in config.processes:
                if "daq" in p.layers:
                    client = self.rig.controller(owner=f"controller-{p.name}")
                else:
                    client = Client.attach(self.name, layout=self.rig.layout, clock_now=self.clock.now)
                    self._readers.append(client)

                def sim_sources(dp: DistributedProcess) -> Mapping[str, SectionSource]:
                    return {q: _SimSource(self, q, dp.signature) for q in config.names if q != dp.name}
                self.processes[p.name] = DistributedProcess(
                    config, p.name, client, wm_base=wm_base, sources=links or sim_sources, frames=frames,
                    clock=self.clock, require_ft=require_ft, trace_frames=trace_frames)
                self.running[p.name] = True
        except BaseException:
            self.close()
            raise
        self.layer_process = {k: config.process_of(k) for k in LAYER_KEYS}

        def controller_frames(info) -> None:  # right after each service frame
            self.service_frames += 1
            live = [dp for dp in self.processes.values() if self.running[dp.name]]
            for dp in live:  # 1. every process imports the others' sections of the frame before
                assert dp.importer is not None
                dp.importer.fetch()
                dp.importer.prefetched = True
            for dp in live:  # 2. each runs its minor frame, in the file's order
                dp.rt.tick()
            for fn in self.after_step:
                fn()
        self.rig.after_frame.append(controller_frames)

    # --- the processes -------------------------------------------------------------------
    def rt(self, process_or_layer: str) -> ControllerRuntime:
        """The runtime of a process, or of the process that runs a layer."""
        p = self.layer_process.get(process_or_layer, process_or_layer)
        return self.processes[p].rt

    @property
    def top(self) -> ControllerRuntime:
        """The runtime that runs System Up/Down (user requests go there)."""
        return self.rt("updown")

    @property
    def daq(self) -> ControllerRuntime:
        """The runtime that runs Data Acquisition (the Bit3 command writer)."""
        return self.rt("daq")

    def stop(self, process: str) -> None:
        """Stop a process: it runs no more frames (as if it died); its section goes stale."""
        self.running[self.config.process(process).name] = False

    def resume(self, process: str) -> None:
        self.running[self.config.process(process).name] = True

    # --- running: FrameStepping (each frame: the service's, then every process's) -----------

    def statuses(self) -> dict[str, Status]:
        """Each layer's status in the world model of the process that runs it."""
        return {k: Status(self.rt(k).wm.get_state_variable(f"{k}.status")) for k in LAYER_KEYS}

    def all_status(self, status: Status) -> bool:
        return all(s == status for s in self.statuses().values())

    def first_change(self, layer: str, to: Status, since_frame: int = -1) -> int | None:
        """Frame in which layer ``layer``'s table (in its process) first decided ``to``."""
        return self.rt(layer).first_change(layer, to, since_frame)

    def power_up(self, max_frames: int = 1000) -> int:
        """Request POWER UP (System Up/Down's process) and run until every layer is START
        UP COMPLETE in its own process; frames taken."""
        self.top.request(Request.POWER_UP)
        return self.run_until(lambda: self.all_status(Status.START_UP_COMPLETE), max_frames)

    @property
    def updown_rt(self) -> ControllerRuntime:  # FrameStepping.request/response
        return self.top

    # --- looking -------------------------------------------------------------------------
    def svc_frame(self) -> int:
        return int(self.rig.reader.header().frame) if self.rig.reader is not None else -1

    def close(self) -> None:
        for dp in self.processes.values():
            dp.close(unlink=True)
        self.processes = {}
        for c in self._readers:
            c.close()
        self._readers = []
        self.rig.close()

    def __enter__(self) -> "DistributedSimulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["DistributedSimulator"]


def figures(config: "DistributedConfig | str | Path | Mapping", *, cost_frames: int = 960) -> dict:
    """What docs/controller.md quotes for a distribution (simulated time; the costs are this
    host's): power-up frames, a resolver loss of signal at the rack from detection to System
    Up/Down ERROR, each process lost (frames to its neighbour's fault and to System Up/Down
    ERROR or 0 V on the rate channels), and each process's frame cost powered up beside the
    import's share of it. ``pfma bench`` may call it (benchmarks live in bench/)."""
    import time as _time
    out: dict = {}
    with DistributedSimulator(config) as sim:
        sim.step(10)
        out["power_up_frames"] = sim.power_up(1000)
        out["power_up_ms"] = out["power_up_frames"] * sim.period_s * 1e3
        costs: dict[str, list[float]] = {p: [] for p in sim.processes}
        imports: dict[str, list[float]] = {p: [] for p in sim.processes}
        for p, dp in sim.processes.items():
            dp.rt.on_frame.append(lambda r, p=p: costs[p].append(r.cost_s))
            imp = dp.importer
            assert imp is not None

            def timed_fetch(fetch=imp.fetch, p=p) -> None:  # the simulator calls it before the frames
                t0 = _time.perf_counter()
                fetch()
                imports[p].append(_time.perf_counter() - t0)
            imp.fetch = timed_fetch  # type: ignore[method-assign]
        sim.step(cost_frames)
        out["cost_us"] = {p: {"p50": float(np.percentile(np.array(c) * 1e6, 50)),
                              "p99": float(np.percentile(np.array(c) * 1e6, 99)),
                              "fetch_p50": float(np.percentile(np.array(imports[p]) * 1e6, 50))}
                          for p, c in costs.items()}
        k = sim.daq.frame
        sim.world.bus["rtd1"].inject("loss_of_signal", channel=0)
        sim.run_until(lambda: sim.daq.daq.fault_bits != 0, 50)
        k_detect = sim.daq.frame
        sim.run_until(lambda: sim.first_change("updown", Status.ERROR, k) is not None, 50)
        out["resolver_detect_to_updown_frames"] = sim.first_change("updown", Status.ERROR, k) - k_detect
        out["resolver_inject_to_updown_frames"] = sim.first_change("updown", Status.ERROR, k) - k
    from sim.system import SystemSimulator
    with SystemSimulator() as one:  # the same frames in one process, same host, same run
        one.step(10)
        one.power_up(1000)
        single: list[float] = []
        one.rt.on_frame.append(lambda r: single.append(r.cost_s))
        one.step(cost_frames)
        out["single_process_cost_us"] = {"p50": float(np.percentile(np.array(single) * 1e6, 50)),
                                         "p99": float(np.percentile(np.array(single) * 1e6, 99))}
    for victim in sim.config.names:
        with DistributedSimulator(config) as sim:
            sim.step(10)
            sim.power_up(1000)
            sim.step(10)
            k = sim.daq.frame
            sim.stop(victim)
            if victim == sim.layer_process["daq"]:
                top = sim.top
                n = sim.run_until(lambda: top.first_change("updown", Status.ERROR, k) is not None, 400)
                out[f"{victim}_lost_to_updown_frames"] = n
            else:
                n = sim.run_until(lambda: bool(np.all(sim.dac_volts()[:6] == 0.0)) and
                                  sim.daq.status("daq") == Status.SHUT_DOWN, 400)
                out[f"{victim}_lost_to_rates_0v_disarmed_frames"] = n
    return out
