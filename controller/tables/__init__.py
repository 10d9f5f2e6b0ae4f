"""One decision table per layer (report 2.2.4), each in its own file, as data.

``TABLES`` maps a layer's key to its table; :func:`table_for` is what a layer compiles.
The rows the layers share are in :mod:`controller.tables.shared`; ``pfma controller
--tables`` prints the seven (docs/controller.md shows them).
"""

from __future__ import annotations

from controller.decision import DecisionTable
from controller.tables import cartesian, daq, joint, msp, servo, trajectory, updown
from controller.tables.shared import BOTTOM_TABLE, LAYER_TABLE

#: the seven tables, highest layer first
TABLES: dict[str, DecisionTable] = {m.TABLE.key: m.TABLE for m in (updown, msp, trajectory, cartesian, joint,
                                                                   servo, daq)}


#: the generated part of docs/controller.md (``python -m sim.tables``)
DOC_BEGIN = "<!-- tables: generated from controller/tables; regenerate: python -m sim.tables -->"
DOC_END = "<!-- end of generated tables -->"


def markdown() -> str:
    """docs/controller.md's tables section: each layer's parts 1 and 4 and its tasks with
    the rows that create and delete them, then the shared rows in full."""
    from controller.decision import describe, row_tasks, status_text
    out = [DOC_BEGIN, "", "| layer | table | part 1 reads | part 4 posts | periodic tasks (exist while) | "
                          "rows that create (+) or delete (-) them |", "|---|---|---|---|---|---|"]
    for key, t in TABLES.items():
        sub = f"`{t.sub_key}.status`" if t.sub_key else "(no subordinate)"
        down = f", `{t.sub_key}.command`" if t.sub_key else ""
        tasks = "; ".join(f"`{n}` ({'every status' if len(st) == 9 else ', '.join(status_text(s) for s in sorted(st))})"
                          for n, st in t.tasks) or "none"
        acts = "; ".join(f"{r.rid}: {row_tasks(t, r)}" for r in t.rows if row_tasks(t, r)) or "none"
        out.append(f"| {t.title} | `controller/tables/{key}.py` | `{key}.command`, `{key}.status`, {sub}, "
                   f"`{key}.task`, the fault flag | `{key}.status`{down}, `{key}.row`, `{key}.task` | {tasks} | {acts} |")
    out += ["", "The rows every layer with a subordinate shares (`controller/tables/shared.py`), parts 2 "
                "and 3 (`pfma controller --tables` prints each layer's table with its own task column):",
            "", "```", describe(LAYER_TABLE), "```", "", "Data Acquisition's rows:", "", "```",
            describe(TABLES["daq"]), "```", "", DOC_END]
    return "\n".join(out)


def table_for(key: str, bottom: bool = False) -> DecisionTable:
    """The table of the layer ``key``; a layer with none of its own (a test's stand-in)
    runs the shared rows alone."""
    return TABLES.get(key) or (BOTTOM_TABLE if bottom else LAYER_TABLE)
