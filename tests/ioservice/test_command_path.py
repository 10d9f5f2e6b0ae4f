"""The command path: the service obeys only fresh commands, within their limits, from the
claim holder; everything else is refused or forced to 0 V, with a message and a counter.

Simulated time throughout (``SimRig``): a "controller" writes commands right before each
service frame, so in normal operation the command's inputs are one frame old.
"""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bit3.layout import CMD_ABSENT, CMD_FOREIGN, CMD_REFUSED, CMD_STALE, ServiceState
from ioservice.service import (
    DAC_CLIPPED, DAC_FORCED_SAFE, FAULT_COMMAND, FAULT_FOREIGN, FAULT_NONE, FAULT_WATCHDOG, IoService,
)
from bit3.buffer import Bit3Buffer
from sim.rig import SimRig
from pfma.errors import ConfigError
from pfma.rack import CommandPolicy, load_rack

P = 1 / 320
LIMITS = (5.0, 5.0, 5.0, 2.5, 2.5, 2.5, 0.0)
#: DAC channels of the default rack: rates 0-5, gripper 6, current limits 7-13
RATE_CH = list(range(6))


class Ctl:
    """A controller that writes before each service frame from ``self.cmd`` (kwargs of
    ``write_commands``); ``self.skip`` frames are not written (a stalled controller)."""

    def __init__(self, rig, **cmd) -> None:
        self.rig = rig
        self.client = rig.controller()
        self.cmd = {"joint_rate_rad_s": [0.0] * 6, "current_limit_a": list(LIMITS), "arm_request": 1}
        self.cmd.update(cmd)
        self.frames_old = None  # None: open-loop stamping (newest frame); else inputs_frame = newest - n
        self.enabled = True
        rig.on_frame.append(self)

    def __call__(self, info) -> None:
        if not self.enabled:
            return
        extra = {}
        if self.frames_old is not None:
            extra["inputs_frame"] = max(0, info.index - 1 - self.frames_old)
        self.client.write_commands(**self.cmd, **extra)


def armed(rig, **cmd) -> Ctl:
    ctl = Ctl(rig, **cmd)
    rig.run(0.05)
    assert rig.reader.read_inputs().service_state == ServiceState.ARMED
    return ctl


def texts(rig) -> list[str]:
    return [m.text for m in rig.reader.messages()]


def volts(rig) -> np.ndarray:
    return np.asarray(rig.world.bus["dac"].output_volts_all(), dtype=float)


def test_an_absurd_rate_is_refused_not_clipped(rig):
    ctl = armed(rig)
    ctl.cmd["joint_rate_rad_s"] = [0.0, 0.0, 1e9, 0.0, 0.0, 0.0]
    rig.run(0.02)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.SAFE  # refused: outputs safe, not saturated and obeyed
    assert s.fault_code == FAULT_COMMAND and s.refused_commands == 1
    assert s.command_status & CMD_REFUSED
    assert np.all(volts(rig) == 0.0)
    msg = [t for t in texts(rig) if t.startswith("refused")]
    assert msg == ["refused elbow_pitch_command=1e+09 rad/s, limit +-0.5"]


@pytest.mark.parametrize("field,value,needle", [
    ("joint_rate_rad_s", [0, 0, 0, 0, 0, math.nan], "wrist_roll_command=nan"),
    ("joint_rate_rad_s", [math.inf, 0, 0, 0, 0, 0], "shoulder_pitch_command=inf"),
    ("current_limit_a", [0, 0, -3.0, 0, 0, 0, 0], "elbow_pitch_current_limit=-3 A, limit 0..10"),
    ("current_limit_a", [0, 0, 0, 5.2, 0, 0, 0], "wrist_yaw_current_limit=5.2 A, limit 0..5"),
    ("gripper", 11.0, "gripper_command=11 V, limit +-10"),
])
def test_nan_inf_and_beyond_limit_values_are_refused_with_field_value_and_limit(rig, field, value, needle):
    ctl = armed(rig)
    # a NaN scribbled straight into the command record (write_commands itself refuses NaN)
    ctl.client.command[field] = value
    ctl.enabled = False
    ctl.client.publish_commands()
    rig.run_frames(1)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.SAFE and s.refused_commands == 1
    assert np.all(volts(rig) == 0.0)
    assert any(needle in t for t in texts(rig)), texts(rig)


