"""``python -m sim.tables``: rewrite docs/controller.md's decision-table section from the
seven tables (controller/tables ``markdown``)."""

from __future__ import annotations

from pathlib import Path

from controller.tables import DOC_BEGIN, DOC_END, markdown

DOC = Path(__file__).resolve().parent.parent / "docs" / "controller.md"


def main() -> int:
    text = DOC.read_text()
    begin, end = text.index(DOC_BEGIN), text.index(DOC_END) + len(DOC_END)
    DOC.write_text(text[:begin] + markdown() + text[end:])
    print(DOC)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
