"""Forward and inverse kinematics of the PFMA for the controller (Joint Planner and above).

Model: pfma-model.md 8.1 (the project's nominal PFMA model, ALL VALUES ASSUMED there),
copied here once. Standard (distal) DH, ``T_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``,
``theta_i = q_i + offset_i``:

====  ==============  ========  =======  ==========  =======
 i    joint           offset    d (m)    a (m)       alpha
====  ==============  ========  =======  ==========  =======
 1    shoulder yaw    0         0        0           +90 deg
 2    shoulder pitch  0         0        0.90        0
 3    elbow pitch     0         0        0.90        0
 4    wrist pitch     0         0        0           -90 deg
 5    wrist yaw       +90 deg   0        0           +90 deg
 6    wrist roll      0         0.30     0           0
====  ==============  ========  =======  ==========  =======

Base frame 0 is at the shoulder (z up along the shoulder-yaw axis, x forward along the
arm at q = 0, y left). The manually indexed shoulder roll is configuration, not a joint:
``T_world_base = Rx(shoulder_roll)`` (8.1, with T_mount = identity). Poses are "tool in
world": tool point (origin of frame 6, 0.30 m beyond the wrist centre along the approach
z6) and a (w, x, y, z) quaternion (:mod:`controller.quat`).

**Joint order.** Every public function here takes and returns joint vectors in the
controller's command-area order, ``controller.params.JOINT_NAMES`` (shoulder pitch,
shoulder yaw, elbow pitch, wrist yaw, wrist pitch, wrist roll), NOT the DH order;
:data:`DH_FROM_CA` does the permutation internally. Jacobian columns follow it too.

**Closed-form inverse** (8.1): the wrist centre ``p - 0.30 z6`` fixes shoulder yaw
(atan2, or that + 180 deg "reaching back over the top"), the elbow (law of cosines:
elbow angle of either sign) and shoulder pitch (planar two-link); the wrist
``R_36 = Rz(q_wp) Ry(q_wy + 90 deg) Rz(q_wr)`` is a ZYZ Euler set with two branches
("wrist flip": wrist pitch + 180 deg, wrist yaw mirrored about -90 deg, roll + 180 deg).
**Branch choice**: of the up to 8 solutions, the ones inside the joint limits are kept
and the one nearest ``q_ref`` (Euclidean in rad) is returned, so a caller passing the
current joint angles stays on its current elbow/shoulder/wrist branch. In the degenerate
cases the free angle is taken from ``q_ref``: wrist yaw at +-90 deg (only wrist pitch +
wrist roll is defined: wrist pitch keeps its ``q_ref`` value) and the wrist centre on
the shoulder-yaw axis (shoulder yaw keeps its ``q_ref`` value).

**Singularities** (8.1): wrist yaw at +-90 deg (roll axis parallel to the pitch axes),
full stretch (elbow 0) and the wrist centre on the shoulder-yaw axis. :func:`ik` is exact
but can be far from ``q_ref`` next to them; the Joint Planner therefore moves with
:func:`ik_step` (damped least squares, joint rates bounded every step), which passes
through or next to a singular set without a jump.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from controller.params import JOINT_NAMES, JOINTS
from controller.quat import q_from_matrix, q_to_matrix, q_to_rotvec
from pfma.errors import PfmaError

SOURCE = "pfma-model.md 8.1 (DH table, frames, singular sets) and 8.2 (limits) - nominal, assumed"
DEG = math.pi / 180.0


class KinematicsError(PfmaError, ValueError):
    """A pose the arm cannot take: out of reach, or only outside the joint limits."""


@dataclass(frozen=True)
class DhRow:
    """One standard-DH row (pfma-model.md 8.1)."""

    joint: str  #: command-area joint name
    offset_rad: float
    d_m: float
    a_m: float
    alpha_rad: float


#: pfma-model.md 8.1 DH table, in DH (kinematic chain) order
DH: tuple[DhRow, ...] = (
    DhRow("shoulder_yaw", 0.0, 0.0, 0.0, 90 * DEG),
    DhRow("shoulder_pitch", 0.0, 0.0, 0.90, 0.0),
    DhRow("elbow_pitch", 0.0, 0.0, 0.90, 0.0),
    DhRow("wrist_pitch", 0.0, 0.0, 0.0, -90 * DEG),
    DhRow("wrist_yaw", 90 * DEG, 0.0, 0.0, 90 * DEG),
    DhRow("wrist_roll", 0.0, 0.30, 0.0, 0.0),
)
A2_M = DH[1].a_m  #: upper arm
A3_M = DH[2].a_m  #: forearm
D6_M = DH[5].d_m  #: wrist centre to tool point
REACH_M = A2_M + A3_M + D6_M  #: 2.10 m at q = 0 (8.1)

#: q_dh = q_ca[DH_FROM_CA]; q_ca = q_dh[CA_FROM_DH]
DH_FROM_CA = np.array([JOINT_NAMES.index(r.joint) for r in DH])
CA_FROM_DH = np.array([[r.joint for r in DH].index(n) for n in JOINT_NAMES])
#: command-area indices of the joints (for readable code)
J = {n: i for i, n in enumerate(JOINT_NAMES)}

#: soft limits and software rate limits (pfma-model.md 8.2 via controller.params), command-area order
SOFT_LO_RAD = np.array([j.soft_lo_rad for j in JOINTS])
SOFT_HI_RAD = np.array([j.soft_hi_rad for j in JOINTS])
RATE_LIMIT_RAD_S = np.array([j.omega_lim_rad_s for j in JOINTS])

#: distance to a singular set below which :func:`singular_sets` reports it (assumed, this
#: project): 5 deg of wrist yaw from +-90 deg or of elbow from 0, and 0.05 m of wrist-centre
#: distance from the shoulder-yaw axis.
SINGULAR_MARGIN_RAD = 5 * DEG
SINGULAR_MARGIN_M = 0.05

_OFFSET = np.array([r.offset_rad for r in DH])
_D = np.array([r.d_m for r in DH])
_A = np.array([r.a_m for r in DH])
_CA = np.array([math.cos(r.alpha_rad) for r in DH])
_SA = np.array([math.sin(r.alpha_rad) for r in DH])
_CAF = tuple(float(v) for v in _CA)
_SAF = tuple(float(v) for v in _SA)
_AF = tuple(float(v) for v in _A)
_DF = tuple(float(v) for v in _D)
_LIMIT_TOL = 1e-9


def _q(q6: Sequence[float]) -> np.ndarray:
    a = np.asarray(q6, dtype=float).reshape(-1)
    if a.shape[0] < 6:
        raise KinematicsError(f"need 6 joint angles ({', '.join(JOINT_NAMES)}), got {a.shape[0]}")
    return a[:6]


def _rx(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0, 0.0], [0.0, c, -s, 0.0], [0.0, s, c, 0.0], [0.0, 0.0, 0.0, 1.0]])


def base_transform(shoulder_roll_rad: float = 0.0) -> np.ndarray:
    """``T_world_base = Rx(shoulder_roll)`` (8.1; T_mount = identity)."""
    return _rx(shoulder_roll_rad)


def _dh_matrix(i: int, theta: float) -> np.ndarray:
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = _CAF[i], _SAF[i]
    return np.array([
        [ct, -st * ca, st * sa, _AF[i] * ct],
        [st, ct * ca, -ct * sa, _AF[i] * st],
        [0.0, sa, ca, _DF[i]],
        [0.0, 0.0, 0.0, 1.0],
    ])


def fk_frames(q6: Sequence[float], shoulder_roll_rad: float = 0.0) -> list[np.ndarray]:
    """World transforms (4x4) of DH frames 0..6; frame 6 is the tool frame at the tool point.

    :param q6: joint angles, rad, command-area order (extra entries are ignored)
    """
    th = _q(q6)[DH_FROM_CA] + _OFFSET
    out = [base_transform(shoulder_roll_rad)]
    for i in range(6):
        out.append(out[-1] @ _dh_matrix(i, float(th[i])))
    return out


def fk_matrix(q6: Sequence[float], shoulder_roll_rad: float = 0.0) -> np.ndarray:
    """World transform (4x4) of the tool frame."""
    return fk_frames(q6, shoulder_roll_rad)[-1]


def fk(q6: Sequence[float], shoulder_roll_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Tool pose in the world frame: (tool point, m, shape 3; quaternion (w, x, y, z))."""
    t = fk_matrix(q6, shoulder_roll_rad)
    return t[:3, 3].copy(), q_from_matrix(t)


