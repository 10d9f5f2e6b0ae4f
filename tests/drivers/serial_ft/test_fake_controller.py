"""The fake controller as a pure byte-stream state machine (simulated time, no pty)."""

from __future__ import annotations

from drivers.serial_ft import protocol as P
from fakes.ft_sensor import FakeFtController, FtTransducer
from pfma.clock import SimClock


class Wire:
    """Moves bytes out of the model at 19200 baud in simulated time."""

    def __init__(self, model: FakeFtController, baud: int = 19200) -> None:
        self.model, self.clock, self.byte_s = model, SimClock(), 10 / baud

    def run(self, seconds: float, step_s: float = 0.001) -> bytes:
        out = bytearray()
        credit = 0.0
        for _ in range(round(seconds / step_s)):
            self.clock.advance(step_s)
            self.model.advance(step_s)
            credit += step_s / self.byte_s
            data = self.model.transmit(int(credit))
            credit = credit - len(data) if data else min(credit, 1.0)
            out += data
        return bytes(out)


def test_line_editor_echoes_and_prompts():
    m = FakeFtController()
    w = Wire(m)
    m.receive(b"SB\r")
    assert w.run(0.01) == b"SB\r\n\r\n>"
    m.receive(b"XX\r")
    assert w.run(0.05).startswith(b"XX\r\nERROR")


def test_ctrl_t_gives_one_record_without_echo_or_prompt():
    m = FakeFtController()
    m.set_load((1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
    m.receive(b"CD B\r")
    w = Wire(m)
    w.run(0.02)
    m.advance(0.01)  # take a sample of the new load
    m.receive(P.CTRL_T)
    out = w.run(0.02)
    assert P.decode_binary(out) == (0, (16, 32, 48, 20, 40, 60)) and not m.commands[1:]


def test_stream_is_paced_by_the_line_and_any_byte_stops_it():
    m = FakeFtController(sample_rate_hz=150.0)
    m.receive(b"CD B\r")
    w = Wire(m)
    w.run(0.01)
    m.receive(b"QS\r")
    out = w.run(1.0)
    n = (len(out) - 4) / 13
    assert 140 <= n <= 148  # 150 Hz internal, 147.7 records/s line limit
    assert m.skipped_samples >= 1  # the line, not the controller, was the limit
    m.receive(b"\r")
    tail = w.run(0.05)
    assert tail.endswith(P.STOP_PROMPT) and not m.streaming


def test_ascii_stream_rate_is_what_the_line_allows():
    m = FakeFtController()
    w = Wire(m)
    m.receive(b"QS\r")
    out = w.run(1.0)
    assert 40 <= out.count(b"\r\n") - 1 <= 43


def test_bias_stack_is_three_deep_and_subtracts_the_top():
    t = FtTransducer()
    for f in (1.0, 2.0, 3.0, 4.0):
        t.set_load((f, 0, 0), (0, 0, 0))
        t.sample(0.0)
        t.bias()
    assert [b[0] for b in t.biases] == [32, 48, 64]  # oldest dropped
    t.set_load((5.0, 0, 0), (0, 0, 0))
    t.sample(0.0)
    assert t.reading()[1][0] == 80 - 64
    t.unbias()
    assert t.reading()[1][0] == 80 - 48
    t.clear_bias()
    assert t.reading()[1][0] == 80


def test_moving_average_over_n_samples():
    t = FtTransducer()
    t.set_average(4)
    for f in (0.0, 0.0, 0.0, 0.0):
        t.set_load((f, 0, 0), (0, 0, 0))
        t.sample(0.0)
    t.set_load((10.0, 0, 0), (0, 0, 0))
    t.sample(0.0)
    assert t.reading()[1][0] == 40  # (0+0+0+160)/4
    t.set_average(0)
    assert t.reading()[1][0] == 160


def test_overload_sets_status_one_and_counts_saturate():
    t = FtTransducer()
    t.set_load((200.0, 0, 0), (0, 0, 0))  # > 110 % of 133 N
    t.sample(0.0)
    assert t.reading()[0] == 1


def test_scheduled_noise_and_drop_faults_are_deterministic():
    m = FakeFtController()
    m.receive(b"CD B\r")
    w = Wire(m)
    w.run(0.01)
    m.inject_noise(b"\xaa", after_bytes=2)
    m.drop_next(3, after_bytes=6)
    m.receive(P.CTRL_T)
    out = w.run(0.02)
    rec = P.encode_binary(*m.transducer.reading())
    assert out == rec[:2] + b"\xaa" + rec[2:6] + rec[9:]
    assert m.noise_bytes_sent == 1 and m.bytes_dropped == 3


def test_stall_and_disconnect():
    m = FakeFtController()
    w = Wire(m)
    m.stall(0.1)
    m.receive(b"SZ\r")
    assert w.run(0.05) == b""
    assert w.run(0.1) == b"SZ\r\n\r\n>"
    m.disconnect()
    m.receive(b"SZ\r")
    assert w.run(0.05) == b""


def test_ground_truth_history_is_bounded(monkeypatch):
    """A simulated rack runs for hours: the fake keeps the newest HISTORY_KEEP records of
    ground truth, not every record since start (memory did grow ~250 MB an hour)."""
    import fakes.ft_sensor as ft
    monkeypatch.setattr(ft, "HISTORY_KEEP", 50)
    m = FakeFtController()
    w = Wire(m)
    m.receive(b"CD B\r")
    w.run(0.02)
    m.receive(b"QS\r")
    w.run(2.0)  # ~270 records on the line at 19200 baud
    assert m.records_sent > 200
    assert len(m.sent_records) == 50
    assert m.sent_records[-1].index == m.records_sent - 1  # the newest kept
