"""The console's World Status names the root of the current episode (issue 29 item 3): the
controller's ERROR episode's first cause (``runtime.first_cause``) and the service's first
trip since the last arm (Bit3 ``inputs.first_trip_*``), not the cascade's last messages.
The system simulator in simulated time."""

from __future__ import annotations

from controller.decision import Status
from sim.faults import FaultSet
from tools.console import view


def _world(sim, reader) -> list[str]:
    return view.world_status(view.Sources(reader, sim.rt.wm, rack="simulated").read(), "simulated").splitlines()


def test_world_status_shows_the_controllers_first_cause_and_the_services_first_trip(sim, reader):
    sim.power_up(max_frames=400)
    sim.step(20)
    assert not [l for l in _world(sim, reader) if "first" in l]  # no episode: no line
    FaultSet(sim.world).inject("resolver-los:shoulder_pitch_angle")
    sim.run_until(lambda: sim.rt.status("updown") == Status.ERROR, 200)
    sim.step(50)  # the cascade's messages come after it
    fc = sim.rt.first_cause
    lines = _world(sim, reader)
    assert f"controller first cause: {fc.source}: {fc.text}" in lines
    assert "shoulder_pitch" in fc.text and "subordinate" not in fc.text


def test_world_status_shows_the_services_first_trip_until_armed_again(sim, reader):
    sim.power_up(max_frames=400)
    sim.step(20)
    assert not [l for l in _world(sim, reader) if l.startswith("service first trip")]  # armed: none
    sim.controller_enabled = False  # the controller stops: the service's watchdog trips
    sim.step(20)
    code, reason, _t = sim.svc.guard.first_trip
    assert "stale heartbeat" in reason
    lines = _world(sim, reader)
    assert f"service first trip: {reason}" in lines
