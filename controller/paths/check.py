"""Checks a path or a move before it starts: the whole interpolated motion, sampled.

A playback or a move is refused before the arm moves when, anywhere on its way, it would

* **turn the tool** more than a stated threshold from its orientation at the start
  (:data:`MAX_TURN_RAD`, 30 degrees, assumed; ``msp.max_turn_rad`` and a move's own
  override raise it explicitly): the largest angle between the tool's orientation at a
  sample and at the start of the motion;
* **cross a soft limit** (``controller.params`` via :mod:`controller.kinematics`; a joint
  that starts outside its soft limit may not go further out);
* **come near a singular set** (:func:`controller.kinematics.singular_sets`' margins:
  5 degrees of wrist yaw from +-90 or of elbow from 0, 0.05 m of wrist centre from the
  shoulder-yaw axis; a set the arm is in at the start counts once the motion has left
  it), or need a branch change of the closed form (a joint stepping more than
  :data:`JUMP_RAD` between neighbouring samples), or leave the arm's reach.

Cartesian motion (a path's segments, a pose move) is sampled as the Trajectory Planner
executes it (straight line, geodesic orientation: :func:`controller.trajectory.plan_segment`),
every :data:`SAMPLE_STEP_M` of travel and :data:`SAMPLE_STEP_RAD` of turn, and solved with
the vectorised closed form (:func:`controller.kinematics.ik_batch`) on the branch the arm
is on at the start (the branch nearest the Joint Planner's joint command), each joint
followed continuously from its starting angle. A joint move is the straight line in joint
space the Joint Planner runs, sampled every :data:`SAMPLE_STEP_RAD` of the joint that
moves most, its tool orientation from :func:`controller.kinematics.fk_batch`.

The check runs in slices (:meth:`MotionCheck.advance`, at most ``max_samples`` samples a
call: the Multi-Segment Path Planner spends one slice per 20 Hz run, so no frame carries
a whole path); :meth:`MotionCheck.run` does all of it at once (tests, the CLI). The
refusal (:class:`Refusal`) names the point and the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from controller import kinematics as kin
from controller.params import JOINT_NAMES
from controller.quat import q_to_matrix
from controller.trajectory import plan_segment

#: Largest tool rotation a path or move may make from its starting orientation unless
#: raised explicitly (assumed, this project: a playback or move that turns the tool more
#: than this was probably not meant to; issue 30 item 5)
MAX_TURN_RAD = math.radians(30.0)
#: sampling of the interpolated motion (assumed: a tenth of the singular-set margins)
SAMPLE_STEP_M = 0.005
SAMPLE_STEP_RAD = math.radians(1.0)
#: a joint stepping more than this between two neighbouring samples means the closed form
#: changed branch (a singular set) (assumed: samples 5 mm / 1 deg apart move a joint a few
#: degrees at most elsewhere)
JUMP_RAD = math.radians(10.0)
#: samples one :meth:`MotionCheck.advance` of the Multi-Segment Path Planner takes (assumed:
#: ~0.15 ms on this host, inside the 20 Hz task's slot)
SAMPLES_PER_RUN = 128
#: segments one :meth:`MotionCheck.advance` plans at most (assumed: ~0.05 ms each)
SEGMENTS_PER_RUN = 8
#: slack on the soft limits (the kinematics' own tolerance)
_LIMIT_TOL = 1e-9
_SET_NAMES = ("wrist", "stretch", "axis")


@dataclass(frozen=True)
class Refusal:
    """Why a motion may not start: where (``point``: the path point or "the target") and
    what (``reason``), with the tool position there."""

    point: str
    reason: str
    pos_m: tuple[float, float, float]

    def text(self) -> str:
        x, y, z = self.pos_m
        return f"{self.point}: {self.reason} (tool at {x:+.3f}, {y:+.3f}, {z:+.3f} m)"


@dataclass(frozen=True)
class Target:
    """One Cartesian segment's end: the pose and the words that name it in a refusal."""

    label: str  #: e.g. "point 3" or "the target"
    pos_m: np.ndarray
    quat: np.ndarray


def _deg(x: float) -> str:
    return f"{math.degrees(x):.1f} deg"


def _rot_angles(r0: np.ndarray, rs: np.ndarray) -> np.ndarray:
    """Angle (rad) of each rotation ``rs[i]`` from ``r0``."""
    tr = np.einsum("ji,nji->n", r0, rs)  # trace(r0.T @ rs[i])
    return np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))