def wrist_centre(q6: Sequence[float], shoulder_roll_rad: float = 0.0) -> np.ndarray:
    """World position of the wrist centre (origin of frames 3, 4, 5), m."""
    return fk_frames(q6, shoulder_roll_rad)[3][:3, 3].copy()


def jacobian(q6: Sequence[float], shoulder_roll_rad: float = 0.0) -> np.ndarray:
    """Geometric Jacobian, 6x6: rows (linear velocity of the tool point, m/s; angular
    velocity, rad/s) in the world frame; columns per joint in command-area order."""
    return _jacobian_from_frames(fk_frames(q6, shoulder_roll_rad))


def _jacobian_from_frames(f: list[np.ndarray]) -> np.ndarray:
    st = np.stack(f[:6])
    z, o = st[:, :3, 2], st[:, :3, 3]
    jd = np.empty((6, 6))
    jd[:3, :] = np.cross(z, f[6][:3, 3] - o).T
    jd[3:, :] = z.T
    return jd[:, CA_FROM_DH]


def within_limits(q6: Sequence[float], lo_rad: np.ndarray | None = None, hi_rad: np.ndarray | None = None,
                  tol_rad: float = _LIMIT_TOL) -> bool:
    """True when every joint is inside the (default: soft) limits, with ``tol_rad`` slack."""
    q = _q(q6)
    lo = SOFT_LO_RAD if lo_rad is None else lo_rad
    hi = SOFT_HI_RAD if hi_rad is None else hi_rad
    return bool(np.all(q >= lo - tol_rad) and np.all(q <= hi + tol_rad))


