"""A board whose transactions failed goes back to OK in ``board_status`` once it answers again
(its error count stays), for the output and serial boards as for the input boards. Simulated
time, the register-level fakes' ``no_answer`` fault (a bus error on every access)."""

from __future__ import annotations

import pytest

from bit3.layout import BOARD_FAULT, BOARD_INIT, BOARD_OK


def _status(rig, board: str) -> tuple[int, int]:
    slot = rig.layout.slot("board", board)
    v = rig.reader.read_inputs()
    return int(v["board_status"][slot]), int(v["board_errors"][slot])


@pytest.mark.parametrize("board", ["dac", "sio", "rtd1", "adc"])
def test_a_board_that_answers_again_is_ok_again(rig, board):
    rig.run_frames(20)
    assert _status(rig, board) == (BOARD_OK | BOARD_INIT, 0)
    fake = rig.world.bus[board]
    fake.inject("no_answer")
    rig.run_frames(8)  # every board is touched within 8 frames (the PIO every 8th)
    status, errors = _status(rig, board)
    assert status & BOARD_FAULT and errors > 0, (board, status, errors)
    fake.clear("no_answer")
    rig.run_frames(8)
    status, errors_after = _status(rig, board)
    assert status == BOARD_OK | BOARD_INIT, (board, status)
    assert errors_after >= errors  # the count of what happened stays