def _rodrigues(axis_angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of world-frame rotation vectors (N, 3)."""
    th = np.linalg.norm(axis_angle, axis=1)
    k = np.divide(axis_angle, th[:, None], out=np.zeros_like(axis_angle), where=th[:, None] > 1e-15)
    kx = np.zeros((len(th), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 0] = -k[:, 2], k[:, 1], k[:, 2]
    kx[:, 1, 2], kx[:, 2, 0], kx[:, 2, 1] = -k[:, 0], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], (1.0 - np.cos(th))[:, None, None]
    return np.eye(3)[None] + s * kx + c * (kx @ kx)


class MotionCheck:
    """The check of one motion (module doc). Build it with :meth:`cartesian` or
    :meth:`joint`; call :meth:`advance` until it returns True, then read :attr:`refusal`
    (None: the motion may start) and :attr:`worst_turn_rad`."""

    def __init__(self, q_start: Sequence[float], start_pos_m: Sequence[float], start_quat: Sequence[float],
                 max_turn_rad: float, shoulder_roll_rad: float) -> None:
        self.q_start = np.asarray(q_start, dtype=float).reshape(6).copy()
        self.start_pos = np.asarray(start_pos_m, dtype=float).reshape(3).copy()
        self.start_quat = np.asarray(start_quat, dtype=float).reshape(4).copy()
        self.r_start = q_to_matrix(self.start_quat)
        self.max_turn_rad = float(max_turn_rad)
        self.roll = float(shoulder_roll_rad)
        self.refusal: Refusal | None = None
        self.done = False
        self.samples = 0  #: samples checked so far
        self.worst_turn_rad = 0.0  #: largest tool rotation from the start seen so far
        self._allowed = set(kin.singular_sets(self.q_start))  # sets the arm starts in
        self._out_lo = self.q_start < kin.SOFT_LO_RAD - _LIMIT_TOL  # joints starting outside
        self._out_hi = self.q_start > kin.SOFT_HI_RAD + _LIMIT_TOL
        self._q_prev = self.q_start.copy()
        self._branch: tuple[bool, bool, bool] | None = None
        self._pending: list[tuple[int, np.ndarray]] = []  # (segment index, its s values still to check)
        self._next_seg = 0
        self._targets: list[Target] = []
        self._segs: list = []  # the planned segments queued so far (CartesianSegment)
        self._goal: np.ndarray | None = None  # a joint move's goal

    # --- construction ----------------------------------------------------------------------
    @classmethod
    def cartesian(cls, q_start: Sequence[float], start_pos_m: Sequence[float], start_quat: Sequence[float],
                  targets: Sequence[Target], *, max_turn_rad: float = MAX_TURN_RAD,
                  shoulder_roll_rad: float = 0.0) -> "MotionCheck":
        """Straight-line, geodesic segments from the start pose through ``targets`` in turn.
        ``q_start``: the Joint Planner's joint command (the arm's branch)."""
        c = cls(q_start, start_pos_m, start_quat, max_turn_rad, shoulder_roll_rad)
        c._targets = list(targets)
        return c

    @classmethod
    def joint(cls, q_start: Sequence[float], q_goal: Sequence[float], *, max_turn_rad: float = MAX_TURN_RAD,
              shoulder_roll_rad: float = 0.0) -> "MotionCheck":
        """The straight line in joint space from ``q_start`` to ``q_goal``."""
        q0 = np.asarray(q_start, dtype=float).reshape(6)
        p0, quat0 = kin.fk(q0, shoulder_roll_rad)
        c = cls(q0, p0, quat0, max_turn_rad, shoulder_roll_rad)
        c._goal = np.asarray(q_goal, dtype=float).reshape(6).copy()
        return c

    # --- running ---------------------------------------------------------------------------
    def run(self) -> Refusal | None:
        """The whole check at once; the refusal or None."""
        while not self.advance(1 << 30):
            pass
        return self.refusal

    def advance(self, max_samples: int = SAMPLES_PER_RUN) -> bool:
        """Check up to ``max_samples`` more samples; True once finished (refused or passed)."""
        if self.done:
            return True
        if self._goal is not None:
            self._check_joint_line()
            self.done = True
            return True
        budget = max(1, int(max_samples))
        new_segs = 0
        seg_idx: list[np.ndarray] = []
        s_vals: list[np.ndarray] = []
        while budget > 0:
            if not self._pending:
                if self._next_seg >= len(self._targets) or new_segs >= SEGMENTS_PER_RUN:
                    break
                new_segs += 1
                self._queue_segment(self._next_seg)
                self._next_seg += 1
                continue
            k, s = self._pending[0]
            take = s[:budget]
            rest = s[budget:]
            if len(rest):
                self._pending[0] = (k, rest)
            else:
                self._pending.pop(0)
            seg_idx.append(np.full(len(take), k))
            s_vals.append(take)
            budget -= len(take)
        if seg_idx:
            self._check_cartesian(np.concatenate(seg_idx), np.concatenate(s_vals))
        if self.refusal is not None or (not self._pending and self._next_seg >= len(self._targets)):
            self.done = True
        return self.done

    def _queue_segment(self, k: int) -> None:
        if k == 0:
            p0, q0 = self.start_pos, self.start_quat
        else:
            p0, q0 = self._targets[k - 1].pos_m, self._targets[k - 1].quat
        t = self._targets[k]
        seg = plan_segment(p0, q0, t.pos_m, t.quat, (1.0, 1.0, 1.0, 1.0))  # the geometry (limits unused)
        n = max(1, math.ceil(seg.length_m / SAMPLE_STEP_M), math.ceil(seg.angle_rad / SAMPLE_STEP_RAD))
        self._segs.append(seg)
        self._pending.append((k, np.linspace(0.0, 1.0, n + 1)[1:]))

    def _check_cartesian(self, seg_idx: np.ndarray, s: np.ndarray) -> None:
        ks, inv = np.unique(seg_idx, return_inverse=True)  # the segments in this slice
        segs = [self._segs[int(k)] for k in ks]
        p0 = np.array([g.p0 for g in segs])[inv]
        p1 = np.array([g.p1 for g in segs])[inv]
        rv = np.array([g.rotvec for g in segs])[inv]
        r0 = np.array([q_to_matrix(g.q0) for g in segs])[inv]
        pos = p0 + s[:, None] * (p1 - p0)
        rot = _rodrigues(s[:, None] * rv) @ r0
        where = [self._targets[int(k)].label for k in seg_idx]
        if self._branch is None:
            self._branch = self._nearest_branch()
        q, reach = kin.ik_batch(pos, rot, self._branch, self.roll)
        if not reach.all():
            i = int(np.argmin(reach))
            self._refuse(where[i], "out of the arm's reach", pos[i])
            return
        # each joint followed continuously from the last sample (2 pi turns)
        q = np.vstack([self._q_prev[None], q])
        q = np.unwrap(q, axis=0)
        q = q[1:]
        self._judge(q, pos, rot, where)

    def _nearest_branch(self) -> tuple[bool, bool, bool]:
        """The closed-form branch whose solution at the start pose is nearest ``q_start``."""
        n = len(kin.BRANCHES)
        cols = tuple(np.array([b[i] for b in kin.BRANCHES]) for i in range(3))
        q, _ = kin.ik_batch(np.repeat(self.start_pos[None], n, axis=0), np.repeat(self.r_start[None], n, axis=0),
                            cols, self.roll)
        d = np.abs((q - self.q_start[None] + math.pi) % (2.0 * math.pi) - math.pi).max(axis=1)
        return kin.BRANCHES[int(np.argmin(d))]

    def _check_joint_line(self) -> None:
        d = self._goal - self.q_start
        n = max(1, math.ceil(float(np.max(np.abs(d))) / SAMPLE_STEP_RAD))
        s = np.linspace(0.0, 1.0, n + 1)[1:]
        q = self.q_start[None] + s[:, None] * d[None]
        pos, rot = kin.fk_batch(q, self.roll)
        self._judge(q, pos, rot, ["the joint goal"] * len(s), joint_line=True)

    def _judge(self, q: np.ndarray, pos: np.ndarray, rot: np.ndarray, where: list[str],
               joint_line: bool = False) -> None:
        """Refuse at the first sample that breaks a rule (rotation, soft limit, singular set,
        branch jump), in the order of the samples."""
        n = len(q)
        bad = np.full(n, False)
        turn = _rot_angles(self.r_start, rot)
        bad |= turn > self.max_turn_rad + 1e-9
        lo, hi = kin.SOFT_LO_RAD, kin.SOFT_HI_RAD
        below = q < lo - _LIMIT_TOL
        above = q > hi + _LIMIT_TOL
        # a joint that starts outside may stay there, but not go further out
        below &= ~(self._out_lo[None] & (q >= self.q_start[None] - _LIMIT_TOL))
        above &= ~(self._out_hi[None] & (q <= self.q_start[None] + _LIMIT_TOL))
        bad |= below.any(axis=1) | above.any(axis=1)
        dist = kin.singular_distances(q)
        near = np.stack([dist[:, 0] < kin.SINGULAR_MARGIN_RAD, dist[:, 1] < kin.SINGULAR_MARGIN_RAD,
                         dist[:, 2] < kin.SINGULAR_MARGIN_M], axis=1)
        # a set the arm starts in is allowed until the motion has left it once
        allowed = np.array([name in self._allowed for name in _SET_NAMES])
        left = np.logical_or.accumulate(~near, axis=0)
        excused = allowed[None] & ~left
        near_bad = near & ~excused
        bad |= near_bad.any(axis=1)
        step = np.abs(np.diff(np.vstack([self._q_prev[None], q]), axis=0))
        jump = step.max(axis=1) > JUMP_RAD if not joint_line else np.full(n, False)
        bad |= jump
        k = int(np.argmax(bad)) if bad.any() else n
        self.worst_turn_rad = max(self.worst_turn_rad, float(turn[:k].max()) if k else 0.0)
        self.samples += k
        if k:  # the sets the arm started in and has left in the samples that passed
            for c in np.flatnonzero(allowed & left[k - 1]):
                self._allowed.discard(_SET_NAMES[int(c)])
        if k == n:
            self._q_prev = q[-1].copy()
            return
        i = k
        self.worst_turn_rad = max(self.worst_turn_rad, float(turn[i]))
        if turn[i] > self.max_turn_rad + 1e-9:
            self._refuse(where[i], f"turns the tool {_deg(float(turn[i]))} from its starting orientation, more than "
                                   f"the {_deg(self.max_turn_rad)} allowed (msp.max_turn_rad or --max-turn to "
                                   f"allow more)", pos[i])
        elif below[i].any() or above[i].any():
            j = int(np.argmax(below[i] | above[i]))
            self._refuse(where[i], f"crosses a soft limit: {JOINT_NAMES[j]} would reach {_deg(float(q[i, j]))}, "
                                   f"outside {math.degrees(lo[j]):+.0f}..{math.degrees(hi[j]):+.0f} deg", pos[i])
        elif near_bad[i].any():
            j = int(np.argmax(near_bad[i]))
            self._refuse(where[i], self._singular_text(_SET_NAMES[j], q[i]), pos[i])
        else:
            j = int(np.argmax(step[i]))
            self._refuse(where[i], f"passes a singular set: {JOINT_NAMES[j]} would jump {_deg(float(step[i, j]))} "
                                   f"between two samples {SAMPLE_STEP_M * 1e3:g} mm apart (the arm changes "
                                   f"configuration)", pos[i])

    @staticmethod
    def _singular_text(name: str, q: np.ndarray) -> str:
        j = kin.J
        if name == "wrist":
            return (f"comes near the wrist singular set: wrist yaw {_deg(float(q[j['wrist_yaw']]))} "
                    f"(within {_deg(kin.SINGULAR_MARGIN_RAD)} of +-90 deg)")
        if name == "stretch":
            return (f"comes near the stretched-arm singular set: elbow {_deg(float(q[j['elbow_pitch']]))} "
                    f"(within {_deg(kin.SINGULAR_MARGIN_RAD)} of 0 or 180 deg)")
        d = float(kin.singular_distances(q[None])[0, 2])
        return (f"comes near the shoulder-axis singular set: the wrist centre {d * 1e3:.0f} mm from the "
                f"shoulder-yaw axis (margin {kin.SINGULAR_MARGIN_M * 1e3:.0f} mm)")

    def _refuse(self, where: str, reason: str, pos: np.ndarray) -> None:
        self.refusal = Refusal(where, reason, tuple(float(x) for x in pos))  # type: ignore[arg-type]
        self.done = True


__all__ = ["MotionCheck", "Refusal", "Target", "MAX_TURN_RAD", "SAMPLE_STEP_M", "SAMPLE_STEP_RAD", "JUMP_RAD",
           "SAMPLES_PER_RUN", "SEGMENTS_PER_RUN"]
