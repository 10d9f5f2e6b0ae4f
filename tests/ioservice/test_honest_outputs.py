"""Issue 28 item 5, "Honest outputs": a DAC board that stops answering (``bus-error:dac``)
while the arm moves. Every safe action goes through that board, so no message may call the
outputs safe; the service says what they may hold and what to do, keeps writing 0 V every
frame, and stops the amplifier-enable charge pump when the rack has one (whose relay, modelled
by the fake PIO board, then stops the simulated arm). Simulated time throughout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bit3.layout import FAULT_AMP_ENABLE, FAULT_DAC_UNREACHABLE, ServiceState
from drivers.pio.registers import CHARGE_PUMP
from ioservice.guardian import Guardian
from ioservice.safety import OutputGuard
from ioservice.service import FAULT_DAC
from pfma.clock import SimClock
from pfma.rack import load_rack
from sim.faults import FaultSet
from sim.rig import SimRig

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rack-chargepump.toml"
RATE = 0.24  # rad/s on the shoulder pitch: +6.00 V at K_w = 25 V per rad/s
AXIS = 1  # shoulder pitch in the arm model's axis order (SY SP EP ...)


def _moving(rig):
    """Arm the service with a controller that writes a fresh command every frame, then drive
    the shoulder pitch at RATE for 0.5 s."""
    ctl = rig.controller()
    rates = [0.0] * len(rig.layout.joint_names)

    def command(info):
        ctl.write_commands(joint_rate_rad_s=rates, current_limit_a=(5, 5, 5, 2.5, 2.5, 2.5, 0), arm_request=1)
    rig.on_frame.append(command)
    rig.run(0.05)
    assert rig.reader.read_inputs().service_state == ServiceState.ARMED
    rates[list(rig.layout.joint_names).index("shoulder_pitch")] = RATE
    rig.run(0.5)
    assert rig.world.sim.true_state().qdot[AXIS] == pytest.approx(RATE, rel=0.15)


def _texts(rig) -> list[str]:
    return [m.text for m in rig.buf.queue("service_messages").read(0)]


def _dac_errors(rig) -> int:
    return int(rig.reader.read_inputs().board_errors[rig.layout.slot("board", "dac")])


@pytest.fixture
def plain():
    """The seed's rack: no amplifier-enable output."""
    with SimRig(prefix="pfma-honest-") as r:
        yield r


@pytest.fixture
def pumped():
    with SimRig(load_rack(EXAMPLE), prefix="pfma-pump-") as r:
        yield r


def test_without_a_charge_pump_the_dac_failure_is_said_honestly_and_cannot_be_stopped(plain):
    rig = plain
    _moving(rig)
    dac = rig.world.bus["dac"]
    ch = rig.svc.rack.channel("shoulder_pitch_command").channel
    fs = FaultSet(rig.world)
    fs.inject("bus-error:dac")
    q0 = rig.world.sim.true_state().q[AXIS]
    e0 = _dac_errors(rig)
    rig.run(0.5)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.FAULT and s.fault_code == FAULT_DAC_UNREACHABLE
    texts = _texts(rig)
    said = [t for t in texts if "DAC not answering" in t]
    assert len(said) == 1  # one message for the episode, not one per frame
    t = said[0]
    assert t.startswith("outputs NOT known safe: DAC not answering (bus error: write16 dac DAC[0]")
    assert "its outputs may hold their last values (last written +6.00 V on shoulder_pitch_command" in t
    assert "this rack has no amplifier-enable output" in t and "press the hardware E-stop" in t
    assert not any("outputs safe" in x for x in texts)
    # what software cannot do: the latch keeps +6 V and the joint keeps moving
    assert dac.output_volts(ch) == pytest.approx(6.0, abs=0.01)
    assert rig.world.sim.true_state().q[AXIS] - q0 == pytest.approx(0.5 * RATE, rel=0.15)
    from tools.cli import stats as stats_cli  # pfma stats says it too (its JSON, and a line)
    assert stats_cli.collect(rig.reader)["commands"]["outputs_known_safe"] is False
    # ... though the service tries 0 V in every frame (each try is a counted bus error)
    assert _dac_errors(rig) - e0 >= 0.5 * 320 - 2
    # the board answers again: 0 V written at once, said, the fault code says "was the DAC",
    # and the service stays FAULT until a re-arm
    fs.clear("bus-error:dac")
    rig.run(0.01)
    s = rig.reader.read_inputs()
    assert dac.output_volts(ch) == 0.0
    assert s.service_state == ServiceState.FAULT and s.fault_code == FAULT_DAC
    assert _texts(rig)[-1] == "DAC answering again: outputs 0 V; the service stays FAULT until re-armed"
    assert not rig.svc.dac_unreachable and rig.svc.guard.outputs_known_safe
    assert stats_cli.collect(rig.reader)["commands"]["outputs_known_safe"] is True


