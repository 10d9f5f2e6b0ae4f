"""DeviceFileBus on an ordinary temporary file standing in for the VME window."""

from __future__ import annotations

import os

import numpy as np
import pytest

from drivers.bus import open_bus
from drivers.bus.devicefile import DeviceFileBus, open_devicefile_bus
from drivers.bus.spy import SpyBus
from pfma.errors import AlignmentError, BusError, LinkError


@pytest.fixture
def window(tmp_path):
    path = tmp_path / "vme_a16"
    path.write_bytes(bytes(0x10000))
    return path


def test_words_are_big_endian_in_the_file(window):
    with DeviceFileBus(window) as bus:
        bus.write16(0xD000, 0xC100)
        bus.write16(0x0102, 0x1234)
        raw = window.read_bytes()
    assert raw[0xD000:0xD002] == b"\xC1\x00"
    assert raw[0x0102:0x0104] == b"\x12\x34"


def test_outside_writes_to_the_file_are_seen(window):
    with DeviceFileBus(window) as bus:
        with open(window, "r+b") as f:
            f.seek(0x0100)
            f.write(b"\x3F\xFF\xAB")
            f.flush()
        assert bus.read16(0x0100) == 0x3FFF
        assert bus.read8(0x0102) == 0xAB


def test_offset_and_base_place_a_partial_window(window):
    # A window of A16 0xC000-0xDFFF that starts at file offset 0x1000.
    with DeviceFileBus(window, size=0x2000, offset=0x1000, base=0xC000) as bus:
        bus.write16(0xC002, 0xBEEF)
        assert window.read_bytes()[0x1002:0x1004] == b"\xBE\xEF"
        with pytest.raises(BusError) as info:
            bus.read16(0xBFFE)
        assert "outside the mapped window 0xC000-0xDFFF" in str(info.value)
        with pytest.raises(BusError):
            bus.read16(0xE000)
        with pytest.raises(BusError):
            bus.write8(0xE000, 1)


def test_unaligned_file_offset_is_handled(window):
    with DeviceFileBus(window, size=0x100, offset=0x1002, base=0x0100) as bus:
        bus.write16(0x0100, 0x0102)
    assert window.read_bytes()[0x1002:0x1004] == b"\x01\x02"


def test_odd_word_access_is_an_alignment_error(window):
    with DeviceFileBus(window) as bus:
        with pytest.raises(AlignmentError) as info:
            bus.read16(0x0101)
        assert isinstance(info.value, ValueError) and isinstance(info.value, BusError)
        assert (info.value.addr, info.value.width, info.value.op) == (0x0101, 16, "read")
        with pytest.raises(ValueError):
            bus.write16(0x0101, 1)


def test_numpy_integers_are_values_floats_are_not(window):
    with DeviceFileBus(window) as bus:
        bus.write16(0xD000, np.uint16(0x0800))
        assert bus.read16(0xD000) == 0x0800
        with pytest.raises(ValueError, match="0xD000"):
            bus.write16(0xD000, 2048.0)


def test_missing_or_short_file_is_a_link_error(tmp_path):
    with pytest.raises(LinkError, match="no_such"):
        DeviceFileBus(tmp_path / "no_such")
    short = tmp_path / "short"
    short.write_bytes(bytes(16))
    with pytest.raises(LinkError, match="short"):
        DeviceFileBus(short)


def test_closed_bus_refuses_access(window):
    bus = DeviceFileBus(window)
    bus.close()
    bus.close()  # idempotent
    with pytest.raises(BusError, match="closed"):
        bus.read16(0)


def test_bad_geometry_is_refused(window):
    with pytest.raises(ValueError):
        DeviceFileBus(window, size=0x101)
    with pytest.raises(ValueError, match="runs past the A16 space"):
        DeviceFileBus(window, size=0x2000, base=0xF000)


def test_url_forms(window):
    with open_bus(f"file:{window}?size=0x2000&offset=0x1000&base=0xC000") as bus:
        assert isinstance(bus, DeviceFileBus)
        assert (bus.size, bus.offset, bus.base) == (0x2000, 0x1000, 0xC000)
        assert str(window) in bus.describe()
    with pytest.raises(ValueError, match="unknown option 'sise'"):
        open_devicefile_bus(f"file:{window}?sise=4")
    with pytest.raises(ValueError, match="is not an integer"):
        open_devicefile_bus(f"file:{window}?size=big")
    with pytest.raises(ValueError, match="names no file"):
        open_devicefile_bus("file:")


def test_spy_url_records_every_access(window):
    with open_bus(f"spy+file:{window}") as bus:
        assert isinstance(bus, SpyBus)
        bus.write16(0xD000, 0xC100)
        assert bus.read8(0xD000) == 0xC1
        with pytest.raises(AlignmentError):
            bus.read16(0xD001)
        assert [(a.op, a.width, a.addr, a.value) for a in bus.log] == [
            ("write", 16, 0xD000, 0xC100), ("read", 8, 0xD000, 0xC1), ("read", 16, 0xD001, None)]
        assert "odd address" in bus.log[-1].error
        assert str(bus.log[0]) == "write16 0xD000 <- 0xC100"
        assert bus.describe().startswith("spy on device file")


def test_file_is_not_grown_or_truncated(window):
    with DeviceFileBus(window) as bus:
        bus.write16(0xFFFE, 0xFFFF)
    assert os.path.getsize(window) == 0x10000
