"""What the checkout runs against: a simulated rack in simulated time, or a running service.

Both targets offer the same small API to the checks:

- ``reader``: a read-only :class:`bit3.client.Client` on the service's buffer;
- ``now()``, ``wait(seconds)``, ``wait_until(cond, timeout_s)``: time, in simulated
  seconds (:class:`SimTarget`, deterministic and fast) or real ones (:class:`LiveTarget`);
- ``commander()``: claims the command area; while ``keepalive`` is on the target keeps
  the heartbeat fresh (every frame in simulation, every 5 ms from a thread when live);
- ``stimulus``: a :class:`FakeStimulus` on the simulated rack, ``None`` on a real one
  (where the checkout prompts the operator instead).

:class:`SimTarget` runs on :class:`sim.rig.SimRig` (``FakeWorld`` + ``IoService``
on a private buffer, with hooks that run before every service frame).
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from typing import Any, Callable

from bit3.client import Client
from bit3.layout import ServiceState
from pfma.errors import PfmaError
from pfma.rack import RackConfig, load_rack


class ServiceLost(PfmaError):
    """The service stopped publishing frames while the checkout was running."""


class Commander:
    """The claimed command area, shared by the checks and the heartbeat keeper."""

    def __init__(self, client: Client) -> None:
        self.client = client
        self.lock = threading.Lock()
        self.keepalive = False

    def set(self, **fields: Any) -> int:
        """Set command fields and publish (heartbeat + 1)."""
        with self.lock:
            return self.client.write_commands(**fields)

    def beat(self) -> None:
        """Publish the command record unchanged (heartbeat + 1) when ``keepalive`` is on."""
        if self.keepalive:
            with self.lock:
                self.client.publish_commands()

    @property
    def record(self):
        return self.client.command


class Target:
    """Common part of both targets (see the module docstring)."""

    kind = "target"
    stimulus: "FakeStimulus | None" = None

    def __init__(self, reader: Client, rack: RackConfig, name: str) -> None:
        self.reader = reader
        self.layout = reader.layout
        self.rack = rack
        self.name = name
        self._commander: Commander | None = None

    # time ----------------------------------------------------------------------------
    def now(self) -> float:
        raise NotImplementedError

    def wait(self, seconds: float) -> None:
        raise NotImplementedError

    def wait_until(self, cond: Callable[[], bool], timeout_s: float, poll_s: float = 0.0125) -> bool:
        """Poll ``cond`` every ``poll_s`` until it holds (True) or ``timeout_s`` passed (False)."""
        t_end = self.now() + timeout_s
        while True:
            if cond():
                return True
            if self.now() >= t_end:
                return False
            self.wait(min(poll_s, max(t_end - self.now(), 1e-6)))

    def inputs(self):
        return self.reader.read_inputs()

    # commands -------------------------------------------------------------------------
    def commander(self) -> Commander:
        raise NotImplementedError

    def release_commands(self) -> None:
        """Stop the heartbeat and give the command area back."""
        if self._commander is not None:
            self._commander.keepalive = False
            self._commander.client.close()
            self._commander = None

    def describe(self) -> str:
        return self.name

    def close(self) -> None:
        self.release_commands()
        self.reader.close()


class FakeStimulus:
    """The operator's hands on the simulated rack: only the fake rack has one.

    The checkout calls these instead of prompting an operator. Each method changes
    what the fake hardware presents; the service then samples it as usual.
    """

    def __init__(self, world) -> None:
        self.world = world
        self._axes = [0.0] * 6
        self._discretes = [False] * 3

    def _cae_signals(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        from fakes.sim_rack import CAE_AXIS_SIGNALS, CAE_DISCRETE_SIGNALS
        return CAE_AXIS_SIGNALS, CAE_DISCRETE_SIGNALS

    def cae_axis(self, signal: str, volts: float) -> None:
        """Hold one CAE axis at ``volts`` (0 = centred)."""
        axes, _ = self._cae_signals()
        self._axes[axes.index(signal)] = float(volts)
        self.world.set_cae(self._axes, tuple(self._discretes))

    def cae_discrete(self, signal: str, on: bool) -> None:
        """Close (``on``) or open one CAE discrete."""
        _, discretes = self._cae_signals()
        self._discretes[discretes.index(signal)] = bool(on)
        self.world.set_cae(self._axes, tuple(self._discretes))

    def user_inputs(self, word: int) -> None:
        """Drive the 16 user I/F box inputs."""
        self.world.set_user_inputs(int(word))

    def joint_angle_rad(self, joint: str) -> float | None:
        """The joint's true angle, as a person reads it on the arm's scale (the simulated
        arm's state, not the resolver's reading); None for a joint the arm model lacks."""
        from fakes.arm_params import AXES
        axis = next((i for i, a in enumerate(AXES) if a.joint == joint), None)
        return None if axis is None else float(self.world.sim.arm.q[axis])

    def release(self) -> None:
        """Stick centred, switches open (inputs keep their last word)."""
        self._axes = [0.0] * 6
        self._discretes = [False] * 3
        self.world.set_cae(self._axes, tuple(self._discretes))


def _fault_kinds() -> list[tuple[str, str]]:
    from sim.faults import KINDS
    return list(KINDS.values())


class SimTarget(Target):
    """The simulated rack and the I/O service in this process, in simulated time.

    :param rack: rack configuration (default: the IRSS rack)
    :param service_kw: extra ``IoService`` arguments
    """

    kind = "simulated rack"

    def __init__(self, rack: RackConfig | None = None, buffer_name: str | None = None,
                 sim_errors: int = 0, **service_kw) -> None:
        from sim.errors import seeded
        from sim.rig import SimRig
        rack = rack if rack is not None else load_rack()
        self.rig = SimRig(rack, name=buffer_name or f"pfma-checkout-{os.getpid()}-{uuid.uuid4().hex[:6]}",
                          service_kw=service_kw, errors=seeded(sim_errors, rack))
        self.buffer_name = self.rig.name
        self.clock = self.rig.clock
        self.world = self.rig.world
        self.svc = self.rig.svc
        self.on_frame: list[Callable] = self.rig.on_frame  #: run before each service frame
        reader = self.rig.reader
        super().__init__(reader, rack, f"simulated rack {rack.name!r} (in-process service, simulated time)")
        self.stimulus = FakeStimulus(self.world)
        self._faults = None  # a sim.faults.FaultSet, made by the first inject_fault

    #: fault specs :meth:`inject_fault` understands (``pfma checkout --sim-fault``): every
    #: kind of :mod:`sim.faults` (``pfma fault list``), the four the checkout always had among them
    FAULTS = {syntax: meaning for syntax, meaning in _fault_kinds()}

    def inject_fault(self, spec: str) -> str:
        """Inject one fault into the simulated rack from a spec (:mod:`sim.faults`, the same
        grammar as ``pfma serve --fault`` and ``pfma fault inject``).

        :returns: a one-line description
        :raises ConfigError: for an unknown spec, board, signal or register (did you mean)
        """
        if self._faults is None:
            from sim.faults import FaultSet
            self._faults = FaultSet(self.world)
        return self._faults.inject(spec, since=self.now()).description

    def now(self) -> float:
        return self.clock.now()

    def wait(self, seconds: float) -> None:
        frames = max(1, int(round(seconds * self.svc.schedule.frame_rate_hz)))
        self.svc.loop.run(frames=frames, freeze_gc=False)

    def commander(self) -> Commander:
        if self._commander is None:
            c = Client.attach(self.buffer_name, writer="commands", owner="pfma-checkout",
                              layout=self.layout, clock_now=self.clock.now)
            self._commander = Commander(c)
            self.on_frame.append(lambda info, cmd=self._commander: cmd.beat())
        return self._commander

    def release_commands(self) -> None:
        if self._commander is not None:
            self.on_frame.clear()
        super().release_commands()

    def close(self) -> None:
        try:
            super().close()  # releases the commands, closes the reader
        finally:
            self.rig.reader = None
            self.rig.close()


class LiveTarget(Target):
    """A running service's buffer, in real time.

    :param client: a read-only client (from :func:`tools.attach.attach_waiting`)
    :param rack: the rack configuration the service runs (scales, I_max)
    :param service_timeout_s: no new frame for this long raises :class:`ServiceLost`
    :param heartbeat_s: command heartbeat period while ``keepalive`` is on (< 15 ms watchdog)
    """

    kind = "running service"

    def __init__(self, client: Client, rack: RackConfig, *, service_timeout_s: float = 2.0,
                 heartbeat_s: float = 0.005) -> None:
        super().__init__(client, rack, f"service on buffer {client.buffer.name!r} (real time)")
        self.service_timeout_s = service_timeout_s
        self.heartbeat_s = heartbeat_s
        self._frame = -1
        self._frame_t = time.monotonic()
        self._hb_thread: threading.Thread | None = None
        self._hb_stop = threading.Event()

    def now(self) -> float:
        return time.monotonic()

    def _check_alive(self) -> None:
        h = self.reader.header()
        now = time.monotonic()
        if h.frame != self._frame:
            self._frame, self._frame_t = h.frame, now
        elif now - self._frame_t > self.service_timeout_s:
            raise ServiceLost(f"service on buffer {self.reader.buffer.name!r} published no frame for "
                              f"{now - self._frame_t:.1f} s (frame {h.frame}, state "
                              f"{ServiceState(h.service_state).name})")
        if h.service_state == ServiceState.STOPPED:
            raise ServiceLost(f"service on buffer {self.reader.buffer.name!r} stopped")

    def wait(self, seconds: float) -> None:
        t_end = time.monotonic() + seconds
        while True:
            self._check_alive()
            left = t_end - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, 0.05))

    def commander(self) -> Commander:
        if self._commander is None:
            c = Client.attach(self.reader.buffer.name, writer="commands", owner="pfma-checkout",
                              layout=self.layout)
            self._commander = Commander(c)
            self._hb_stop.clear()
            self._hb_thread = threading.Thread(target=self._heartbeat, args=(self._commander,),
                                               name="checkout-heartbeat", daemon=True)
            self._hb_thread.start()
        return self._commander

    def _heartbeat(self, cmd: Commander) -> None:
        while not self._hb_stop.wait(self.heartbeat_s):
            try:
                cmd.beat()
            except PfmaError:
                return

    def release_commands(self) -> None:
        self._hb_stop.set()
        if self._hb_thread is not None:
            self._hb_thread.join(1.0)
            self._hb_thread = None
        super().release_commands()


def make_sim_target(rack: str | RackConfig | None = None, sim_errors: int = 0) -> SimTarget:
    """A :class:`SimTarget` for ``rack`` ("fake"/None = the IRSS rack, or a TOML path), with
    the imperfections of seed ``sim_errors`` (sim/errors.py; 0: none)."""
    if isinstance(rack, RackConfig):
        return SimTarget(rack, sim_errors=sim_errors)
    return SimTarget(load_rack(None if rack in (None, "fake", "default") else rack), sim_errors=sim_errors)


__all__ = ["Commander", "FakeStimulus", "LiveTarget", "ServiceLost", "SimTarget", "Target",
           "make_sim_target"]
