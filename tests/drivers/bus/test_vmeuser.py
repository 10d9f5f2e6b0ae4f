"""The vme_user bus adapter: the VME_SET_MASTER ioctl (its number and struct bytes)
through a recording double of ``fcntl.ioctl``, and every ``pread``/``pwrite`` (offset,
length, byte order) through recording doubles over an ordinary file standing in for
the master window. The lab test needs a real /dev/bus/vme/m0."""

from __future__ import annotations

import errno
import os
import struct
import sys

import pytest

from drivers.bus import BusUrlError, open_bus
from drivers.bus import devicefile
from drivers.bus.devicefile import _iow
from drivers.bus.vmeuser import VmeUserBus, open_vme_bus
from pfma.errors import AlignmentError, BusError, LinkError


class Recorder:
    """``set_master``, ``pread`` and ``pwrite`` doubles over a real file; ``dead`` offsets
    end a transfer early, as vme_tsi148 with err_chk=1 does at the first bus error."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.dead: set[int] = set()
        self.eio = False

    def set_master(self, path, **kw):
        self.calls.append(("set_master", path, kw))

    def _good(self, offset: int, n: int) -> int:
        if self.eio:
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        for i in range(n):
            if offset + i in self.dead:
                return i
        return n

    def pread(self, fd, n, offset):
        self.calls.append(("pread", n, offset))
        return os.pread(fd, self._good(offset, n), offset)

    def pwrite(self, fd, data, offset):
        self.calls.append(("pwrite", bytes(data), offset))
        return os.pwrite(fd, data[:self._good(offset, len(data))], offset)


@pytest.fixture
def window(tmp_path):
    path = tmp_path / "m0"
    path.write_bytes(bytes(0x10000))
    return path


@pytest.fixture
def rec():
    return Recorder()


@pytest.fixture
def bus(window, rec):
    b = VmeUserBus(str(window), set_master=rec.set_master, pread=rec.pread, pwrite=rec.pwrite)
    rec.calls.clear()
    yield b
    b.close()


# -- the window set-up ----------------------------------------------------------------------
def test_opening_configures_a16_user_data_d16_over_the_whole_a16_space(window, rec):
    VmeUserBus(str(window), set_master=rec.set_master).close()
    assert rec.calls == [("set_master", str(window),
                          {"vme_addr": 0, "size": 0x10000, "cycle": 0x1 | 0x2000 | 0x8000})]


def test_am_0x2d_configures_supervisory_data(window, rec):
    open_vme_bus(f"vme:{window}?am=0x2D", set_master=rec.set_master).close()
    assert rec.calls[0][2]["cycle"] == 0x1 | 0x1000 | 0x8000


def test_vme_set_master_ioctl_number_and_struct_bytes(window, monkeypatch):
    """What reaches the kernel: _IOW(0xAE, 4, struct vme_master) and the 32 packed bytes
    enable, vme_addr, size, aspace, cycle, dwidth (host byte order)."""
    seen = []

    class FakeFcntl:
        @staticmethod
        def ioctl(fd, request, arg):
            seen.append((os.path.realpath(f"/proc/self/fd/{fd}"), request, bytes(arg)))

    monkeypatch.setattr(devicefile, "fcntl", FakeFcntl)
    VmeUserBus(str(window)).close()
    [(path, request, arg)] = seen
    assert path == os.path.realpath(window)
    assert len(arg) == 32
    assert struct.unpack("=IQQIII", arg) == (1, 0, 0x10000, 0x1, 0x2001 | 0x8000, 0x2)
    if sys.byteorder == "little":
        assert arg == bytes.fromhex("01000000" "0000000000000000" "0000010000000000"
                                    "01000000" "01a00000" "02000000")
    assert request == _iow(0xAE, 4, 32)


def test_ioctl_direction_bits_per_architecture():
    assert _iow(0xAE, 4, 32, machine="x86_64") == 0x4020AE04
    assert _iow(0xAE, 4, 32, machine="aarch64") == 0x4020AE04
    assert _iow(0xAE, 4, 32, machine="ppc") == 0x8020AE04  # an MVME5500/6100 SBC
    assert _iow(0xAE, 4, 32, machine="mips") == 0x8020AE04


@pytest.mark.parametrize("err, words", [
    (FileNotFoundError(errno.ENOENT, "No such file or directory"), "modprobe vme_tsi148 err_chk=1 vme_user"),
    (PermissionError(errno.EACCES, "Permission denied"), "udev rule"),
    (OSError(errno.ENOTTY, "Inappropriate ioctl for device"), "is this a vme_user master window"),
])
def test_a_window_that_cannot_be_configured_is_one_link_error(window, err, words):
    def refuse(path, **kw):
        raise err

    with pytest.raises(LinkError) as info:
        VmeUserBus(str(window), set_master=refuse)
    assert "cannot configure (VME_SET_MASTER) the VME master window" in str(info.value)
    assert words in str(info.value)


def test_cli_names_the_missing_window_without_a_traceback(capsys, tmp_path):
    from tools.cli import main
    missing = tmp_path / "no-such-window"
    assert main(["reg", "read", "0x0100", "--bus", f"vme:{missing}"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and "modprobe" in err


@pytest.mark.parametrize("url, words", [
    ("vme:", "names no master window"),
    ("vme:/dev/bus/vme/m0?base=0x100", "unknown option 'base'"),
    ("vme:/dev/bus/vme/m0?am=0x39", "am must be 0x29"),
    ("vme:/dev/bus/vme/m0?am=x", "not a number"),
])
def test_bad_urls_are_one_clear_message(url, words):
    with pytest.raises(BusUrlError) as info:
        open_bus(url)
    assert words in str(info.value)


# -- cycles --------------------------------------------------------------------------------------
def test_read16_is_one_two_byte_pread_at_the_address_big_endian(bus, rec, window):
    with open(window, "r+b") as f:
        f.seek(0xD000)
        f.write(b"\xC1\x00")
    assert bus.read16(0xD000) == 0xC100
    assert rec.calls == [("pread", 2, 0xD000)]


def test_write16_is_one_two_byte_big_endian_pwrite(bus, rec, window):
    bus.write16(0xD002, 0x1234)
    assert rec.calls == [("pwrite", b"\x12\x34", 0xD002)]
    assert window.read_bytes()[0xD002:0xD004] == b"\x12\x34"


def test_byte_accesses_are_one_byte_at_the_odd_address(bus, rec, window):
    bus.write8(0xC001, 0xA5)
    assert bus.read8(0xC001) == 0xA5
    assert rec.calls == [("pwrite", b"\xA5", 0xC001), ("pread", 1, 0xC001)]


def test_blocks_are_one_pread_or_pwrite(bus, rec, window):
    bus.write_block16(0x0100, [0x0102, 0x0304, 0xFFFF])
    assert bus.read_block16(0x0100, 3) == [0x0102, 0x0304, 0xFFFF]
    assert rec.calls == [("pwrite", bytes.fromhex("01020304FFFF"), 0x0100), ("pread", 6, 0x0100)]


def test_mistakes_are_refused_before_any_system_call(bus, rec):
    with pytest.raises(AlignmentError):
        bus.read16(0xD001)
    with pytest.raises(AlignmentError):
        bus.write16(0xD001, 0)
    with pytest.raises(ValueError):
        bus.write16(0xD000, 0x10000)
    with pytest.raises(ValueError):
        bus.write8(0xC001, -1)
    with pytest.raises(ValueError):
        bus.write_block16(0xD000, [0, 0x10000])
    with pytest.raises(ValueError):
        bus.read_block16(0xFFFE, 2)
    with pytest.raises(AlignmentError):
        bus.read_block16(0x0101, 1)
    assert rec.calls == []


# -- bus errors --------------------------------------------------------------------------------
def test_a_short_transfer_is_a_bus_error_at_the_first_word_not_transferred(bus, rec):
    rec.dead.add(0x0104)
    with pytest.raises(BusError) as info:
        bus.read_block16(0x0100, 4)
    assert (info.value.addr, info.value.width, info.value.op) == (0x0104, 16, "read")
    assert "VME bus error" in info.value.reason and "AM 0x29" in info.value.reason
    with pytest.raises(BusError) as info:
        bus.write16(0x0104, 1)
    assert (info.value.addr, info.value.op) == (0x0104, "write")
    with pytest.raises(BusError):
        bus.read8(0x0104)


def test_eio_is_a_bus_error(bus, rec):
    rec.eio = True
    with pytest.raises(BusError) as info:
        bus.read16(0x8000)
    assert (info.value.addr, info.value.width, info.value.op) == (0x8000, 16, "read")
    assert "EIO" in info.value.reason
    assert isinstance(info.value.__cause__, OSError)


def test_a_closed_bus_refuses(bus):
    bus.close()
    bus.close()
    with pytest.raises(BusError) as info:
        bus.read16(0x0100)
    assert "closed" in str(info.value)


# -- lab -------------------------------------------------------------------------------------------
@pytest.mark.lab
def test_real_vme_user_window_reads_a_board_and_gets_berr_from_an_empty_address():
    """Lab: an SBC or bridge with vme_user (vme_tsi148 loaded with err_chk=1) and write
    access to PFMA_LAB_VME (default /dev/bus/vme/m0); PFMA_LAB_ADDR (default 0x0100, the
    first resolver board of the default rack) answers, PFMA_LAB_DEAD (default 0x8000)
    does not."""
    path = os.environ.get("PFMA_LAB_VME", "/dev/bus/vme/m0")
    if not os.path.exists(path):
        pytest.skip(f"no {path} (vme_user not loaded)")
    with open_bus(f"vme:{path}") as bus:
        value = bus.read16(int(os.environ.get("PFMA_LAB_ADDR", "0x0100"), 0))
        assert 0 <= value <= 0xFFFF
        with pytest.raises(BusError):
            bus.read16(int(os.environ.get("PFMA_LAB_DEAD", "0x8000"), 0))
