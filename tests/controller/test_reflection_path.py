"""CRL force reflection end to end: Cartesian engine (teleop) -> DAQ layer -> Bit3
command area -> service -> MVME400 port B -> the CRL master fake."""

import numpy as np

from sim.system import SystemSimulator


def test_reflected_force_reaches_the_crl_display():
    with SystemSimulator() as sim:
        sim.power_up()
        wm = sim.rt.wm
        # what the engine computes is covered by its own tests; here the path below it:
        # post a reflection as the engine's writer and follow it to the fake's motors
        writer = wm.spec("teleop.reflect_force_n").writer
        sim.world.crl.deadman = True
        for _ in range(64):
            wm.post_task_outputs(writer, {"teleop.reflect_force_n": np.array([8.0, 0.0, -4.0]),
                                          "teleop.reflect_torque_nm": np.zeros(3),
                                          "teleop.reflect_enabled": True})
            sim.step(1)
        cmd = sim.rig.reader.read_commands()
        assert cmd.crl_reflect_enable == 1 and list(cmd.crl_reflect_force_n) == [8.0, 0.0, -4.0]
        assert np.allclose(sim.world.crl.displayed_force_n, [8.0, 0.0, -4.0], atol=0.01)