def limit_violations(q6: Sequence[float], lo_rad: np.ndarray | None = None,
                     hi_rad: np.ndarray | None = None) -> list[str]:
    """Human-readable list of the joints outside the limits (empty when inside)."""
    q = _q(q6)
    lo = SOFT_LO_RAD if lo_rad is None else lo_rad
    hi = SOFT_HI_RAD if hi_rad is None else hi_rad
    out = []
    for i, n in enumerate(JOINT_NAMES):
        if q[i] < lo[i] - _LIMIT_TOL or q[i] > hi[i] + _LIMIT_TOL:
            out.append(f"{n} {q[i] / DEG:+.1f} deg outside {lo[i] / DEG:+.0f}..{hi[i] / DEG:+.0f}")
    return out


def singular_sets(q6: Sequence[float], margin_rad: float = SINGULAR_MARGIN_RAD,
                  margin_m: float = SINGULAR_MARGIN_M) -> tuple[str, ...]:
    """Which singular sets (8.1) ``q6`` is within the margin of: any of ``"wrist"`` (wrist
    yaw near +-90 deg), ``"stretch"`` (elbow near 0 or +-180 deg), ``"axis"`` (wrist centre
    near the shoulder-yaw axis)."""
    q = _q(q6)
    out = []
    if abs(math.cos(q[J["wrist_yaw"]])) < math.sin(margin_rad):
        out.append("wrist")
    if abs(math.sin(q[J["elbow_pitch"]])) < math.sin(margin_rad):
        out.append("stretch")
    q2, q3 = q[J["shoulder_pitch"]], q[J["elbow_pitch"]]
    if abs(A2_M * math.cos(q2) + A3_M * math.cos(q2 + q3)) < margin_m:
        out.append("axis")
    return tuple(out)


