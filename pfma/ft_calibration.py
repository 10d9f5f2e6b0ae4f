"""The wrist F/T sensor's calibration, as a calibration file's ``ft`` section holds it.

The reader the controller needs (the tool payload for gravity compensation) and the
service (bias and counts -> wrench matrix), on the ground floor so neither imports
``calibration``. The file itself (versions, history, validation of every section) is
:mod:`calibration.files`, which uses this module for its ``ft`` section.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class FtCalibration:
    """F/T sensor calibration: ``wrench = matrix @ (counts - bias_counts)``; tool payload."""

    bias_counts: np.ndarray  #: (6,) counts subtracted before the matrix
    matrix: np.ndarray  #: (6, 6) counts -> (Fx, Fy, Fz [N], Tx, Ty, Tz [N*m])
    payload_mass_kg: float  #: tool + payload mass behind the sensor
    payload_com_m: np.ndarray  #: (3,) its centre of mass in sensor coordinates

    def wrench(self, counts) -> np.ndarray:
        """Counts (6) -> wrench (6): forces N, torques N*m, in the sensor frame."""
        return self.matrix @ (np.asarray(counts, dtype=float) - self.bias_counts)

    def gravity_wrench(self, g_sensor) -> np.ndarray:
        """The payload's weight in the sensor frame, given gravity (m/s^2) in sensor axes."""
        f = self.payload_mass_kg * np.asarray(g_sensor, dtype=float)
        return np.concatenate([f, np.cross(self.payload_com_m, f)])


def ft_calibration(cal: Any) -> FtCalibration | None:
    """The F/T section (bias, 6x6 matrix, payload) of a validated calibration (its ``ft``
    dict, as :class:`calibration.files.Calibration` has it); None when absent."""
    ft = cal.ft
    if not ft:
        return None
    return FtCalibration(np.array(ft["bias_counts"], dtype=float), np.array(ft["matrix"], dtype=float),
                         float(ft["payload_mass_kg"]), np.array(ft["payload_com_m"], dtype=float))
