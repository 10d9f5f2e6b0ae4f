"""The length half of `make lint`'s complexity gate (issue 31): no function longer than
``max-lines`` lines (its docstring and comments included: a reader scrolls through them too)
outside tests. ruff's mccabe rule (C901, ``max-complexity`` in pyproject.toml) is the other half.

Exceptions are named in pyproject.toml, ``[tool.pfma.function-length] allow``, each as
``"PATH:FUNCTION" = "why"``; an exception that no longer applies is reported too, so the
list cannot rot. Run: ``python devtools/function_length.py`` (exit 1 naming each function).
"""

from __future__ import annotations

import ast
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SKIP = {".venv", "build", "tests", ".git", "out", "devtools"}


def functions(path: Path):
    """(qualified name, first line, length) of every function and method in ``path``."""
    tree = ast.parse(path.read_text(), str(path))

    def walk(node, prefix: str):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = f"{prefix}{child.name}"
                first = min([child.lineno] + [d.lineno for d in child.decorator_list])
                yield name, first, child.end_lineno - first + 1
                yield from walk(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, f"{prefix}{child.name}.")
            else:
                yield from walk(child, prefix)

    yield from walk(tree, "")


def main() -> int:
    conf = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pfma"]["function-length"]
    limit, allow = int(conf["max-lines"]), dict(conf.get("allow", {}))
    long, seen = [], set()
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if SKIP & set(rel.parts):
            continue
        for name, line, n in functions(path):
            key = f"{rel}:{name}"
            if n > limit:
                if key in allow:
                    seen.add(key)
                else:
                    long.append(f"{rel}:{line}: {name} is {n} lines long (> {limit}): split it, "
                                f"or name it in pyproject.toml [tool.pfma.function-length] allow with why")
    stale = [f"pyproject.toml [tool.pfma.function-length] allow: {key} is not over {limit} lines "
             f"(or is gone): remove it" for key in sorted(set(allow) - seen)]
    for text in long + stale:
        print(text)
    return 1 if long or stale else 0


if __name__ == "__main__":
    sys.exit(main())
