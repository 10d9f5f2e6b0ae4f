"""pfma.log: one logging configuration, the terse line an operator always saw, the journal's priorities."""

from __future__ import annotations

import io
import logging
import os
import tempfile

import pytest

from pfma import log


@pytest.fixture(autouse=True)
def _restore_root_logger():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def test_terse_line_is_prog_colon_message_and_the_level_filters():
    out = io.StringIO()
    log.configure("pfma serve", "info", stream=out)
    logging.getLogger("ioservice.test").debug("not shown")
    logging.getLogger("ioservice.test").warning("trip: joint 2 does not follow")
    assert out.getvalue() == "pfma serve: trip: joint 2 does not follow\n"


def test_configure_twice_replaces_the_handler():
    out1, out2 = io.StringIO(), io.StringIO()
    log.configure("a", "info", stream=out1)
    log.configure("b", "debug", stream=out2)
    logging.getLogger("x").debug("once")
    assert out1.getvalue() == ""
    assert out2.getvalue() == "b: once\n"


def test_the_journal_gets_sd_daemon_priorities(monkeypatch):
    with tempfile.TemporaryFile("w+") as f:
        st = os.fstat(f.fileno())
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        log.configure("pfma serve", "debug", stream=f)
        logging.getLogger("x").error("bus lost")
        logging.getLogger("x").info("frames again")
        f.seek(0)
        assert f.read() == "<3>pfma serve: bus lost\n<6>pfma serve: frames again\n"


def test_an_unknown_level_is_one_clear_message():
    with pytest.raises(ValueError, match="--log-level 'loud': one of debug, info, warning, error"):
        log.level_number("loud")


def test_the_default_handler_follows_sys_stderr_so_a_closed_capture_is_never_written(monkeypatch, capsys):
    first = io.StringIO()
    monkeypatch.setattr("sys.stderr", first)
    log.configure("pfma serve", "info")
    first.close()  # a test's capture, gone
    second = io.StringIO()
    monkeypatch.setattr("sys.stderr", second)
    logging.getLogger("x").warning("still said")
    assert second.getvalue() == "pfma serve: still said\n"


def test_for_process_undoes_itself():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    modbus_level = logging.getLogger("pymodbus").level
    with log.for_process("pfma serve", "warning", hush=("pymodbus",)):
        assert logging.getLogger("pymodbus").level == logging.CRITICAL
        assert root.level == logging.WARNING
    assert root.handlers == handlers and root.level == level
    assert logging.getLogger("pymodbus").level == modbus_level
