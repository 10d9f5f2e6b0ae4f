"""User-definable live menus (issue 18 item 2; docs/console.md "Live menus"): named pages
of world-model variables, each with a format, each page with its refresh rate, read from a
TOML file (``pfma console --menu FILE.toml``; ``examples/console-menu.toml``)::

    title = "arm"                 # optional
    [[page]]
    name = "Joints"               # required
    refresh_hz = 5                # optional, 0 < r <= 10 (the console's rate); default 10
    [[page.var]]
    name = "daq.joint_angle_rad"  # required: a world-model variable
    format = "+.4f"               # optional: a Python format spec per element; default ".6g"
    label = "joint angles"        # optional: default the name

A page shows live and modifies: the console's Enter on a variable takes the world-model
browser's write path (the ownership rules decide; ``MenuScreen`` in tools/console/app.py).

A mistake is one :class:`MenuError` naming the file, the line and the field
(``menu.toml:7: page 1 var 2 format: ...``); ``pfma console`` prints it and exits 2
before it shows anything.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, NoReturn

import msgspec

from pfma import config

#: the console's refresh rate: a page cannot refresh faster (tools.console.app.REFRESH_HZ)
MAX_REFRESH_HZ = 10.0
DEFAULT_FORMAT = ".6g"
PAGE_FIELDS = ("name", "refresh_hz", "var")
VAR_FIELDS = ("name", "format", "label")
TOP_FIELDS = ("title", "page")


class MenuError(Exception):
    """A menu file mistake: file, line, field, what is wrong (one line)."""

    def __init__(self, path: str, line: int, field: str, msg: str) -> None:
        self.path, self.line, self.field, self.msg = path, line, field, msg
        super().__init__(f"{path}:{line}: {field}: {msg}" if line > 0 else f"--menu {path}: {msg}")


@dataclass(frozen=True)
class MenuVar:
    name: str
    format: str
    label: str
    line: int  #: where it is in the file (its errors name it)
    format_line: int


@dataclass(frozen=True)
class MenuPage:
    name: str
    refresh_hz: float
    vars: tuple[MenuVar, ...]

    def every(self, console_hz: float = MAX_REFRESH_HZ) -> int:
        """Console refreshes per page refresh (a whole number: the console ticks at 10 Hz)."""
        return max(1, round(console_hz / self.refresh_hz))


@dataclass(frozen=True)
class Menu:
    path: str
    title: str
    pages: tuple[MenuPage, ...]

    def check(self, wm) -> None:
        """Every variable exists in ``wm`` and its format fits the variable's type.

        :raises MenuError: the first that does not (file, line, field)
        """
        from pfma.errors import did_you_mean
        names = set(wm.names())
        for p, page in enumerate(self.pages, 1):
            for k, v in enumerate(page.vars, 1):
                where = f"page {p} var {k}"
                if v.name not in names:
                    raise MenuError(self.path, v.line, f"{where} name",
                                    f"no variable {v.name!r} in the world model{did_you_mean(v.name, names)}")
                sample = wm.spec(v.name).np_dtype.type(0).item()
                try:
                    format(sample, v.format)
                except (ValueError, TypeError) as err:
                    raise MenuError(self.path, v.format_line, f"{where} format",
                                    f"{v.format!r} does not format a {wm.spec(v.name).dtype} value ({err})") from None


class _VarEntry(msgspec.Struct, forbid_unknown_fields=True):
    name: Annotated[str, msgspec.Meta(min_length=1)]
    format: str = DEFAULT_FORMAT
    label: str | None = None


class _PageEntry(msgspec.Struct, forbid_unknown_fields=True):
    name: Annotated[str, msgspec.Meta(pattern=r"\S")]
    var: Annotated[list[_VarEntry], msgspec.Meta(min_length=1)]
    refresh_hz: Annotated[float, msgspec.Meta(gt=0, le=MAX_REFRESH_HZ)] = MAX_REFRESH_HZ


class _MenuFile(msgspec.Struct, forbid_unknown_fields=True):
    page: Annotated[list[_PageEntry], msgspec.Meta(min_length=1)]
    title: str | None = None


_NO_PAGES = "no pages: add [[page]] tables, each with name and [[page.var]] tables"
_NO_VARS = "a page needs variables: [[page.var]] tables with a name"
#: what is wrong with a field (pfma.config.convert names the field: ``page 1 var 2 format``)
_MESSAGES = {
    "*": f"unknown field (a menu file has {', '.join(TOP_FIELDS)})",
    "title": "must be a string",
    "page": _NO_PAGES, "page?": _NO_PAGES,
    "page[]": "must be a table ([[page]])",
    "page[].*": f"unknown field (a page has {', '.join(PAGE_FIELDS)})",
    "page[].name": "a page needs a name (a non-empty string)", "page[].name?": "a page needs a name (a non-empty string)",
    "page[].refresh_hz": f"{{value!r}} is not a rate in (0, {MAX_REFRESH_HZ:g}] Hz (the console refreshes at "
                         f"{MAX_REFRESH_HZ:g} Hz)",
    "page[].var": _NO_VARS, "page[].var?": _NO_VARS,
    "page[].var[]": "must be a table ([[page.var]])",
    "page[].var[].*": f"unknown field (a variable has {', '.join(VAR_FIELDS)})",
    "page[].var[].name": "a variable needs a name (a world-model variable)",
    "page[].var[].name?": "a variable needs a name (a world-model variable)",
    "page[].var[].format": "must be a string: a Python format spec such as '+.4f'",
    "page[].var[].label": "must be a string",
}


def _menu_error(p: config.Problem) -> MenuError:
    return MenuError(p.source, p.line or 1, p.field, p.message)


def _read(path: str) -> tuple[str, dict]:
    """The file's text and TOML data. :raises MenuError: unreadable or not TOML"""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise MenuError(path, 0, "file", f"cannot read it ({err.__class__.__name__}: "
                                         f"{getattr(err, 'strerror', None) or err})") from None
    try:
        return text, tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        msg = str(err)
        m = re.search(r"\(at line (\d+), column \d+\)", msg)
        line = int(m.group(1)) if m else 0
        raise MenuError(path, line, "TOML", re.sub(r"\s*\(at line \d+, column \d+\)", "", msg)
                        or "not TOML") from None


