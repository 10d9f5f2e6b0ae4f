"""FtSensor on the fake MVME400's channel (rack signal ft_sensor), FakeFtController at the far
end of the cable; simulated time, so the rate is exact and deterministic."""

from __future__ import annotations

import pytest

from drivers.serial_ft import FtSensor
from drivers.serial_ft import protocol as P
from fakes.ft_sensor import FakeFtController
from pfma.rack import load_rack

from .conftest import ground_truth_check, safe_load

import drivers.mvme400 as mvme400
import fakes.rack as fakes_rack


@pytest.fixture
def ft_on_mvme400():
    rack = load_rack()
    sig = rack.channel("ft_sensor")
    cfg = rack.board(sig.board)
    fr = fakes_rack.FakeRack.from_config(rack)
    model = FakeFtController(load_fn=safe_load)
    fr[cfg.name].peer(sig.channel).attach(model)
    board = mvme400.Mvme400(fr, cfg.base, name=cfg.name, clock=fr.clock)
    board.init()
    port = board.port(sig.channel, timeout=0.01)
    return model, FtSensor(port, clock=fr.clock), fr.clock


def test_binary_checksum_stream_through_the_mvme400_at_the_line_rate(ft_on_mvme400):
    model, s, clock = ft_on_mvme400
    s.set_mode("binary")
    s.set_checksum(True)
    s.start_stream(rate_hz=80.0)
    got = []
    t0 = clock.now()
    while clock.now() < t0 + 1.0:
        got += s.read_records()
    got += s.stop_stream()
    assert ground_truth_check(model, got) == 0
    st = s.stats()
    assert st.bad_records == 0
    assert 0.95 * P.max_rate_hz("binary", checksum_on=True) <= len(got) <= P.max_rate_hz("binary", checksum_on=True) + 2
    assert st.rate_hz == pytest.approx(P.max_rate_hz("binary", checksum_on=True), rel=0.03)


def test_poll_and_bias_through_the_mvme400(ft_on_mvme400):
    model, s, clock = ft_on_mvme400
    model.set_load((10.0, 2.0, -3.0), (0.5, 0.0, 0.1))
    s.set_mode("binary")
    s.query()
    assert s.poll().force_n == (10.0, 2.0, -3.0)
    s.bias()
    assert s.poll().counts == (0,) * 6
