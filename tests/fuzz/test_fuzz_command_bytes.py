"""Random bytes in the command record (issue 20 item 3): the claim holder's command body,
armed, has bytes of its fields overwritten with random bytes (or is replaced by random
bytes whole) and published through the area's sequence lock, frame after frame. The
service never drives a DAC channel beyond its configured limit (current limits never
below 0 V), and whenever it refuses a command or leaves ARMED it posts a message naming
the cause (refused field and value, a foreign writer, a stale heartbeat, a heartbeat that
breaks the holder's stream: two writers on the claim ...).

Simulated time (``SimRig``). Not repeated here: tests/ioservice/test_command_path.py
fuzzes the command *fields* with values (NaN, inf, beyond limits), torn writes, a rogue
writer and re-arms; this test writes *bytes* (any field, the heartbeat, the writer's pid
and token, the mode, padding) as a corrupted or hostile writer would.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bit3.layout import ServiceState, default_layout
from sim.rig import SimRig
from tests.fuzz._mutate import FUZZ

LIMITS = (5.0, 5.0, 5.0, 2.5, 2.5, 2.5, 0.0)
LAYOUT = default_layout()
_AREA = LAYOUT.area("commands")
#: (field, body offset, bytes) of every command field
FIELDS = [(f.name, f.offset - _AREA.body_offset, f.nbytes) for f in LAYOUT.fields if f.area == "commands"]
HEARTBEAT = next(off for name, off, _ in FIELDS if name == "heartbeat")
INPUTS_FRAME = next(off for name, off, _ in FIELDS if name == "inputs_frame")
RATES = next(off for name, off, _ in FIELDS if name == "joint_rate_rad_s")

#: one write: patch bytes inside a field (then, as a live open-loop writer would, the
#: heartbeat + 1 and inputs_frame = the newest frame, unless the patch hit them), the bytes
#: of a small rate (so that outputs move and the limits matter: random bytes are mostly
#: huge or NaN as a float64), or a whole body of random bytes
_KINDS = {
    "patch": st.tuples(st.just("patch"), st.sampled_from(range(len(FIELDS))), st.floats(0, 1, exclude_max=True),
                       st.binary(min_size=1, max_size=8)),
    "rate": st.tuples(st.just("patch"), st.just(-1), st.integers(0, 5),
                      st.floats(-0.6, 0.6).map(lambda x: np.float64(x).tobytes())),
    "whole": st.tuples(st.just("whole"), st.just(0), st.just(0.0),
                       st.binary(min_size=_AREA.body_size, max_size=_AREA.body_size)),
    "same": st.tuples(st.just("same"), st.just(0), st.just(0.0), st.just(b"")),  # the last body, heartbeat + 1
    "rearm": st.tuples(st.just("rearm"), st.just(0), st.just(0.0), st.just(b"")),  # a good body asking to re-arm
}
_write = st.sampled_from(["patch", "patch", "rate", "rate", "rate", "whole", "same", "rearm"]).flatmap(
    _KINDS.__getitem__)


def volts(rig) -> np.ndarray:
    return np.asarray(rig.world.bus["dac"].output_volts_all(), dtype=float)


@settings(FUZZ, max_examples=20)
@given(st.lists(_write, min_size=1, max_size=24))
def test_random_bytes_in_the_command_record_never_drive_beyond_a_limit_and_every_trip_is_named(writes):
    rig = SimRig(prefix="pfma-fzcmd-")
    try:
        ctl = rig.controller()
        for _ in range(8):
            ctl.write_commands(joint_rate_rad_s=[0.0] * 6, current_limit_a=list(LIMITS), arm_request=1)
            rig.run_frames(1)
        assert rig.reader.read_inputs().service_state == ServiceState.ARMED
        svc = rig.svc
        lock = ctl.buffer.lock("commands")  # the holder's own counter: one writer's stream
        good = ctl.command.copy()
        body = bytearray(good.tobytes())
        n_msgs = len(rig.reader.messages())
        for kind, which, at, data in writes:
            if kind == "whole":
                body = bytearray(data)
            elif kind == "rearm":  # the claim holder's good record, rates 0, the re-arm counter + 1
                good["rearm_counter"] += 1
                good["heartbeat"] = int.from_bytes(body[HEARTBEAT:HEARTBEAT + 8], "little") + 1
                good["inputs_frame"] = rig.reader.read_inputs().frame
                body = bytearray(good.tobytes())
            else:
                hit = range(0)
                if kind == "patch":
                    if which < 0:  # a rate of joint `at`, as float64 bytes
                        i = RATES + 8 * int(at)
                    else:
                        _name, off, n = FIELDS[which]
                        i = off + int(at * n)
                    body[i:i + len(data)] = data[:max(0, _AREA.body_size - i)]
                    hit = range(i, i + len(data))
                if HEARTBEAT not in hit and HEARTBEAT + 7 not in hit:
                    hb = int.from_bytes(body[HEARTBEAT:HEARTBEAT + 8], "little")
                    body[HEARTBEAT:HEARTBEAT + 8] = ((hb + 1) % 2**64).to_bytes(8, "little")
                if INPUTS_FRAME not in hit and INPUTS_FRAME + 7 not in hit:
                    body[INPUTS_FRAME:INPUTS_FRAME + 8] = int(rig.reader.read_inputs().frame).to_bytes(8, "little")
            before = rig.reader.read_inputs()
            state0, refused0 = before.service_state, before.refused_commands
            lock.write(memoryview(bytes(body)))  # as the claim holder, through the sequence lock
            rig.run_frames(1)
            v = volts(rig)
            for ch in range(svc._dac_n):  # never beyond the configured limit, in volts
                assert abs(v[ch]) <= svc._dac_sat_v[ch] + 1e-3, (ch, v[ch])
                if svc._dac_is_limit[ch]:
                    assert v[ch] >= 0.0, (ch, v[ch])
            s = rig.reader.read_inputs()
            msgs = rig.reader.messages()
            new = [m.text for m in msgs[n_msgs:]]
            n_msgs = len(msgs)
            if s.refused_commands > refused0:  # a refusal: the message names field and value, or the writer
                # (a patched heartbeat breaks the holder's stream: "two writers on the claim ...")
                assert any(t.startswith(("refused", "arm refused", "outputs safe: refused", "two writers on the claim"))
                           for t in new), new
            if state0 == ServiceState.ARMED and s.service_state != ServiceState.ARMED:  # a trip: its cause said
                assert new and all(t for t in new), (ServiceState(s.service_state).name, new)
            if s.service_state != ServiceState.ARMED:
                assert np.all(v[[ch for ch in range(svc._dac_n) if svc._dac_is_limit[ch]]] == 0.0)  # brakes set
    finally:
        rig.close()