def load(path: str | Path) -> Menu:
    """Read and check a menu file (everything but the variables' existence: :meth:`Menu.check`).

    :raises MenuError: unreadable, not TOML, a missing, unknown or bad field
    """
    path = str(path)
    text, data = _read(path)
    raw = config.convert(data, _MenuFile, source=path, text=text, messages=_MESSAGES, named=True,
                         error=_menu_error)

    def fail(where: config.KeyPath, msg: str) -> NoReturn:
        config.fail(path, text, where, msg, field=config.field_name(where), error=_menu_error)

    def line(where: config.KeyPath) -> int:
        return config.line_of(text, where) or 1

    pages = []
    seen: dict[str, int] = {}
    for pi, pg in enumerate(raw.page):
        if pg.name in seen:
            fail(("page", pi, "name"), f"page name {pg.name!r} is used by page {seen[pg.name]} too")
        seen[pg.name] = pi + 1
        vars_ = []
        for vi, vv in enumerate(pg.var):
            at = ("page", pi, "var", vi)
            try:
                format(0, vv.format) if re.search(r"[bcdoxXn]$", vv.format) else format(0.0, vv.format)
            except ValueError as err:
                fail((*at, "format"), f"{vv.format!r} is not a format spec ({err}); e.g. '+.4f', '.6g', 'd'")
            label = vv.name if vv.label is None else vv.label
            vars_.append(MenuVar(vv.name, vv.format, label, line((*at, "name")), line((*at, "format"))))
        pages.append(MenuPage(pg.name, float(pg.refresh_hz), tuple(vars_)))
    title = Path(path).stem if raw.title is None else raw.title
    return Menu(path, title, tuple(pages))


def _fmt(v: Any, spec) -> str:
    import numpy as np
    a = np.asarray(v)
    if a.ndim == 0:
        return format(a.item(), spec)
    return "  ".join(format(x, spec) for x in a.ravel().tolist())


#: the menu page's line on modifying (the write path of the world-model browser, docs/console.md)
MODIFY_HELP = "up/down select   Enter/e modify (where the ownership rules let a user: the browser's write path)"


def page_text(menu: Menu, index: int, values: dict[str, Any], wm, row: int = 0, status: str = "") -> str:
    """One page: the tabs, then one line per variable (label, formatted value(s), units),
    ``>`` marking the variable at ``row`` (Enter/``e`` modifies it), then ``status`` (the
    last write's outcome or refusal) when there is one."""
    page = menu.pages[index % len(menu.pages)]
    tabs = "  ".join(f"[{p.name}]" if p is page else p.name for p in menu.pages)
    width = max(len(v.label) for v in page.vars)
    lines = [f"{menu.title}: {tabs}",
             f"page {index % len(menu.pages) + 1}/{len(menu.pages)}, refresh {page.refresh_hz:g} Hz   "
             f"<- -> / tab page   Escape/l close   ({menu.path})", MODIFY_HELP]
    for k, v in enumerate(page.vars):
        units = wm.spec(v.name).units
        mark = ">" if k == row % len(page.vars) else " "
        lines.append(f"{mark} {v.label:<{width}}  {_fmt(values[v.name], v.format)}" + (f"  {units}" if units else ""))
    if status:
        lines += ["", status]
    return "\n".join(lines)
