import json

import numpy as np
import pytest

from bit3.layout import (
    BUFFER_SIZE, CAPACITY, DOC_PATH, SEQ_BLOCK, build_layout, default_layout, layout_markdown,
)
from tools.cli import main
from pfma.errors import ConfigError
from pfma.rack import DEFAULT_RACK, load_rack, parse_rack


def test_areas_tile_exactly_32768_bytes():
    lay = default_layout()
    pos = 0
    for a in lay.areas:
        assert a.offset == pos and a.offset % 64 == 0
        pos += a.size
        if a.body_dtype is not None:
            assert a.body_dtype.itemsize == a.body_size
            assert a.body_size == a.size - (SEQ_BLOCK if a.seqlocked else 0)
    assert pos == BUFFER_SIZE == lay.size == 32768


def test_fields_do_not_overlap_and_stay_in_their_area():
    lay = default_layout()
    spans = sorted((f.offset, f.offset + f.nbytes, f.name) for f in lay.fields)
    for (s0, e0, n0), (s1, _e1, n1) in zip(spans, spans[1:]):
        assert e0 <= s1, f"{n0} overlaps {n1}"
    for f in lay.fields:
        a = lay.area(f.area)
        assert a.body_offset <= f.offset and f.offset + f.nbytes <= a.offset + a.size, f.name
        if a.seqlocked:  # the counter block is never a field
            assert f.offset >= a.offset + SEQ_BLOCK
        # the numpy record agrees with the field list
        if a.body_dtype is not None and f.name in a.body_dtype.names:
            assert a.body_dtype.fields[f.name][1] == f.offset - a.body_offset


def test_every_rack_channel_has_entries_inside_its_fields():
    rack = load_rack()
    lay = default_layout()
    for c in rack.channels():
        entries = [e for e in lay.channels if e.name == c.signal]
        assert entries, c.signal
        for e in entries:
            for fname, idx, off in e.fields:
                f = lay.field(fname, e.area)
                assert f.offset <= off < f.offset + f.nbytes
    # DAC channels have both an applied (inputs) and, for non-spares, a requested (commands) entry
    assert lay.channel("elbow_pitch_command", "commands").fields[0][0] == "joint_rate_rad_s"
    assert lay.channel("gripper_current_limit", "commands").fields[0] == \
        ("current_limit_a", 6, lay.field("current_limit_a").offset + 48)
    assert lay.joint_names[:3] == ("shoulder_pitch", "shoulder_yaw", "elbow_pitch")
    assert lay.slot("link", "ft_sensor") == 0 and lay.slot("hc", "crl") == 1


def test_required_fields_exist():
    lay = default_layout()
    names = {(f.area, f.name) for f in lay.fields}
    for need in [("header", "magic"), ("header", "layout_hash"), ("header", "calibration_hash"),
                 ("header", "owners"), ("header", "frame"), ("header", "service_state"),
                 ("inputs", "rtd_counts"), ("inputs", "adc_value"), ("inputs", "dac_value"),
                 ("inputs", "ft_force_n"), ("inputs", "ft_torque_nm"), ("inputs", "link_resyncs"),
                 ("inputs", "hc_axes"), ("inputs", "hc_deadman"), ("inputs", "pio_user_inputs"),
                 ("inputs", "matrix_route"), ("inputs", "t_dac_s"), ("inputs", "board_errors"),
                 ("stats", "wake_latency_p999_us"), ("stats", "work_max_us"),
                 ("stats", "dropped_frames"), ("stats", "device_rate_hz"),
                 ("commands", "heartbeat"), ("commands", "joint_rate_rad_s"),
                 ("commands", "current_limit_a"), ("commands", "rearm_counter"),
                 ("service_messages", "entries"), ("controller_messages", "entries")]:
        assert need in names, need
    assert lay.field("rtd_angle_rad").shape == (CAPACITY["rtd"],)
    assert lay.field("hc_axes").shape == (CAPACITY["hc"], 6)
    assert lay.field("entries", "service_messages").shape == (50,)


def test_hash_is_deterministic_and_follows_the_rack():
    a = build_layout(load_rack())
    b = build_layout(load_rack(DEFAULT_RACK))
    assert a.hash == b.hash and len(a.hash) == 8
    text = DEFAULT_RACK.read_text().replace('"elbow_pitch_angle"', '"elbow_angle"')
    other = build_layout(parse_rack(text, "renamed.toml"))
    assert other.hash != a.hash
    # renaming a channel moves nothing: offsets are stable, only the names (and hash) change
    assert [(f.name, f.offset) for f in other.fields] == [(f.name, f.offset) for f in a.fields]
    assert other.channel("elbow_angle").fields == a.channel("elbow_pitch_angle").fields


