"""``python -m tools.cli``: the ``pfma`` command without the console script."""

from tools.cli import main

raise SystemExit(main())
