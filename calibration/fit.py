"""Least-squares fits with residuals (numpy), shared by every calibration procedure.

Every fit returns a :class:`Fit`: the coefficients, the points it used, the residual
of each point and the RMS/max residual, so a procedure can store them as provenance
and judge pass/fail on them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pfma.errors import CalibrationError


@dataclass
class Fit:
    """Result of one least-squares fit."""

    coef: np.ndarray  #: fitted coefficients (meaning given by ``names``)
    names: tuple[str, ...]  #: one name per coefficient, e.g. ("gain", "offset")
    x: np.ndarray  #: independent values (rows = points)
    y: np.ndarray  #: measured values
    residuals: np.ndarray  #: y - model(x), same shape as y
    extra: dict = field(default_factory=dict)

    @property
    def rms(self) -> float:
        r = np.asarray(self.residuals, dtype=float)
        return float(np.sqrt(np.mean(r * r))) if r.size else 0.0

    @property
    def max_abs(self) -> float:
        r = np.asarray(self.residuals, dtype=float)
        return float(np.max(np.abs(r))) if r.size else 0.0

    def __getitem__(self, name: str) -> float:
        return float(self.coef[self.names.index(name)])

    def as_dict(self) -> dict:
        """Plain lists for the calibration file's provenance."""
        return {
            "coefficients": {n: _plain(c) for n, c in zip(self.names, self.coef)},
            "points": (np.column_stack([self.x, self.y]).round(9).tolist()
                       if self.x.ndim == 1 and self.y.ndim == 1
                       else {"x": np.round(self.x, 9).tolist(), "y": np.round(self.y, 9).tolist()}),
            "residuals": np.round(self.residuals, 9).tolist(),
            "rms_residual": self.rms,
            "max_residual": self.max_abs,
        }


def _plain(v):
    a = np.asarray(v)
    return a.round(12).tolist() if a.ndim else float(a)


def _need(n_points: int, n_unknowns: int, what: str) -> None:
    if n_points < n_unknowns:
        raise CalibrationError(f"{what}: {n_points} point(s) cannot determine {n_unknowns} unknown(s)")


def linear(x, y, what: str = "linear fit") -> Fit:
    """Fit ``y = gain * x + offset``.

    :raises CalibrationError: fewer than 2 points, non-finite data, or all x equal
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    if x.shape != y.shape:
        raise CalibrationError(f"{what}: {x.size} x values but {y.size} y values")
    _need(x.size, 2, what)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise CalibrationError(f"{what}: non-finite data")
    if np.ptp(x) == 0:
        raise CalibrationError(f"{what}: all points at x = {x[0]:g}; need at least two different values")
    a = np.column_stack([x, np.ones_like(x)])
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    return Fit(coef, ("gain", "offset"), x, y, y - a @ coef)


def mean_offset(samples, what: str = "offset") -> Fit:
    """Constant fit: the mean, residuals = deviations from it."""
    s = np.asarray(samples, dtype=float).ravel()
    _need(s.size, 1, what)
    if not np.all(np.isfinite(s)):
        raise CalibrationError(f"{what}: non-finite data")
    m = float(np.mean(s))
    return Fit(np.array([m]), ("mean",), np.arange(s.size, dtype=float), s, s - m)


def design(a, y, names: tuple[str, ...], what: str = "least squares") -> Fit:
    """General linear least squares ``y = A @ coef`` (y may be a matrix: one column per output)."""
    a = np.asarray(a, dtype=float)
    y = np.asarray(y, dtype=float)
    _need(a.shape[0], a.shape[1], what)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(y))):
        raise CalibrationError(f"{what}: non-finite data")
    coef, _, rank, _ = np.linalg.lstsq(a, y, rcond=None)
    if rank < a.shape[1]:
        raise CalibrationError(f"{what}: the points do not determine all unknowns (rank {rank} of "
                               f"{a.shape[1]}); vary the stimulus more")
    return Fit(coef, names, a, y, y - a @ coef)


def slope(t, y) -> float:
    """Least-squares slope of ``y`` against ``t`` (e.g. velocity from unwrapped angles)."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    tc = t - t.mean()
    den = float(tc @ tc)
    if den == 0:
        raise CalibrationError("slope: all samples at the same time")
    return float(tc @ (y - y.mean()) / den)
