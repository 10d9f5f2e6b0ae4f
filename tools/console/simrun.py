"""The whole simulated system for ``make run`` / ``pfma console --sim``: the system
simulator (simulated rack, the real I/O service, the real controller) run in a thread,
paced to the wall clock, the controller powered up and flying the short demo path
(:func:`sim.demo.demo_goal`) through the Joint Planner; the console reads it like a live
system. So do the other tools: on the names it is given (``pfma console --sim``: the default
buffer ``pfma`` and world model ``pfma_wm`` unless in use, :mod:`tools.runnames`) it keeps
what ``pfma serve --rack fake`` keeps beside its buffer: the frame history ring (``pfma
record``, ``watch``, ``scope``) and the fault control socket (``pfma fault``).

Assumed (docs/console.md): simulated time follows the wall clock when the host is fast
enough and falls behind otherwise (never ahead); the console shows the ratio. The
simulated service's watchdog runs on simulated time, so a slow host never trips it.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from controller.decision import Status
from controller.layers import Request
from sim.demo import DEMO_JAW_OBJECT_M, demo_goal, demo_gripper
from sim.system import SystemSimulator

#: simulated frames run per lock of the pacing loop (a few: the console's reads interleave)
FRAMES_PER_SLICE = 4
#: simulated seconds the orderly stop waits for SHUT DOWN before stopping the service anyway
STOP_POWER_DOWN_S = 2.0


class SimulatedSystem:
    """The system simulator stepped in a background thread at (at most) wall-clock speed.

    :param buffer: Bit3 shared-memory name (None: a private random one), taken as given (the
        caller decides it is free: :func:`tools.runnames.claim`)
    :param wm: world-model shared-memory name (None: private memory), removed by :meth:`close`
    :param sim_errors: the simulated rack's imperfections (sim/errors.py; 0: none)
    """

    def __init__(self, *, demo: bool = True, power_up: bool = True, buffer: str | None = None,
                 wm: str | None = None, sim_errors: int = 0) -> None:
        from sim.errors import seeded
        self.wm_name = wm
        self.sim = SystemSimulator(name=buffer, wm_name=wm, ring=True, errors=seeded(sim_errors))
        #: why ``pfma fault`` cannot reach this system (None: it can), said by the caller
        self.fault_note: str | None = None
        self._faults = None
        try:
            self._open_fault_control()
            self.sim.step(10)  # the service's first frames (links open)
        except BaseException:
            self.close()
            raise
        self.demo = demo
        self.lock = threading.Lock()  # held while frames run (the sim is not thread-safe itself)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._q0: list[float] | None = None
        self._t_up: float | None = None
        self._pose = -1
        self.speed = 1.0  #: simulated seconds per wall second over the last second
        if power_up:
            self.sim.rt.request(Request.POWER_UP)

    @property
    def name(self) -> str:
        return self.sim.name

    def _open_fault_control(self) -> None:
        """``pfma fault inject|clear|list --buffer NAME`` into this simulated rack, as into
        ``pfma serve --rack fake``'s (the requests are applied between two frames, in the
        thread that runs them)."""
        from pfma.errors import PfmaError
        from tools.faultctl import FaultController, FaultEndpoint, socket_path
        ctl = FaultController(self.sim.svc, self.sim.world)
        ctl.install()
        endpoint = FaultEndpoint(socket_path(self.name), ctl)
        try:
            endpoint.start()
        except PfmaError as err:
            self.fault_note = f"no fault control endpoint ({err}): pfma fault cannot reach this system"
            return
        self._faults = endpoint

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="pfma-sim", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        sim = self.sim
        wall0, sim0 = time.monotonic(), sim.clock.now()
        mark_w, mark_s = wall0, sim0
        while not self._stop.is_set():
            ahead = (sim.clock.now() - sim0) - (time.monotonic() - wall0)
            if ahead > 0:
                time.sleep(min(ahead, 0.01))
                continue
            with self.lock:
                sim.step(FRAMES_PER_SLICE)
                self._fly()
            now = time.monotonic()
            if now - mark_w >= 1.0:
                self.speed = (sim.clock.now() - mark_s) / (now - mark_w)
                mark_w, mark_s = now, sim.clock.now()

    def _fly(self) -> None:
        """The demo path: a new joint goal every few seconds once START UP COMPLETE."""
        rt = self.sim.rt
        if not self.demo or rt.halted or rt.status("updown") != Status.START_UP_COMPLETE:
            return
        t = self.sim.clock.now()
        if self._q0 is None:
            self._q0 = [float(v) for v in rt.wm.get("daq.joint_angle_rad")]
            self._t_up = t
            self._place_jaw_object()
        from controller.params import JOINT_NAMES
        k, goal = demo_goal(JOINT_NAMES, self._q0, t - (self._t_up or t))
        if k != self._pose:
            self._pose = k
            rt.set_joint_goal(goal)
            grip = demo_gripper(k)
            if grip is not None:
                from pfma.gripper import ACTIONS
                rt.gripper_request(ACTIONS[grip])

    def _place_jaw_object(self) -> None:
        """The demo's part between the jaws of the simulated world (sim.demo.DEMO_JAW_OBJECT_M)."""
        arm = self.sim.world.sim.arm
        if arm.jaw_object_m is None:
            try:
                arm.place_jaw_object(DEMO_JAW_OBJECT_M)
            except ValueError:
                pass  # the jaw is narrower than the part: the demo's close then closes on nothing

    def stop(self) -> np.ndarray:
        """Stop the frames, power down in order (halted: release the halt), stop the
        service (outputs 0 V and disconnected); returns the DAC's volts afterwards."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        sim = self.sim
        with self.lock:
            rt = sim.rt
            if rt.halted:
                rt.release_halt()
            elif rt.status("updown") not in (Status.SHUT_DOWN, Status.ERROR):
                rt.request(Request.POWER_DOWN)
                try:
                    sim.run_until(lambda: rt.all_status(Status.SHUT_DOWN), int(STOP_POWER_DOWN_S / sim.period_s))
                except TimeoutError:
                    pass  # the service stop below makes the outputs safe anyway
            sim.svc.stop("make run ended")
            volts = sim.dac_volts()
        return volts

    def close(self) -> None:
        """Remove what the system made: the fault socket, the buffer and its ring, the world model."""
        if self._faults is not None:
            self._faults.close()
            self._faults = None
        self.sim.close()
        if self.wm_name is not None:
            from controller.worldmodel import WorldModel
            WorldModel.remove_segment(self.wm_name)
