"""The grade half of `make lint`'s complexity gate (issue 31): at most ``max-d-or-worse``
functions, methods and classes outside tests rate D or worse in radon's cyclomatic
complexity (over 20 by radon's count, which also counts each ``and``/``or``, so it reads
higher than ruff's C901 on the same function). pyproject.toml ``[tool.pfma.complexity]``
holds the bound; this prints each such block, worst first, and exits 1 when there are more.
Run: ``python devtools/complexity_grades.py``.
"""

from __future__ import annotations

import sys
import tomllib

from radon.complexity import cc_rank, cc_visit

from function_length import ROOT, SKIP


def main() -> int:
    bound = int(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pfma"]["complexity"]["max-d-or-worse"])
    worse = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if SKIP & set(rel.parts):
            continue
        for block in cc_visit(path.read_text()):
            if cc_rank(block.complexity) >= "D":
                name = f"{block.classname}.{block.name}" if getattr(block, "classname", None) else block.name
                worse.append((block.complexity, f"{rel}:{block.lineno}: {name} rates {cc_rank(block.complexity)} "
                                                f"({block.complexity})"))
    worse.sort(key=lambda w: -w[0])
    if len(worse) > bound:
        for _, text in worse:
            print(text)
        print(f"{len(worse)} blocks rate D or worse, over the bound of {bound} (pyproject.toml "
              f"[tool.pfma.complexity] max-d-or-worse): split one")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
