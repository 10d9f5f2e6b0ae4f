"""Multi-Segment Path Planner layer (20 Hz): record, store, edit, plan and play back paths.

IRSS report 2.2.1: "This layer manages tasks that handle multi-segment path manipulation
(recording and execution) and generates intermediate level commands for the Trajectory
Path Planner Layer which exists below it. ... Tasks at this layer execute at relatively
low frequencies (20 Hz)". 2.2.8: "a small menu tree within the multi-segment path
planner used to edit various path buffers" - here ``pfma path`` and :class:`PathStore`.

Three parts:

* **Path files** (:class:`Path`, :class:`PathStore`): one JSON file per path in a small
  directory (default ``$PFMA_PATH_DIR``, else ``$XDG_DATA_HOME/pfma/paths``, else
  ``~/.local/share/pfma/paths``). Files carry a format version (:data:`FORMAT_VERSION`)
  and a revision counter; they are written atomically (temporary file, fsync, rename)
  and a save refuses to overwrite a revision it did not load. Editing is pure functions
  (:func:`delete_points`, :func:`insert_point`, :func:`move_point`, :func:`set_speed`)
  returning a new :class:`Path`; nothing here needs the controller.
* **Planning** (:func:`simplify`, :func:`plan_path`): the recorded points become
  key points (teach points always kept; continuously captured points reduced with a
  position/angle tolerance, Douglas-Peucker on the pose) and each key point the target
  of one rest-to-rest segment with the path's limits (per-point speed overrides, a
  playback speed scale).
* **The layer** (:class:`MultiSegmentLayer`): ``msp.mode`` 1 records the measured tool
  pose ``joint.tool_pos_m``/``joint.tool_quat`` (a teach point each time ``msp.teach``
  changes; continuous capture whenever the pose moved ``msp.capture_dist_m`` or turned
  ``msp.capture_angle_rad`` since the last point) and saves the path under
  ``msp.path_id`` when the mode leaves 1; ``msp.mode`` 2 loads path ``msp.path_id``,
  plans it and hands the segments one at a time to the Trajectory Planner
  (:mod:`controller.trajectory`), the next one each time ``traj.done_seq`` reports the
  last one done. Mode 0 during a playback stops it (the Trajectory Planner decelerates).

Moves (issue 30 item 5): a move-to request (``msp.move_request``,
:mod:`controller.paths.move`: a pose or a joint goal) runs through the same layer; every
playback and move is checked before it starts (:mod:`controller.paths.check`: tool
rotation, soft limits, singular sets along the sampled motion) and its tracking error is
measured while it runs (OK only within ``msp.track_tol_*``). A point without an
orientation keeps the tool's.

The package, one module per part (``from controller.paths import X`` gives all of it):
:mod:`controller.paths.model` (path buffers, checks, pure edits),
:mod:`controller.paths.store` (the path files), :mod:`controller.paths.planner` (planning),
:mod:`controller.paths.check` (the check before a motion starts),
:mod:`controller.paths.move` (move-to requests) and :mod:`controller.paths.layer` (the layer).
"""

from controller.paths.check import (
    MAX_TURN_RAD as MAX_TURN_RAD,
    MotionCheck,
    Refusal,
    Target,
)
from controller.paths.layer import (
    CAPTURE_ANGLE_RAD as CAPTURE_ANGLE_RAD,
    CAPTURE_DIST_M as CAPTURE_DIST_M,
    CMD_POSE as CMD_POSE,
    JMOVE_SPEED as JMOVE_SPEED,
    TRACK_TOL_M as TRACK_TOL_M,
    TRACK_TOL_RAD as TRACK_TOL_RAD,
    TOOL_POSE as TOOL_POSE,
    USER_VARS as USER_VARS,
    MspMode,
    MspResult,
    MultiSegmentLayer,
    RecordSource,
)
from controller.paths.model import (
    DEFAULT_LIMITS,
    FORMAT as FORMAT,
    FORMAT_VERSION,
    POINT_KINDS as POINT_KINDS,
    Path,
    PathError,
    PathPoint,
    check_limits as check_limits,
    check_name as check_name,
    delete_points,
    insert_gripper,
    insert_point,
    make_point,
    move_point,
    resolve_orientations,
    set_limits,
    set_speed,
)
from controller.paths.move import MOVE_REQUEST_LEN as MOVE_REQUEST_LEN, MoveKind, MoveRequest
from controller.paths.planner import (
    PLAN_TOL_M as PLAN_TOL_M,
    PLAN_TOL_RAD as PLAN_TOL_RAD,
    PlannedSegment,
    offline_start_quat,
    plan_duration_s,
    plan_path,
    simplify,
)
from controller.paths.store import (
    PATH_DIR_ENV as PATH_DIR_ENV,
    PathInfo,
    PathStore,
    default_dir,
    path_missing as path_missing,
)

__all__ = ["Path", "PathPoint", "PathStore", "PathInfo", "PathError", "make_point", "delete_points",
           "insert_point", "insert_gripper", "move_point", "set_speed", "set_limits", "simplify", "plan_path", "plan_duration_s",
           "PlannedSegment", "MultiSegmentLayer", "MspMode", "MspResult", "RecordSource", "default_dir", "FORMAT_VERSION",
           "DEFAULT_LIMITS", "resolve_orientations", "offline_start_quat", "MotionCheck", "Refusal", "Target",
           "MoveRequest", "MoveKind"]