def test_within_the_margin_a_command_is_saturated_with_its_status_bit_and_obeyed(rig):
    ctl = armed(rig)
    ctl.cmd["joint_rate_rad_s"] = [0.405, 0, 0, 0, 0, 0]  # limit 0.4 rad/s, margin 2 %
    ctl.cmd["current_limit_a"] = [5.0, 5.0, -0.1, 2.5, 2.5, 2.5, 0.0]  # -0.1 A: within 2 % of 10 A
    rig.run(0.1)  # the envelope's slew limit ramps 0 -> full scale in 50 ms (8 rad/s^2)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.ARMED and s.refused_commands == 0
    assert s.dac_status[0] == DAC_CLIPPED and s.dac_volts[0] == pytest.approx(10.0, abs=0.01)
    assert s.dac_status[9] == DAC_CLIPPED and s.dac_volts[9] == 0.0  # a current limit below 0: 0 V


def test_a_rate_from_old_inputs_drives_0_v_and_says_how_old(rig):
    ctl = armed(rig)
    ctl.cmd["joint_rate_rad_s"] = [0.1, 0, 0, 0, 0, 0]
    ctl.frames_old = 0  # closed loop: the controller names the inputs it used
    rig.run_frames(8)  # the slew limit ramps 0 -> 0.1 rad/s in 4 frames
    s = rig.reader.read_inputs()
    assert s.command_input_age_frames == 1 and not s.command_status & CMD_STALE
    assert volts(rig)[0] == pytest.approx(0.1 / 0.04, abs=0.01)
    ctl.frames_old = 4  # computed from inputs 5 frames old at the service: beyond 4
    rig.run_frames(3)
    s = rig.reader.read_inputs()
    assert s.command_status & CMD_STALE and s.command_input_age_frames == 5
    assert s.stale_commands == 3 and s.service_state == ServiceState.ARMED
    assert np.all(volts(rig)[RATE_CH] == 0.0) and s.dac_status[0] == DAC_FORCED_SAFE
    assert volts(rig)[7] == pytest.approx(5.0, abs=0.01)  # current limits stay: brakes stay off
    assert sum("cmd inputs 5 fr old > 4" in t for t in texts(rig)) == 1  # one message per episode
    ctl.frames_old = 0
    rig.run_frames(6)  # fresh again: from the 0 V it drove, the slew limit ramps in 4 frames
    assert volts(rig)[0] == pytest.approx(0.1 / 0.04, abs=0.01)


def test_a_keep_alive_does_not_refresh_a_closed_loop_rate(rig):
    ctl = armed(rig)
    ctl.cmd["joint_rate_rad_s"] = [0.1, 0, 0, 0, 0, 0]
    ctl.frames_old = 0
    rig.run_frames(2)
    ctl.enabled = False  # the heartbeat goes on, the rate is not recomputed
    rig.on_frame.append(lambda info: ctl.client.publish_commands())
    rig.run_frames(5)
    s = rig.reader.read_inputs()
    assert s.command_status & CMD_STALE and volts(rig)[0] == 0.0
    assert s.service_state == ServiceState.ARMED  # the heartbeat is fresh: not a watchdog trip


def test_a_second_writer_is_refused_not_obeyed(rig):
    ctl = armed(rig)
    ctl.enabled = False
    rogue = Bit3Buffer.attach(rig.name, readonly=False, layout=rig.layout)
    try:
        body = ctl.client.command.copy()
        body["joint_rate_rad_s"] = [0.3, 0, 0, 0, 0, 0]
        body["heartbeat"] += 1
        body["writer_pid"] = 4242
        rogue.lock("commands").write(memoryview(body.tobytes()))
        rig.run_frames(1)
        s = rig.reader.read_inputs()
        assert s.service_state == ServiceState.SAFE and s.fault_code == FAULT_FOREIGN
        assert s.foreign_writes == 1 and s.command_status & CMD_FOREIGN
        assert np.all(volts(rig) == 0.0)
        assert any("refused write by pid 4242" in t for t in texts(rig)), texts(rig)
        # a forged token with the right pid is refused too
        body["writer_pid"] = ctl.client.command["writer_pid"]
        body["writer_token"] = 12345
        body["heartbeat"] += 1
        rogue.lock("commands").write(memoryview(body.tobytes()))
        rig.run_frames(1)
        assert rig.reader.read_inputs().foreign_writes == 2
    finally:
        rogue.close()


def test_fault_flags_are_cleared_by_a_successful_re_arm(rig):
    ctl = armed(rig)
    ctl.enabled = False
    rig.run(0.03)  # the heartbeat stops: watchdog
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.FAULT and s.watchdog_tripped and s.fault_code == FAULT_WATCHDOG
    ctl.cmd["rearm_counter"] = 1
    ctl.enabled = True
    rig.run(0.03)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.ARMED
    assert s.fault_code == FAULT_NONE and not s.watchdog_tripped


