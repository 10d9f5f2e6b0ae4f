"""A tiny demonstration controller for ``make run``: arms the simulated arm and
swings the wrist roll and shoulder yaw slowly back and forth.

It is an ordinary commanding process: it claims the Bit3 buffer's command area,
writes joint rate commands and current limits once per service frame (320 Hz, right
after each new input snapshot, stamped with its frame so the service sees fresh commands:
docs/safety.md), and disarms (rates 0, limits 0, arm request off) when it ends. The real controller
layers replace it.

Run: ``python -m controller.demo --buffer pfma --duration 30``
"""

from __future__ import annotations

import argparse
import math
import sys
import time

from ioservice.client import Client

#: current limits while armed (A): enough to release the brakes and hold the arm
DEMO_CURRENT_LIMIT_A = (5.0, 5.0, 5.0, 2.5, 2.5, 2.5, 0.0)
#: joint rate amplitude (rad/s) and period (s) of the swing, per command-area joint
SWING = {"wrist_roll": (0.8, 6.0), "shoulder_yaw": (0.05, 10.0)}  # WR: above its Coulomb friction


def run(buffer: str = "pfma", duration_s: float = 30.0, wait_s: float = 10.0) -> int:
    deadline = time.monotonic() + wait_s
    while True:
        try:
            c = Client.attach(buffer, writer="commands", owner="demo-controller")
            break
        except Exception as err:  # the service may not have created the buffer yet
            if time.monotonic() > deadline:
                print(f"demo controller: cannot attach to Bit3 buffer {buffer!r}: {err}", file=sys.stderr)
                return 1
            time.sleep(0.1)
    joints = list(c.layout.joint_names)
    rates = [0.0] * len(joints)
    frame = 0
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
            frame = c.read_inputs().frame
            t = now - t0
            if t > 0.5:  # let the service arm first (rates must be 0 when arming)
                for name, (amp, per) in SWING.items():
                    if name in joints:
                        rates[joints.index(name)] = amp * math.sin(2 * math.pi * (t - 0.5) / per)
            c.write_commands(joint_rate_rad_s=rates, current_limit_a=DEMO_CURRENT_LIMIT_A,
                             arm_request=1, inputs_frame=frame)
    except KeyboardInterrupt:
        pass
    finally:
        c.write_commands(joint_rate_rad_s=[0.0] * len(joints), current_limit_a=[0.0] * 7, arm_request=0,
                         inputs_frame=frame)
        c.close()
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--buffer", default="pfma")
    p.add_argument("--duration", type=float, default=30.0)
    a = p.parse_args(argv)
    return run(a.buffer, a.duration)


if __name__ == "__main__":
    sys.exit(main())
