"""FtSensor against the fake controller over REAL ptys at 19200 baud.

No sleeps: every wait is a bounded wait for data. Wall-clock speed is not asserted
tightly; counts come from the fake's own ground truth.
"""

from __future__ import annotations

import time
import warnings

import pytest

from drivers.serial_ft import protocol as P
from drivers.serial_ft.ftsensor import FtReader, FtSensor
from fakes.pty import PtyDevice
from pfma.errors import ConfigError, LinkError, PfmaTimeoutError

from .conftest import ground_truth_check

pytestmark = pytest.mark.realtime


def read_until(sensor: FtSensor, n: int, timeout_s: float = 3.0) -> list:
    out: list = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        out += sensor.read_records()
    return out


def test_binary_stream_with_checksum_decodes_every_record_at_more_than_80_hz(rig):
    model, dev, sensor = rig("binary", checksum=True)
    sensor.start_stream(rate_hz=80.0)
    got = read_until(sensor, 60)
    got += sensor.stop_stream()
    assert len(got) >= 60
    assert ground_truth_check(model, got) == 0  # none lost, none corrupt
    st = sensor.stats()
    assert st.bad_records == 0 and st.resyncs == 0
    # rate measured by the fake's own clock: records put on the wire per second
    sent = [r for r in model.sent_records]
    fake_rate = (len(sent) - 1) / (sent[-1].t_s - sent[0].t_s)
    assert 80.0 <= fake_rate <= P.max_rate_hz("binary", checksum_on=True) * 1.05
    assert 40.0 < st.rate_hz < 200.0  # plausible, not a timing assertion