def test_a_re_arm_while_the_dac_does_not_answer_trips_again(plain):
    rig = plain
    _moving(rig)
    faults = FaultSet(rig.world)
    faults.inject("bus-error:dac")
    rig.run(0.05)
    ctl = rig.controller()
    rig.on_frame.clear()  # a controller that asks for a new arm with zero rates
    rig.on_frame.append(lambda info: ctl.write_commands(joint_rate_rad_s=[0.0] * 6, arm_request=1,
                                                        rearm_counter=2))
    rig.run(0.05)
    s = rig.reader.read_inputs()
    assert rig.svc.guard.trips == 2  # armed again for a frame: the write failed, tripped again
    assert s.service_state == ServiceState.FAULT and s.fault_code == FAULT_DAC_UNREACHABLE
    texts = _texts(rig)
    assert "armed" in texts and len([t for t in texts if "DAC not answering" in t]) == 2
    assert not any("outputs safe" in t for t in texts)


def test_a_stop_while_the_dac_does_not_answer_is_not_called_safe(plain):
    rig = plain
    _moving(rig)
    FaultSet(rig.world).inject("bus-error:dac")
    rig.run(0.05)
    rig.svc.stop()
    texts = _texts(rig)
    stop = [t for t in texts if "service stopped" in t and t.startswith("outputs")]
    assert len(stop) == 1
    assert stop[0].startswith("outputs NOT known safe: service stopped; the DAC did not answer: its outputs "
                              "may hold their last values (last written +6.00 V on shoulder_pitch_command")
    assert stop[0].endswith("press the hardware E-stop")
    assert not any("outputs safe" in t for t in texts)
    s = rig.reader.read_inputs()  # the stopped service's last word: still not known safe
    assert s.service_state == ServiceState.STOPPED and s.fault_code == FAULT_DAC_UNREACHABLE


def test_a_stop_once_the_dac_answers_again_disconnects_and_is_called_safe(plain):
    rig = plain
    _moving(rig)
    faults = FaultSet(rig.world)
    faults.inject("bus-error:dac")
    rig.run(0.05)
    faults.clear("bus-error:dac")
    rig.svc.stop()  # no frame between: the stop's own disconnect is the first write that answers
    assert _texts(rig)[-2].startswith("outputs safe: service stopped")
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.STOPPED and s.fault_code == FAULT_DAC
    assert not rig.world.bus["dac"].outputs_connected


def test_a_stop_with_the_dac_answering_still_says_outputs_safe(plain):
    rig = plain
    _moving(rig)
    rig.svc.stop()
    assert "outputs safe: service stopped" in _texts(rig)


def test_the_guard_never_calls_outputs_safe_while_the_dac_does_not_answer():
    posted = []
    g = OutputGuard(SimClock(), post=lambda sev, code, text: posted.append(text))
    g.trip("stale heartbeat")
    g.state = ServiceState.ARMED
    g.outputs_known_safe = False
    g.trip("stale heartbeat")
    g.stop()
    assert posted == ["outputs safe: stale heartbeat", "outputs NOT known safe: stale heartbeat",
                      "outputs NOT known safe: service stopped"]


def test_the_guardian_that_cannot_write_the_dac_says_what_that_means():
    class DeadDac:
        def zero_all(self):
            raise OSError("no answer")

    said: list[str] = []
    g = Guardian(DeadDac(), 4242, 0.02, parent_alive=lambda: False, say=said.append)
    assert g.step() == "died"
    assert "the DAC could NOT be written: its outputs may hold their last values" in said[-1]
    assert "this rack has no amplifier-enable output: only the hardware E-stop stops the arm" in said[-1]
    g = Guardian(DeadDac(), 4242, 0.02, parent_alive=lambda: False, say=said.append,
                 amplifier_enable="pio_video port 1 bit 0")
    g.step()
    assert "charge pump (pio_video port 1 bit 0) is no longer toggled" in said[-1]
    assert not any("safe" in t for t in said)


# -- with the amplifier-enable charge pump ---------------------------------------------------
def test_the_charge_pump_runs_only_while_armed(pumped):
    rig = pumped
    relay = rig.world.sim.relay
    rig.run(0.1)
    assert relay is not None and relay.edges == 0 and not relay.energized()  # SAFE: no edges
    _moving(rig)
    assert relay.energized()
    # one edge per frame while ARMED (0.55 s of frames, less the two frames arming took)
    assert relay.edges >= 0.5 * 320
    s = rig.reader.read_inputs()
    bits = int(s.pio_port_bits[rig.layout.slot("pio", "amplifier_enable_pump")])
    assert bits in (0, 1) and bits == relay.level


