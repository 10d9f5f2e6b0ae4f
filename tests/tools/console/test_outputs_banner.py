"""The console's banner while the service reports its outputs NOT known safe (issue 28 item
5: ``bus-error:dac``, fault code FAULT_DAC_UNREACHABLE): docked above the five areas, with
what is known and what the operator must do; gone once the DAC answers again. Simulated
time; the console's timer is off (each refresh is the test's)."""

from __future__ import annotations

import uuid

from bit3.client import Client
from sim.faults import FaultSet
from sim.rig import SimRig
from tools.console import view
from tools.console.app import ConsoleApp
from tools.console.control import ControllerLink
from tests.tools.console._pilot import frames, run_app, screen_text


def test_the_banner_names_the_last_values_and_the_e_stop(sim):
    """A service driving the shoulder pitch at +6 V when its DAC stops answering (the
    simulator's world model stands in for the controller's: only the service's inputs matter)."""
    with SimRig(name="pfma-banner-" + uuid.uuid4().hex[:8]) as rig:
        ctl = rig.controller()
        rates = [0.0] * 6
        rig.on_frame.append(lambda info: ctl.write_commands(
            joint_rate_rad_s=rates, current_limit_a=(5, 5, 5, 2.5, 2.5, 2.5, 0), arm_request=1))
        rig.run(0.05)
        rates[list(rig.layout.joint_names).index("shoulder_pitch")] = 0.24
        rig.run(0.1)
        client = Client.attach(rig.name, layout=rig.layout)
        try:
            src = view.Sources(client, sim.rt.wm)
            assert view.outputs_banner(src.read()) == ""
            faults = FaultSet(rig.world)
            faults.inject("bus-error:dac")
            rig.run(0.02)
            r = src.read()
            text = view.outputs_banner(r)
            assert text.startswith("OUTPUTS NOT KNOWN SAFE: the DAC board is not answering; its outputs may "
                                   "hold their last values (+6.00 V shoulder_pitch_command, +5.00 V ")
            assert "PRESS THE HARDWARE E-STOP if the arm moves" in text
            assert "outputs NOT KNOWN SAFE  brakes" in view.world_status(r, src.rack)
            faults.clear("bus-error:dac")
            rig.run(0.01)
            r = src.read()
            assert view.outputs_banner(r) == ""
            assert "outputs safe (0 V)" in view.world_status(r, src.rack)  # FAULT, DAC written 0 V
        finally:
            client.close()


def test_the_console_shows_the_banner_at_the_top_while_the_dac_does_not_answer(sim, reader):
    app = ConsoleApp(view.Sources(reader, sim.rt.wm, rack="simulated"), ControllerLink(sim.rt.wm),
                     auto_refresh=False)
    faults = FaultSet(sim.world)

    async def body(pilot):
        frames(sim, app, 2)
        await pilot.pause()
        assert app.banner_text == ""
        assert "OUTPUTS NOT KNOWN SAFE" not in screen_text(app)
        faults.inject("bus-error:dac")
        frames(sim, app, 2)
        await pilot.pause()
        assert app.banner_text.startswith("OUTPUTS NOT KNOWN SAFE: the DAC board is not answering")
        rows = screen_text(app).splitlines()
        top = "\n".join(rows[:5])  # docked above the areas: the first rows of the terminal
        assert "OUTPUTS NOT KNOWN SAFE" in top and "PRESS THE HARDWARE E-STOP" in top
        assert app.area_text("world").count("NOT KNOWN SAFE") == 1
        faults.clear("bus-error:dac")
        frames(sim, app, 2)
        await pilot.pause()
        assert app.banner_text == ""
        assert "OUTPUTS NOT KNOWN SAFE" not in screen_text(app)
    run_app(app, body)
