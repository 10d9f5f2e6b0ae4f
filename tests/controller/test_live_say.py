"""The live controller says what happens as it happens (issue 29 item 3):
:class:`controller.messages.LivePrinter` - one line per message, System Up/Down's state
changes and every WARNING and ERROR, at most LIVE_PER_SECOND lines a second then one
"... K more" line, at most LIVE_PER_FLUSH lines per flush (after a frame); a fake clock."""

from __future__ import annotations

import re

from controller.messages import (
    LIVE_PER_FLUSH, LIVE_PER_SECOND, Level, LivePrinter, MessageBoard, is_live_worthy, live_line,
)


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _board_and_printer(**kw):
    lines: list[str] = []
    clock = FakeClock()
    board = MessageBoard()
    say = LivePrinter(lines.append, clock, **kw)
    board.listeners.append(say)
    return board, say, lines, clock


def test_one_line_per_message_with_time_source_level_and_text():
    board = MessageBoard()
    m = board.post("servo", Level.ERROR, "fault 18: elbow_pitch following error\nlikely DAC bit", 1.25, 400)
    line = live_line(m)
    assert "\n" not in line
    assert line.split() [:4] == ["1.250", "s", "servo", "ERROR"]
    assert line.endswith("fault 18: elbow_pitch following error | likely DAC bit")


def test_what_is_said_warnings_errors_and_the_up_down_state_changes_only():
    board = MessageBoard()
    said = [m.text for m in (
        board.post("servo", Level.WARNING, "w", 0, 0),
        board.post("daq", Level.ERROR, "e", 0, 0),
        board.post("updown", Level.INFO, "SHUT DOWN -> INITIALIZATION IN PROGRESS (row 11: INIT TO START)", 0, 0),
        board.post("joint", Level.INFO, "SHUT DOWN -> INITIALIZATION IN PROGRESS (row 11: ...)", 0, 0),
        board.post("updown", Level.INFO, "request 3: POWER UP -> ACCEPTED", 0, 0),
        board.post("updown", Level.DEBUG, "command X: SHUT DOWN", 0, 0),
    ) if is_live_worthy(m)]
    assert said == ["w", "e", "SHUT DOWN -> INITIALIZATION IN PROGRESS (row 11: INIT TO START)"]


def test_nothing_is_written_in_the_frame_only_at_flush_and_bounded_per_flush():
    board, say, lines, clock = _board_and_printer()
    for i in range(LIVE_PER_FLUSH + 2):
        board.post("servo", Level.WARNING, f"w{i}", 0, i)
    assert lines == []  # posting (in the frame) only queues
    say.flush()
    assert [ln.split()[-1] for ln in lines] == [f"w{i}" for i in range(LIVE_PER_FLUSH)]
    say.flush()
    assert len(lines) == LIVE_PER_FLUSH + 2 and say.said == LIVE_PER_FLUSH + 2


def test_rate_limit_then_one_more_line_when_the_second_is_over():
    board, say, lines, clock = _board_and_printer()
    n = LIVE_PER_SECOND + 25
    for i in range(n):
        board.post("joint", Level.ERROR, f"e{i}", 0, i)
        say.flush()
        clock.t += 0.01  # 100 flushes a second
    assert len(lines) == LIVE_PER_SECOND  # the rest counted, not said
    assert [ln.split()[-1] for ln in lines] == [f"e{i}" for i in range(LIVE_PER_SECOND)]
    clock.t += 1.0
    board.post("joint", Level.ERROR, "after", 0, n)
    say.flush()
    assert lines[LIVE_PER_SECOND] == f"... {n - LIVE_PER_SECOND} more messages not shown (at most {LIVE_PER_SECOND} lines a second)"
    assert lines[-1].split()[-1] == "after" and say.held == n - LIVE_PER_SECOND


def test_up_down_changes_and_the_first_cause_are_said_over_the_rate():
    """A cascade's last line (System Up/Down entering ERROR) is the one a person needs; seen
    live: it fell under the limit behind the layers' lines."""
    board, say, lines, clock = _board_and_printer()
    for i in range(LIVE_PER_SECOND):
        board.post("joint", Level.ERROR, f"e{i}", 0, i)
    board.post("servo", Level.ERROR, "over", 0, 10)
    board.post("runtime", Level.WARNING, "first cause: daq: fault 1: x", 0, 10)
    board.post("updown", Level.ERROR, "START UP COMPLETE -> ERROR (row 1: subordinate in ERROR (X))", 0, 11)
    while say.queue:
        say.flush()
    assert len(lines) == LIVE_PER_SECOND + 2 and say.held == 1
    assert lines[-2].endswith("first cause: daq: fault 1: x")
    assert lines[-1].endswith("START UP COMPLETE -> ERROR (row 1: subordinate in ERROR (X))")