# --- closed-form inverse ------------------------------------------------------------------

def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


_RX90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _nearest_turn(a: float, ref: float, lo: float, hi: float) -> float:
    """``a + 2 pi k`` nearest ``ref`` among those inside [lo, hi] (else ``a`` wrapped)."""
    best = _wrap(a)
    best_d = math.inf
    for k in (-1, 0, 1):
        c = _wrap(a) + 2.0 * math.pi * k
        if lo - _LIMIT_TOL <= c <= hi + _LIMIT_TOL and abs(c - ref) < best_d:
            best, best_d = c, abs(c - ref)
    return best


def ik_all(p_m: Sequence[float], quat: Sequence[float], q_ref: Sequence[float] | None = None,
           shoulder_roll_rad: float = 0.0, lo_rad: np.ndarray | None = None,
           hi_rad: np.ndarray | None = None, singular_eps: float = 1e-9) -> list[np.ndarray]:
    """Every closed-form solution inside the limits, nearest ``q_ref`` first (may be empty).

    Raises :class:`KinematicsError` when the wrist centre is out of reach (no solution at
    all, limits or not). ``q_ref`` (default zeros) also fixes the free angle in the
    degenerate cases (module docstring).
    """
    return _ik_solutions(p_m, quat, q_ref, shoulder_roll_rad, lo_rad, hi_rad, singular_eps)[0]


def _ik_solutions(p_m, quat, q_ref, shoulder_roll_rad, lo_rad, hi_rad,
                  singular_eps: float = 1e-9) -> tuple[list[np.ndarray], str]:
    ref = np.zeros(6) if q_ref is None else _q(q_ref).astype(float)
    lo = SOFT_LO_RAD if lo_rad is None else lo_rad
    hi = SOFT_HI_RAD if hi_rad is None else hi_rad
    p = np.asarray(p_m, dtype=float).reshape(3)
    r_world = q_to_matrix(quat)
    base_r = base_transform(shoulder_roll_rad)[:3, :3]
    rb = base_r.T @ r_world
    pb = base_r.T @ p
    wc = pb - D6_M * rb[:, 2]
    dist = math.hypot(math.hypot(wc[0], wc[1]), wc[2])
    if dist > A2_M + A3_M + 1e-9:
        raise KinematicsError(f"pose out of reach: tool point ({p[0]:+.3f}, {p[1]:+.3f}, {p[2]:+.3f}) m puts "
                              f"the wrist centre {dist:.3f} m from the shoulder, reach {A2_M + A3_M:.2f} m")
    if dist < abs(A2_M - A3_M) - 1e-9:
        raise KinematicsError(f"pose out of reach: wrist centre {dist:.3f} m from the shoulder, "
                              f"minimum {abs(A2_M - A3_M):.2f} m")
    rxy = math.hypot(wc[0], wc[1])
    if rxy < singular_eps:
        q1s = [float(ref[J["shoulder_yaw"]])]
    else:
        a = math.atan2(wc[1], wc[0])
        q1s = [a, _wrap(a + math.pi)]
    cos3 = (dist * dist - A2_M * A2_M - A3_M * A3_M) / (2.0 * A2_M * A3_M)
    cos3 = min(1.0, max(-1.0, cos3))
    e = math.acos(cos3)
    q3s = [e, -e] if e > 1e-12 else [0.0]
    sols: list[np.ndarray] = []
    for q1 in q1s:
        c1, s1 = math.cos(q1), math.sin(q1)
        r = wc[0] * c1 + wc[1] * s1
        h = wc[2]
        for q3 in q3s:
            q2 = math.atan2(h, r) - math.atan2(A3_M * math.sin(q3), A2_M + A3_M * math.cos(q3))
            q2 = _wrap(q2)
            r03 = _rot_z(q1) @ _RX90 @ _rot_z(q2 + q3)
            w = r03.T @ rb  # = Rz(t4) Ry(t5) Rz(t6), t5 = q_wy + 90 deg
            sb = math.hypot(w[0, 2], w[1, 2])
            wrists: list[tuple[float, float, float]] = []
            if sb < singular_eps:
                t4 = float(ref[J["wrist_pitch"]])
                if w[2, 2] > 0:  # t5 = 0: only t4 + t6 defined
                    s = math.atan2(w[1, 0], w[0, 0])
                    wrists.append((t4, 0.0, s - t4))
                else:  # t5 = pi: only t4 - t6 defined
                    d = math.atan2(-w[1, 0], -w[0, 0])
                    wrists.append((t4, math.pi, t4 - d))
            else:
                t4 = math.atan2(w[1, 2], w[0, 2])
                t5 = math.atan2(sb, w[2, 2])
                t6 = math.atan2(w[2, 1], -w[2, 0])
                wrists.append((t4, t5, t6))
                wrists.append((t4 + math.pi, -t5, t6 + math.pi))
            for t4, t5, t6 in wrists:
                q_dh = [q1, q2, q3, t4, t5 - DH[4].offset_rad, t6]
                q = np.empty(6)
                for k, v in enumerate(q_dh):
                    i = DH_FROM_CA[k]
                    q[i] = _nearest_turn(v, float(ref[i]), float(lo[i]), float(hi[i]))
                sols.append(q)
    ok = [s for s in sols if within_limits(s, lo, hi)]
    ok.sort(key=lambda s: float(np.sum((s - ref) ** 2)))
    why = ""
    if not ok and sols:
        near = min(sols, key=lambda s: float(np.sum((s - ref) ** 2)))
        why = "; ".join(limit_violations(near, lo, hi))
    return ok, why


