"""The ``pfma`` command. Each verb is one module in this package with
``add_parser(subparsers)`` and ``run(args) -> int``; modules are found automatically,
so a new verb is a new file.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import pkgutil
import struct
import sys
from pathlib import Path

from pfma.errors import PfmaError, os_error_text

#: the first 8 bytes of every MCAP file
MCAP_MAGIC = b"\x89MCAP0\r\n"


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
    try:  # a Ctrl-C while the verbs are imported (the first ~0.3 s) ends quietly too
        parser = build_parser()
        args = parser.parse_args(argv)
    except KeyboardInterrupt:
        return 130
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
    except OSError as err:  # a file the user named: missing, unreadable, a directory ...
        print(f"pfma {args.verb}: {os_error_text(err)}", file=sys.stderr)
        return 1


def _mcap_damage() -> tuple[type[BaseException], ...]:
    """What the mcap reader raises on a damaged file (its own errors, short reads,
    a corrupt compressed chunk)."""
    from mcap.exceptions import McapError
    kinds: list[type[BaseException]] = [McapError, struct.error, EOFError]
    try:
        import zstandard
        kinds.append(zstandard.ZstdError)
    except ImportError:  # pragma: no cover - mcap then cannot read zstd chunks at all
        pass
    return tuple(kinds)


@contextlib.contextmanager
def mcap_errors(path: str | Path):
    """Reading MCAP ``path`` inside this block: damage becomes one :class:`PfmaError`."""
    try:
        yield
    except _mcap_damage() as err:
        why = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
        raise PfmaError(f"{path}: damaged MCAP file ({why}); try: pfma record recover {path}") from err


def check_mcap(path: str | Path, *, summary: bool = True):
    """Refuse, with one :class:`PfmaError`, a file that is not a readable MCAP recording.

    OSErrors (missing, no permission, a directory) propagate; :func:`main` prints them.
    With ``summary`` the file must also be finished (have its summary), and the summary
    is returned.
    """
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
        if not head:
            raise PfmaError(f"{path}: empty file, not an MCAP recording")
        if head != MCAP_MAGIC:
            raise PfmaError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
        if not summary:
            return None
        f.seek(0, 2)
        if f.tell() < 2 * len(MCAP_MAGIC) or (f.seek(-len(MCAP_MAGIC), 2), f.read())[1] != MCAP_MAGIC:
            raise PfmaError(f"{path}: truncated or unfinished MCAP file (no end magic); "
                            f"try: pfma record recover {path}")
        from mcap.reader import make_reader
        f.seek(0)
        with mcap_errors(path):
            s = make_reader(f).get_summary()
    if s is None or s.statistics is None:
        raise PfmaError(f"{path}: no summary (unfinished recording?); try: pfma record recover {path}")
    return s


if __name__ == "__main__":
    sys.exit(main())