def test_a_stuck_odd_command_seqlock_costs_one_bounded_read_per_frame(rig):
    ctl = armed(rig)
    ctl.enabled = False
    seq = rig.buf.lock("commands")._seq
    seq[0] = seq[0] + 1  # the writer died between "begin" and "end"
    f0 = rig.reader.read_inputs().frame
    rig.run_frames(64)  # simulated time: a 100 ms wait per frame would take 6.4 s here
    s = rig.reader.read_inputs()
    assert s.frame == f0 + 64  # every frame published
    assert s.absent_commands == 64 and s.command_status & CMD_ABSENT
    assert s.service_state == ServiceState.FAULT and s.watchdog_tripped  # the watchdog acted
    assert sum("no stable copy" in t for t in texts(rig)) == 1  # one message for the episode


def test_an_input_age_beyond_the_watchdog_is_refused_at_start(rig):
    rack = load_rack()
    rack.commands = CommandPolicy(max_input_age_frames=6)  # 18.75 ms > 15 ms
    buf = Bit3Buffer.create(rig.name + "x", rig.layout)
    try:
        with pytest.raises(ConfigError, match="exceeds the 15 ms command watchdog"):
            IoService(rack, rig.world.bus, buf, rig.tclock)
    finally:
        buf.close(unlink=True)


def test_a_host_stall_is_detected_and_named_as_the_cause_of_the_trip(rig):
    ctl = armed(rig)
    ctl.frames_old = 0
    stalled = []

    def stall(info):  # after a service frame the machine freezes for 60 ms; the service
        if not stalled:  # wakes first and finds the heartbeat it saw last 60 ms old
            stalled.append(info.index)
            rig.clock.advance(0.060)
            ctl.enabled = False
        else:
            ctl.enabled = True
    rig.after_frame.append(stall)
    rig.run(0.05)
    s = rig.reader.read_inputs()
    assert s.host_stall_s == pytest.approx(0.060, abs=0.004)
    t = texts(rig)
    assert any(x.startswith("host stall: service did not run for 6") for x in t), t
    trip = [x for x in t if "stale heartbeat" in x]
    assert trip and "(stall 6" in trip[0], t


# ------------------------------------------------------------------------------ fuzzing

FIELDS = ("joint_rate_rad_s", "current_limit_a", "gripper")
_num = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                 st.floats(min_value=-12, max_value=12), st.just(0.0))
_write = st.one_of(
    st.tuples(st.just("field"), st.sampled_from(FIELDS), st.integers(0, 6), _num),
    st.tuples(st.just("torn"), st.just(""), st.integers(0, 0), st.just(0.0)),
    st.tuples(st.just("rogue"), st.just(""), st.integers(0, 0), st.floats(-1, 1)),
    st.tuples(st.just("rearm"), st.just(""), st.integers(0, 0), st.just(0.0)),
)


@settings(derandomize=True, max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.lists(_write, min_size=1, max_size=40))
def test_fuzzed_command_areas_never_drive_a_channel_beyond_its_limit(writes):
    rig = SimRig(prefix="pfma-fuzz-")
    rogue = Bit3Buffer.attach(rig.name, readonly=False, layout=rig.layout)
    try:
        ctl = armed(rig)
        ctl.enabled = False
        svc = rig.svc
        seq = rig.buf.lock("commands")._seq
        rearm = 0
        for kind, field, i, x in writes:
            rec = ctl.client.command
            if kind == "field":
                if field == "gripper":
                    rec["gripper"] = x
                else:
                    rec[field][i % rec[field].shape[0]] = x
                ctl.client.publish_commands()
            elif kind == "torn":
                seq[0] = seq[0] | 1  # left odd until the next good write
            elif kind == "rogue":
                body = rec.copy()
                body["joint_rate_rad_s"][0] = x
                body["heartbeat"] += 1
                body["writer_pid"] = 99999
                rogue.lock("commands").write(memoryview(body.tobytes()))
            else:
                rearm += 1
                rec["joint_rate_rad_s"] = 0.0
                rec["rearm_counter"] = rearm
                ctl.client.publish_commands()
            rig.run_frames(1)
            v = volts(rig)
            for ch in range(svc._dac_n):  # never beyond the configured limit, in volts
                assert abs(v[ch]) <= svc._dac_sat_v[ch] + 1e-3, (ch, v[ch])
                if svc._dac_is_limit[ch]:
                    assert v[ch] >= 0.0
        s = rig.reader.read_inputs()
        refusals = [m for m in rig.reader.messages() if m.text.startswith(("refused", "arm refused"))]
        assert len(refusals) == s.refused_commands == svc.guard.refusals  # every refusal is a message
    finally:
        rogue.close()
        rig.close()