def test_rack_beyond_capacity_is_refused_by_name():
    extra = "".join(f"""
[[board]]
name = "adc{i}"
kind = "dvme611"
base = {0xA000 + 0x100 * i}
rate_hz = 160
channels = [{", ".join(f'{{ ch = {c}, signal = "x{i}_{c}", label = "x", units = "V" }}' for c in range(32))}]
""" for i in (2, 3))
    rack = parse_rack(DEFAULT_RACK.read_text() + extra, "big.toml")
    with pytest.raises(ConfigError, match="adc entries but the layout has room for 64"):
        build_layout(rack)


def test_committed_doc_is_the_generated_text():
    assert DOC_PATH.read_text() == layout_markdown(default_layout()), \
        "docs/bit3-layout.md is stale: pfma layout --markdown > docs/bit3-layout.md"


def test_cli_layout_json_lists_every_field(capsys):
    assert main(["layout", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    lay = default_layout()
    assert data["size"] == 32768 and data["hash"] == lay.hash_hex
    assert len(data["fields"]) == len(lay.fields)
    f = next(x for x in data["fields"] if x["name"] == "adc_value")
    assert f["area"] == "inputs" and f["dtype"] == "<f8" and f["shape"] == [64]
    assert {"name", "area", "offset", "dtype", "shape", "units"} <= set(f)


def test_cli_layout_table_and_markdown(capsys):
    assert main(["layout", "--channels"]) == 0
    out = capsys.readouterr().out
    assert "joint_rate_rad_s" in out and "elbow_pitch_angle" in out and "32768" in out
    assert main(["layout", "--markdown"]) == 0
    assert capsys.readouterr().out == layout_markdown(default_layout())


def test_message_record_is_80_bytes():
    lay = default_layout()
    e = lay.area("service_messages").body_dtype.fields["entries"][0]
    assert e.subdtype[0].itemsize == 80 and e.shape == (50,)
    assert np.dtype(lay.area("commands").body_dtype).itemsize == 960


def test_every_status_word_reads_by_name_ok_when_healthy():
    """bit3.layout.status_text: the one table pfma read, watch, monitor and stats name a
    channel's, board's or link's status by (issue 29 item 5)."""
    from bit3.layout import (
        BOARD_FAULT, BOARD_INIT, BOARD_OK, CHANNEL_BUS_ERROR, DAC_CLIPPED, DAC_FORCED_SAFE, LINK_FAULT, LINK_OPEN,
        LINK_STALE, LINK_SYNCED, RTD_LOSS_OF_SIGNAL, RTD_NO_REFERENCE, STATUS_HEALTHY, status_text,
    )
    for kind, healthy in STATUS_HEALTHY.items():
        assert status_text(kind, healthy) == "ok", kind
    assert status_text("rtd", RTD_LOSS_OF_SIGNAL) == "LOS"  # the resolver in loss of signal
    assert status_text("rtd", RTD_LOSS_OF_SIGNAL | RTD_NO_REFERENCE | CHANNEL_BUS_ERROR) == "LOS|NOREF|BUSERR"
    assert status_text("adc", CHANNEL_BUS_ERROR) == "BUSERR" and status_text("adc", 0x40) == "0x40"
    assert status_text("dac", DAC_CLIPPED | DAC_FORCED_SAFE) == "CLIPPED|SAFE"
    assert status_text("board", BOARD_OK | BOARD_INIT | BOARD_FAULT) == "FAULT"  # was "7 OK|INIT|FAULT"
    assert status_text("board", BOARD_FAULT) == "FAULT"  # its init failed
    assert status_text("board", 0) == "NOT INITIALISED" and status_text("board", BOARD_OK) == "NOT INITIALISED"
    assert status_text("link", LINK_OPEN | LINK_STALE) == "STALE"
    assert status_text("link", LINK_OPEN | LINK_SYNCED | LINK_FAULT) == "FAULT"
    assert status_text("link", LINK_FAULT | LINK_STALE) == "FAULT|STALE|CLOSED"
    assert status_text("link", 0) == "CLOSED" and status_text("link", LINK_OPEN) == "NOT SYNCED"
    assert status_text("ft", 1) == "OVERLOAD" and status_text("ft", 0x80) == "0x80"  # the F/T status byte


def test_fault_codes_have_one_home_and_a_name_each():
    import ioservice.service as svc
    from bit3 import layout
    codes = {n: getattr(layout, n) for n in dir(layout)
             if n.startswith("FAULT_") and n != "FAULT_CODE_NAMES" and isinstance(getattr(layout, n), int)}
    assert sorted(codes.values()) == sorted(set(codes.values())) == sorted(layout.FAULT_CODE_NAMES)
    assert all(getattr(svc, n) == v for n, v in codes.items())  # the service's are these, re-exported
    assert all(len(n) <= 11 for n in layout.FAULT_CODE_NAMES.values())  # the console's World Status line
