"""Checkout results and their three renderings: terminal lines, JSON, standalone HTML."""

from __future__ import annotations

import datetime as _dt
import html
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

PASS, FAIL, SKIP = "PASS", "FAIL", "SKIP"


@dataclass
class Result:
    """One checked item: a channel (rack signal, link, joint) and what was checked on it."""

    group: str
    channel: str
    check: str
    status: str  #: PASS, FAIL or SKIP
    measured: float | int | str | None = None
    low: float | None = None
    high: float | None = None
    units: str = ""
    detail: str = ""

    @property
    def passed(self) -> bool:
        return self.status == PASS

    def limits_text(self) -> str:
        """The pass band in words: ``0.5 .. 2 V``, ``<= 0.01 V``, ``>= 3 V`` (an open side,
        None or infinite, is not printed as a number)."""
        lo = None if self.low is None or not math.isfinite(self.low) else _num(self.low)
        hi = None if self.high is None or not math.isfinite(self.high) else _num(self.high)
        units = f" {self.units}" if self.units and self.units != "1" else ""
        if lo is None and hi is None:
            return ""
        if lo is None:
            return f"<= {hi}{units}"
        if hi is None:
            return f">= {lo}{units}"
        if lo == hi:
            return f"= {lo}{units}"
        return f"{lo} .. {hi}{units}"

    def measured_text(self) -> str:
        return "" if self.measured is None else _num(self.measured)

    def line(self) -> str:
        """One terminal line: status, group, channel, check, measured, limits, units, detail."""
        m = self.measured_text()
        parts = [f"{self.status:4s}  {self.group:9s} {self.channel:30s} {self.check:24s}",
                 f"{m:>12s} {self.units:7s}", self.limits_text()]
        text = " ".join(p for p in parts if p)
        return f"{text}  {self.detail}" if self.detail else text


def _num(v: Any) -> str:
    if isinstance(v, bool) or isinstance(v, str):
        return str(v)
    if isinstance(v, int):
        return str(v)
    if v is None or not math.isfinite(v):
        return str(v)
    a = abs(v)
    if a != 0 and (a < 1e-3 or a >= 1e5):
        return f"{v:.3e}"
    return f"{v:.4g}"


def _jsonable(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if hasattr(v, "item"):  # numpy scalars
        return _jsonable(v.item())
    return v


@dataclass
class Report:
    """Everything a checkout run produced."""

    target: str
    rack: str
    groups: list[str]
    results: list[Result] = field(default_factory=list)
    started_utc: str = field(default_factory=lambda: _dt.datetime.now(_dt.timezone.utc)
                             .isoformat(timespec="seconds"))
    duration_s: float = 0.0
    target_time_s: float = 0.0  #: simulated or real seconds the checkout took on the target
    stopped_early: str = ""  #: why the run stopped before the end ("" = it ran to the end)
    config: dict = field(default_factory=dict)
    config_source: str = ""
    #: the servo chassis' front panel before the joints group, in words, with who said so
    #: (the operator, the command line, or assumed): a statement, never a measurement
    #: ("" = not asked: the joints group did not run)
    panel: str = ""

    def count(self, status: str) -> int:
        return sum(1 for r in self.results if r.status == status)

    @property
    def passed(self) -> bool:
        """True only when something was checked, nothing failed and the run was complete."""
        return self.count(FAIL) == 0 and self.count(PASS) > 0 and not self.stopped_early

    def failures(self) -> list[Result]:
        return [r for r in self.results if r.status == FAIL]

    def summary_lines(self) -> list[str]:
        out = [f"checkout of {self.target}: {self.count(PASS)} passed, {self.count(FAIL)} failed, "
               f"{self.count(SKIP)} skipped in {self.target_time_s:.1f} s "
               f"({self.duration_s:.1f} s wall)"]
        if self.panel:
            out.append(f"servo chassis panel: {self.panel}")
        if self.stopped_early:
            out.append(f"stopped early: {self.stopped_early}")
        for r in self.failures():
            out.append(f"FAILED: {r.channel} ({r.group}, {r.check}): measured {r.measured_text()} "
                       f"{r.units} {r.limits_text()} {r.detail}".rstrip())
        out.append("RESULT: PASS" if self.passed else "RESULT: FAIL")
        return out

    def as_dict(self) -> dict:
        return _jsonable({
            "tool": "pfma checkout", "format": 1,
            "target": self.target, "rack": self.rack, "started_utc": self.started_utc,
            "duration_s": round(self.duration_s, 3), "target_time_s": round(self.target_time_s, 4),
            "passed": self.passed, "stopped_early": self.stopped_early,
            "counts": {"pass": self.count(PASS), "fail": self.count(FAIL), "skip": self.count(SKIP)},
            "groups": self.groups, "panel": self.panel,
            "results": [asdict(r) for r in self.results],
            "config_source": self.config_source, "config": self.config,
        })

    def write_json(self, path: str | Path) -> Path:
        p = Path(path)
        p.write_text(json.dumps(self.as_dict(), indent=1, allow_nan=False) + "\n")
        return p

    def summary_table(self):
        """The summary for a terminal (rich): counts, the failures as a table, the result.
        The same facts as :meth:`summary_lines`, which a pipe gets."""
        from rich import box
        from rich.console import Group
        from rich.table import Table
        from rich.text import Text
        parts: list = [Text(f"checkout of {self.target}: {self.count(PASS)} passed, {self.count(FAIL)} failed, "
                            f"{self.count(SKIP)} skipped in {self.target_time_s:.1f} s "
                            f"({self.duration_s:.1f} s wall)")]
        if self.panel:
            parts.append(Text(f"servo chassis panel: {self.panel}"))
        if self.stopped_early:
            parts.append(Text(f"stopped early: {self.stopped_early}", style="yellow"))
        if self.failures():
            t = Table(title="FAILED", title_justify="left", box=box.SIMPLE_HEAD, title_style="bold red")
            for col in ("channel", "group", "check", "measured", "limits", "detail"):
                t.add_column(col, overflow="fold")
            for r in self.failures():
                t.add_row(r.channel, r.group, r.check, f"{r.measured_text()} {r.units}".strip(),
                          r.limits_text(), r.detail)
            parts.append(t)
        parts.append(Text("RESULT: PASS" if self.passed else "RESULT: FAIL",
                          style="bold green" if self.passed else "bold red"))
        return Group(*parts)

    def html(self) -> str:
        """One self-contained HTML page (inline CSS, no scripts, no external resources)."""
        e = html.escape
        verdict = "PASS" if self.passed else "FAIL"
        rows = []
        for i, r in enumerate(self.results):
            rows.append(
                f'<tr class="{r.status.lower()}" id="r{i}"><td class="status">{e(r.status)}</td>'
                f'<td class="group">{e(r.group)}</td><td class="channel">{e(r.channel)}</td>'
                f'<td class="check">{e(r.check)}</td><td class="num">{e(r.measured_text())}</td>'
                f'<td class="num">{e(r.limits_text())}</td><td>{e(r.units)}</td>'
                f'<td class="detail">{e(r.detail)}</td></tr>')
        early = f'<p class="early">Stopped early: {e(self.stopped_early)}</p>' if self.stopped_early else ""
        fails = "".join(f"<li>{e(r.channel)} ({e(r.group)}, {e(r.check)}): {e(r.measured_text())} "
                        f"{e(r.units)} {e(r.limits_text())} {e(r.detail)}</li>" for r in self.failures())
        fails = f"<h2>Failures</h2><ul>{fails}</ul>" if fails else ""
        panel = f"<tr><td>Servo chassis panel</td><td>{e(self.panel)}</td></tr>\n" if self.panel else ""
        return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>pfma checkout {e(verdict)} - {e(self.rack)} - {e(self.started_utc)}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }}
