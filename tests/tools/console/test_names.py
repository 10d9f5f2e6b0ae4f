"""The console shows states, tasks and error codes by name (issue 29 item 5, pfma/show.py),
the same names ``pfma wm`` shows. The system simulator in simulated time."""

from __future__ import annotations

import math

from controller.decision import Status
from sim.faults import FaultSet
from tools.console import view


def test_local_status_names_the_layers_task_and_error_code_and_world_status_the_fault(sim, reader):
    sim.power_up(max_frames=400)
    sim.step(20)
    src = view.Sources(reader, sim.rt.wm, rack="simulated")
    daq = [k for k, _ in view.LAYERS].index("daq")
    lines = view.local_status(src.read(), daq).splitlines()
    assert "Data Acquisition: row " in lines[-3] and ", last error none" in lines[-3]
    assert lines[-2] == "hardware checks: clear"
    FaultSet(sim.world).inject("resolver-los:shoulder_pitch_angle")
    sim.run_until(lambda: sim.rt.status("updown") == Status.ERROR, 200)
    sim.step(20)
    r = src.read()
    lines = view.local_status(r, daq).splitlines()
    detail = next(ln for ln in lines if ln.startswith("Data Acquisition: row "))
    assert detail.endswith("last error resolver (1)") and ", task " in detail  # was "last error 1"
    assert lines[-2] == "hardware checks: resolver"
    task = detail.split(", task ")[1].split(",")[0]
    assert task == sim.rt.wm.spec("daq.task").enum_names[int(sim.rt.wm.get("daq.task"))].lower()
    world = view.world_status(r, "simulated").splitlines()
    assert world[1].endswith("fault none")  # the service itself did not fault: the controller made it safe
    assert all(len(ln) <= 76 for ln in world[1:3])
    angles = next(ln for ln in world if ln.startswith("rad ")).split()[1:]
    assert all(-math.pi < float(a) <= math.pi for a in angles)


def test_world_status_names_the_services_fault_code(sim, reader):
    src = view.Sources(reader, sim.rt.wm, rack="simulated")
    FaultSet(sim.world).inject("bus-error:dac")  # the DAC stops answering: outputs not known safe
    sim.step(10)
    world = view.world_status(src.read(), "simulated").splitlines()
    assert world[1].endswith("fault DAC LOST") and len(world[1]) <= 76  # was "fault code 7"
