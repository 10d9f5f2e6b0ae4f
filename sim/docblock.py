"""Rewrite a generated block of a document in place (the ``python -m sim.<x>`` generators)."""

from __future__ import annotations

from pathlib import Path

#: docs/controller.md, where the controller's generated tables live
CONTROLLER_DOC = Path(__file__).resolve().parent.parent / "docs" / "controller.md"


def rewrite(doc: Path, begin: str, end: str, block: str) -> int:
    """Replace the text from the line ``begin`` through ``end`` of ``doc`` with ``block``
    (which carries both markers); print the file's path. Returns 0 (a ``main``'s exit)."""
    text = doc.read_text()
    b, e = text.index(begin), text.index(end) + len(end)
    doc.write_text(text[:b] + block + text[e:])
    print(doc)
    return 0