h1 .verdict {{ padding: 0.1em 0.5em; border-radius: 4px; color: #fff; }}
h1 .PASS {{ background: #2e7d32; }} h1 .FAIL {{ background: #c62828; }}
table {{ border-collapse: collapse; font-size: 0.9em; }}
th, td {{ border: 1px solid #ccc; padding: 0.2em 0.5em; text-align: left; }}
th {{ background: #eee; position: sticky; top: 0; }}
td.num {{ text-align: right; font-family: monospace; }}
td.channel {{ font-family: monospace; }}
tr.pass td.status {{ color: #2e7d32; font-weight: bold; }}
tr.fail {{ background: #fdecea; }} tr.fail td.status {{ color: #c62828; font-weight: bold; }}
tr.skip td {{ color: #777; }}
.meta td {{ border: none; padding: 0.1em 1em 0.1em 0; }}
.early {{ color: #c62828; font-weight: bold; }}
</style></head>
<body>
<h1>pfma checkout <span class="verdict {e(verdict)}">{e(verdict)}</span></h1>
<table class="meta">
<tr><td>Target</td><td>{e(self.target)}</td></tr>
<tr><td>Rack</td><td>{e(self.rack)}</td></tr>
<tr><td>Started (UTC)</td><td>{e(self.started_utc)}</td></tr>
<tr><td>Duration</td><td>{self.target_time_s:.1f} s on the target, {self.duration_s:.1f} s wall</td></tr>
<tr><td>Groups</td><td>{e(", ".join(self.groups))}</td></tr>
<tr><td>Counts</td><td>{self.count(PASS)} passed, {self.count(FAIL)} failed, {self.count(SKIP)} skipped</td></tr>
<tr><td>Tolerances</td><td>{e(self.config_source)}</td></tr>
{panel}</table>
{early}{fails}
<h2>Channels</h2>
<table class="results">
<tr><th>Status</th><th>Group</th><th>Channel</th><th>Check</th><th>Measured</th><th>Limits</th><th>Units</th><th>Detail</th></tr>
{chr(10).join(rows)}
</table>
</body></html>
"""

    def write_html(self, path: str | Path) -> Path:
        p = Path(path)
        p.write_text(self.html())
        return p
