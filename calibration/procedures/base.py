"""What every procedure shares: its context, checks, result, progress, drift and saving."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calibration.files import Calibration, diff, provenance
from calibration.fit import Fit
from calibration.session import Operator, Session
from pfma.errors import CalibrationError
from pfma.rack import RackConfig


@dataclass
class Context:
    """Everything a procedure needs.

    :param calibration: the calibration in force (the previous one; drift is against it)
    :param plot_dir: where PNG plots go
    :param options: procedure options (signals, joints, tolerances ...)
    """

    session: Session
    operator: Operator
    calibration: Calibration
    rack: RackConfig
    plot_dir: Path
    operator_name: str = ""
    options: dict = field(default_factory=dict)

    def progress(self, i: int, n: int, text: str) -> None:
        """Step ``i`` of ``n``. An operator with a ``progress(i, n, text)`` method draws it
        itself (``pfma calibrate`` on a terminal: a rich bar); otherwise one plain line."""
        draw = getattr(self.operator, "progress", None)
        if callable(draw):
            draw(i, n, text)
            return
        width = 20
        done = int(round(width * i / max(1, n)))
        self.operator.show(f"[{'#' * done}{'.' * (width - done)}] {i}/{n} {text}")

    def provenance(self, method: str, fit: Fit | None = None, **extra: Any) -> dict:
        if fit is not None:
            d = fit.as_dict()
            extra = {"points": d["points"], "residuals": d["residuals"], "rms_residual": d["rms_residual"],
                     "max_residual": d["max_residual"], **extra}
        return provenance(method, self.operator_name, **extra)


@dataclass
class Check:
    """One pass/fail line: ``|value| <= limit`` (or a boolean when limit is None)."""

    name: str
    value: float
    limit: float | None
    units: str = ""
    ok: bool | None = None

    @property
    def passed(self) -> bool:
        if self.ok is not None:
            return bool(self.ok)
        return math.isfinite(self.value) and abs(self.value) <= (self.limit or 0.0)

    def line(self) -> str:
        lim = "" if self.limit is None else f" (limit {self.limit:.4g} {self.units})"
        return f"  {'PASS' if self.passed else 'FAIL'}  {self.name}: {self.value:.6g} {self.units}{lim}"


@dataclass
class ProcedureResult:
    """The outcome of one procedure run: checks, fits, updates, plots and drift."""

    procedure: str
    tolerances: dict[str, Any] = field(default_factory=dict)
    checks: list[Check] = field(default_factory=list)
    fits: dict[str, Fit] = field(default_factory=dict)
    channels: dict[str, dict] = field(default_factory=dict)  #: updated channel entries
    cae: dict | None = None
    ft: dict | None = None
    found: dict[str, Any] = field(default_factory=dict)  #: identified values, for reports/tests
    plots: list[Path] = field(default_factory=list)
    drift: list[dict] = field(default_factory=list)
    #: why a channel's scale changed (signal -> reason), said under its drift line when the
    #: change is beyond ``scale_tolerance`` (a large change that passes must say why)
    why: dict[str, str] = field(default_factory=dict)
    scale_tolerance: float = 0.01  #: relative; the procedure's stated gain tolerance
    calibration: Calibration | None = None  #: previous + these updates (validated)
    saved: Calibration | None = None

    @property
    def passed(self) -> bool:
        return bool(self.checks) and all(c.passed for c in self.checks)

    def check(self, name: str, value: float, limit: float | None, units: str = "", ok: bool | None = None) -> Check:
        c = Check(name, float(value), limit, units, ok)
        self.checks.append(c)
        return c

    def _why_scale(self, d: dict) -> str:
        """Why a scale moved beyond the tolerance ("" when it did not, or it is no scale)."""
        rel = _scale_change(d)
        if rel is None or abs(rel) <= self.scale_tolerance:
            return ""
        sig = str(d["entry"]).split(".")[1]
        return self.why.get(sig) or (f"{rel:+.1%}, beyond the {self.scale_tolerance:.1%} tolerance: the fit above "
                                     f"found it (no cause known to the procedure)")

    def report(self) -> str:
        lines = [f"calibration procedure {self.procedure}: {'PASSED' if self.passed else 'FAILED'}"]
        if self.tolerances:
            lines.append("  tolerances: " + ", ".join(f"{k} {v}" for k, v in self.tolerances.items()))
        for name, f in self.fits.items():
            coef = ", ".join(f"{n}={c:.6g}" for n, c in zip(f.names, np.ravel(f.coef)) if np.ndim(c) == 0) \
                if np.ndim(f.coef) == 1 else f"{np.shape(f.coef)} matrix"
            lines.append(f"  fit {name}: {coef}; rms residual {f.rms:.3g}, max {f.max_abs:.3g}")
        lines += [c.line() for c in self.checks]
        if self.drift:
            lines.append("  drift against the previous calibration:")
            for d in self.drift:
                ch = d["change"]
                old, new = d["old"], d["new"]
                fmt = (lambda v: f"{v:.6g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else
                       ("(list)" if isinstance(v, list) else str(v)))
                lines.append(f"    {d['entry']}: {fmt(old)} -> {fmt(new)}"
                             + (f" (change {ch:+.4g})" if isinstance(ch, float) else ""))
                why = self._why_scale(d)
                if why:
                    lines.append(f"      why: {why}")
        for p in self.plots:
            lines.append(f"  plot: {p}")
        return "\n".join(lines)


def _scale_change(d: dict) -> float | None:
    """The relative change of a drift entry ``channels.<signal>.scale`` (None for another
    entry, or no old value)."""
    old, new = d.get("old"), d.get("new")
    if not str(d.get("entry", "")).endswith(".scale") or not isinstance(old, (int, float)) or \
            not isinstance(new, (int, float)) or old == 0:
        return None
    return float(new) / float(old) - 1.0


def finish(ctx: Context, res: ProcedureResult) -> ProcedureResult:
    """Merge the updates into the calibration in force (validated) and compute the drift."""
    if res.channels or res.cae is not None or res.ft is not None:
        res.calibration = ctx.calibration.updated(channels=res.channels, cae=res.cae, ft=res.ft, rack=ctx.rack)
        res.drift = diff(ctx.calibration, res.calibration)
    else:
        res.calibration = ctx.calibration
    return res


def require(cond: bool, msg: str) -> None:
    if not cond:
        raise CalibrationError(msg)


def plot_name(ctx: Context, procedure: str, what: str) -> Path:
    safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in what)
    return ctx.plot_dir / f"{procedure}-{safe}.png"
