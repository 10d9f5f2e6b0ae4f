"""Calibration tests run on the service tests' simulated-time rig (imported, not copied)."""

import contextlib
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


#: the procedures in a lab's bring-up order (docs/calibration.md)
BRINGUP_ORDER = ("adc", "current-offsets", "tach", "resolver", "dac-rate", "cae", "ft-bias", "ft-payload",
                 "ft-matrix")


@contextlib.contextmanager
def bringup_run(errors, workdir, before=None):
    """Every procedure of :data:`BRINGUP_ORDER` on one simulated rack with ``errors``
    (``SimErrors``), each saved file loaded by the service before the next; ``before(name)``
    is called as each starts. Yields (results by name, the simulated time at the end, the
    operator's output); each procedure must pass."""
    from calibration.files import load_calibration
    from calibration.procedures import run_procedure
    rig = Rig(name="pfma-bringup-" + uuid.uuid4().hex[:8], errors=errors)
    rack = rig.world.rack_config
    path = workdir / "cal.json"
    save_calibration(nominal_calibration(rack, operator="test"), path, rack=rack)
    session = SimSession(rig)
    out = io.StringIO()
    operator = SimOperator(rig.world, out=out)
    operator.show = lambda text: print(text, file=out)
    results = {}
    try:
        for name in BRINGUP_ORDER:
            if before is not None:
                before(name)
            ctx = Context(session, operator, load_calibration(path, rack), rack, workdir / "plots",
                          operator_name="test")
            res = run_procedure(name, ctx, save_to=path)
            assert res.passed, f"{name} failed:\n{res.report()}\n{out.getvalue()[-2000:]}"
            assert res.plots and all(p.exists() for p in res.plots), name
            session.reload_service(path)
            results[name] = res
        yield results, rig.clock.now(), out.getvalue()
    finally:
        session.close()
        rig.close()
