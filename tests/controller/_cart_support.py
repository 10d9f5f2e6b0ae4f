"""Shared helpers for the Cartesian-engine tests on the system simulator."""

from __future__ import annotations

import numpy as np

from controller.kinematics import fk
from sim.system import SystemSimulator

#: CAE volts giving a shaped demand of 0.25 (pfma-model 8.5: u = ((|v| - 0.5) / 9.5)^2)
V_QUARTER = 0.5 + 9.5 * 0.5
#: set_cae axis order: up/down (z), forward/backward (x), right/left (-y), yaw, pitch, roll
CAE_INDEX = {"z": 0, "x": 1, "y": 2}
CAE_SIGN = {"z": 1.0, "x": 1.0, "y": -1.0}


def powered_sim(**user) -> SystemSimulator:
    """A simulator powered up with the given user variables set (applied before start-up)."""
    sim = SystemSimulator()
    sim.step(10)
    wm = sim.rt.wm
    for name, value in user.items():
        wm.set_user(name.replace("__", "."), value, wm.access_key)
    sim.power_up()
    return sim


def stick(sim: SystemSimulator, axis: str | None, volts: float = V_QUARTER, deadman: bool = True) -> None:
    axes = [0.0] * 6
    if axis is not None:
        axes[CAE_INDEX[axis]] = CAE_SIGN[axis] * volts
    sim.world.set_cae(axes, (deadman, False, False))


def tool_pos(sim: SystemSimulator) -> np.ndarray:
    """True tool point of the simulated arm (fk of its true joint angles), world, m."""
    return np.asarray(fk(sim.joint_angles_rad())[0])


def record(sim: SystemSimulator, frames: int, extra=None) -> np.ndarray:
    out = []
    for _ in range(frames):
        sim.step(1)
        out.append(tool_pos(sim) if extra is None else extra())
    return np.array(out)
