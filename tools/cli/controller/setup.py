"""A ``pfma controller`` run's settings before its frames and its lines after them: the
shoulder-roll index (issue 30 item 2; docs/controller.md "The shoulder-roll index") and
teleoperation, force control, time delay (the Cartesian engine, issue 6)."""

from __future__ import annotations

import math

from tools.cli.controller.common import refuse


def setup_roll(d, args) -> int:
    """Set the index (``--shoulder-roll``) and, with ``--power-up``, show it and check it was
    confirmed; 0, or 2 after one line saying why the power-up is refused."""
    from controller.params import SHOULDER_ROLL_STEPS_TEXT, shoulder_roll_text
    wm = d.rt.wm
    if args.shoulder_roll is not None:
        d.rt.set_shoulder_roll(args.shoulder_roll)
        d.frame()  # applied at this frame's communications segment (still powered down)
    deg = float(wm.get("joint.shoulder_roll_deg"))
    if d.sim is not None and args.shoulder_roll is None:
        return 0  # the simulated arm and the controller both at 0: nothing to confirm or say
    if not args.power_up:
        if args.shoulder_roll is not None:
            print(f"shoulder-roll index {shoulder_roll_text(deg)} (joint.shoulder_roll_deg; the next power-up "
                  f"takes it)", flush=True)
        return 0
    if d.sim is not None:
        why = "the simulated arm is pinned there too"
    elif args.shoulder_roll is not None:
        why = f"confirmed by --shoulder-roll {args.shoulder_roll}"
    else:
        rack = _rack_kind(d.client)
        if rack != "simulated":
            return refuse(f"the shoulder roll is indexed by hand and has no sensor: --power-up on "
                          f"{'an' if rack == 'unknown' else 'a'} {rack} rack needs --shoulder-roll DEG, the index the "
                          f"joint is pinned at ({SHOULDER_ROLL_STEPS_TEXT}); check the joint, then say it (the "
                          f"controller's is {shoulder_roll_text(deg)})")
        why = "not confirmed: the service's rack is simulated, its arm pinned where `pfma serve --shoulder-roll` put it"
    print(f"power-up with the shoulder-roll index {shoulder_roll_text(deg)} ({why})", flush=True)
    return 0


def _rack_kind(client) -> str:
    """"simulated", "real" or "unknown": what the service publishes of its rack (Bit3 header)."""
    try:
        return str(client.header().rack_kind)
    except Exception:  # noqa: BLE001 - what cannot be read is unknown (and needs the confirmation)
        return "unknown"


def roll_summary(d) -> str:
    from controller.params import shoulder_roll_text
    v = d.rt.wm.get_task_inputs(("joint.shoulder_roll_deg", "joint.shoulder_roll_rad"))
    used = math.degrees(float(v["joint.shoulder_roll_rad"]))
    line = f"shoulder-roll index {shoulder_roll_text(float(v['joint.shoulder_roll_deg']))} (joint.shoulder_roll_deg)"
    if d.rt.wm.powered_up:
        line += f"; the kinematics use {shoulder_roll_text(round(used))}"
    if d.sim is not None:
        line += f"; the simulated arm is pinned at {shoulder_roll_text(round(math.degrees(d.sim.shoulder_roll_rad)))}"
    return line


def motion_settings(args) -> dict:
    """World-model user variables the motion flags set (empty: none given)."""
    from controller.teleop import HC_SOURCES
    out: dict = {}
    if args.teleop is not None:
        out.update({"cart.mode": 1, "cart.hc_source": HC_SOURCES.index(args.teleop)})
    if args.teleop is not None or args.hc_frame != "world":
        out["cart.hc_frame"] = 1 if args.hc_frame == "tool" else 0
    if args.vernier:
        out["cart.vernier"] = True
    if args.impedance is not None:
        out["force.enable"] = args.impedance == "on"
    if args.delay is not None:
        out["delay.round_trip_s"] = args.delay
    if args.jitter is not None:
        out["delay.jitter"] = args.jitter
    return out


def setup_motion(d, args) -> None:
    """Apply the motion flags (user writes, applied at the next frames) and the sim demos."""
    if (args.demo_stick or args.demo_wall is not None) and d.sim is None:
        raise SystemExit(refuse("--demo-stick and --demo-wall need --sim", code=1))
    settings = motion_settings(args)
    if args.demo_stick and "cart.mode" not in settings:
        settings.update({"cart.mode": 1, "cart.hc_source": 0})
    wm = d.rt.wm
    for name, value in settings.items():
        wm.set_user(name, value, wm.access_key)
    if settings:
        d.frame()  # applied at this frame's communications segment
        print("motion settings: " + ", ".join(f"{k}={wm.spec(k).value_text(v) or v}" for k, v in settings.items()))
    if args.demo_wall is not None:
        from fakes.environment import Wall
        p, _ = d.sim.tool_pose()
        x = float(p[0]) + args.demo_wall
        d.sim.world.sim.environment.add(Wall(point_m=(x, 0.0, 0.0), normal=(-1.0, 0.0, 0.0)))
        print(f"virtual wall at x = {x:.3f} m (normal -x, 2e4 N/m)")
    if args.demo_stick:
        world, t0 = d.sim.world, [None]

        def stick(rec) -> None:
            from controller.decision import Status
            if d.rt.status("updown") != Status.START_UP_COMPLETE:
                return
            if t0[0] is None:
                t0[0] = rec.t_s
            t = rec.t_s - t0[0]
            if t < 1.0:  # CAE axis order: up/down, forward/backward, right/left, yaw, pitch, roll
                world.set_cae([0.0, 5.25, 0, 0, 0, 0], (True, False, False))
            elif t < 2.0:
                world.set_cae([5.25, 0.0, 0, 0, 0, 0], (True, False, False))
            else:
                world.set_cae([0.0] * 6, (False, False, False))
        d.rt.on_frame.append(stick)


def motion_summary(d) -> str:
    v = d.rt.wm.get_task_inputs(("cart.pos_cmd_m", "cart.cmd_valid", "force.state", "force.wrench_n",
                                 "teleop.reflect_enabled"))
    p = v["cart.pos_cmd_m"]
    w = v["force.wrench_n"]
    line = (f"Cartesian command ({p[0]:+.4f}, {p[1]:+.4f}, {p[2]:+.4f}) m valid={bool(v['cart.cmd_valid'])}  "
            f"force {d.rt.wm.spec('force.state').value_text(v['force.state'])} "
            f"F ({w[0]:+.2f}, {w[1]:+.2f}, {w[2]:+.2f}) N  "
            f"reflection {'on' if v['teleop.reflect_enabled'] else 'off'}")
    if d.sim is not None:
        t, _ = d.sim.tool_pose()
        line += f"\ntool (true) ({t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}) m"
    return line