def test_drain_at_exit_says_the_queue_within_the_rate_and_counts_the_rest():
    board, say, lines, clock = _board_and_printer(keep=20)
    for i in range(30):  # 10 more than the queue keeps
        board.post("servo", Level.WARNING, f"w{i}", 0, i)
    say.drain()
    more = f"more messages not shown (at most {LIVE_PER_SECOND} lines a second)"
    # the 10 the queue could not keep were the oldest: counted first; then the rate's worth; then the rest
    assert lines[0] == f"... 10 {more}"
    assert [ln.split()[-1] for ln in lines[1:1 + LIVE_PER_SECOND]] == [f"w{i}" for i in range(10, 10 + LIVE_PER_SECOND)]
    assert lines[-1] == f"... {20 - LIVE_PER_SECOND} {more}"
    assert len(lines) == LIVE_PER_SECOND + 2 and say.held == 30 - LIVE_PER_SECOND


def test_an_idle_flush_does_not_read_the_clock():
    reads = []
    say = LivePrinter(print, lambda: reads.append(1) or 0.0)
    for _ in range(1000):
        say.flush()
    assert reads == []


# --- `pfma controller --sim` with a fault: said as it happens, the first cause at exit ------------
def test_sim_controller_with_a_fault_says_the_changes_and_errors_then_the_first_cause_at_exit(capsys):
    from tools.cli import main
    rc = main(["controller", "--sim", "--wm", "none", "--power-up", "--duration", "1.2",
               "--sim-fault", "resolver-los:shoulder_pitch_angle", "--sim-fault-at", "0.8", "--messages", "3"])
    out = capsys.readouterr().out
    assert rc == 0
    lines = out.splitlines()
    live = lines[:lines.index("--- last 3 messages ---")]
    # System Up/Down's state changes, as they happen, in order
    ups = [l for l in live if " updown " in l and "(row " in l]
    assert [l.split("INFO")[1].split("(row")[0].strip() for l in ups[:2]] == [
        "SHUT DOWN -> INITIALIZATION IN PROGRESS", "INITIALIZATION IN PROGRESS -> WAITING FOR SUBORDINATE TO INIT"]
    assert any("START UP -> START UP COMPLETE" in l for l in ups)
    injected = live.index("pfma controller: simulated fault injected: resolver-los:shoulder_pitch_angle")
    errors = [l for l in live[injected:] if " ERROR " in l]
    assert "shoulder_pitch resolver" in errors[0] and " daq " in errors[0]
    assert any("subordinate in ERROR" in l for l in errors)
    # at exit: the first cause is the root, though the last 3 messages no longer hold it
    cause = next(l for l in lines if l.startswith("first cause of the ERROR: "))
    assert cause.startswith("first cause of the ERROR: daq: hardware check: resolver: shoulder_pitch")
    assert lines[lines.index(cause) - 1].startswith("UPDN=ERROR")  # the summary at exit
    assert all("shoulder_pitch" not in l for l in lines[lines.index("--- last 3 messages ---"):])


def test_quiet_says_nothing_as_it_happens_but_keeps_the_summary(capsys):
    from tools.cli import main
    assert main(["controller", "--sim", "--wm", "none", "--power-up", "--duration", "0.4", "-q",
                 "--messages", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("UPDN=START UP COMPLETE")
    assert lines[1] == "first cause: none (no ERROR episode)" and lines[2] == "--- last 2 messages ---"


def test_a_sim_fault_without_sim_or_with_a_bad_spec_is_one_line_and_exit_2(capsys):
    from tools.cli import main
    assert main(["controller", "--sim-fault", "resolver-los:shoulder_pitch_angle"]) == 2
    assert main(["controller", "--sim", "--sim-fault", "resolver-los:nose"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and err[0].startswith("pfma controller: --sim-fault needs --sim")
    assert err[1].startswith("pfma controller: --sim-fault ") and "Traceback" not in "".join(err)


def test_motion_settings_and_the_force_state_are_said_by_name(capsys):
    """``pfma controller`` printed ``cart.mode=1, cart.hc_source=0`` and ``force state 2``
    (issue 29): now the names of the variables' enumerations, the numbers beside them."""
    from tools.cli import main
    assert main(["controller", "--sim", "--wm", "none", "--power-up", "--duration", "0.3", "--teleop", "crl",
                 "--impedance", "on", "-q", "--messages", "0"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == ("motion settings: cart.mode=TELEOP (1), cart.hc_source=CRL (1), cart.hc_frame=WORLD (0), "
                        "force.enable=True")
    summary = next(ln for ln in lines if ln.startswith("Cartesian command "))
    assert re.search(r" force (OFF \(0\)|ZEROING \(1\)|IMPEDANCE \(2\)) F \(", summary), summary
