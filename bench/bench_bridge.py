"""The Bit3 areas over the Zenoh bridge on loopback (issue 19's performance figures):
inputs latency across ``pfma bridge`` beside a shared-memory reader in the same run
(p50/p99), the share of 320 Hz frames delivered (goal >= 99 %), the bridge's CPU (goal <=
15 % of a core). Real time: ``pfma serve``, ``pfma bridge`` and two reader processes
(tools/bridge/latency.py). ``pfma bench --json`` carries them under ``bridge``.
"""

from __future__ import annotations


from tools.bridge.latency import measure, report


def figures(seconds: float = 5.0) -> dict:
    """The figures of :func:`tools.bridge.latency.measure` (``{"skipped": why}`` without
    the eclipse-zenoh package)."""
    try:
        import zenoh  # noqa: F401
    except ImportError:
        return {"skipped": "the eclipse-zenoh package is not installed"}
    return measure(seconds)


def run(seconds: float = 5.0) -> dict:
    f = figures(seconds)
    print(f.get("skipped") or report(f))
    return f
