"""Calibration tests run on the service tests' simulated-time rig (imported, not copied)."""

import io
import uuid

import pytest

from calibration.files import nominal_calibration, save_calibration
from calibration.procedures import Context
from calibration.session import SimSession
from sim.calibration import SimOperator
from sim.calibration import CalibrationRig as Rig


class CalRig:
    """A Rig (service tests) + a calibration file + a session and a simulated operator."""

    def __init__(self, tmp_path, **rig_kw):
        self.path = tmp_path / "pfma-cal.json"
        self.rig = Rig(name="pfma-caltest-" + uuid.uuid4().hex[:8], **rig_kw)
        self.world = self.rig.world
        self.rack = self.world.rack_config
        if not self.path.exists():
            save_calibration(nominal_calibration(self.rack, operator="test"), self.path, rack=self.rack)
        self.session = SimSession(self.rig)
        self.out = io.StringIO()
        self.operator = SimOperator(self.world, out=self.out)
        self.operator.show = lambda text: print(text, file=self.out)
        self.tmp_path = tmp_path

    def context(self, **options) -> Context:
        from calibration.files import load_calibration
        return Context(self.session, self.operator, load_calibration(self.path, self.rack), self.rack,
                       self.tmp_path / "plots", operator_name="test", options=options)

    def close(self):
        self.session.close()
        self.rig.close()


@pytest.fixture
def cal(tmp_path):
    r = CalRig(tmp_path)
    yield r
    r.close()
