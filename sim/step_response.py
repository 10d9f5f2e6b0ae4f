"""Joint position steps on the system simulator, before and after the plant's filters
(issue 33 item 6): what the anti-aliasing board and the rate servo cards' gain switch
change in what the servo flies and in what the A/D shows.

``python -m sim.step_response DIR`` writes two PNGs into DIR (docs/simulated-arm.md shows
them, from ``docs/img``):

- ``step-anti-alias.png``: a shoulder yaw step with the anti-aliasing board left out (the
  simulator before it was modelled) and in: the angle the servo flies, and the tach as
  the A/D reads it against the joint's true rate;
- ``step-gain-switch.png``: a wrist roll step with its card's switch at each position
  (the controller told the same), against :func:`controller.servo.predict_step` (which
  leaves Coulomb friction out: the flown step stops short by the friction's dead band,
  1 N*m / (lambda J K), 0.04 rad at the nominal switch).

Everything runs in simulated time; the figures are the same on every run.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

from calibration.plot import Panel, Series, plot_fit
from controller.params import GAIN_SWITCH_POSITIONS, JOINT_NAMES, joint
from controller.servo import predict_step
from fakes.arm import ArmModel
from fakes.arm_params import NOMINAL


@dataclasses.dataclass
class StepRun:
    """One step: times (s from the goal), the angle moved (rad), the tach as published
    (``daq.joint_rate_rad_s``) and the true rate (rad/s)."""

    t_s: np.ndarray
    q_rad: np.ndarray
    tach_rad_s: np.ndarray
    true_rad_s: np.ndarray


def fly_step(name: str, step_rad: float, *, anti_alias_hz: float | None = NOMINAL.anti_alias_hz,
             gain_switch: float = 1.0, seconds: float = 1.0) -> StepRun:
    """Power up the simulated system, then step joint ``name`` by ``step_rad`` through the
    Joint Planner's goal; its card's switch at ``gain_switch`` (the controller told so)."""
    from sim.system import SystemSimulator

    k = JOINT_NAMES.index(name)
    axis = next(i for i, a in enumerate(NOMINAL.axes) if a.joint == name)
    switch = tuple(gain_switch if i == axis else 1.0 for i in range(len(NOMINAL.axes)))
    params = dataclasses.replace(NOMINAL, anti_alias_hz=anti_alias_hz, gain_switch=switch)
    with SystemSimulator(arm=ArmModel(params=params)) as sim:
        sim.step(10)
        told = [gain_switch if j == k else 1.0 for j in range(len(JOINT_NAMES))]
        sim.rt.wm.set_user("servo.gain_switch", told, sim.rt.wm.access_key)
        sim.power_up(400)
        sim.step(60)
        q0 = float(sim.joint_angles_rad()[k])
        goal = np.array(sim.rt.wm.get("daq.joint_angle_rad"), dtype=float)
        goal[k] += step_rad
        sim.rt.set_joint_goal(goal)
        rows = []
        for n in range(int(seconds / sim.period_s)):
            sim.step(1)
            rows.append((n * sim.period_s, float(sim.joint_angles_rad()[k]) - q0,
                         float(sim.rt.wm.get("daq.joint_rate_rad_s")[k]), float(sim.world.sim.arm.qdot[axis])))
        if sim.rt.servo.trip is not None:
            raise RuntimeError(f"the step tripped the supervision: {sim.rt.servo.trip.text}")
    t, q, w_tach, w_true = (np.array(c) for c in zip(*rows))
    return StepRun(t, q, w_tach, w_true)


def anti_alias_panels(name: str = "shoulder_yaw", step_rad: float = 0.1) -> list[Panel | None]:
    before = fly_step(name, step_rad, anti_alias_hz=None)
    after = fly_step(name, step_rad)
    near = after.t_s <= 0.3  # the tach while the joint speeds up: where the lag shows
    return [
        Panel([Series(before.t_s, before.q_rad, "line", "grey", "before"),
               Series(after.t_s, after.q_rad, "line", "blue", "after")],
              f"{name}: the angle of a {step_rad:g} rad step", "time from the goal (s)", "angle (rad)",
              notes=["the same before and after:", "the servo flies the resolver"]),
        Panel([Series(after.t_s[near], after.true_rad_s[near], "line", "black", "true rate"),
               Series(before.t_s[near], before.tach_rad_s[near], "line", "grey", "tach read, before"),
               Series(after.t_s[near], after.tach_rad_s[near], "line", "red", "tach read, after")],
              f"{name}: the tach as the A/D reads it", "time from the goal (s)", "rate (rad/s)",
              notes=["after: 10 ms more lag", "(4-pole 40 Hz board)"]),
    ]


def gain_switch_panels(name: str = "wrist_roll", step_rad: float = 0.2) -> list[Panel | None]:
    panels: list[Panel | None] = []
    for pos, g in GAIN_SWITCH_POSITIONS.items():
        run = fly_step(name, step_rad, gain_switch=g)
        pred = predict_step(dataclasses.replace(joint(name), gain_switch=g), step_rad, duration_s=1.0)
        panels.append(Panel([Series(run.t_s, run.q_rad, "line", "blue", "flown"),
                             Series(pred.t_s, pred.q_rad, "line", "grey", "predicted")],
                            f"{name}, switch {pos} ({g:g})", "time from the goal (s)", "angle (rad)",
                            notes=[f"overshoot {max(0.0, float(run.q_rad.max()) - step_rad):.4f} rad "
                                   f"(predicted {pred.overshoot_rad:.4f})"]))
    return panels


def write_plots(out: Path) -> list[Path]:
    """Both figures into ``out``; their paths."""
    return [plot_fit(out / "step-anti-alias.png", anti_alias_panels(), "Before and after the anti-aliasing board"),
            plot_fit(out / "step-gain-switch.png", gain_switch_panels(), "The rate servo card's gain switch")]


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m sim.step_response DIR", file=sys.stderr)
        return 2
    for p in write_plots(Path(args[0])):
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
