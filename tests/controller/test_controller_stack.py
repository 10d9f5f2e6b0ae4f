"""The controller process's composition root (tools.stacks.controller.ControllerStack):
opened in order, closed in reverse on every way out, the outputs left safe first."""

from __future__ import annotations

import logging
import os
import signal
import uuid

import pytest

from controller.decision import Status
from controller.layers import Request
from controller.worldmodel import WorldModel
from tools.stacks import controller as stacks
from tools.stacks.controller import ControllerOptions, ControllerStack, LocalDriver


@pytest.fixture
def wm_name():
    name = "pfma-test-stack-" + uuid.uuid4().hex[:6]
    yield name
    WorldModel.remove_segment(name)


def _exists(name: str) -> bool:
    return os.path.exists(f"/dev/shm/{name}")


def test_a_simulated_controller_runs_and_leaves_nothing_behind(wm_name):
    with ControllerStack(ControllerOptions(sim=True, wm=wm_name, quiet=True)) as stack:
        d = stack.driver
        assert isinstance(d, LocalDriver) and d.sim is not None and stack.rt is d.rt
        assert _exists(wm_name) and _exists(d.sim.name)
        d.rt.request(Request.POWER_UP)
        for _ in range(int(round(0.2 / d.period_s))):
            d.frame()
        assert d.rt.status("updown") != Status.SHUT_DOWN
    assert not _exists(d.sim.name)  # the simulated service stopped, its buffer removed


def test_a_halted_controller_is_released_safe_on_exit(wm_name, caplog):
    with caplog.at_level(logging.INFO, logger="tools.stacks.controller"):
        with ControllerStack(ControllerOptions(sim=True, wm=wm_name, quiet=True)) as stack:
            d = stack.driver
            d.rt.request(Request.HALT)
            for _ in range(4):
                d.frame()
            assert d.rt.halted
        assert not d.rt.halted
    assert "was halted; outputs left safe (0 V, brakes set)" in caplog.text
    assert not _exists(d.sim.name)


def test_an_exception_in_the_frames_still_closes_everything(wm_name):
    with pytest.raises(RuntimeError, match="boom"):
        with ControllerStack(ControllerOptions(sim=True, wm=wm_name, quiet=True)) as stack:
            stack.driver.frame()
            name = stack.driver.sim.name
            raise RuntimeError("boom")
    assert not _exists(name)


def test_a_part_that_fails_to_open_closes_what_was_opened(wm_name, monkeypatch):
    opened = []

    def broken(_rt, _options, sim=None, **_k):
        opened.append(sim.name)
        assert _exists(sim.name)  # the simulator was open
        raise RuntimeError("driver refused")
    monkeypatch.setattr(stacks, "LocalDriver", broken)
    stack = ControllerStack(ControllerOptions(sim=True, wm=wm_name, quiet=True))
    with pytest.raises(RuntimeError, match="driver refused"):
        stack.open()
    assert stack.driver is None and opened and not _exists(opened[0])


def test_the_signal_handlers_come_back_after_the_power_down(wm_name):
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with ControllerStack(ControllerOptions(sim=True, wm=wm_name, quiet=True)) as stack:
        stack.stop_on_signals()
        assert signal.getsignal(signal.SIGTERM) is not before[signal.SIGTERM]
        os.kill(os.getpid(), signal.SIGTERM)  # acted on between frames: the next frame stops
        with pytest.raises(KeyboardInterrupt):
            stack.driver.frame()
        assert stack.driver.stop_signal == signal.SIGTERM
    assert {s: signal.getsignal(s) for s in before} == before


@pytest.mark.parametrize("level", ["info", "error"])
def test_a_usage_mistake_is_one_line_at_any_log_level(capsys, level):
    from tools.cli import main
    assert main(["controller", "halt", "--rearm", "--log-level", level]) == 2
    cap = capsys.readouterr()
    assert cap.err == "pfma controller halt: --rearm belongs to resume\n" and cap.out == ""
    # the verb's log handler is gone with it: no later record goes to a stderr that is closed
    assert not [h for h in logging.getLogger().handlers if h.get_name() == "pfma"]


def test_every_live_driver_stops_between_frames_on_a_taken_signal():
    """The live frame of every driver (one process or one of a distributed controller) checks
    for a SIGINT/SIGTERM that :meth:`ControllerStack.stop_on_signals` took before it waits
    for the service's frame, so the stop comes between two frames (a KeyboardInterrupt inside
    one could leave the world model mid-write and the power-down hung); while closing (the
    power-down's own frames) it does not."""
    from tools.stacks.controller import DistributedDriver, Driver
    d = DistributedDriver.__new__(DistributedDriver)  # no service: the check comes first
    d.stop_signal, d.closing, d.pacer = signal.SIGINT, False, None
    with pytest.raises(KeyboardInterrupt):
        Driver.frame(d)
    d.closing = True
    with pytest.raises(AssertionError):  # past the check: the pacer it would wait on
        Driver.frame(d)


def _stack_options(*argv: str) -> ControllerOptions:
    import argparse

    from tools.cli.controller.arguments import add_parser
    from tools.cli.controller.common import stack_options
    p = argparse.ArgumentParser(prog="pfma")
    add_parser(p.add_subparsers(dest="verb"), "controller")
    return stack_options(p.parse_args(["controller", *argv]))


@pytest.mark.parametrize("argv, run", [((), 2), (("--max-missed-run", "5"), 5), (("--max-missed-run", "0"), 0)])
def test_max_missed_run_reaches_the_runtime_s_frames(wm_name, argv, run):
    opts = _stack_options("--sim", "--wm", wm_name, "-q", *argv)
    with ControllerStack(opts) as stack:
        assert stack.rt.frames.max_missed_run == run
        assert stack.rt.stats()["max_missed_run"] == run


@pytest.mark.parametrize("bad", ["17", "-1", "two"])
def test_a_max_missed_run_outside_a_major_frame_is_a_usage_error(bad, capsys):
    with pytest.raises(SystemExit) as e:
        _stack_options("--sim", "--max-missed-run", bad)
    assert e.value.code == 2
    assert "--max-missed-run" in capsys.readouterr().err
