"""Cartesian engine on the system simulator (simulated time): hand-controller rate mode
moves the tool along the matching world axis at the commanded rate, the deadman stops it,
hold and mode changes do not jump, the command is composed with quaternions."""

from __future__ import annotations

import numpy as np
import pytest

from controller.quat import q_angle
from tests.controller._cart_support import V_QUARTER, powered_sim, record, stick, tool_pos

FRAME_S = 1.0 / 320.0
RATE_M_S = 0.25 * 0.15  # u = 0.25 at V_QUARTER, default gain 0.15 m/s (pfma-model 8.5, 8.2)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_stick_axis_moves_tool_along_world_axis_at_commanded_rate(axis):
    """Tolerance: mean speed over the second second within 3 % of 0.0375 m/s; off-axis speed
    below 10 % of it (the arm sags a little as it extends: P-only servo under gravity)."""
    i = "xyz".index(axis)
    with powered_sim(cart__mode=1) as sim:
        sim.step(20)
        p0 = tool_pos(sim)
        stick(sim, axis)
        path = record(sim, 640)  # 2 s
        v = (path[639] - path[319]) / (320 * FRAME_S)  # steady part: 1 s .. 2 s
        assert v[i] == pytest.approx(RATE_M_S, rel=0.03)
        off = np.delete(v, i)
        assert np.abs(off).max() < 0.1 * RATE_M_S
        assert path[-1][i] - p0[i] > 0.06  # really moved ~7 cm
        # deadman released: zero rate, hold (the servo finishes its tracking lag ~ v/Kp = 5 mm)
        stick(sim, axis, deadman=False)
        after = record(sim, 480)
        assert abs(after[-1][i] - path[-1][i]) < 0.008
        v_end = np.linalg.norm(after[-1] - after[-33]) / (32 * FRAME_S)
        assert v_end < 1e-3  # stopped: < 1 mm/s after 1.5 s
        assert sim.rt.wm.get("cart.hc_active") == False  # noqa: E712


def test_no_motion_without_deadman_or_in_hold_mode():
    with powered_sim() as sim:  # cart.mode 0: hold
        sim.step(320)  # the arm settles after the brakes release (~1.5 mm sag)
        p0 = tool_pos(sim)
        stick(sim, "x")  # deadman held but hold mode
        sim.step(320)
        assert np.linalg.norm(tool_pos(sim) - p0) < 1e-3
        sim.rt.wm.set_user("cart.mode", 1, sim.rt.wm.access_key)
        stick(sim, "x", deadman=False)  # teleop mode, deadman released
        sim.step(320)
        assert np.linalg.norm(tool_pos(sim) - p0) < 1e-3
        assert any("mode HOLD -> TELEOP" in m.text for m in sim.rt.messages.recent())


def test_tool_frame_rates_and_orientation_held():
    """In the tool frame, stick x moves along the tool's x axis (world +y at this pose:
    pfma-model 8.1 x6 = +y0); the orientation command stays put (quaternions)."""
    with powered_sim(cart__mode=1, cart__hc_frame=1) as sim:
        sim.step(20)
        wm = sim.rt.wm
        q0 = np.array(wm.get("cart.quat_cmd"))
        p0 = tool_pos(sim)
        stick(sim, "x")
        sim.step(320)
        stick(sim, None, deadman=False)
        sim.step(160)
        d = tool_pos(sim) - p0
        assert d[1] > 0.025 and abs(d[0]) < 0.005 and abs(d[2]) < 0.005
        assert q_angle(wm.get("cart.quat_cmd"), q0) < 1e-6


def test_rotation_rate_and_vernier_limit():
    """Yaw at u = 0.25 rotates the command at 0.25 x 0.25 rad/s; vernier scales by 0.2."""
    with powered_sim(cart__mode=1) as sim:
        sim.step(20)
        wm = sim.rt.wm
        q0 = np.array(wm.get("cart.quat_cmd"))
        sim.world.set_cae([0, 0, 0, V_QUARTER, 0, 0], (True, False, False))  # yaw
        sim.step(320)
        a1 = q_angle(wm.get("cart.quat_cmd"), q0)
        assert a1 == pytest.approx(0.0625, rel=0.05)
        wm.set_user("cart.vernier", True, wm.access_key)
        sim.step(16)  # the slow task (40 Hz) has taken it
        q1 = np.array(wm.get("cart.quat_cmd"))
        sim.step(320)
        assert q_angle(wm.get("cart.quat_cmd"), q1) == pytest.approx(0.0625 * 0.2, rel=0.05)


def test_back_to_hold_does_not_jump():
    with powered_sim(cart__mode=1) as sim:
        wm = sim.rt.wm
        stick(sim, "z")
        sim.step(320)
        cmds = []
        wm.set_user("cart.mode", 0, wm.access_key)  # hold while still moving: held = measured pose
        for _ in range(160):
            sim.step(1)
            cmds.append(np.array(wm.get("cart.pos_cmd_m")))
        steps = np.linalg.norm(np.diff(np.array(cmds), axis=0), axis=1)
        assert steps.max() <= 0.15 / 80 + 1e-9  # never faster than the coarse limit per 80 Hz run
        assert wm.get("cart.cmd_valid")
