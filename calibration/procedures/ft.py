"""Wrist F/T sensor: bias, tool payload (with sensor offset) and the full 6x6 matrix.

All three read the raw counts the service publishes (``ft_counts``, 80 Hz) and use
the F/T section of the calibration in force (or the sensor's nominal CPF/CPT) to turn
counts into a wrench: ``wrench = matrix @ (counts - bias_counts)``.

- **bias**: tool removed, nothing touching the sensor; the mean counts are the bias.
  Tolerances: noise <= 3 counts rms; |bias| <= 10 % of full scale (else the sensor or
  its zero is suspect).
- **payload**: the wrist is posed in several orientations (the operator jogs it; on the
  simulated rack the simulated operator places it); at each, gravity in sensor axes
  comes from the calibrated resolver angles through the 8.1 kinematics. Least squares:
  ``F = m g_s + f0`` and ``T = p x g_s + t0`` (p = m c), giving mass m, centre of mass
  c = p / m and the sensor offset (f0, t0), which is folded into the bias. Then a known
  weight is hung on the tool point and the compensated force must match it.
  Tolerances: mass +-0.02 kg, centre of mass +-2 mm, force residual rms <= 0.1 N,
  check weight within 2 % (or 0.02 kg).
- **matrix**: the tool is removed and known loads are applied with a calibration
  fixture (each axis both ways, a few combined loads and zero); least squares
  ``load = M counts + b`` for the 6x6 matrix M and the bias. Tolerances: every residual
  <= 0.5 % of full scale (0.67 N, 0.057 N*m; pfma-model 8.7 ranges); the fitted matrix
  well conditioned (cond < 1e3 relative to the nominal).
"""

from __future__ import annotations

import math

import numpy as np

from calibration import fit as F
from calibration.files import nominal_ft
from pfma.ft_calibration import FtCalibration, ft_calibration
from calibration.kinematics import GRAVITY_M_S2, gravity_in_sensor
from calibration.plot import Fit, Panel, Series, fit_grid, plot_fit, residual_panel
from calibration.procedures.base import Context, ProcedureResult, finish, plot_name
from calibration.procedures.motion import COUNTS_PER_REV

#: the F/T channels in the order the sensor reports them (ft_counts, the 6x6 matrix rows)
AXIS_NAMES = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")

RANGE_N, RANGE_NM = 133.0, 11.3  #: pfma-model 8.7 (Lord-type "30/100", assumed)
DEG = math.pi / 180


def current_ft(ctx: Context) -> FtCalibration:
    cal = ft_calibration(ctx.calibration)
    if cal is None:
        n = nominal_ft()
        cal = FtCalibration(np.array(n["bias_counts"]), np.array(n["matrix"]), 0.0, np.zeros(3))
    return cal


def _ft_section(ft: FtCalibration, **prov) -> dict:
    return {"bias_counts": ft.bias_counts.tolist(), "matrix": ft.matrix.tolist(),
            "payload_mass_kg": float(ft.payload_mass_kg), "payload_com_m": np.asarray(ft.payload_com_m).tolist(),
            "provenance": prov}


def _prev_prov(ctx: Context) -> dict:
    ft = ctx.calibration.ft
    return dict(ft.get("provenance", {})) if ft else {"matrix": ctx.provenance("nominal (sensor CPF/CPT)")}


def _mean_counts(ctx: Context, seconds: float = 0.25, extra: tuple[str, ...] = ()):
    smp = ctx.session.collect(seconds, ("ft_counts",) + extra, key="t_ft_s")
    return smp["ft_counts"].astype(float).mean(axis=0), smp