def ik(p_m: Sequence[float], quat: Sequence[float], q_ref: Sequence[float] | None = None,
       shoulder_roll_rad: float = 0.0, lo_rad: np.ndarray | None = None,
       hi_rad: np.ndarray | None = None) -> np.ndarray:
    """Closed-form inverse: the joint angles (command-area order) of the tool pose, on the
    branch nearest ``q_ref`` inside the (default soft) limits.

    :raises KinematicsError: out of reach, or reachable only outside the limits
    """
    sols, why = _ik_solutions(p_m, quat, q_ref, shoulder_roll_rad, lo_rad, hi_rad)
    if not sols:
        p = np.asarray(p_m, dtype=float).reshape(3)
        raise KinematicsError(f"pose at ({p[0]:+.3f}, {p[1]:+.3f}, {p[2]:+.3f}) m is reachable only outside "
                              f"the joint limits (nearest branch: {why})")
    return sols[0]


# --- the closed form on many poses at once (the path checks, controller.paths.check) --------

#: the closed-form branches :func:`ik_batch` takes: (shoulder yaw reaching back over the top,
#: elbow angle negative, wrist flipped); 8 in all
BRANCHES: tuple[tuple[bool, bool, bool], ...] = tuple((b, e, w) for b in (False, True) for e in (False, True)
                                                      for w in (False, True))