def test_binary_without_checksum_reader_polls_with_ctrl_t_at_more_than_80_hz(rig):
    model, dev, sensor = rig("binary", checksum=False)
    reader = FtReader(sensor, rate_hz=80.0, keep=1000).start()
    assert reader.framing == "poll"
    assert reader.wait_records(40, timeout_s=3.0)
    reader.stop()
    got = list(reader.history)
    assert ground_truth_check(model, got) == 0
    assert sensor.stats().bad_records == 0
    # one poll = request + 13 bytes of wire time + a 1.6 ms silence guard: ~105 polls/s on an
    # idle host. The median spacing is robust to scheduling hiccups of a busy CI box.
    gaps = sorted(b.t_s - a.t_s for a, b in zip(got, got[1:]))
    assert gaps[len(gaps) // 2] < 1 / 80.0


def test_binary_stream_without_checksum_warns(rig):
    model, dev, sensor = rig("binary", checksum=False)
    with pytest.warns(RuntimeWarning, match="without checksum"):
        sensor.start_stream(rate_hz=80.0)
    got = read_until(sensor, 10) + sensor.stop_stream()
    assert ground_truth_check(model, got) == 0


def test_ascii_cannot_carry_80_hz_and_says_so(rig):
    model, dev, sensor = rig("ascii")
    with pytest.raises(ConfigError, match=r"ASCII at 19200 baud gives at most 42\.7 records/s, below the 80 Hz"):
        sensor.start_stream(rate_hz=80.0)
    assert not model.streaming
    with pytest.warns(RuntimeWarning, match="42.7 records/s"):
        sensor.start_stream(rate_hz=80.0, on_slow="warn")
    got = read_until(sensor, 15)
    got += sensor.stop_stream()
    assert ground_truth_check(model, got) == 0 and sensor.stats().bad_records == 0
    sent = list(model.sent_records)
    assert (len(sent) - 1) / (sent[-1].t_s - sent[0].t_s) <= P.max_rate_hz("ascii") * 1.05


@pytest.mark.parametrize("mode,checksum", [("binary", True), ("binary", False), ("ascii", False)])
def test_noise_and_dropped_bytes_never_give_a_corrupt_reading_and_are_counted(rig, mode, checksum):
    model, dev, sensor = rig(mode, checksum=checksum)
    L = P.record_bytes(mode, checksum)
    # faults at fixed places in the stream (4 = the "QS\r\n" echo); 8 records apart
    events = [("noise", 4 + L * 5 + 3), ("drop", 4 + L * 13 + 7), ("noise", 4 + L * 21 + 0),
              ("drop", 4 + L * 29 + 0), ("noise", 4 + L * 37 + L - 1)]
    for kind, at in events:
        if kind == "noise":
            model.inject_noise(b"\xaa\x55\x07", after_bytes=at)
        else:
            model.drop_next(2, after_bytes=at)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # ascii rate / binary-no-checksum notices
        sensor.start_stream(rate_hz=10.0)
    got = read_until(sensor, 45 - 2 * len(events), timeout_s=5.0)
    got += sensor.stop_stream()
    lost = ground_truth_check(model, got)  # raises if any reading is corrupt
    st = sensor.stats()
    assert st.bad_records >= len(events) and st.resyncs == len(events)
    assert lost <= 2 * len(events)
    assert model.noise_bytes_sent == 9 and model.bytes_dropped == 4


def test_wire_level_noise_and_stall_from_the_pty_device(rig):
    model, dev, sensor = rig("binary", checksum=True)
    reader = FtReader(sensor, rate_hz=80.0, keep=5000).start()
    assert reader.wait_records(20, 3.0)
    dev.stall(0.2)
    n0 = sensor.stats().records
    assert reader.wait_records(n0 + 20, 3.0)  # resumes after the stall
    dev.inject_noise(b"\x02\x03\x04")  # noise bytes are never a plausible status (0/1)
    n1 = sensor.stats().records
    assert reader.wait_records(n1 + 20, 3.0)
    reader.stop()
    got = list(reader.history)
    ground_truth_check(model, got)
    gaps = [b.t_s - a.t_s for a, b in zip(got, got[1:])]
    assert max(gaps) >= 0.15  # the stall shows as a gap, and age_s grew meanwhile
    assert sensor.stats().resyncs >= 1


def test_stop_stream_handshake_then_commands_work(rig):
    model, dev, sensor = rig("binary", checksum=True)
    sensor.start_stream()
    read_until(sensor, 5)
    sensor.stop_stream()
    assert not model.streaming and not sensor.streaming
    sensor.bias()  # the line editor answers again
    assert len(model.transducer.biases) == 1
    with pytest.raises(LinkError, match="while streaming"):
        sensor.start_stream()
        sensor.bias()
    sensor.stop_stream()


def test_bias_stack_unbias_clear_over_the_line(rig):
    model, dev, sensor = rig("binary", checksum=False, load_fn=None)
    model.set_load((10.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    sensor.query()  # let at least one sample of the load in
    assert sensor.poll().force_n[0] == pytest.approx(10.0)
    sensor.bias()
    r = sensor.poll()
    assert r.force_n == (0.0, 0.0, 0.0) and r.torque_nm == (0.0, 0.0, 0.0)
    model.set_load((15.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    deadline = time.monotonic() + 1.0
    while sensor.poll().force_n[0] != pytest.approx(5.0) and time.monotonic() < deadline:
        pass
    sensor.bias()
    assert sensor.poll().force_n[0] == 0.0
    sensor.unbias()
    assert sensor.poll().force_n[0] == pytest.approx(5.0)
    sensor.clear_bias()
    assert sensor.poll().force_n[0] == pytest.approx(15.0)
    assert model.commands[-3:] == ["SB", "SU", "SZ"]


def test_averaging_command(rig):
    model, dev, sensor = rig("ascii", load_fn=None)
    sensor.set_average(8)
    assert model.transducer.average_n == 8
    sensor.set_average(0)
    assert model.transducer.average_n == 0
    with pytest.raises(ValueError):
        sensor.set_average(-1)


def test_checksum_on_off_and_query(rig):
    model, dev, sensor = rig("binary", checksum=True, load_fn=None)
    model.set_load((1.0, -2.0, 3.0), (0.1, -0.2, 0.3))
    assert model.checksum_on
    sensor.query()
    r = sensor.query()
    assert r.counts == (16, -32, 48, 20, -40, 60) and r.force_n == (1.0, -2.0, 3.0)
    sensor.set_checksum(False)
    assert not model.checksum_on and sensor.query().counts == r.counts
    sensor.set_mode("ascii")
    assert sensor.query().counts == r.counts


def test_ctrl_t_poll_has_no_echo_and_matches_ground_truth(rig):
    model, dev, sensor = rig("binary")
    n_cmds = len(model.commands)
    r = sensor.poll()
    assert r.counts == model.sent_records[-1].counts
    assert len(model.commands) == n_cmds  # Ctrl-T is not a line command
    sensor.set_mode("ascii")
    assert sensor.poll().counts == model.sent_records[-1].counts


def test_silent_controller_times_out_with_a_clear_message():
    class Silent:
        def receive(self, data): pass
        def transmit(self, n): return b""
        def advance(self, dt): pass

    with PtyDevice(Silent()) as dev:
        import serial
        port = serial.serial_for_url(dev.port_name, baudrate=19200, timeout=0.02)
        try:
            s = FtSensor(port, reply_timeout_s=0.1)
            with pytest.raises(PfmaTimeoutError, match="did not answer 'SB' within 0.1 s"):
                s.bias()
            with pytest.raises(PfmaTimeoutError, match="Ctrl-T"):
                s.poll()
        finally:
            port.close()


def test_disconnect_is_a_link_error_and_stops_the_reader(rig):
    model, dev, sensor = rig("binary", checksum=True)
    reader = FtReader(sensor).start()
    assert reader.wait_records(5, 3.0)
    dev.disconnect()
    reader.wait_records(10 ** 9, 3.0)  # returns when the reader records its error
    assert isinstance(reader.error, LinkError)
    reader.stop()
