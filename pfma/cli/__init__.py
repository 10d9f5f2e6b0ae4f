"""The ``pfma`` command. Each verb is one module in this package with
``add_parser(subparsers)`` and ``run(args) -> int``; modules are found automatically,
so a new verb is a new file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from pfma.errors import PfmaError


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``--bus`` and ``--rack`` options shared by every verb that touches registers."""
    parser.add_argument("--bus", default="fake",
                        help="register bus: fake (default), modbus://HOST:PORT, file:PATH, spy+URL")
    parser.add_argument("--rack", default="fake",
                        help="rack configuration TOML (default: the IRSS report's tables)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pfma", description="PFMA rack I/O service and tools")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(module, "add_parser"):
            p = module.add_parser(sub)
            p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except PfmaError as err:
        print(f"pfma {args.verb}: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `pfma ... | head`: the reader left; not an error
        import os
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
