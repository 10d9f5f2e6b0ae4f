"""Data on its way to a layer further away, passed on by the layers between (issue 33 item 2).

The report allows a layer to share variables with its two neighbours only (2.3.2: "all other
variables may be shared by two adjacent layers but by no others"), hardware data excepted
(controller/neighbours.py). Where a layer needs what a layer further away writes, each layer
in between republishes it under its own name, as its decision table's data acquisition and
output parts do with commands and statuses (2.2.4): a request goes down a layer a minor frame,
an answer comes up a layer a minor frame.

:data:`RELAYS` is the one table of these: the variables, the layers that pass them on (in
the direction they travel) and the layer they are for. Each layer in the chain writes the
variable as ``<its prefix>.<the origin's name with "_" for ".">`` (``traj.joint_tool_pos_m``:
the Trajectory Planner's copy of ``joint.tool_pos_m``), of the origin's type, shape, units
and valid range, and reads the copy of the layer before it. A layer copies a value only when
its bytes changed (``WorldModel.relay``), every minor frame, after its decision table.

Assumed (this project): all of a relay's variables are copied together in the same minor
frame, so a request's payload and its sequence number arrive together, as they were posted.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from controller.worldmodel import VarSpec, WorldModelError

if TYPE_CHECKING:
    from controller.layers import Layer

#: each layer's variable prefix
PREFIX: Mapping[str, str] = {"updown": "updown", "msp": "msp", "trajectory": "traj", "cartesian": "cart",
                             "joint": "joint", "servo": "servo", "daq": "daq"}


@dataclass(frozen=True)
class Relay:
    """Variables written near one end of the layers and read further away."""

    names: tuple[str, ...]  #: the origin's variables
    via: tuple[str, ...]  #: the layers that pass them on, from the origin's side
    to: str  #: the layer that reads them (from the last of ``via``)
    what: str  #: what they are for


#: Every variable a layer reads from further than its neighbour (the report's rule met by passing
#: it on); the docs' table is generated from it (python -m sim.neighbours)
RELAYS: tuple[Relay, ...] = (
    Relay(("joint.tool_pos_m", "joint.tool_quat"), ("cartesian", "trajectory"), "msp",
          "the measured tool pose: teach points and playback starts"),
    Relay(("cart.cmd_valid", "cart.pos_cmd_m", "cart.quat_cmd"), ("trajectory",), "msp",
          "the Cartesian command a path starts from"),
    Relay(("servo.q_cmd_rad", "servo.q_cmd_valid", "joint.jmove_done_seq", "joint.jmove_done_code",
           "joint.shoulder_roll_rad"), ("cartesian", "trajectory"), "msp",
          "a joint move's start and its end; the shoulder-roll index path files are checked against"),
    Relay(("msp.jmove_goal_rad", "msp.jmove_seq", "msp.jmove_speed", "msp.jmove_stop"),
          ("trajectory", "cartesian"), "joint", "a joint move's request"),
    Relay(("msp.gripper_request", "msp.gripper_force_n", "msp.gripper_seq"),
          ("trajectory", "cartesian", "joint"), "servo", "a path's gripper step"),
    Relay(("gripper.event", "gripper.event_force_n", "gripper.event_seq", "gripper.msp_done_code",
           "gripper.msp_done_seq"), ("joint", "cartesian", "trajectory"), "msp",
          "the gripper's events (recorded into a path) and a path's gripper step done"),
    Relay(("force.state", "teleop.reflect_enabled", "teleop.reflect_force_n", "teleop.reflect_torque_nm"),
          ("joint", "servo"), "daq", "force reflection to the hand controller"),
    Relay(("updown.route_request", "updown.route_request_seq"),
          ("msp", "trajectory", "cartesian", "joint", "servo"), "daq",
          "the operator's camera route request"),
)


def relayed(layer: str, name: str) -> str:
    """The name under which ``layer`` republishes ``name`` (the origin's variable)."""
    return f"{PREFIX[layer]}.{name.replace('.', '_')}"


def at(reader: str, name: str, relays: Sequence[Relay] = RELAYS) -> str:
    """The name ``reader`` reads ``name`` (the origin's variable) under: the copy of the layer
    before it in the relay's chain (``reader`` is the layer it is for, or one that passes it on)."""
    for r in relays:
        chain = (*r.via, r.to)
        if name in r.names and reader in chain:
            k = chain.index(reader)
            return relayed(chain[k - 1], name) if k else name
    raise KeyError(f"{name} is not relayed to {reader} (controller/relays.py RELAYS)")


def wire(layers: Sequence["Layer"], specs: Sequence[VarSpec], relays: Sequence[Relay] = RELAYS) -> None:
    """Give each layer the variables it passes on: ``relay_specs`` (its copies, declared like
    the origins) and ``relay_pairs`` ((its copy, what it copies) in one tuple).

    :raises WorldModelError: a relay whose chain is not a run of neighbours ending next to
        its reader, an origin no layer declares, or a copy's name already taken
    """
    order = [l.key for l in layers]
    by_key = {l.key: l for l in layers}
    by_name = {s.name: s for s in specs}
    made: dict[str, list[VarSpec]] = {k: [] for k in order}
    pairs: dict[str, list[tuple[str, str]]] = {k: [] for k in order}
    for r in relays:
        chain = [*r.via, r.to]
        steps = [order.index(k) for k in chain]
        if any(abs(a - b) != 1 for a, b in zip(steps, steps[1:])):
            raise WorldModelError(f"relay of {', '.join(r.names)}: {' -> '.join(chain)} is not a run of neighbours")
        for name in r.names:
            origin = by_name.get(name)
            if origin is None:
                raise WorldModelError(f"relay of {name}: no layer declares it")
            src = name
            for k in r.via:
                dst = relayed(k, name)
                if dst in by_name:
                    raise WorldModelError(f"relay of {name}: {dst} is already a variable")
                made[k].append(replace(origin, name=dst, writer=k, protected=False, user=False,
                                       doc=f"{name} passed on to {r.to}: {r.what} (controller/relays.py)"))
                pairs[k].append((dst, src))
                src = dst
    for k in order:
        by_key[k].relay_specs = tuple(made[k])
        by_key[k].relay_pairs = tuple(pairs[k])


__all__ = ["PREFIX", "RELAYS", "Relay", "at", "relayed", "wire"]
