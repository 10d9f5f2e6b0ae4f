"""A small harness for the path and trajectory layers without the rest of the stack.

``MiniRt`` has what the two layers' tasks use of a ControllerRuntime (``wm``, ``now``,
``frame``, ``post``) on a SimClock, 320 Hz minor frames and the default schedule phases
(trajectory planner 40 Hz phase 7, path planner 20 Hz phase 9). It stands in for the
layers below: a perfect Cartesian follower (``cart.pos_cmd_m`` = ``traj.pos_m`` while
``traj.active``) and a tool pose (``joint.tool_pos_m``) that either follows the command
or is scripted (recording). Used until / besides the whole-system tests.
"""

from __future__ import annotations

import numpy as np

from dataclasses import replace

from controller.decision import Status
from controller.frames import FrameConfig
from controller.messages import MessageBoard
from controller.paths import MultiSegmentLayer, PathStore
from controller.relays import relayed
from controller.trajectory import TrajectoryLayer
from controller.worldmodel import VarSpec, WorldModel
from pfma.clock import SimClock

Q_ID = [1.0, 0.0, 0.0, 0.0]
TOOL = ("joint.tool_pos_m", "joint.tool_quat")
CMD = ("cart.cmd_valid", "cart.pos_cmd_m", "cart.quat_cmd")
#: what the Trajectory Planner passes on to the Path Planner (controller/relays.py): the tool
#: pose (the Cartesian engine's copy) and the Cartesian command
TRAJ_PAIRS = tuple((relayed("trajectory", n), relayed("cartesian", n)) for n in TOOL) + \
    tuple((relayed("trajectory", n), n) for n in CMD)


def below_specs() -> list[VarSpec]:
    return [
        VarSpec("joint.tool_pos_m", "task_io", "f8", (3,), "joint", [0.0, 0.0, 0.0], "m"),
        VarSpec("joint.tool_quat", "task_io", "f8", (4,), "joint", Q_ID),
        VarSpec("cart.pos_cmd_m", "task_io", "f8", (3,), "cartesian", [0.0, 0.0, 0.0], "m"),
        VarSpec("cart.quat_cmd", "task_io", "f8", (4,), "cartesian", Q_ID),
        VarSpec("cart.cmd_valid", "task_io", "b1", (), "cartesian", False),
    ]


def relay_specs(below: list[VarSpec]) -> list[VarSpec]:
    """The copies the Cartesian engine (of the tool pose) and the Trajectory Planner (of the
    tool pose and the command) pass on (controller/relays.py)."""
    by = {s.name: s for s in below}
    return [replace(by[n], name=relayed("cartesian", n), writer="cartesian") for n in TOOL] + \
        [replace(by[n], name=relayed("trajectory", n), writer="trajectory") for n in TOOL + CMD]


class MiniRt:
    def __init__(self, store: PathStore, p0=(1.5, 0.0, -0.3), q0=Q_ID) -> None:
        self.frames = FrameConfig()
        self.clock = SimClock()
        self.msp = MultiSegmentLayer(store, background_save=False)
        self.traj = TrajectoryLayer()
        below = below_specs()
        self.wm = WorldModel.create(self.msp.specs() + self.traj.specs() + below + relay_specs(below),
                                    clock=self.clock)
        self.key = self.wm.access_key
        self.messages = MessageBoard()
        self.frame = 0
        self.now = 0.0
        self._pending_sample: float | None = None
        self.script = None  #: t -> (p, q): scripted tool pose (recording); None: follow the command
        self.samples: list[tuple[float, np.ndarray, np.ndarray, bool]] = []  #: traj outputs per 40 Hz run
        self.cmd_p, self.cmd_q = np.array(p0, float), np.array(q0, float)
        self.wm.post_task_outputs("joint", {"joint.tool_pos_m": self.cmd_p, "joint.tool_quat": self.cmd_q})
        self.wm.post_task_outputs("cartesian", {"cart.pos_cmd_m": self.cmd_p, "cart.quat_cmd": self.cmd_q,
                                                "cart.cmd_valid": True})
        self.wm.post_state_variable("msp", "msp.status", int(Status.START_UP_COMPLETE))
        self.wm.post_state_variable("trajectory", "trajectory.status", int(Status.START_UP_COMPLETE))
        self.wm.communications_segment()

    def post(self, source, level, text):
        return self.messages.post(source, level, text, self.now, self.frame)

    def set(self, name: str, value) -> None:
        self.wm.set_user(name, value, self.key)

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.frame += 1
            self.clock.advance(self.frames.period_s)
            self.now = self.clock.now()
            self.wm.communications_segment()
            v = self.wm.get_task_inputs(("traj.active", "traj.pos_m", "traj.quat"))
            if bool(v["traj.active"]):  # the Cartesian Engine in trajectory mode, perfect
                self.cmd_p, self.cmd_q = v["traj.pos_m"], v["traj.quat"]
            if self.script is not None:
                p, q = self.script(self.now)
                self.cmd_p, self.cmd_q = np.asarray(p, float), np.asarray(q, float)
            self.wm.post_task_outputs("cartesian", {"cart.pos_cmd_m": self.cmd_p, "cart.quat_cmd": self.cmd_q})
            self.wm.post_task_outputs("joint", {"joint.tool_pos_m": self.cmd_p, "joint.tool_quat": self.cmd_q})
            self.wm.post_task_outputs("cartesian", {relayed("cartesian", TOOL[0]): self.cmd_p,
                                                    relayed("cartesian", TOOL[1]): self.cmd_q})
            self.wm.relay("trajectory", TRAJ_PAIRS)  # as the runtime does after the layer's table
            k = self.frame % 16
            if k % 8 == 7:
                self.traj.plan_task(self)
                self._pending_sample = self.now  # its posts are visible from the next frame
            if k == 9:
                self.msp.plan_task(self)
            if k % 8 == 0 and self._pending_sample is not None:  # the posts of the run above
                v = self.wm.get_task_inputs(("traj.pos_m", "traj.quat", "traj.active"))
                self.samples.append((self._pending_sample, np.array(v["traj.pos_m"]), np.array(v["traj.quat"]),
                                     bool(v["traj.active"])))
                self._pending_sample = None

    def run_until(self, pred, max_frames: int) -> int:
        for n in range(1, max_frames + 1):
            self.step()
            if pred():
                return n
        raise TimeoutError(f"not within {max_frames} frames")

    def get(self, name: str):
        return self.wm.get(name)

    def close(self) -> None:
        self.wm.close()
