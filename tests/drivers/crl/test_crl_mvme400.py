"""CrlHandController on the fake MVME400's channel (rack signal crl_hand_controller), with
FakeCrlMaster as the far end of the cable; simulated time, polled port."""

from __future__ import annotations

import pytest

from drivers.crl import CrlHandController
from drivers.crl import crl_codec as codec
from fakes.crl import FakeCrlMaster
from pfma.rack import load_rack

import drivers.mvme400 as mvme400
import fakes.rack as fakes_rack

POLL_S = 0.0005  # under one character time (0.52 ms) at 19200: the 3-deep FIFO never overruns


def test_crl_through_the_fake_mvme400():
    rack = load_rack()
    sig = rack.channel("crl_hand_controller")
    board_cfg = rack.board(sig.board)
    fr = fakes_rack.FakeRack.from_config(rack)
    clock = fr.clock
    fake = FakeCrlMaster()
    fake.set_axes((0.1, 0.2, -0.3, 0.0, 0.5, -1.0))
    fr[board_cfg.name].peer(sig.channel).attach(fake)
    board = mvme400.Mvme400(fr, board_cfg.base, name=board_cfg.name, clock=clock)
    board.init()
    port = board.port(sig.channel, timeout=0)
    drv = CrlHandController(port, clock)

    def run(seconds):
        st = drv.state
        t_end = clock.now() + seconds
        next_update = clock.now()
        while clock.now() < t_end:
            clock.advance(POLL_S)
            port.poll()
            if clock.now() >= next_update:
                st = drv.update()
                next_update += codec.FRAME_PERIOD_S
        return st

    st = run(0.1)
    assert st.valid and not st.deadman
    assert st.axes == pytest.approx((0.1, 0.2, -0.3, 0.0, 0.5, -1.0), abs=1e-4)
    fake.deadman = True
    assert run(0.06).active
    drv.send_force((0.0, 0.0, 15.0), (0.0, 0.0, 0.0))
    drv.send_force((0.0, 0.0, 15.0), (0.0, 0.0, 0.0))
    run(0.02)
    assert fake.last_force is not None and fake.last_force.force_n[2] == pytest.approx(15.0, abs=2e-3)
    assert port.stats.overruns == 0 and drv.link_stats()["frames_bad"] == 0
    fake.stall(0.2)
    st = run(0.1)
    assert st.fault and not st.deadman and drv.link_stats()["watchdog_trips"] == 1
