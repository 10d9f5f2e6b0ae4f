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

A mistake is one :class:`MenuError` naming the file, the line and the field
(``menu.toml:7: page 1 var 2 format: ...``); ``pfma console`` prints it and exits 2
before it shows anything.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

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


def _lines(text: str) -> dict[tuple[int, int, str | None], int]:
    """Where each table and key is: (page, var, key) -> line (page/var -1: none; key None:
    the table's header). Only the plain layout of the module doc is located; anything else
    falls back to its table's header line."""
    where: dict[tuple[int, int, str | None], int] = {}
    p = v = -1
    key_re = re.compile(r"^\s*([A-Za-z0-9_\-]+)\s*=")
    for n, raw in enumerate(text.splitlines(), 1):
        s = raw.strip()
        if s.startswith("[[") and s.split("#")[0].strip().replace(" ", "") == "[[page]]":
            p, v = p + 1, -1
            where[(p, v, None)] = n
        elif s.startswith("[[") and s.split("#")[0].strip().replace(" ", "") == "[[page.var]]":
            v += 1
            where[(p, v, None)] = n
        else:
            m = key_re.match(raw)
            if m:
                where.setdefault((p, v, m.group(1)), n)
    return where


def load(path: str | Path) -> Menu:
    """Read and check a menu file (everything but the variables' existence: :meth:`Menu.check`).

    :raises MenuError: unreadable, not TOML, a missing, unknown or bad field
    """
    path = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise MenuError(path, 0, "file", f"cannot read it ({err.__class__.__name__}: "
                                         f"{getattr(err, 'strerror', None) or err})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        msg = str(err)
        m = re.search(r"\(at line (\d+), column \d+\)", msg)
        line = int(m.group(1)) if m else 0
        raise MenuError(path, line, "TOML", re.sub(r"\s*\(at line \d+, column \d+\)", "", msg)
                        or "not TOML") from None
    where = _lines(text)

    def line(p: int, v: int, key: str | None) -> int:
        return where.get((p, v, key)) or where.get((p, v, None)) or where.get((p, -1, None)) or 1

    def fail(p: int, v: int, key: str | None, field: str, msg: str):
        raise MenuError(path, line(p, v, key), field, msg)

    for k in data:
        if k not in TOP_FIELDS:
            fail(-1, -1, k, k, f"unknown field (a menu file has {', '.join(TOP_FIELDS)})")
    title = data.get("title", Path(path).stem)
    if not isinstance(title, str):
        fail(-1, -1, "title", "title", "must be a string")
    raw_pages = data.get("page")
    if not isinstance(raw_pages, list) or not raw_pages:
        fail(-1, -1, "page", "page", "no pages: add [[page]] tables, each with name and [[page.var]] tables")
    pages = []
    seen: dict[str, int] = {}
    for pi, pg in enumerate(raw_pages):
        w = f"page {pi + 1}"
        if not isinstance(pg, dict):
            fail(pi, -1, None, w, "must be a table ([[page]])")
        for k in pg:
            if k not in PAGE_FIELDS:
                fail(pi, -1, k, f"{w} {k}", f"unknown field (a page has {', '.join(PAGE_FIELDS)})")
        name = pg.get("name")
        if not isinstance(name, str) or not name.strip():
            fail(pi, -1, "name", f"{w} name", "a page needs a name (a non-empty string)")
        if name in seen:
            fail(pi, -1, "name", f"{w} name", f"page name {name!r} is used by page {seen[name]} too")
        seen[name] = pi + 1
        rate = pg.get("refresh_hz", MAX_REFRESH_HZ)
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not 0 < rate <= MAX_REFRESH_HZ:
            fail(pi, -1, "refresh_hz", f"{w} refresh_hz",
                 f"{rate!r} is not a rate in (0, {MAX_REFRESH_HZ:g}] Hz (the console refreshes at {MAX_REFRESH_HZ:g} Hz)")
        raw_vars = pg.get("var")
        if not isinstance(raw_vars, list) or not raw_vars:
            fail(pi, -1, "var", f"{w} var", "a page needs variables: [[page.var]] tables with a name")
        vars_ = []
        for vi, vv in enumerate(raw_vars):
            wv = f"{w} var {vi + 1}"
            if not isinstance(vv, dict):
                fail(pi, vi, None, wv, "must be a table ([[page.var]])")
            for k in vv:
                if k not in VAR_FIELDS:
                    fail(pi, vi, k, f"{wv} {k}", f"unknown field (a variable has {', '.join(VAR_FIELDS)})")
            vname = vv.get("name")
            if not isinstance(vname, str) or not vname:
                fail(pi, vi, "name", f"{wv} name", "a variable needs a name (a world-model variable)")
            fmt = vv.get("format", DEFAULT_FORMAT)
            if not isinstance(fmt, str):
                fail(pi, vi, "format", f"{wv} format", "must be a string: a Python format spec such as '+.4f'")
            try:
                format(0, fmt) if re.search(r"[bcdoxXn]$", fmt) else format(0.0, fmt)
            except ValueError as err:
                fail(pi, vi, "format", f"{wv} format", f"{fmt!r} is not a format spec ({err}); e.g. '+.4f', '.6g', 'd'")
            label = vv.get("label", vname)
            if not isinstance(label, str):
                fail(pi, vi, "label", f"{wv} label", "must be a string")
            vars_.append(MenuVar(vname, fmt, label, line(pi, vi, "name"), line(pi, vi, "format")))
        pages.append(MenuPage(name, float(rate), tuple(vars_)))
    return Menu(path, title, tuple(pages))


def _fmt(v: Any, spec) -> str:
    import numpy as np
    a = np.asarray(v)
    if a.ndim == 0:
        return format(a.item(), spec)
    return "  ".join(format(x, spec) for x in a.ravel().tolist())


def page_text(menu: Menu, index: int, values: dict[str, Any], wm) -> str:
    """One page: the tabs, then one line per variable (label, formatted value(s), units)."""
    page = menu.pages[index % len(menu.pages)]
    tabs = "  ".join(f"[{p.name}]" if p is page else p.name for p in menu.pages)
    width = max(len(v.label) for v in page.vars)
    lines = [f"{menu.title}: {tabs}",
             f"page {index % len(menu.pages) + 1}/{len(menu.pages)}, refresh {page.refresh_hz:g} Hz   "
             f"<- -> / tab page   Escape/l close   ({menu.path})", ""]
    for v in page.vars:
        units = wm.spec(v.name).units
        lines.append(f"{v.label:<{width}}  {_fmt(values[v.name], v.format)}" + (f"  {units}" if units else ""))
    return "\n".join(lines)
