"""The system simulator: fake rack, I/O service and controller in one process, in
simulated time, deterministic.

IRSS report 2.4.4: a non-real-time simulator of the whole multi-rate system in which
"task execution can be performed one line at a time", with a complete world model,
so that "virtually all of the non time related bugs" are rung out before the robot is
turned on, and compensators can be designed against a plant model. Here:

* :class:`fakes.world.FakeWorld` (the simulated arm, boards, F/T sensor, CRL master)
  on a :class:`pfma.clock.SimClock`;
* the real :class:`ioservice.service.IoService` on a private Bit3 buffer, its frame
  loop on the same clock (a :class:`ioservice.ticking.TickingClock` advancing the world
  between frames);
* the real :class:`controller.runtime.ControllerRuntime`, its minor frame run right
  after every service frame (the lock of the controller's frame to the service's), or,
  with ``FrameConfig(clock="own")``, at its own frame clock's times while the service keeps
  its own rates (a timer on the service's ticking clock: the two meet only in the buffer).

:meth:`SystemSimulator.step` advances whole minor frames; nothing else moves time.
Halting the simulator halts everything (as IRSS's halt stopped the frame interrupts);
:meth:`step` with ``frames=1`` is the single step. Halting the controller alone
(``Request.HALT``, docs/console.md) leaves the service running: the controller then holds
the outputs in the service's HALTED state every frame (:meth:`ControllerRuntime.tick`). Two simulators built the same way
and driven the same way produce identical traces.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

import numpy as np

from controller.frames import FrameConfig
from controller.layers import Request
from controller.params import check_shoulder_roll_deg
from controller.runtime import ControllerRuntime
from ioservice.schedule import Schedule
from sim.rig import SimRig

if TYPE_CHECKING:
    from fakes.world import FakeWorld
    from ioservice.service import IoService


class FrameStepping:
    """Stepping a simulated system frame by frame (its ``svc`` runs the service's loop, whose
    frame body also runs the controller's frames; ``frames`` is the FrameConfig)."""

    frames: FrameConfig
    svc: "IoService"
    world: "FakeWorld"

    @property
    def period_s(self) -> float:
        return self.frames.period_s

    def step(self, frames: int = 1) -> None:
        """Advance ``frames`` minor frames (each: the service frame, then the controller's)."""
        self.svc.loop.run(frames=frames, freeze_gc=False)

    def run_until(self, predicate, max_frames: int) -> int:
        """Step one frame at a time until ``predicate()`` is true; returns the frames run.

        :raises TimeoutError: not true after ``max_frames``
        """
        for n in range(1, max_frames + 1):
            self.step(1)
            if predicate():
                return n
        raise TimeoutError(f"condition not met within {max_frames} frames "
                           f"({max_frames * self.period_s * 1e3:.1f} ms simulated)")

    def dac_volts(self) -> np.ndarray:
        """What the DAC board drives right now (all channels), volts."""
        return np.asarray(self.world.bus["dac"].output_volts_all(), dtype=float)

    def joint_angles_rad(self) -> np.ndarray:
        """True joint angles of the simulated arm in command-area joint order."""
        from controller.params import JOINT_NAMES
        from fakes.arm_params import AXES
        q = self.world.sim.true_state().q
        stems = [a.joint for a in AXES]
        return np.array([q[stems.index(n)] for n in JOINT_NAMES], dtype=float)

    @property
    def shoulder_roll_rad(self) -> float:
        """Where the simulated arm's shoulder roll is pinned (its truth; the controller's
        index is its parameter ``joint.shoulder_roll_deg``, which may differ)."""
        return float(self.world.sim.arm.shoulder_roll_rad)

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """True tool pose of the simulated arm in the world (position m, quaternion w x y z):
        the kinematics of its true joint angles and its true shoulder-roll index."""
        from controller.kinematics import fk
        return fk(self.joint_angles_rad(), self.shoulder_roll_rad)

    @property
    def updown_rt(self) -> ControllerRuntime:
        """The runtime whose world model has System Up/Down (the user requests go there)."""
        raise NotImplementedError

    def request(self, kind: int, arg: int = 0, max_frames: int = 400) -> tuple[int, str]:
        """Post a user request (``Request.*``) and run frames until System Up/Down gives it a
        final answer (``Response.FINAL``: not QUEUED or IN PROGRESS) or ``max_frames`` have
        run; returns (Response code, text) of its newest answer."""
        from controller.layers import Response
        seq = self.updown_rt.request(kind, arg)
        code, text = Response.NONE, ""
        for _ in range(max_frames):
            self.step(1)
            a = self.updown_rt.answer(seq)
            if a is not None:
                code, text = a
                if code in Response.FINAL:
                    break
        return code, text

    def response(self) -> tuple[int, int, str]:
        """(request number answered, Response code, the answer in words)."""
        v = self.updown_rt.wm.get_task_inputs(("ui.response_seq", "ui.response", "ui.response_text"))
        text = bytes(v["ui.response_text"]).rstrip(b"\0").decode(errors="replace")
        return int(v["ui.response_seq"]), int(v["ui.response"]), text


class SystemSimulator(FrameStepping):
    """The whole stack in simulated time.

    :param frames: controller frame configuration; the service runs at its frame rate
    :param profile: shortcut for ``FrameConfig.profile(profile)``
    :param name: Bit3 shared-memory name (default: a private random one)
    :param wm_name: world-model shared-memory name (None: private memory)
    :param require_ft: a stale F/T link is a Data Acquisition fault
    :param shoulder_roll_deg: the shoulder-roll index (pfma-model 8.1: -90, -45, 0, 45, 90):
        the simulated arm is pinned there and the controller's parameter
        ``joint.shoulder_roll_deg`` is set to it (a user write, applied at the first frame)
    :param ring: also keep the buffer's frame history ring (:class:`sim.rig.SimRig`)
    :param world_kw: extra keyword arguments for :class:`fakes.world.FakeWorld`
    :raises ValueError: a shoulder roll that is not an index position
    """

    def __init__(self, *, frames: FrameConfig | None = None, profile: str | None = None,
                 name: str | None = None, wm_name: str | None = None, require_ft: bool = True,
                 trace_frames: int = 4096, shoulder_roll_deg: int = 0, ring: bool = False,
                 **world_kw) -> None:
        if frames is None:
            frames = FrameConfig.profile(profile) if profile else FrameConfig()
        self.frames = frames
        roll = check_shoulder_roll_deg(shoulder_roll_deg)
        own = frames.clock == "own"  # the service keeps its default rates
        self.rig = SimRig(name=name, prefix="pfma-sim-", ring=ring,
                          service_kw={"schedule": Schedule() if own else Schedule(frame_rate_hz=frames.frame_rate_hz)},
                          shoulder_roll_rad=math.radians(roll), **world_kw)
        self.name, self.clock, self.world, self.svc = self.rig.name, self.rig.clock, self.rig.world, self.rig.svc
        self.rt = None
        try:
            self.client = self.rig.controller(owner="controller")
            self.rt = ControllerRuntime(self.client, frames=frames, wm_name=wm_name, clock=self.clock,
                                        require_ft=require_ft, trace_frames=trace_frames)
            if roll:
                self.rt.set_shoulder_roll(roll)
        except BaseException:
            self.rig.close()
            raise
        self.controller_enabled = True  #: False: the service runs alone (controller "dead")
        #: optional pattern: service frame number (own clock: the controller's own tick,
        #: counted from 0) -> controller steps after it (0 skips the frame: a missed frame;
        #: 2 or more: a burst on the same inputs); None = 1 each
        self.controller_steps: Callable[[int], int] | None = None
        self.service_frames = 0

        def controller_frame(info) -> None:  # right after each service frame
            self.service_frames += 1
            if not own:
                self._controller_ticks(self.svc_frame())
        self.rig.after_frame.append(controller_frame)
        if own:
            self.rig.tclock.timers.append(_OwnClock(self))

    def _controller_ticks(self, key: int) -> None:
        if not self.controller_enabled:
            return
        n = 1 if self.controller_steps is None else int(self.controller_steps(key))
        for _ in range(n):
            self.rt.tick()  # a minor frame, or the halted hold (docs/console.md)

    @property
    def service_period_s(self) -> float:
        """The service's frame period (the controller's, ``period_s``, unless on its own clock)."""
        return 1.0 / self.svc.schedule.frame_rate_hz

    # --- running: FrameStepping --------------------------------------------------------------

    def power_up(self, max_frames: int = 1000) -> int:
        """Request POWER UP and run until every layer is START UP COMPLETE; frames taken."""
        from controller.decision import Status
        self.rt.request(Request.POWER_UP)
        return self.run_until(lambda: self.rt.all_status(Status.START_UP_COMPLETE), max_frames)

    @property
    def updown_rt(self) -> ControllerRuntime:  # FrameStepping.request/response
        return self.rt

    # --- looking -------------------------------------------------------------------------
    def svc_frame(self) -> int:
        """The service frame number of the newest inputs published."""
        return int(self.client.header().frame)

    def close(self) -> None:
        self.controller_enabled = False  # no controller frame while the service stops
        self.rig.tclock.timers.clear()
        if self.rt is not None:
            self.rt.close()
        self.rig.close()

    def __enter__(self) -> "SystemSimulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _OwnClock:
    """The controller's own frame interrupt in simulated time (a timer of the service's
    ticking clock): its first frame at the first sleep after the service's first frame,
    then one every controller period, exactly, whatever the service does."""

    def __init__(self, sim: SystemSimulator) -> None:
        self.sim = sim
        self.due = -math.inf
        self.t0: float | None = None
        self.k = 0  #: the next tick's number

    def fire(self, now: float) -> None:
        if self.t0 is None:
            self.t0 = now
        self.sim._controller_ticks(self.k)
        self.k += 1
        self.due = self.t0 + self.k * self.sim.frames.period_s