def ik_batch(p_m: np.ndarray, r_world: np.ndarray, branch,
             shoulder_roll_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The closed-form inverse of ``N`` poses on one branch, vectorised (the same equations
    as :func:`ik`; no joint limits, no choice of branch, no 2 pi turns: angles wrapped to
    -pi..pi). For checking sampled paths (:mod:`controller.paths.check`), where calling
    :func:`ik` per sample would cost ~0.25 ms each.

    :param p_m: tool points, shape (N, 3), world frame
    :param r_world: tool orientations as rotation matrices, shape (N, 3, 3)
    :param branch: one of :data:`BRANCHES`, or three bool arrays of shape (N,) (a branch per pose)
    :returns: (joint angles (N, 6) in command-area order, reachable (N,) bool: the wrist
        centre within the arm's reach; the angles of an unreachable pose are the nearest
        the closed form gives)
    """
    back, elbow_neg, flip = (np.asarray(b, dtype=bool) for b in branch)
    base_r = base_transform(shoulder_roll_rad)[:3, :3]
    rb = np.einsum("ji,njk->nik", base_r, r_world)  # base_r.T @ r_world
    pb = p_m @ base_r  # (base_r.T @ p) per row
    wc = pb - D6_M * rb[:, :, 2]
    dist = np.linalg.norm(wc, axis=1)
    reach = (dist <= A2_M + A3_M + 1e-9) & (dist >= abs(A2_M - A3_M) - 1e-9)
    q1 = np.arctan2(wc[:, 1], wc[:, 0]) + np.where(back, math.pi, 0.0)
    cos3 = np.clip((dist * dist - A2_M * A2_M - A3_M * A3_M) / (2.0 * A2_M * A3_M), -1.0, 1.0)
    q3 = np.arccos(cos3) * np.where(elbow_neg, -1.0, 1.0)
    c1, s1 = np.cos(q1), np.sin(q1)
    q2 = np.arctan2(wc[:, 2], wc[:, 0] * c1 + wc[:, 1] * s1) - np.arctan2(A3_M * np.sin(q3),
                                                                          A2_M + A3_M * np.cos(q3))
    c23, s23 = np.cos(q2 + q3), np.sin(q2 + q3)
    # r03 = Rz(q1) Rx(90 deg) Rz(q2 + q3), row by row
    r03 = np.empty((len(q1), 3, 3))
    r03[:, 0, 0], r03[:, 0, 1], r03[:, 0, 2] = c1 * c23, -c1 * s23, s1
    r03[:, 1, 0], r03[:, 1, 1], r03[:, 1, 2] = s1 * c23, -s1 * s23, -c1
    r03[:, 2, 0], r03[:, 2, 1], r03[:, 2, 2] = s23, c23, 0.0
    w = np.einsum("nji,njk->nik", r03, rb)  # r03.T @ rb = Rz(t4) Ry(t5) Rz(t6)
    sb = np.hypot(w[:, 0, 2], w[:, 1, 2])
    t4 = np.arctan2(w[:, 1, 2], w[:, 0, 2])
    t5 = np.arctan2(sb, w[:, 2, 2])
    t6 = np.arctan2(w[:, 2, 1], -w[:, 2, 0])
    t4, t5, t6 = np.where(flip, t4 + math.pi, t4), np.where(flip, -t5, t5), np.where(flip, t6 + math.pi, t6)
    q_dh = np.stack([q1, q2, q3, t4, t5 - DH[4].offset_rad, t6], axis=1)
    q_dh = (q_dh + math.pi) % (2.0 * math.pi) - math.pi
    return q_dh[:, CA_FROM_DH], reach


def fk_batch(q: np.ndarray, shoulder_roll_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fk` of ``N`` configurations at once: (tool points (N, 3), tool rotation
    matrices (N, 3, 3)), world frame; ``q`` shape (N, 6), command-area order."""
    th = np.atleast_2d(np.asarray(q, dtype=float))[:, DH_FROM_CA] + _OFFSET
    n = th.shape[0]
    t = np.broadcast_to(base_transform(shoulder_roll_rad), (n, 4, 4)).copy()
    for i in range(6):
        ct, st = np.cos(th[:, i]), np.sin(th[:, i])
        m = np.zeros((n, 4, 4))
        m[:, 0, 0], m[:, 0, 1], m[:, 0, 2], m[:, 0, 3] = ct, -st * _CAF[i], st * _SAF[i], _AF[i] * ct
        m[:, 1, 0], m[:, 1, 1], m[:, 1, 2], m[:, 1, 3] = st, ct * _CAF[i], -ct * _SAF[i], _AF[i] * st
        m[:, 2, 1], m[:, 2, 2], m[:, 2, 3] = _SAF[i], _CAF[i], _DF[i]
        m[:, 3, 3] = 1.0
        t = t @ m
    return t[:, :3, 3].copy(), t[:, :3, :3].copy()


def singular_distances(q: np.ndarray) -> np.ndarray:
    """How far configurations are from each singular set (8.1), shape (N, 3): columns
    wrist (rad: wrist yaw from +-90 deg), stretch (rad: elbow from 0 or 180 deg), axis (m:
    wrist centre from the shoulder-yaw axis). :func:`singular_sets` reports a set when its
    distance is below the margin."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    wy, el, sp = q[:, J["wrist_yaw"]], q[:, J["elbow_pitch"]], q[:, J["shoulder_pitch"]]
    return np.stack([np.arcsin(np.minimum(1.0, np.abs(np.cos(wy)))),
                     np.arcsin(np.minimum(1.0, np.abs(np.sin(el)))),
                     np.abs(A2_M * np.cos(sp) + A3_M * np.cos(sp + el))], axis=1)


# --- rate-limited damped-least-squares step --------------------------------------------------

#: Damped least squares (assumed, this project; Nakamura & Hanafusa's variable damping):
#: no damping while the smallest singular value of the Jacobian is above DLS_SIGMA_MIN,
#: rising smoothly to DLS_LAMBDA_MAX at a singular configuration.
DLS_SIGMA_MIN = 0.08
DLS_LAMBDA_MAX = 0.08


@dataclass(frozen=True)
class StepResult:
    """What :func:`ik_step_ex` did."""

    q_rad: np.ndarray  #: the next joint command (command-area order)
    pos_err_m: float  #: tool-point distance to the target at the start of the step
    rot_err_rad: float  #: orientation angle to the target at the start of the step
    rate_limited: bool  #: the joint step was scaled down to the rate limits
    limited: bool  #: a joint was held at a (soft) limit
    singular: bool  #: damping was active (near a singular configuration)
    sigma_min: float  #: smallest singular value of the Jacobian at q_now


def _pose_error(f: list[np.ndarray], p_t: np.ndarray, r_t: np.ndarray) -> np.ndarray:
    """(position error, world-frame rotation vector taking the tool to the target)."""
    t = f[6]
    return np.concatenate((p_t - t[:3, 3], q_to_rotvec(q_from_matrix(r_t @ t[:3, :3].T))))


def _dls(jm: np.ndarray, e: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, float, bool]:
    jf = jm * free[None, :]
    u, s, vt = np.linalg.svd(jf)
    smin = float(s[-1]) if free.all() else float(s[int(free.sum()) - 1]) if free.any() else 0.0
    lam2 = 0.0
    if smin < DLS_SIGMA_MIN:
        lam2 = DLS_LAMBDA_MAX ** 2 * (1.0 - (smin / DLS_SIGMA_MIN) ** 2)
    gain = s / (s * s + lam2) if lam2 > 0.0 else np.where(s > 1e-12, 1.0 / np.maximum(s, 1e-12), 0.0)
    dq = vt.T @ (gain * (u.T @ e))
    return dq * free, smin, lam2 > 0.0


def ik_step_ex(q_now: Sequence[float], p_m: Sequence[float], quat: Sequence[float], dt_s: float, *,
               rate_limit_rad_s: np.ndarray | None = None, lo_rad: np.ndarray | None = None,
               hi_rad: np.ndarray | None = None, shoulder_roll_rad: float = 0.0,
               iterations: int = 3) -> StepResult:
    """One rate-limited damped-least-squares step from ``q_now`` toward the tool pose.

    Up to ``iterations`` Gauss-Newton refinements are taken while the accumulated joint
    step fits inside ``rate_limit_rad_s * dt_s`` (default: the software rate limits,
    8.2); a larger step is scaled down as a whole (same direction, so the tool heads
    straight for the pose), so no joint ever moves more than its rate limit times
    ``dt_s``. Joints at a soft limit that the step would push further out are locked
    for the step and the others compensate; a joint that would cross a limit during the
    step stops on it (and is locked in the next step); the result is inside the limits, or, for a
    joint that starts outside them, no further out than it started (it is never pulled
    in by more than its rate budget). Never raises for an unreachable pose: it moves
    toward it and stops where the error is smallest.
    """
    if dt_s <= 0.0:
        raise KinematicsError(f"ik_step needs dt_s > 0, got {dt_s}")
    q0 = _q(q_now).astype(float).copy()
    lo = np.minimum(SOFT_LO_RAD if lo_rad is None else lo_rad, q0)
    hi = np.maximum(SOFT_HI_RAD if hi_rad is None else hi_rad, q0)
    rate = RATE_LIMIT_RAD_S if rate_limit_rad_s is None else np.asarray(rate_limit_rad_s, dtype=float)
    budget = rate * dt_s
    p_t = np.asarray(p_m, dtype=float).reshape(3)
    r_t = q_to_matrix(quat)
    q = q0.copy()
    f = fk_frames(q, shoulder_roll_rad)
    e = _pose_error(f, p_t, r_t)
    pos_err, rot_err = float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:]))
    rate_limited = limited = singular = False
    smin0 = math.nan
    for it in range(max(1, iterations)):
        if float(np.linalg.norm(e)) < 1e-12:
            break
        jm = _jacobian_from_frames(f)
        free = np.ones(6, dtype=bool)
        for _ in range(3):  # joints already at a limit that the step pushes further out are locked
            dq, smin, damped = _dls(jm, e, free.astype(float))
            push = free & (((q <= lo + _LIMIT_TOL) & (dq < 0.0)) | ((q >= hi - _LIMIT_TOL) & (dq > 0.0)))
            if not push.any():
                break
            free &= ~push
            limited = True
        if it == 0:
            smin0 = smin
        singular |= damped
        total = (q + dq) - q0
        over = float(np.max(np.abs(total) / budget))
        if over > 1.0:
            if it == 0:
                q = np.clip(q0 + total / over, lo, hi)
                rate_limited = True
            break  # later iteration: keep the last step that fitted
        nxt = np.clip(q + dq, lo, hi)
        if np.any(nxt != q + dq):
            q, limited = nxt, True
            break  # a joint stopped on a limit: no refinement past it
        q = nxt
        f = fk_frames(q, shoulder_roll_rad)
        e = _pose_error(f, p_t, r_t)
    return StepResult(q, pos_err, rot_err, rate_limited, limited, singular, smin0)


def ik_step(q_now: Sequence[float], p_m: Sequence[float], quat: Sequence[float], dt_s: float, *,
            rate_limit_rad_s: np.ndarray | None = None, lo_rad: np.ndarray | None = None,
            hi_rad: np.ndarray | None = None, shoulder_roll_rad: float = 0.0) -> np.ndarray:
    """The next joint command (see :func:`ik_step_ex`; this returns only the angles)."""
    return ik_step_ex(q_now, p_m, quat, dt_s, rate_limit_rad_s=rate_limit_rad_s, lo_rad=lo_rad,
                      hi_rad=hi_rad, shoulder_roll_rad=shoulder_roll_rad).q_rad


def joint_step_toward(q_now: Sequence[float], q_goal: Sequence[float], dt_s: float,
                      rate_limit_rad_s: np.ndarray | None = None) -> np.ndarray:
    """One joint-space step from ``q_now`` toward ``q_goal``: the whole step scaled down so
    that no joint moves more than its rate limit times ``dt_s`` (a straight line in joint
    space; used to leave a soft limit the damped least squares cannot leave)."""
    q0 = _q(q_now).astype(float)
    d = _q(q_goal).astype(float) - q0
    rate = RATE_LIMIT_RAD_S if rate_limit_rad_s is None else np.asarray(rate_limit_rad_s, dtype=float)
    over = float(np.max(np.abs(d) / (rate * dt_s)))
    return q0 + (d / over if over > 1.0 else d)
