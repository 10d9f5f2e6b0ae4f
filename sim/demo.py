"""A tiny demonstration controller for ``make run``: arms the simulated arm,
swings the wrist roll and shoulder yaw slowly back and forth and holds the other
joints at their start pose (a position loop on the resolver angles, so the shoulder
pitch does not sag under residual gravity with a zero rate command).

It is an ordinary commanding process: it claims the Bit3 buffer's command area,
writes joint rate commands and current limits once per service frame (320 Hz, right
after each new input snapshot, stamped with its frame so the service sees fresh commands:
docs/safety.md), and disarms (rates 0, limits 0, arm request off) when it ends. The real controller
layers replace it.

Run: ``python -m sim.demo --buffer pfma --duration 30``

:func:`demo_goal` is the short demo path the real controller flies in ``make run`` (the
console over the system simulator, docs/console.md): joint goals through the Joint
Planner, a few poses around the start pose, one every :data:`DEMO_GOAL_EVERY_S`; at some
poses the gripper opens or closes (:func:`demo_gripper`) on a part placed between its jaws
(:data:`DEMO_JAW_OBJECT_M`).
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import time

from bit3.client import Client

log = logging.getLogger(__name__)

#: current limits while armed (A): enough to release the brakes and hold the arm
DEMO_CURRENT_LIMIT_A = (5.0, 5.0, 5.0, 2.5, 2.5, 2.5, 0.0)
#: joint rate amplitude (rad/s) and period (s) of the swing, per command-area joint
SWING = {"wrist_roll": (0.8, 6.0), "shoulder_yaw": (0.05, 10.0)}  # WR: above its Coulomb friction
#: the hold loop of the other joints: rate = -k (q - q0), clipped to +-HOLD_MAX_RATE_RAD_S
HOLD_GAIN_1_S = 2.0
HOLD_MAX_RATE_RAD_S = 0.1  # well under every joint's rate limit (0.4 rad/s at the shoulder)
#: seconds after the arm request before any joint moves (rates must be 0 when arming)
ARM_SETTLE_S = 0.5


#: the demo path of ``make run``: joint offsets (rad, command-area joint name -> offset) from
#: the start pose, visited in turn and repeated (small: well inside every joint's range)
DEMO_PATH: tuple[dict[str, float], ...] = (
    {"shoulder_yaw": 0.25, "wrist_roll": 0.6},
    {"shoulder_yaw": 0.25, "elbow_pitch": 0.15, "wrist_roll": -0.6},
    {"shoulder_yaw": -0.2, "wrist_pitch": -0.2},
    {},
)
#: seconds between two goals of the demo path (the Joint Planner needs ~2 s per move)
DEMO_GOAL_EVERY_S = 4.0
#: the demo path's gripper events: pose index of DEMO_PATH -> the gripper request made when the
#: demo goes to that pose (open, close: pfma.gripper.ACTIONS). An open or a close takes about
#: 3 s at the gripper's 20 mm/s (controller/gripper.py), within the pose's 4 s
DEMO_GRIPPER: dict[int, str] = {0: "open", 2: "close"}
#: width of the part between the jaws of the simulated world while the demo runs (m): the
#: demo's close grips it (GRIPPING at the grip force), its open lets go
DEMO_JAW_OBJECT_M = 0.04


def demo_goal(joints, q0, t: float) -> tuple[int, list[float]]:
    """The demo path's goal ``t`` s after power up: (index of the pose, joint angles in
    the order of ``joints``) from the start pose ``q0``."""
    k = int(t // DEMO_GOAL_EVERY_S) % len(DEMO_PATH)
    off = DEMO_PATH[k]
    return k, [float(q) + off.get(name, 0.0) for name, q in zip(joints, q0)]


def demo_gripper(k: int) -> str | None:
    """The gripper request the demo path makes at pose ``k`` (None: none)."""
    return DEMO_GRIPPER.get(k % len(DEMO_PATH))


def hold_rate(q: float, q0: float, k: float = HOLD_GAIN_1_S,
              max_rate: float = HOLD_MAX_RATE_RAD_S) -> float:
    """Rate (rad/s) pulling the resolver angle ``q`` back to ``q0``; the error is taken
    around ``q0`` (the resolvers read 0..2 pi, so 6.28 is next to 0.0)."""
    err = math.remainder(q - q0, 2 * math.pi)
    return max(-max_rate, min(max_rate, -k * err))


def frame_rates(t: float, joints, q, q0) -> list[float]:
    """The demo's joint rate commands ``t`` s after its arm request, per command-area joint
    (``joints``), from the resolver angles ``q`` and the start pose ``q0`` (None: no angle)."""
    if t <= ARM_SETTLE_S:
        return [0.0] * len(joints)
    out = []
    for name, qi, q0i in zip(joints, q, q0):
        if name in SWING:
            amp, per = SWING[name]
            out.append(amp * math.sin(2 * math.pi * (t - ARM_SETTLE_S) / per))
        elif qi is None or q0i is None:
            out.append(0.0)
        else:
            out.append(hold_rate(qi, q0i))
    return out


def joint_angles(snap, joints) -> list[float | None]:
    """Resolver angle (rad) of each command-area joint (its rack channel of quantity
    ``angle``), None if the rack has none."""
    out = []
    for name in joints:
        try:
            entry = snap.layout.joint_entry("rtd", name, "angle")
        except KeyError:
            out.append(None)
            continue
        out.append(float(snap.value(entry.name)))
    return out


def run(buffer: str = "pfma", duration_s: float = 30.0, wait_s: float = 10.0) -> int:
    deadline = time.monotonic() + wait_s
    while True:
        try:
            c = Client.attach(buffer, writer="commands", owner="demo-controller")
            break
        except Exception as err:  # the service may not have created the buffer yet
            if time.monotonic() > deadline:
                log.error("cannot attach to Bit3 buffer %r: %s", buffer, err)
                return 1
            time.sleep(0.1)
    joints = list(c.layout.joint_names)
    rates = [0.0] * len(joints)
    frame = 0
    q0 = None
    try:
        # power-up sequence (pfma-model 8.4): rate 0 V first, then raise the current limits
        # a new arm request: the service never re-arms on a request it has already seen
        c.write_commands(joint_rate_rad_s=rates, current_limit_a=DEMO_CURRENT_LIMIT_A,
                         arm_request=1, rearm_counter=int(c.command["rearm_counter"]) + 1)
        t0 = time.monotonic()
        while (now := time.monotonic()) - t0 < duration_s:
            if not c.changed("inputs"):  # locked to the service: one write per new frame
                time.sleep(0.0002)
                continue
            snap = c.read_inputs()
            frame = snap.frame
            q = joint_angles(snap, joints)
            if q0 is None:
                q0 = q  # the start pose the hold loop keeps
            rates = frame_rates(now - t0, joints, q, q0)
            c.write_commands(joint_rate_rad_s=rates, current_limit_a=DEMO_CURRENT_LIMIT_A,
                             arm_request=1, inputs_frame=frame)
    except KeyboardInterrupt:
        pass
    finally:
        # a second Ctrl-C (or the group's SIGINT twice: make run, timeout) must not cut the disarm short
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        except ValueError:  # run() called outside the main thread: its caller owns the signals
            pass
        c.write_commands(joint_rate_rad_s=[0.0] * len(joints), current_limit_a=[0.0] * 7, arm_request=0,
                         inputs_frame=frame)
        c.close()
    return 0


def main(argv=None) -> int:
    from pfma.log import add_argument, configure
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--buffer", default="pfma")
    p.add_argument("--duration", type=float, default=30.0)
    add_argument(p)
    a = p.parse_args(argv)
    configure("demo controller", a.log_level)
    return run(a.buffer, a.duration)


if __name__ == "__main__":
    sys.exit(main())