# ---------------------------------------------------------------- bias
def run_bias(ctx: Context) -> ProcedureResult:
    res = ProcedureResult("ft-bias", tolerances={"noise": "<= 3 counts rms", "bias": "<= 10 % FS"})
    ft = current_ft(ctx)
    ctx.progress(0, 2, "unload the sensor")
    ctx.operator.prompt("ft.unload", "Remove the tool from the wrist F/T sensor; nothing may touch it")
    ctx.session.wait(0.1)
    ctx.progress(1, 2, "averaging 0.5 s")
    mean, smp = _mean_counts(ctx, ctx.options.get("average_s", 0.5))
    counts = smp["ft_counts"].astype(float)
    ctx.operator.prompt("ft.mount", "Mount the tool again")
    ctx.progress(2, 2, "done")
    fits = [F.mean_offset(counts[:, i], what=f"F/T bias axis {i}") for i in range(6)]
    fs_counts = np.abs(np.linalg.solve(ft.matrix, np.array([RANGE_N] * 3 + [RANGE_NM] * 3)))
    for i, (name, f) in enumerate(zip(("Fx", "Fy", "Fz", "Tx", "Ty", "Tz"), fits)):
        res.fits[f"bias {name}"] = f
        res.check(f"{name} noise rms", f.rms, 3.0, "counts")
        res.check(f"{name} bias", f["mean"], 0.1 * fs_counts[i], "counts")
    ft.bias_counts = mean
    prov = _prev_prov(ctx)
    prov["bias"] = ctx.provenance("F/T bias, sensor unloaded", None, bias_counts=mean,
                                  residuals=[f.rms for f in fits], samples=len(counts))
    res.ft = _ft_section(ft, **prov)
    res.found["bias_counts"] = mean
    # one small panel per gauge: their biases differ by far more than their noise
    res.plots.append(plot_fit(plot_name(ctx, "ft-bias", "counts"), [
        Panel([Series(np.arange(len(counts)), counts[:, i], "line", "blue")],
              f"{AXIS_NAMES[i]} gauge\nmean {f['mean']:.1f}, {f.rms:.2f} rms (counts)", "sample", "counts")
        for i, f in enumerate(fits)], title="F/T bias: gauge counts, sensor unloaded", width=840,
        height_per_panel=200, columns=3))
    return finish(ctx, res)


# ---------------------------------------------------------------- payload
def default_poses() -> list[tuple[float, ...]]:
    """Wrist orientations spanning gravity in sensor axes (SY SP EP at the 8.1 ready pose)."""
    base = (0.0, 30 * DEG, -90 * DEG)
    wrist = [(60, 0, 0), (60, 0, 90), (60, 0, 180), (60, 0, -90), (0, 0, 45), (-60, 0, 0),
             (0, 60, 0), (0, -60, 135), (30, 30, -45)]
    return [base + tuple(w * DEG for w in ww) for ww in wrist]


