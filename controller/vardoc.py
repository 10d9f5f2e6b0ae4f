"""docs/world-model.md's list of the declared world-model variables (generated; a test,
tests/controller/test_variables.py, keeps the file equal to it). A leaf module: it imports
every module that declares a group (controller/variables.py, controller/servo.py,
controller/layers.py, controller/gripper.py, controller/force.py, controller/delay.py,
controller/teleop.py, controller/trajectory.py, controller/paths/layer.py,
controller/runtime.py).

Regenerate: ``python -m controller.vardoc`` prints the block.
"""

from __future__ import annotations

from controller.delay import DelayVars
from controller.force import ForceVars
from controller.gripper import GripperVars, PathGripperVars
from controller.layers import JointMoveVars, JointVars, UiVars
from controller.paths.layer import MspVars
from controller.runtime import RuntimeVars
from controller.servo import ServoVars
from controller.teleop import TeleopVars
from controller.trajectory import SegmentVars, TrajVars
from controller.variables import CartVars, DaqVars
from controller.worldmodel.var import VarGroup

#: every declared group, in the order the document lists them
#: (the layers' from the bottom up, then System Up/Down's requests and the runtime's own)
GROUPS: tuple[type[VarGroup], ...] = (DaqVars, ServoVars, GripperVars, JointVars, CartVars, TrajVars, ForceVars, DelayVars,
                                      TeleopVars, MspVars, SegmentVars, JointMoveVars, PathGripperVars, UiVars,
                                      RuntimeVars)

DOC_BEGIN = "<!-- variables: generated from the VarGroup declarations; regenerate: python -m controller.vardoc -->"
DOC_END = "<!-- end of the generated variables -->"


def markdown() -> str:
    """The declared variables as the table docs/world-model.md carries between
    :data:`DOC_BEGIN` and :data:`DOC_END`."""
    lines = [DOC_BEGIN]
    for group in GROUPS:
        lines += ["", f"`{group.__name__}` (`{group.prefix}.*`, writer `{group.writer}` unless the row says):", "",
                  "| attribute | name | area | type | units | writer | doc |", "|---|---|---|---|---|---|---|"]
        for attr, v in group.attributes():
            s = v.spec
            units, doc = s.units.replace("|", "\\|"), s.doc.replace("|", "\\|")  # a table cell
            lines.append(f"| `{attr}` | `{v}` | {s.area} | {s.type_text} | {units} | {s.writer} | {doc} |")
    return "\n".join(lines + ["", DOC_END])


if __name__ == "__main__":  # pragma: no cover
    print(markdown())
