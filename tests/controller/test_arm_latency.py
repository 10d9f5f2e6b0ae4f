"""A re-arm through a link with latency (a remote controller over ``pfma bridge``, or a local
one whose command lands after the service's next frame began): the service is still in the
FAULT of the last episode for the frames before the arm request reaches it, and that is the
arm request's answer pending, not a fault of the hardware (Data Acquisition's check 16
waits for it, the start-up task times out after ARM_TIMEOUT_S naming the state).

The CI kill matrix (bench/bench_chaos.py, bridge kind) met this: a remote controller
re-arming a service in FAULT after its bridge was killed went to ERROR on "hardware check:
service state: service FAULT" 0.12 s into its power-up."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from bit3.layout import ServiceState
from controller.daq_layer import ARM_TIMEOUT_S
from controller.decision import Status
from controller.layers import Request, Response


def _delay_commands(sim, frames: int) -> None:
    """The controller's command writes reach the buffer ``frames`` writes (one per
    controller frame) late, as over a link: each write is copied and released later."""
    real = sim.client.write_commands
    queue: deque = deque()

    def delayed(**fields):
        queue.append({k: np.array(v, copy=True) if isinstance(v, np.ndarray) else v for k, v in fields.items()})
        return real(**queue.popleft()) if len(queue) > frames else 0

    sim.client.write_commands = delayed


def _service_faulted_then_reset(sim) -> None:
    """Powered up, then the controller misses the watchdog (service FAULT, every layer ERROR),
    then an error reset: the service stays in FAULT until the next arm request."""
    sim.controller_enabled = False
    sim.step(20)  # 62 ms: more than the 15 ms watchdog
    assert int(sim.client.read_inputs().service_state) == ServiceState.FAULT
    sim.controller_enabled = True
    sim.run_until(lambda: sim.rt.status("updown") == Status.ERROR, 400)
    sim.step(400)  # the safe tasks finished
    code, text = sim.request(Request.ERROR_RESET, max_frames=600)
    assert code == Response.COMPLETE, text
    assert int(sim.client.read_inputs().service_state) == ServiceState.FAULT


@pytest.mark.parametrize("late", [0, 1, 2])  # 3 frames late is a stale command (4-frame age)
def test_a_re_arm_whose_request_reaches_the_service_late_powers_up(powered, late):
    sim = powered
    _service_faulted_then_reset(sim)
    _delay_commands(sim, late)
    sim.rt.request(Request.POWER_UP)
    for _ in range(600):
        sim.step(1)
        if sim.rt.all_status(Status.START_UP_COMPLETE):
            break
    assert sim.rt.all_status(Status.START_UP_COMPLETE), (late, sim.rt.first_cause, [m.text for m in sim.rt.messages.recent(6)])
    assert int(sim.client.read_inputs().service_state) == ServiceState.ARMED


def test_a_service_that_never_answers_the_arm_request_is_named_after_the_time_out(powered):
    sim = powered
    _service_faulted_then_reset(sim)
    _delay_commands(sim, 10_000)  # the arm request never arrives
    sim.rt.request(Request.POWER_UP)
    frames = int(ARM_TIMEOUT_S / sim.period_s) + 200
    sim.run_until(lambda: sim.rt.status("daq") == Status.ERROR, frames)
    assert sim.rt.status("daq") == Status.ERROR
    texts = [m.text for m in sim.rt.messages.recent(100)]
    assert any(f"service did not arm within {ARM_TIMEOUT_S} s (state FAULT)" in t for t in texts), texts[-8:]