def _angles(ctx: Context, rtd_counts: np.ndarray) -> np.ndarray:
    """Calibrated joint angles (DH order) from raw resolver counts (mean over samples)."""
    layout = ctx.session.layout
    q = []
    for j in ctx.rack.joints:
        c = rtd_counts[:, layout.joint_slot("rtd", j, "angle")].astype(float)
        raw = float(np.mean(np.unwrap(c * (2 * np.pi / COUNTS_PER_REV))))
        e = ctx.calibration.channel(ctx.rack.joint_channel(j, "angle").signal)
        q.append((e["scale"] * raw + e["offset"]))
    return np.array(q)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def run_payload(ctx: Context) -> ProcedureResult:
    poses = ctx.options.get("poses") or default_poses()
    roll = float(ctx.options.get("shoulder_roll_rad", 0.0))
    check_kg = float(ctx.options.get("check_mass_kg", 1.0))
    res = ProcedureResult("ft-payload", tolerances={"mass": "+-0.02 kg", "centre of mass": "+-2 mm",
                                                    "force residual": "<= 0.1 N rms",
                                                    "check weight": "within 2 % or 0.02 kg"})
    ft = current_ft(ctx)
    g_list, w_list = [], []
    n = len(poses) + 1
    for k, q in enumerate(poses):
        ctx.progress(k, n, f"pose {k + 1}/{len(poses)}")
        ctx.operator.prompt("ft.pose", "Jog the wrist to (deg) " + " ".join(f"{math.degrees(x):+.0f}" for x in q)
                            + " and let it settle", q_rad=list(q))
        ctx.session.wait(0.2)
        counts, smp = _mean_counts(ctx, 0.25, ("rtd_counts",))
        qm = _angles(ctx, smp["rtd_counts"])
        g_list.append(gravity_in_sensor(qm, roll))
        w_list.append(ft.wrench(counts))
    g = np.array(g_list)
    w = np.array(w_list)
    m_poses = len(poses)
    a_f = np.zeros((3 * m_poses, 4))
    a_t = np.zeros((3 * m_poses, 6))
    for i in range(m_poses):
        a_f[3 * i:3 * i + 3, 0] = g[i]
        a_f[3 * i:3 * i + 3, 1:] = np.eye(3)
        a_t[3 * i:3 * i + 3, :3] = -_skew(g[i])
        a_t[3 * i:3 * i + 3, 3:] = np.eye(3)
    ff = F.design(a_f, w[:, :3].ravel(), ("mass_kg", "f0x", "f0y", "f0z"), "payload force fit")
    ft_ = F.design(a_t, w[:, 3:].ravel(), ("px", "py", "pz", "t0x", "t0y", "t0z"), "payload torque fit")
    res.fits["force"], res.fits["torque"] = ff, ft_
    mass = ff["mass_kg"]
    com = np.array([ft_["px"], ft_["py"], ft_["pz"]]) / mass if mass > 1e-6 else np.zeros(3)
    offset = np.concatenate([ff.coef[1:], ft_.coef[3:]])
    res.found.update(mass_kg=mass, com_m=com, sensor_offset=offset)
    res.check("force residual rms", ff.rms, 0.1, "N")
    res.check("torque residual rms", ft_.rms, 0.01, "N*m")
    # fold the sensor offset into the bias: wrench = M (counts - b) - offset = M (counts - b - M^-1 offset)
    new = FtCalibration(ft.bias_counts + np.linalg.solve(ft.matrix, offset), ft.matrix, mass, com)
    # check with a known weight at the last pose
    ctx.progress(m_poses, n, f"check weight {check_kg:g} kg")
    ctx.operator.prompt("ft.known_weight", f"Hang the {check_kg:.3f} kg check weight on the tool point",
                        mass_kg=check_kg)
    ctx.session.wait(0.2)
    counts, smp = _mean_counts(ctx, 0.25, ("rtd_counts",))
    gs = gravity_in_sensor(_angles(ctx, smp["rtd_counts"]), roll)
    extra = new.wrench(counts) - new.gravity_wrench(gs)
    seen_kg = float(np.linalg.norm(extra[:3]) / GRAVITY_M_S2)
    ctx.operator.prompt("ft.remove_weight", "Remove the check weight", mass_kg=check_kg)
    ctx.progress(n, n, "done")
    res.found["check_seen_kg"] = seen_kg
    res.check("check weight error", seen_kg - check_kg, max(0.02, 0.02 * check_kg), "kg")
    prov = _prev_prov(ctx)
    prov["payload"] = ctx.provenance("F/T payload from wrist orientations (least squares)", None,
                                     mass_kg=mass, com_m=com, sensor_offset=offset,
                                     points={"gravity_sensor": g, "wrench": w},
                                     residuals=np.concatenate([ff.residuals, ft_.residuals]),
                                     check_mass_kg=check_kg, check_seen_kg=seen_kg)
    res.ft = _ft_section(new, **prov)
    gz = g[:, 2]
    res.plots.append(plot_fit(plot_name(ctx, "ft-payload", "fit"), [
        Panel([Series(gz, w[:, 2], "points", "blue", "measured Fz"),
               Series(gz, mass * gz + offset[2], "line", "red", f"fit: {mass:.3f} kg")],
              "sensor Fz vs gravity along the sensor z axis", "g_z (m/s^2)", "Fz (N)"),
        residual_panel([Series(np.arange(ff.residuals.size), ff.residuals, "points", "blue")], "force fit", "N",
                       "pose sample")], title="F/T payload"))
    return finish(ctx, res)


