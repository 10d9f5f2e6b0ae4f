"""Data between neighbours only (IRSS report 2.3.2; issue 33 item 2).

"Each system layer will and should operate upon only a segmented, identifiable section of
the world model ... all other variables may be shared by two adjacent layers but by no
others ... (other than in the case of certain hardware data)." Here:

- every layer declares the variables of others it reads (``Layer.reads``); its own (those
  it declares and writes, its user parameters among them) need no declaration;
- :func:`read_rules` checks every declaration when the runtime is wired and refuses, naming
  the layer, the variable and its owner, a read of a layer that is not adjacent, unless the
  variable is **user-interface data** (written by the user: report 2.2.8's user interface
  area, which every layer may read), **hardware data** (:data:`HARDWARE_DATA`: what Data
  Acquisition read from the rack); what a layer needs from further away is passed on by
  the layers between (controller/relays.py);
- the world model then refuses, while a layer's table or task runs, a read of anything the
  layer did not declare (``WorldModel.set_read_rules`` / ``read_as``): a declaration cannot
  drift from the code.

Tools, the console and the recorder are no layer: they read everything (docs/world-model.md).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING

from controller.relays import RELAYS
from controller.worldmodel import VarSpec, WorldModelError

if TYPE_CHECKING:
    from controller.layers import Layer

#: writers that are a layer's own task under another name
TASK_LAYER = {"updown_requests": "updown"}
#: the user interface's writes (report 2.2.8): any layer may read them
USER = "user"

#: Hardware data (report 2.3.2's exception): what Data Acquisition read from the rack and
#: published unchanged in meaning, which any layer may read. Its statuses and the commands
#: it sends are not here: those only its neighbour, Servo Control, reads.
HARDWARE_DATA: Mapping[str, str] = {
    "daq.joint_angle_rad": "the resolvers",
    "daq.joint_rate_rad_s": "the tachs",
    "daq.motor_current_a": "the motor-current monitors",
    "daq.ft_force_n": "the force/torque sensor",
    "daq.ft_torque_nm": "the force/torque sensor",
    "daq.hc_axes": "the hand controller",
    "daq.hc_deadman": "the hand controller's deadman",
    "daq.camera_route_applied": "the video matrix switcher's route, as the service applied it",
}

def owner_layer(spec: VarSpec) -> str:
    """The layer that writes ``spec`` (its task's layer), or ``"user"`` / ``"runtime"``."""
    return TASK_LAYER.get(spec.writer, spec.writer)


def own_names(layer: "Layer") -> set[str]:
    """What ``layer`` reads without declaring it: the variables it declares that it (or the
    user, its parameters) writes."""
    state = {s.name for s in layer.state_specs()}  # its command, status, row, mailbox, error
    return state | {s.name for s in layer.all_specs() if owner_layer(s) in (layer.key, USER)}


def why_allowed(reader: str, spec: VarSpec, order: Sequence[str]) -> str | None:
    """Why layer ``reader`` may read ``spec`` (None: it may not)."""
    owner = owner_layer(spec)
    if owner == reader:
        return "its own"
    if owner == USER:
        return "user-interface data"
    if spec.name in HARDWARE_DATA:
        return "hardware data"
    if owner in order and reader in order and abs(order.index(owner) - order.index(reader)) == 1:
        return "a neighbour's"
    return None


def read_rules(layers: Iterable["Layer"], specs: Iterable[VarSpec]) -> dict[str, frozenset[str]]:
    """Per layer key, every name it may read (its own and what it declares), every
    declaration checked against the rule.

    :raises WorldModelError: naming every declared read that the rule refuses, or that names
        no variable of this world model
    """
    layers = list(layers)
    order = [l.key for l in layers]
    by_name = {s.name: s for s in specs}
    problems, rules = [], {}
    for l in layers:
        allowed = own_names(l)
        for n in (l.superior, l.subordinate):  # the tables' neighbours: command down, status up
            if n is not None:
                allowed |= {s.name for s in n.state_specs()}
        for name in (*l.reads, *(src for _, src in l.relay_pairs)):  # what it passes on, too
            spec = by_name.get(name)
            if spec is None:
                problems.append(f"{l.key} declares a read of {name!r}, which no layer declares")
            elif why_allowed(l.key, spec, order) is None:
                owner = owner_layer(spec)
                away = f", {abs(order.index(owner) - order.index(l.key))} layers away" if owner in order else ""
                problems.append(f"{l.key} may not read {name} (written by {owner}{away}): data passes "
                                f"between neighbours only (report 2.3.2)")
            allowed.add(name)
        rules[l.key] = frozenset(allowed)
    if problems:
        raise WorldModelError("world-model wiring: " + "; ".join(problems))
    return rules


def table(layers: Iterable["Layer"], specs: Iterable[VarSpec]) -> list[tuple[str, str, str, str]]:
    """(reader, variable, owner, why) of every declared read, for the docs and the CLI."""
    layers = list(layers)
    order = [l.key for l in layers]
    by_name = {s.name: s for s in specs}
    return [(l.key, n, owner_layer(by_name[n]), why_allowed(l.key, by_name[n], order) or "REFUSED")
            for l in layers for n in l.reads]


DOC_BEGIN = "<!-- neighbours: generated from the layers' declared reads; regenerate: python -m sim.neighbours -->"
DOC_END = "<!-- end of the generated reads -->"


def markdown(layers: Iterable["Layer"], specs: Iterable[VarSpec]) -> str:
    """The rule's table for docs/controller.md: every layer's declared reads of the others,
    grouped by why each is allowed, then the hardware data and what the layers between pass
    on to a layer further away (controller/relays.py)."""
    layers = list(layers)
    rows = table(layers, specs)
    out = [DOC_BEGIN, "", "| layer | reads of its neighbours | hardware data | user-interface data |",
           "|---|---|---|---|"]
    for key in dict.fromkeys(r[0] for r in rows):
        cells = []
        for why in ("a neighbour's", "hardware data", "user-interface data"):
            names = [f"`{n}`" for k, n, _, w in rows if k == key and w == why]
            cells.append(", ".join(names) or "-")
        out.append(f"| {key} | " + " | ".join(cells) + " |")
    out += ["", "Hardware data (any layer may read it: report 2.3.2's exception):", "",
            "| variable | what it is |", "|---|---|"]
    out += [f"| `{n}` | {what} |" for n, what in HARDWARE_DATA.items()]
    out += ["", "Passed on by the layers between (`controller/relays.py`; each layer's copy is "
            "`<its prefix>.<origin with _ for .>`, one minor frame per layer):", "",
            "| variables | from | passed on by | to | what for |", "|---|---|---|---|---|"]
    by_name = {s.name: s for s in specs}
    out += [f"| {', '.join(f'`{n}`' for n in r.names)} | {owner_layer(by_name[r.names[0]])} | "
            f"{', '.join(r.via)} | {r.to} | {r.what} |" for r in RELAYS]
    return "\n".join(out + ["", DOC_END])


__all__ = ["HARDWARE_DATA", "read_rules", "table", "why_allowed", "owner_layer", "markdown"]