def test_with_a_charge_pump_the_dac_failure_drops_the_amplifiers_and_stops_the_joint(pumped):
    rig = pumped
    _moving(rig)
    relay = rig.world.sim.relay
    fs = FaultSet(rig.world)
    fs.inject("bus-error:dac")
    t0 = rig.clock.now()
    edges = relay.edges
    rig.run(CHARGE_PUMP["drop_s"] + 0.004)
    # no edge since the failed write: the relay dropped drop_s after the last one, itself at
    # most a frame before the fault
    assert relay.edges == edges and not relay.energized()
    assert t0 - 1 / 320 <= relay.drops_at - CHARGE_PUMP["drop_s"] <= t0
    # the latch still holds +6 V, but the amplifiers are off and the brakes set: the joint stops
    dac = rig.world.bus["dac"]
    assert dac.output_volts(rig.svc.rack.channel("shoulder_pitch_command").channel) == pytest.approx(6.0, abs=0.01)
    rig.run(0.1)
    st = rig.world.sim.true_state()
    q1 = st.q[AXIS]
    assert st.qdot[AXIS] == 0.0 and st.brake_engaged[AXIS] and st.current_a[AXIS] == 0.0
    rig.run(1.0)
    assert rig.world.sim.true_state().q[AXIS] == q1  # still there a second later
    texts = _texts(rig)
    said = [t for t in texts if "DAC not answering" in t]
    assert len(said) == 1
    assert "amplifier enable dropped: charge pump pio_video port 1 bit 0 stopped, its relay opens within 20 ms" \
        in said[0]
    assert not any("outputs safe" in t for t in texts)


def test_the_relay_also_drops_when_the_service_stops_toggling_for_any_reason(pumped):
    rig = pumped
    _moving(rig)
    relay = rig.world.sim.relay
    rig.on_frame.clear()  # the controller dies: the watchdog trips, the pump stops
    rig.run(0.05)
    assert rig.reader.read_inputs().service_state == ServiceState.FAULT
    assert not relay.energized()
    assert np.all(rig.world.sim.true_state().current_a == 0.0)


def test_a_charge_pump_that_cannot_be_written_while_armed_trips(pumped):
    rig = pumped
    _moving(rig)
    faults = FaultSet(rig.world)
    faults.inject("bus-error:pio_video")
    rig.run(0.05)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.FAULT and s.fault_code == FAULT_AMP_ENABLE
    assert not rig.world.sim.relay.energized()
    said = [t for t in _texts(rig) if "charge pump" in t]
    assert said == ["outputs safe: amplifier-enable charge pump (pio_video port 1 bit 0) not written: bus error: "
                    "write8 pio_video PIA1_PRB at A16 0x0025: board does not answer (injected fault); the "
                    "amplifiers drop within 20 ms"]
    # the DAC answers: its 0 V is what keeps the arm still here, and it is called safe
    assert rig.world.bus["dac"].output_volts(rig.svc.rack.channel("shoulder_pitch_command").channel) == 0.0


def test_pfma_stats_prints_outputs_not_known_safe(plain, capsys):
    from tools.cli import main
    rig = plain
    rig.run(0.05)
    FaultSet(rig.world).inject("bus-error:dac")
    rig.run(0.02)
    assert main(["stats", "--buffer", rig.name]) == 0
    out = capsys.readouterr().out
    assert "OUTPUTS NOT KNOWN SAFE: the DAC board does not answer; its outputs may hold their last values: " \
           "press the hardware E-stop if the arm moves" in out


def test_the_bus_measurement_times_the_pump_without_an_edge(pumped):
    rig = pumped
    relay = rig.world.sim.relay
    fake = rig.world.bus["pio_video"]
    fake.log_traffic = True
    n0 = len(fake.traffic)
    rig.svc.measure_bus(repeats=3)
    writes = [t for t in fake.traffic[n0:] if t[0] == "w"]
    assert len(writes) == 3 and relay.edges == 0  # one port write per DAC probe, no level change


def test_pfma_monitor_says_outputs_not_known_safe(plain):
    from tools.checkout.view import monitor_lines
    rig = plain
    rig.run(0.05)
    assert not any("NOT KNOWN SAFE" in line for line in monitor_lines(rig.reader))
    FaultSet(rig.world).inject("bus-error:dac")
    rig.run(0.02)
    lines = monitor_lines(rig.reader)
    assert lines[1] == "OUTPUTS NOT KNOWN SAFE: the DAC does not answer; press the hardware E-stop"
    assert lines[2].endswith("fault DAC LOST (7)") and lines[3].startswith("outputs UNKNOWN  brakes")
    assert all(len(line) <= 80 for line in lines)