# ---------------------------------------------------------------- 6x6 matrix
def default_loads(force_n: float = 50.0, torque_nm: float = 5.0) -> list[np.ndarray]:
    """Zero, each axis both ways, and four combined loads (sensor axes)."""
    fs = np.array([force_n] * 3 + [torque_nm] * 3)
    loads = [np.zeros(6)]
    for i in range(6):
        for s in (1, -1):
            w = np.zeros(6)
            w[i] = s * fs[i]
            loads.append(w)
    for combo in ((1, 1, 0, 0, 1, 1), (0, -1, 1, 1, 0, -1), (1, 0, -1, -1, 1, 0), (-1, 1, 1, 0, -1, 1)):
        loads.append(0.5 * fs * np.array(combo))
    return loads


def run_matrix(ctx: Context) -> ProcedureResult:
    loads = [np.asarray(x, dtype=float) for x in (ctx.options.get("loads") or default_loads())]
    res = ProcedureResult("ft-matrix", tolerances={"residual": "<= 0.5 % FS per axis",
                                                   "condition": "< 1e3 x nominal"})
    ctx.operator.prompt("ft.unload", "Remove the tool; mount the sensor on the calibration fixture")
    counts = []
    for k, w in enumerate(loads):
        ctx.progress(k, len(loads), "load " + " ".join(f"{x:+.1f}" for x in w))
        ctx.operator.prompt("ft.apply_load", "Apply load Fx Fy Fz [N] Tx Ty Tz [N*m] = "
                            + " ".join(f"{x:+.2f}" for x in w), wrench=w.tolist())
        ctx.session.wait(0.1)
        c, _ = _mean_counts(ctx, 0.25)
        counts.append(c)
    ctx.operator.prompt("ft.release_load", "Remove the fixture load")
    ctx.operator.prompt("ft.mount", "Remount the sensor and the tool")
    ctx.progress(len(loads), len(loads), "fitting")
    c = np.array(counts)
    y = np.array(loads)
    a = np.column_stack([c, np.ones(len(c))])
    f = F.design(a, y, tuple(f"c{i}" for i in range(6)) + ("b",), "F/T 6x6 matrix")
    m = f.coef[:6].T
    b = f.coef[6]
    bias = -np.linalg.solve(m, b)
    res.fits["matrix"] = f
    fs = np.array([RANGE_N] * 3 + [RANGE_NM] * 3)
    for i, name in enumerate(("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")):
        res.check(f"{name} max residual", float(np.max(np.abs(f.residuals[:, i]))), 0.005 * fs[i],
                  "N" if i < 3 else "N*m")
    nominal = np.array(nominal_ft()["matrix"])
    cond = float(np.linalg.cond(m @ np.linalg.inv(nominal)))
    res.check("condition relative to nominal", cond, 1e3)
    old = current_ft(ctx)
    new = FtCalibration(bias, m, old.payload_mass_kg, old.payload_com_m)
    prov = _prev_prov(ctx)
    prov["matrix"] = ctx.provenance("F/T 6x6 matrix from known fixture loads", None,
                                    points={"counts": c, "loads": y}, residuals=f.residuals)
    prov["bias"] = prov["matrix"]
    res.ft = _ft_section(new, **prov)
    res.found.update(matrix=m, bias_counts=bias)
    # small multiples per axis, forces (N) then torques (N*m): each with its own units
    fitted = a @ f.coef
    per_axis = [Fit(AXIS_NAMES[i], y[:, i], fitted[:, i], y[:, i], f.residuals[:, i]) for i in range(6)]
    res.plots.append(plot_fit(plot_name(ctx, "ft-matrix", "residuals"), [
        *fit_grid(per_axis[:3], "applied load (N)", "fitted load (N)", "N", 3, "fitted", "applied (ideal)"),
        *fit_grid(per_axis[3:], "applied load (N*m)", "fitted load (N*m)", "N*m", 3, "fitted", "applied (ideal)")],
        "F/T 6x6 matrix: fitted vs applied fixture load per axis; residuals below", width=840,
        height_per_panel=200, columns=3))
    return finish(ctx, res)