def test_a_modbus_master_can_neither_arm_nor_move_the_arm(rig):
    """issue 28 item 6: the Modbus export (``pfma serve --modbus-writes``), a hostile master
    on loopback TCP: arming, a re-arm counter, current limits and a rate are refused with
    exception 2 (ILLEGAL_DATA_ADDRESS), the service stays SAFE at 0 V and the arm does not
    move; the one request it takes, a camera route from the route table, is applied."""
    from pymodbus.client import ModbusTcpClient

    from tools.modbus_export import ModbusExport, map_row, register_map
    ROWS = register_map(rig.layout)
    DT = ModbusTcpClient.DATATYPE
    rig.run_frames(4)  # the service has seen the (still empty) command area
    angle0 = float(rig.reader.read_inputs().shoulder_pitch_angle)
    with ModbusExport(rig.name, port=0, allow_writes=True, layout=rig.layout) as ex:
        c = ModbusTcpClient("127.0.0.1", port=ex.port, timeout=2, retries=0)
        assert c.connect()
        try:
            def write(field, values, dt):
                row = map_row(ROWS, field, "holding")
                regs = [r for v in values for r in c.convert_to_registers(v, dt)]
                return c.write_registers(row.address, regs, device_id=1)
            for rr in (write("current_limit_a", list(LIMITS), DT.FLOAT64),
                       write("rearm_counter", [1], DT.UINT32),
                       c.write_register(map_row(ROWS, "arm_request", "holding").address, 0x0100, device_id=1),
                       write("joint_rate_rad_s", [0.4, 0, 0, 0, 0, 0], DT.FLOAT64)):
                assert rr.isError() and rr.exception_code == 2
            assert not write("matrix_route", [0x0009], DT.UINT16).isError()  # a route request
            hb = map_row(ROWS, "heartbeat", "holding")
            for _ in range(64):  # keep-alives for 0.2 s: the heartbeat is fresh, still no arming
                assert not c.write_registers(hb.address, [0, 0, 0, 1], device_id=1).isError()
                rig.run_frames(1)
        finally:
            c.close()
        assert ex.refused == 4 and ex.writes == 65
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.SAFE and s.refused_commands == 0
    assert np.all(volts(rig) == 0.0)
    assert float(s.shoulder_pitch_angle) == pytest.approx(angle0, abs=1e-6)
    assert s.matrix_route == 0x0009  # the route request was applied by the service


def test_the_input_age_can_be_set_per_service_and_is_checked_against_the_watchdog(rig):
    buf = Bit3Buffer.create(rig.name + "y", rig.layout)
    try:
        svc = IoService(rig.rack, rig.world.bus, buf, rig.tclock, max_input_age_frames=2)
        assert svc.policy.max_input_age_frames == 2 and rig.svc.policy.max_input_age_frames == 4
        svc.stop()
        for bad in (0, 5, 2.5, True):
            with pytest.raises(ConfigError):
                IoService(rig.rack, rig.world.bus, buf, rig.tclock, max_input_age_frames=bad, owner="x")
    finally:
        buf.close(unlink=True)


def test_pfma_stats_shows_what_the_service_made_of_the_commands(rig):
    from tools.cli import stats as stats_cli
    ctl = armed(rig)
    ctl.frames_old = 4  # 5 frames old at the service
    rig.run_frames(3)
    ctl.frames_old = None
    ctl.cmd["joint_rate_rad_s"] = [0.0, 0.0, 1e9, 0.0, 0.0, 0.0]
    rig.run_frames(1)
    cm = stats_cli.collect(rig.reader)["commands"]
    assert cm["stale_frames"] == 3 and cm["refused"] == 1 and "refused" in cm["status"]
    assert cm["foreign_writes"] == 0 and not cm["watchdog_tripped"]


def test_a_long_frame_of_the_service_itself_is_not_called_a_host_stall(rig, monkeypatch):
    """Only time in which the service could not run is a host stall: a frame whose own work
    takes 12 ms (a slow bus) is an overrun, not a stall of the host."""
    armed(rig)
    slow = rig.svc.rtd.run

    def slow_rtd(k=0):
        slow(k)
        rig.clock.advance(0.012)  # the service itself busy for 12 ms in this frame
    monkeypatch.setattr(rig.svc.rtd, "run", slow_rtd)
    rig.run_frames(4)
    assert rig.reader.read_inputs().host_stall_s == 0.0
    assert not any(t.startswith("host stall") for t in texts(rig))
