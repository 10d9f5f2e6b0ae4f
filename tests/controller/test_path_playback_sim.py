"""A path recorded while teleoperating the simulated arm, played back through the whole
stack (Multi-Segment Path Planner -> Trajectory Planner -> Cartesian Engine -> Joint
Planner -> servo -> simulated arm), in simulated time.

Measured (tolerances stated in docs/controller.md, "Trajectories and paths"):
* every recorded point lies within PATH_TOL_M of the tool path of the playback (the true
  tool point of the simulated arm, fk of its true joint angles, every minor frame), and
  its orientation within PATH_TOL_RAD of the tool orientation there;
* the traj.* samples (40 Hz) never exceed the path's speed and acceleration limits.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.kinematics import fk
from controller.paths import DEFAULT_LIMITS, MspMode, MspResult, PathStore, RecordSource
from controller.quat import q_angle
from tests.controller._cart_support import V_QUARTER, powered_sim, stick

#: tolerances this test measures against (see docs/controller.md "Trajectories and paths")
PLAN_TOL_M = 0.0015  #: recorded points vs the playback's Cartesian command (key points 1 mm + 40 Hz)
PATH_TOL_MEASURED_M = 0.010  #: measured-pose recording: recorded points vs the playback's tool path
PATH_TOL_REPEAT_M = 0.004  #: command recording: the recording's tool path vs the playback's
PATH_TOL_RAD = math.radians(1.0)


def _tool(sim):
    return fk(sim.joint_angles_rad())


def _steps(sim, n):
    out = []
    for _ in range(n):
        sim.step(1)
        out.append(_tool(sim)[0])
    return out


def _dist_to_polyline(x, P):
    a, b = P[:-1], P[1:]
    d = b - a
    L2 = np.einsum("ij,ij->i", d, d)
    u = np.clip(np.einsum("ij,ij->i", x - a, d) / np.where(L2 > 0, L2, 1), 0, 1)
    dist = np.linalg.norm(a + u[:, None] * d - x, axis=1)
    k = int(np.argmin(dist))
    return float(dist[k]), k


@pytest.mark.parametrize("source", [RecordSource.MEASURED, RecordSource.COMMAND])
def test_recorded_teleop_path_is_played_back_within_tolerance(tmp_path, source):
    sim = powered_sim(cart__mode=1, msp__record_source=source)
    try:
        wm, key = sim.rt.wm, sim.rt.wm.access_key
        msp = sim.rt.by_key["msp"]
        msp.store = PathStore(tmp_path)
        sim.step(20)
        # --- record while teleoperating: x, teach point, -y, teach point, z, release
        wm.set_user("msp.mode", MspMode.RECORD, key)
        sim.step(40)
        rec_tool = []  # the true tool point while recording (every minor frame)
        for axis, volts, secs in (("x", V_QUARTER, 1.5), ("y", -V_QUARTER, 1.5), ("z", V_QUARTER, 1.0)):
            stick(sim, axis, volts)
            rec_tool.extend(_steps(sim, int(secs * 320)))
            stick(sim, None, deadman=False)
            rec_tool.extend(_steps(sim, 160))  # come to rest (the servo's tracking lag), then teach
            wm.set_user("msp.teach", int(wm.get("msp.teach")) + 1, key)
            rec_tool.extend(_steps(sim, 40))
        wm.set_user("msp.mode", MspMode.IDLE, key)
        sim.step(40)
        msp.wait_saved()
        sim.step(20)
        assert int(wm.get("msp.result")) == MspResult.OK
        path = msp.store.by_id(1)
        assert sum(p.kind == "teach" for p in path.points) == 3
        assert path.length_m > 0.1
        # --- play it back from where the recording ended (the approach goes back to its start)
        wm.set_user("cart.mode", 2, key)
        wm.set_user("msp.path_id", 1, key)
        wm.set_user("msp.mode", MspMode.PLAY, key)
        n = int(wm.get("msp.finished"))
        tool_p, tool_q, traj, cmd = [], [], [], []
        last_seen = None
        for _ in range(int(40 * 320)):
            sim.step(1)
            p, q = _tool(sim)
            tool_p.append(p)
            tool_q.append(q)
            cmd.append(np.array(wm.get("cart.pos_cmd_m")))
            v = wm.get_task_inputs(("traj.pos_m", "traj.active", "traj.t_s"))
            if bool(v["traj.active"]) and float(v["traj.t_s"]) != last_seen:
                traj.append((float(v["traj.t_s"]), np.array(v["traj.pos_m"])))
                last_seen = float(v["traj.t_s"])
            if int(wm.get("msp.finished")) > n:
                break
        else:
            pytest.fail("playback did not finish in 40 s")
        assert int(wm.get("msp.result")) == MspResult.OK
        sim.step(320)  # settle
        for _ in range(32):
            sim.step(1)
            p, q = _tool(sim)
            tool_p.append(p)
            tool_q.append(q)
        P = np.array(tool_p)
        # start the comparison after the approach segment: from the sample nearest point 0
        k0 = int(np.argmin(np.linalg.norm(P - np.array(path.points[0].pos_m), axis=1)))
        P = P[k0:]
        Qs = tool_q[k0:]
        worst_d = worst_a = 0.0
        for pt in path.points:
            d, k = _dist_to_polyline(np.array(pt.pos_m), P)
            worst_d = max(worst_d, d)
            worst_a = max(worst_a, q_angle(pt.quat, Qs[k]))
        C = np.array(cmd)[k0:]
        worst_c = max(_dist_to_polyline(np.array(pt.pos_m), C)[0] for pt in path.points)
        R = np.array(rec_tool)
        worst_r = max(_dist_to_polyline(x, P)[0] for x in R[::8])
        print(f"\n{RecordSource.NAMES[source]}: recorded points vs playback tool path: max {worst_d * 1e3:.2f} mm, "
              f"{math.degrees(worst_a):.3f} deg over {len(path.points)} points; vs the playback command "
              f"{worst_c * 1e3:.2f} mm; recording's tool path vs playback's {worst_r * 1e3:.2f} mm")
        # the plan and the Cartesian command pass through every recorded point (key points 1 mm)
        assert worst_c <= PLAN_TOL_M
        assert worst_a <= PATH_TOL_RAD
        if source == RecordSource.MEASURED:  # the servo's static error under gravity, once more
            assert worst_d <= PATH_TOL_MEASURED_M
        else:  # the arm retraces the recorded motion (same command, same static error)
            assert worst_r <= PATH_TOL_REPEAT_M
        # --- limits, measured from the traj.* samples (40 Hz, evenly spaced while active)
        t = np.array([s[0] for s in traj])
        x = np.array([s[1] for s in traj])
        dt = np.diff(t)
        assert np.allclose(dt[dt < 0.03], 0.025, atol=1e-4)  # (the simulated bus charges time per access)
        vel = np.diff(x, axis=0) / dt[:, None]
        v = np.linalg.norm(vel, axis=1)
        steady = (dt[1:] < 0.03) & (dt[:-1] < 0.03)
        acc = (np.linalg.norm(np.diff(vel, axis=0), axis=1) / (0.5 * (dt[1:] + dt[:-1])))[steady]
        print(f"traj samples: max speed {v.max():.4f} m/s, max acceleration {acc.max():.4f} m/s^2")
        assert v.max() <= DEFAULT_LIMITS.v_lin_m_s * (1 + 1e-9)
        assert acc.max() <= DEFAULT_LIMITS.a_lin_m_s2 * (1 + 1e-6)
    finally:
        sim.close()
