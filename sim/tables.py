"""``python -m sim.tables``: rewrite docs/controller.md's decision-table section from the
seven tables (controller/tables ``markdown``)."""

from __future__ import annotations

from controller.tables import DOC_BEGIN, DOC_END, markdown
from sim.docblock import CONTROLLER_DOC, rewrite


def main() -> int:
    return rewrite(CONTROLLER_DOC, DOC_BEGIN, DOC_END, markdown())


if __name__ == "__main__":
    raise SystemExit(main())
