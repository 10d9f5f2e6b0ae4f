"""``python -m sim.neighbours``: rewrite docs/controller.md's table of the layers' declared
reads (controller/neighbours.py ``markdown``) from a wired runtime of the system simulator."""

from __future__ import annotations

from controller.neighbours import DOC_BEGIN, DOC_END, markdown
from sim.docblock import CONTROLLER_DOC, rewrite


def generated() -> str:
    """The table as the layers declare it now."""
    from sim.system import SystemSimulator
    with SystemSimulator() as sim:
        return markdown(sim.rt.layers, sim.rt.wm.specs)


def main() -> int:
    return rewrite(CONTROLLER_DOC, DOC_BEGIN, DOC_END, generated())


if __name__ == "__main__":
    raise SystemExit(main())
