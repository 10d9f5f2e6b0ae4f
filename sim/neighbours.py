"""``python -m sim.neighbours``: rewrite docs/controller.md's table of the layers' declared
reads (controller/neighbours.py ``markdown``) from a wired runtime of the system simulator."""

from __future__ import annotations

from pathlib import Path

from controller.neighbours import DOC_BEGIN, DOC_END, markdown

DOC = Path(__file__).resolve().parent.parent / "docs" / "controller.md"


def generated() -> str:
    """The table as the layers declare it now."""
    from sim.system import SystemSimulator
    with SystemSimulator() as sim:
        return markdown(sim.rt.layers, sim.rt.wm.specs)


def main() -> int:
    text = DOC.read_text()
    begin, end = text.index(DOC_BEGIN), text.index(DOC_END) + len(DOC_END)
    DOC.write_text(text[:begin] + generated() + text[end:])
    print(DOC)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
