"""Issue 33 item 5, live: ``pfma controller --clock own --profile overview`` (its own 268 Hz
frame clock) beside a ``pfma serve`` that keeps its 320 Hz frames, on a private buffer. The
two meet only in the buffer: the arm powers up and holds, the controller's published rate is
its own and the service's is its own, and the command each armed frame applied is within the
service's age limit. Bounded polling of processes (real time)."""

from __future__ import annotations

import uuid

import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from tests.controller._live_support import (
    RERUN_ON_HOST_TIMING, armed_and_released, host_timing_named, live_inputs, powered_controller, start_service, stop,
    wait_for,
)

pytestmark = [pytest.mark.realtime, RERUN_ON_HOST_TIMING]


def _rates(name: str) -> tuple[float, float, int]:
    """(the service's frame rate, the controller's, the controller's frames) as published."""
    with Client.attach(name) as c:
        s, k = c.read("stats"), c.read("controller_stats")
        return float(s["rate_hz"]), float(k["rate_hz"]), int(k["frames"])


def test_the_controller_on_its_own_clock_flies_the_live_arm_beside_a_320_hz_service():
    name = "pfma-test-2c-" + uuid.uuid4().hex[:6]
    serve = start_service(name, "--duration", "60")
    ctl = None
    try:
        with host_timing_named(lambda: ctl):
            ctl = powered_controller(name, "--clock", "own", "--profile", "overview", "--duration", "8",
                                     "--messages", "100")
            # the controller publishes its statistics about every 0.5 s: wait for a second set
            assert wait_for(lambda: _rates(name)[2] > 600, 10), "no controller statistics"
            ages: list[int] = []

            def sampled() -> bool:  # the applied command's age, at each poll (every 50 ms)
                ages.append(int(live_inputs(name).command_input_age_frames))
                return len(ages) >= 40
            assert wait_for(sampled, 10)
            svc_hz, ctl_hz, _ = _rates(name)
            assert svc_hz == pytest.approx(320.0, abs=8.0)
            assert ctl_hz == pytest.approx(268.0, abs=8.0)
            s = live_inputs(name)
            assert armed_and_released(name) and int(s.refused_commands) == 0 and int(s.stale_commands) == 0
            assert max(ages) <= 8, ages  # the service's limit here (SLOW_HOST_SERVICE)
            out, _ = ctl.communicate(timeout=60)
            assert "first cause: none (no ERROR episode)" in out, out[-3000:]
    finally:
        stop(ctl, serve)
        Bit3Buffer.unlink(name)
