"""The anti-aliasing filter board between the arm's analog signals and the A/D board.

IRSS report 3.4.2, "Anti-aliasing Filter Board" (sourced): sixteen single-ended and
thirteen differential **four-pole low-pass** active filters "prevent possible aliasing of
tachometer, motor current, and CAE hand controller signals", between the signal source and
the A/D conversion board. The board takes only DC power from the VMEbus (it works whatever
the servo chassis' switches say).

ASSUMED (the drawings 849IRS20600/601/604 are not public): a Butterworth response with its
corner at :data:`pfma.arm.ANTI_ALIAS_HZ` (40 Hz, half the 80 Hz Nyquist frequency of the
160 Hz A/D rate: -24 dB there), unity gain. Its group delay at DC is
:func:`pfma.arm.anti_alias_delay_s` (10.4 ms), the lag the A/D readings of these channels
carry behind the signal.

One filter per channel, all alike: the state of every channel is one ``(4, n)`` array and a
step of ``dt`` is one exact discretisation of the continuous filter with the input taken
linear between the step's two ends (a first-order hold: the arm's signals are smooth on the
scale of a 3 ms step), computed once per ``dt`` and cached.
"""

from __future__ import annotations

import math

import numpy as np

from pfma.arm import ANTI_ALIAS_HZ, ANTI_ALIAS_POLES, butterworth_zetas


def butterworth_state_space(corner_hz: float, poles: int = ANTI_ALIAS_POLES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C) of a unity-gain Butterworth low-pass of ``poles`` (even) poles at
    ``corner_hz``: a cascade of second-order sections ``w^2 / (s^2 + 2 zeta w s + w^2)``,
    state (y1, y1', y2, y2', ...), output the last section's y."""
    if poles < 2 or poles % 2:
        raise ValueError(f"an even number of poles >= 2, got {poles}")
    w = 2.0 * math.pi * corner_hz
    n = poles
    a = np.zeros((n, n))
    b = np.zeros(n)
    for s, zeta in enumerate(butterworth_zetas(n)):
        i = 2 * s
        a[i, i + 1] = 1.0
        a[i + 1, i] = -w * w
        a[i + 1, i + 1] = -2.0 * zeta * w
        if s == 0:
            b[i + 1] = w * w  # the first section takes the input
        else:
            a[i + 1, i - 2] = w * w  # the others the section before them
    c = np.zeros(n)
    c[n - 2] = 1.0
    return a, b, c


def _expm(m: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring of a Taylor series (small matrices, once
    per step length: numpy has none and scipy is not a dependency)."""
    norm = float(np.abs(m).sum(axis=1).max())
    s = max(0, int(math.ceil(math.log2(norm / 0.25))) if norm > 0.25 else 0)
    x = m / (2.0 ** s)
    term = np.eye(len(m))
    out = term.copy()
    for k in range(1, 18):
        term = term @ x / k
        out = out + term
    for _ in range(s):
        out = out @ out
    return out


class AntiAliasBank:
    """``n`` identical anti-aliasing filters, one per channel.

    :param n: channels
    :param corner_hz: the corner (default :data:`pfma.arm.ANTI_ALIAS_HZ`); None or 0: no
        filter (the output is the input; the simulator before this board was modelled)
    """

    def __init__(self, n: int, corner_hz: float | None = ANTI_ALIAS_HZ) -> None:
        self.n = n
        self.corner_hz = corner_hz or None
        self._u = np.zeros(n)
        self._cache: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        if self.corner_hz is not None:
            self._a, self._b, self._c = butterworth_state_space(self.corner_hz)
            self._x = np.zeros((len(self._b), n))
            self._dc = np.linalg.solve(-self._a, self._b)  # the state at rest for a unit input

    def settle(self, u: np.ndarray) -> None:
        """At rest with input ``u`` held forever: the output is ``u``."""
        self._u = np.array(u, dtype=float)
        if self.corner_hz is not None:
            self._x = np.outer(self._dc, self._u)

    def _discrete(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(Phi, G0, G1) of a step ``dt``: ``x1 = Phi x0 + G0 u0 + G1 u1`` for an input
        linear from u0 to u1 (the augmented-matrix exponential of a first-order hold)."""
        got = self._cache.get(dt)
        if got is None:
            n = len(self._b)
            m = np.zeros((n + 2, n + 2))
            m[:n, :n] = self._a * dt
            m[:n, n] = self._b * dt
            m[n, n + 1] = 1.0
            e = _expm(m)
            phi, g_a, g_b = e[:n, :n], e[:n, n], e[:n, n + 1]
            got = (phi, g_a - g_b, g_b)  # u(t) = u0 + (u1 - u0) t/dt
            if len(self._cache) < 16:
                self._cache[dt] = got
        return got

    def step(self, dt: float, u: np.ndarray) -> np.ndarray:
        """Advance by ``dt`` with the input going linearly to ``u``; the outputs now."""
        u = np.asarray(u, dtype=float)
        if self.corner_hz is None or dt <= 0:
            self._u = u.copy()
            return self.output(u)
        phi, g0, g1 = self._discrete(dt)
        x = phi @ self._x
        x += np.outer(g0, self._u)
        x += np.outer(g1, u)
        self._x = x
        self._u = u.copy()
        return self._c @ x

    def output(self, u: np.ndarray | None = None) -> np.ndarray:
        """The outputs now (no filter: the input, ``u`` if given)."""
        if self.corner_hz is None:
            return np.array(self._u if u is None else u, dtype=float)
        return self._c @ self._x


__all__ = ["AntiAliasBank", "butterworth_state_space"]
