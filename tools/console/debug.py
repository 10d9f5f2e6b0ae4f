"""The debug window's displays (issue 18 item 2, docs/console.md "The debug window"), as
plain text like every area: the parameter-modification display.
The Textual screens that show them are in :mod:`tools.console.app`."""

from __future__ import annotations

from controller.params import JOINT_NAMES

# --- the parameter-modification display (p) ----------------------------------------------------
#: the servo compensator's parameters (the rest of servo.* are limits)
COMPENSATORS = ("servo.kp_per_s", "servo.tau_z_s", "servo.tau_p_s")
#: the element names of a per-joint vector: the six joints, then the gripper (servo.current_limit_a)
ELEMENTS = tuple(JOINT_NAMES) + ("gripper",)
#: width of one value column
CELL = 14


def param_group(name: str) -> str:
    """The heading a parameter is shown under."""
    if name in COMPENSATORS:
        return "servo compensators"
    if name.startswith("servo."):
        return "servo limits"
    if name.startswith("traj."):
        return "trajectory limits"
    return name.split(".")[0] + " parameters"


def param_names(wm) -> tuple[str, ...]:
    """The parameters: every world-model variable a user may set only while powered down
    (``VarSpec.user == "powered_down"``: the control-law parameters and limits), the servo
    compensators first, then the servo limits, then the rest, each group in the model's order."""
    names = [s.name for s in wm.specs if s.user == "powered_down"]
    order = ["servo compensators", "servo limits", "trajectory limits"]
    return tuple(sorted(names, key=lambda n: (order.index(param_group(n)) if param_group(n) in order else 99,
                                              param_group(n))))


def param_columns(wm, name: str) -> int:
    """Editable cells of a parameter: its elements (1 for a scalar)."""
    return wm.spec(name).count


def _cell(v: float) -> str:
    return f"{float(v):.6g}"


def params_display(wm, row: int, col: int, status: str = "") -> str:
    """Every parameter by joint, the selected cell in brackets, and whether it can be edited
    now (only while powered down; the ownership rule decides, this only says it)."""
    names = param_names(wm)
    values = wm.get_task_inputs(names) if names else {}
    up = bool(wm.powered_up)
    lines = ["Parameters: the servo compensators and limits (world-model control flags, user=powered_down)",
             ("LOCKED: the system is powered up; power down (d) to edit them" if up else
              "EDITABLE: the system is powered down; Enter/e edits the selected value"),
             f"  {'PARAMETER':<24} {'UNITS':<8}" + "".join(f"{e[:CELL - 1]:>{CELL}}" for e in ELEMENTS)]
    group = ""
    for r, n in enumerate(names):
        g = param_group(n)
        if g != group:
            lines.append(g)
            group = g
        s = wm.spec(n)
        vals = [values[n]] if s.shape == () else list(values[n].ravel())
        cells = []
        for c, v in enumerate(vals):
            t = _cell(v)
            cells.append(f"[{t}]".rjust(CELL) if (r == row and c == col) else f"{t} ".rjust(CELL))
        mark = ">" if r == row else " "
        lines.append(f"{mark} {n:<24} {s.units or '-':<8}" + "".join(cells))
    lines += ["", "up/down parameter  left/right joint  Enter/e edit  Escape/p close", status]
    return "\n".join(lines)
