"""Motion faults injected into a flying arm in the system simulator: is each one stopped,
how far from where the joint should have been, and is the named cause right?

One trial (:func:`run_trial`): the whole stack (fake rack, service, seven layers) powered
up in simulated time; a seeded random joint move (10-40 degrees, either way, inside the
soft limits); the fault injected on that joint at a seeded time (before the move for the
faults that only show in motion, else during it); then frames until the servo layer's
supervision trips and the arm is still. The trial reads the supervision's verdict from
the world model (``servo.trip_joint``, ``servo.trip_cause``) and the truth from the
simulated arm; the supervision itself reads only published inputs.

``pfma bench supervision`` runs the matrix (every fault on every joint, several seeds)
and prints the confusion matrix that docs/safety.md quotes; the tests run a smaller one.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

import numpy as np

from controller.params import JOINT_NAMES, JOINTS
from controller.supervision import (
    CAUSE_AMP_OFF, CAUSE_BRAKE, CAUSE_DAC, CAUSE_LOAD, CAUSE_RESOLVER, CAUSE_TACH_REVERSED, CAUSES,
)

#: fault -> the cause the supervision should name
FAULTS: dict[str, int] = {
    "brake-held": CAUSE_BRAKE,
    "amp-off": CAUSE_AMP_OFF,
    "load": CAUSE_LOAD,
    "tach-reversed": CAUSE_TACH_REVERSED,
    "dac-bit": CAUSE_DAC,
    "resolver-bit": CAUSE_RESOLVER,
}
#: a fault that shows only when the joint is told to move is injected before the move
_BEFORE_MOVE = ("brake-held", "amp-off")
#: the bound docs/safety.md gives: stopped within this far outside the commanded range
BOUND_DEG = 10.0
DEG = math.pi / 180.0


@dataclass(frozen=True)
class TrialResult:
    fault: str
    joint: str
    seed: int
    spec: str  #: the fault spec injected
    tripped: bool  #: the supervision tripped (any joint)
    trip_joint: str  #: the joint it named ('' none)
    expected: int  #: CAUSES index the fault should give
    named: int  #: CAUSES index the supervision named (-1 none)
    stopped: bool  #: every joint still at the end, current limits at 0
    excursion_deg: float  #: furthest the joint went outside [start, goal] of its move
    detect_ms: float  #: injection to trip, simulated
    message: str  #: the trip's message

    @property
    def right(self) -> bool:
        return self.tripped and self.trip_joint == self.joint and self.named == self.expected

    @property
    def ok(self) -> bool:
        """Stopped within the bound."""
        return self.tripped and self.stopped and self.excursion_deg <= BOUND_DEG


def _spec(fault: str, joint: str, direction: float, rng: random.Random, sim) -> str:
    lay = sim.client.layout
    if fault in ("brake-held", "amp-off", "tach-reversed"):
        return f"{fault}:{joint}"
    if fault == "load":
        jf = JOINTS[JOINT_NAMES.index(joint)]
        run_torque = jf.torque_per_amp * 0.5 * jf.i_max_a  # the run current limit's torque
        return f"load:{joint}={-direction * rng.uniform(1.5, 2.5) * run_torque:.1f}"
    if fault == "dac-bit":
        e = lay.joint_entry("dac", joint, "rate_command")
        # the DAC's offset-binary MSB: stuck at 1 drives positive, at 0 negative: against the move
        return f"stuck-bit:{e.board}@DAC[{e.channel}]:11={1 if direction < 0 else 0}"
    if fault == "resolver-bit":
        e = lay.joint_entry("rtd", joint, "angle")
        return f"stuck-bit:{e.board}@CH{e.channel}:{rng.choice((10, 11, 12))}={rng.choice((0, 1))}"
    raise ValueError(f"no motion fault {fault!r}; faults: {', '.join(FAULTS)}")


def run_trial(fault: str, joint: str, seed: int, max_s: float = 6.0) -> TrialResult:
    """One fault on one joint of a flying arm (module docstring)."""
    from sim.faults import FaultSet
    from sim.system import SystemSimulator

    rng = random.Random(f"{fault}/{joint}/{seed}")
    k = JOINT_NAMES.index(joint)
    jf = JOINTS[k]
    with SystemSimulator() as sim:
        sim.step(10)
        sim.power_up(400)
        sim.step(20)
        q0 = np.array(sim.rt.wm.get("daq.joint_angle_rad"), dtype=float)
        amp = rng.uniform(10.0, 40.0) * DEG
        direction = rng.choice((-1.0, 1.0))
        room = (jf.soft_hi_rad - q0[k]) if direction > 0 else (q0[k] - jf.soft_lo_rad)
        if room < amp + 5 * DEG:
            direction = -direction
        goal = q0.copy()
        goal[k] += direction * amp
        faults = FaultSet(sim.world)
        spec = _spec(fault, joint, direction, rng, sim)
        start = sim.joint_angles_rad()[k]
        lo, hi = min(start, goal[k]), max(start, goal[k])
        t_inject = 0.0
        if fault in _BEFORE_MOVE:
            faults.inject(spec)
            t_inject = sim.clock.now()
            sim.rt.set_joint_goal(goal)
        else:
            sim.rt.set_joint_goal(goal)
            sim.step(int(rng.uniform(0.1, 0.5) / sim.period_s))
            if fault == "resolver-bit":  # a stuck bit shows only where it differs from the true bit
                spec = _resolver_flip(sim, spec)
            faults.inject(spec)
            t_inject = sim.clock.now()
        excursion = 0.0
        t_trip = None
        n = int(max_s / sim.period_s)
        still = 0
        for _ in range(n):
            sim.step(1)
            qk = sim.joint_angles_rad()[k]
            excursion = max(excursion, lo - qk, qk - hi)
            if t_trip is None and sim.rt.servo.trip is not None:
                t_trip = sim.clock.now()
            if t_trip is not None:
                qdot = sim.world.sim.true_state().qdot[:6]
                still = still + 1 if float(np.max(np.abs(qdot))) < 0.01 else 0
                if still >= 32 and sim.clock.now() - t_trip > 0.5:
                    break
        trip = sim.rt.servo.trip
        limits = sim.dac_volts()[7:13]
        stopped = t_trip is not None and still >= 32 and bool(np.all(np.abs(limits) < 0.3))
        return TrialResult(fault, joint, seed, spec, trip is not None,
                           JOINT_NAMES[trip.joint] if trip is not None else "", FAULTS[fault],
                           trip.cause if trip is not None else -1, stopped, excursion / DEG,
                           (t_trip - t_inject) * 1e3 if t_trip is not None else math.nan,
                           trip.text if trip is not None else "")


def _resolver_flip(sim, spec: str) -> str:
    """``spec`` with its stuck value set opposite to the bit the resolver's register holds now
    (a bit stuck at the value it has changes nothing until the joint moves far)."""
    head, _, rest = spec.partition("@")
    reg, bit_s, _value = rest.replace("=", ":").split(":")
    board = sim.world.bus[head.split(":", 1)[1]]
    word = board.read16(2 * int(reg[2:]))  # CHn at byte offset 2n (drivers/rtd/registers.py)
    return f"{head}@{reg}:{bit_s}={0 if (word >> int(bit_s)) & 1 else 1}"


def matrix(seeds: int = 3, faults=tuple(FAULTS), joints=JOINT_NAMES) -> list[TrialResult]:
    """Every fault on every joint, ``seeds`` trials each."""
    return [run_trial(f, j, s) for f in faults for j in joints for s in range(seeds)]


def confusion(results: list[TrialResult]) -> list[str]:
    """The confusion matrix as text lines: injected fault (rows) against named cause."""
    named = [-1] + list(range(len(CAUSES)))
    heads = ["none"] + [c.split(" (")[0].split(",")[0] for c in CAUSES]
    used = [c for c in named if any(r.named == c for r in results)]
    lines = [f"{'injected':<14}" + "".join(f"{heads[named.index(c)][:14]:>15}" for c in used)
             + f"{'stopped<=10deg':>16}{'right':>7}"]
    for f in dict.fromkeys(r.fault for r in results):
        rows = [r for r in results if r.fault == f]
        counts = "".join(f"{sum(r.named == c for r in rows):>15}" for c in used)
        lines.append(f"{f:<14}{counts}{sum(r.ok for r in rows):>12}/{len(rows):<3}"
                     f"{sum(r.right for r in rows):>4}/{len(rows)}")
    return lines
