"""The caen bus adapter: what reaches CAEN's binding, through a recording double of
``caen_libs.caenvme`` (its enums with CAEN's values, its ``Error``, a ``Device`` that
records every cycle). The double's names and values are checked against the real
binding's source when caen-libs is installed; the lab test needs a bridge."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import os
from enum import IntEnum, unique
from pathlib import Path
from types import SimpleNamespace

import pytest

from drivers.bus import BusUrlError, open_bus
from drivers.bus import caen
from drivers.bus.caen import MISSING_BINDING, MISSING_LIBRARY, MULTI_CYCLES_MAX, CaenBus, open_caen_bus
from pfma.errors import AlignmentError, BusError, LinkError
from tools.cli import main


# -- the double of caen_libs.caenvme (values: CAEN's CAENVMEtypes.h, as the binding has them) --
@unique
class BoardType(IntEnum):
    V1718 = 0
    V2718 = 1
    A2818 = 2
    A2719 = 3
    A3818 = 4
    USB_V3718_LOCAL = 14
    PCIE_A3818_V3718 = 19
    ETH_V4718 = 27
    INVALID = -1


@unique
class DataWidth(IntEnum):
    D8 = 0x01
    D16 = 0x02
    D32 = 0x04


@unique
class AddressModifiers(IntEnum):
    A16_S = 0x2D
    A16_U = 0x29
    A24_U_DATA = 0x39


class Error(RuntimeError):
    @unique
    class Code(IntEnum):
        SUCCESS = 0
        BUS_ERROR = -1
        COMM_ERROR = -2
        GENERIC_ERROR = -3
        INVALID_PARAM = -4
        TIMEOUT_ERROR = -5
        NOT_SUPPORTED = -8

    def __init__(self, message: str, res: int, func: str) -> None:
        self.code = Error.Code(res)
        super().__init__(f"{func} failed: {message} ({self.code.name})")


class RecordingDevice:
    """``caenvme.Device``: records each call as a tuple of plain ints; words in ``mem``;
    an address in ``dead`` answers with BERR."""

    opened: list[tuple] = []

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.mem: dict[int, int] = {}
        self.dead: set[int] = set()
        self.fail_code = Error.Code.BUS_ERROR
        self.multi = True  # False: the bridge answers NOT_SUPPORTED to multi cycles
        self.closed = False

    @classmethod
    def open(cls, board_type, arg, conet_node=0):
        cls.opened.append((board_type, arg, conet_node))
        return cls()

    def _check(self, func: str, address: int) -> None:
        if address in self.dead:
            raise Error("Bus error", int(self.fail_code), func)

    def read_cycle(self, address, am, dw):
        self.calls.append(("read", address, int(am), int(dw)))
        self._check("CAENVME_ReadCycle", address)
        return self.mem.get(address, 0)

    def write_cycle(self, address, value, am, dw):
        self.calls.append(("write", address, value, int(am), int(dw)))
        self._check("CAENVME_WriteCycle", address)
        self.mem[address] = value

    def _multi(self, func: str) -> None:
        if not self.multi:
            raise Error("Not supported", int(Error.Code.NOT_SUPPORTED), func)

    def multi_read(self, addrs, ams, dws):
        self._multi("CAENVME_MultiRead")
        self.calls.append(("multi_read", list(addrs), [int(a) for a in ams], [int(d) for d in dws]))
        failed = {i: "BUS_ERROR" for i, a in enumerate(addrs) if a in self.dead}
        if failed:  # the binding's own wording (caenvme.Device.multi_read)
            raise RuntimeError(f"multi_read failed at cycles {failed}")
        return [self.mem.get(a, 0) for a in addrs]

    def multi_write(self, addrs, data, ams, dws):
        self._multi("CAENVME_MultiWrite")
        self.calls.append(("multi_write", list(addrs), list(data), [int(a) for a in ams],
                           [int(d) for d in dws]))
        failed = {i: "BUS_ERROR" for i, a in enumerate(addrs) if a in self.dead}
        for a, v in zip(addrs, data):
            if a not in self.dead:
                self.mem[a] = v
        if failed:
            raise RuntimeError(f"multi_write failed at cycles {failed}")

    def close(self):
        self.calls.append(("close",))
        self.closed = True


def fake_binding(device_cls=RecordingDevice) -> SimpleNamespace:
    return SimpleNamespace(BoardType=BoardType, DataWidth=DataWidth, AddressModifiers=AddressModifiers,
                           Error=Error, Device=device_cls)


@pytest.fixture
def cv():
    RecordingDevice.opened = []
    return fake_binding()


@pytest.fixture
def bus(cv):
    b = open_bus("caen://V1718/0", binding=cv)
    yield b
    b.close()


def dev(bus: CaenBus) -> RecordingDevice:
    return bus._dev


# -- opening ---------------------------------------------------------------------------
def test_url_opens_board_type_link_and_node(cv):
    open_bus("caen://V1718/0", binding=cv)
    open_bus("caen://v2718/1?node=3", binding=cv)
    open_bus("caen://ETH_V4718/192.168.10.5", binding=cv)
    assert RecordingDevice.opened == [(BoardType.V1718, 0, 0), (BoardType.V2718, 1, 3),
                                      (BoardType.ETH_V4718, "192.168.10.5", 0)]


@pytest.mark.parametrize("url, words", [
    ("caen://A3818/0", "caen://V2718/LINK"),  # the PCIe card's own registers, not the crate
    ("caen://A2818/0", "not the VME crate"),
    ("caen://USB_V3718_LOCAL/0", "not the VME crate"),
    ("caen://V9999/0", "unknown CAEN board type 'V9999'"),
    ("caen://V1718", "needs a board type and a link"),
    ("caen:///0", "needs a board type and a link"),
    ("caen://V1718/x", "link='x' is not an integer"),
    ("caen://V1718/0?unit=1", "unknown option 'unit'"),
    ("caen://V1718/0?am=0x39", "am must be 0x29"),
    ("caen://V1718/0?node=-1", "negative"),
])
def test_bad_urls_are_one_clear_message(cv, url, words):
    with pytest.raises(BusUrlError) as info:
        open_bus(url, binding=cv)
    assert words in str(info.value)
    assert RecordingDevice.opened == []


def test_a_bridge_that_does_not_answer_open_is_a_link_error(cv):
    class Unplugged(RecordingDevice):
        @classmethod
        def open(cls, board_type, arg, conet_node=0):
            raise Error("Communication error", int(Error.Code.COMM_ERROR), "CAENVME_Init2")

    with pytest.raises(LinkError) as info:
        open_caen_bus("caen://V1718/0", binding=fake_binding(Unplugged))
    assert "cannot open the CAEN bridge V1718 link 0" in str(info.value)
    assert "COMM_ERROR" in str(info.value)


# -- single cycles -----------------------------------------------------------------------
def test_read16_is_one_a16_user_d16_cycle_and_the_word_is_not_swapped(bus):
    dev(bus).mem[0xD000] = 0xC100
    assert bus.read16(0xD000) == 0xC100
    assert dev(bus).calls == [("read", 0xD000, 0x29, 0x02)]


def test_write16_is_one_a16_user_d16_cycle(bus):
    bus.write16(0xD002, 0x8001)
    assert dev(bus).calls == [("write", 0xD002, 0x8001, 0x29, 0x02)]


def test_byte_accesses_are_d8_cycles_at_the_odd_address(bus):
    dev(bus).mem[0xC003] = 0x5A
    assert bus.read8(0xC003) == 0x5A
    bus.write8(0xC001, 0xFF)
    assert dev(bus).calls == [("read", 0xC003, 0x29, 0x01), ("write", 0xC001, 0xFF, 0x29, 0x01)]


def test_supervisory_address_modifier_from_the_url(cv):
    with open_bus("caen://V1718/0?am=0x2D", binding=cv) as b:
        b.read16(0x0100)
        b.write8(0xC001, 1)
        b.read_block16(0x0100, 2)
        assert dev(b).calls == [("read", 0x0100, 0x2D, 0x02), ("write", 0xC001, 1, 0x2D, 0x01),
                                ("multi_read", [0x0100, 0x0102], [0x2D, 0x2D], [0x02, 0x02])]
        assert "AM 0x2D" in b.describe()


def test_mistakes_are_refused_before_any_cycle(bus):
    with pytest.raises(AlignmentError):
        bus.read16(0xD001)
    with pytest.raises(AlignmentError):
        bus.write16(0xD001, 1)
    with pytest.raises(ValueError):
        bus.write16(0xD000, 0x10000)
    with pytest.raises(ValueError):
        bus.write16(0xD000, -1)
    with pytest.raises(ValueError):
        bus.write8(0xC001, 0x100)
    with pytest.raises(ValueError):
        bus.read16(0x10000)
    assert dev(bus).calls == []


# -- errors ------------------------------------------------------------------------------
def test_berr_is_a_bus_error_naming_address_width_and_op(bus):
    dev(bus).dead.add(0x8000)
    with pytest.raises(BusError) as info:
        bus.read16(0x8000)
    err = info.value
    assert (err.addr, err.width, err.op) == (0x8000, 16, "read")
    assert "VME bus error" in err.reason and "AM 0x29" in err.reason and "V1718 link 0" in err.reason
    assert isinstance(err.__cause__, Error)
    with pytest.raises(BusError) as info:
        bus.write8(0x8000, 1)
    assert (info.value.addr, info.value.width, info.value.op) == (0x8000, 8, "write")


def test_a_lost_link_is_a_bus_error_too(bus):
    dev(bus).dead.add(0x0100)
    dev(bus).fail_code = Error.Code.COMM_ERROR
    with pytest.raises(BusError) as info:
        bus.read16(0x0100)
    assert "V1718 link 0" in info.value.reason and "COMM_ERROR" in info.value.reason


def test_a_closed_bus_refuses_and_closes_the_device_once(bus):
    bus.close()
    bus.close()
    assert dev(bus).calls == [("close",)]
    with pytest.raises(BusError) as info:
        bus.read16(0x0100)
    assert "closed" in str(info.value)


# -- blocks ------------------------------------------------------------------------------
def test_read_block16_is_one_multi_read_of_single_d16_cycles(bus):
    for i in range(4):
        dev(bus).mem[0x0100 + 2 * i] = 0x1000 + i
    assert bus.read_block16(0x0100, 4) == [0x1000, 0x1001, 0x1002, 0x1003]
    assert dev(bus).calls == [("multi_read", [0x0100, 0x0102, 0x0104, 0x0106], [0x29] * 4, [0x02] * 4)]


def test_write_block16_is_one_multi_write_in_address_order(bus):
    bus.write_block16(0xD000, [0xC100, 0x0800, 0x0801])
    assert dev(bus).calls == [("multi_write", [0xD000, 0xD002, 0xD004], [0xC100, 0x0800, 0x0801],
                               [0x29] * 3, [0x02] * 3)]


def test_long_blocks_are_split_into_calls_of_at_most_multi_cycles_max(bus):
    n = MULTI_CYCLES_MAX + 3
    bus.read_block16(0x0000, n)
    calls = dev(bus).calls
    assert [len(c[1]) for c in calls] == [MULTI_CYCLES_MAX, 3]
    assert calls[1][1][0] == 2 * MULTI_CYCLES_MAX


def test_block_mistakes_are_refused_before_any_cycle(bus):
    with pytest.raises(ValueError):
        bus.write_block16(0xD000, [1, 0x10000])  # the second word does not fit
    with pytest.raises(AlignmentError):
        bus.read_block16(0xD001, 2)
    with pytest.raises(ValueError):
        bus.read_block16(0xFFFE, 2)  # runs past the A16 space
    with pytest.raises(ValueError):
        bus.read_block16(0xD000, 0)
    assert dev(bus).calls == []


def test_a_berr_inside_a_block_names_that_words_address(bus):
    dev(bus).dead.update({0x0104, 0x0106})
    with pytest.raises(BusError) as info:
        bus.read_block16(0x0100, 4)
    assert (info.value.addr, info.value.width, info.value.op) == (0x0104, 16, "read")
    assert "cycle 2 of a 4-word block" in info.value.reason and "1 later cycle" in info.value.reason
    with pytest.raises(BusError) as info:
        bus.write_block16(0x0102, [1, 2])
    assert (info.value.addr, info.value.op) == (0x0104, "write")


def test_a_bridge_without_multi_cycles_gets_single_cycles(bus):
    d = dev(bus)
    d.multi = False
    d.mem[0x0100], d.mem[0x0102] = 7, 8
    assert bus.read_block16(0x0100, 2) == [7, 8]
    bus.write_block16(0xD000, [1, 2])
    assert d.calls == [("read", 0x0100, 0x29, 0x02), ("read", 0x0102, 0x29, 0x02),
                       ("write", 0xD000, 1, 0x29, 0x02), ("write", 0xD002, 2, 0x29, 0x02)]


# -- caen-libs or CAEN's library missing -----------------------------------------------------
def _import_failing_with(monkeypatch, exc: BaseException) -> None:
    real = importlib.import_module

    def fake_import(name, *args, **kwargs):
        if name.startswith("caen_libs"):
            raise exc
        return real(name, *args, **kwargs)

    monkeypatch.setattr(caen.importlib, "import_module", fake_import)


def test_missing_caen_libs_says_what_to_install(monkeypatch):
    _import_failing_with(monkeypatch, ModuleNotFoundError("No module named 'caen_libs'"))
    with pytest.raises(BusUrlError) as info:
        open_bus("caen://V1718/0")
    assert str(info.value) == MISSING_BINDING
    assert "pip install 'pfma-rack[caen]'" in MISSING_BINDING


def test_missing_libcaenvme_says_what_to_install(monkeypatch):
    # what caen_libs._utils.Lib raises when ctypes cannot load libCAENVME.so
    _import_failing_with(monkeypatch, RuntimeError("Library CAENVME not found. ..."))
    with pytest.raises(BusUrlError) as info:
        open_bus("caen://V1718/0")
    assert str(info.value) == MISSING_LIBRARY
    assert "libCAENVME.so" in MISSING_LIBRARY and "caen.it" in MISSING_LIBRARY


def test_cli_gives_one_line_and_exit_2_without_caen_libs(monkeypatch, capsys):
    _import_failing_with(monkeypatch, ModuleNotFoundError("No module named 'caen_libs'"))
    assert main(["reg", "read", "0x0100", "--bus", "caen://V1718/0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "pip install 'pfma-rack[caen]'" in err


# -- the double against the real binding (needs caen-libs; not its shared library) ----------
def _binding_source() -> Path:
    spec = importlib.util.find_spec("caen_libs")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("caen-libs not installed (pip install 'pfma-rack[caen]')")
    return Path(list(spec.submodule_search_locations)[0])


def test_the_double_has_the_real_bindings_names_and_values():
    _binding_source()
    types = importlib.import_module("caen_libs._caenvmetypes")  # no shared library needed
    for double, real in ((BoardType, types.BoardType), (DataWidth, types.DataWidth),
                         (AddressModifiers, types.AddressModifiers)):
        for member in double:
            assert real[member.name] == member.value, member
    assert caen.AM_A16_USER == types.AddressModifiers.A16_U
    assert caen.AM_A16_SUPER == types.AddressModifiers.A16_S


def test_the_bus_calls_device_methods_the_real_binding_has():
    src = (_binding_source() / "caenvme.py").read_text()
    tree = ast.parse(src)
    device = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Device")
    params = {f.name: [a.arg for a in f.args.args] for f in device.body if isinstance(f, ast.FunctionDef)}
    assert params["open"] == ["cls", "board_type", "arg", "conet_node"]
    assert params["read_cycle"] == ["self", "address", "am", "dw"]
    assert params["write_cycle"] == ["self", "address", "value", "am", "dw"]
    assert params["multi_read"] == ["self", "addrs", "ams", "dws"]
    assert params["multi_write"] == ["self", "addrs", "data", "ams", "dws"]
    assert "close" in params
    error = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Error")
    assert "BUS_ERROR = -1" in ast.get_source_segment(src, error)
    assert "NOT_SUPPORTED = -8" in ast.get_source_segment(src, error)
    assert "multi_read failed at cycles {failed_cycles}" in src  # the wording _multi_failure parses


# -- lab ---------------------------------------------------------------------------------------
@pytest.mark.lab
def test_real_caen_bridge_reads_a_board_and_gets_berr_from_an_empty_address():
    """Lab: a CAEN bridge with CAEN VMELib installed; PFMA_LAB_CAEN (default
    caen://V1718/0) names it, PFMA_LAB_ADDR (default 0x0100, the first resolver board of
    the default rack) a register that answers, PFMA_LAB_DEAD (default 0x8000) an
    address no board answers."""
    url = os.environ.get("PFMA_LAB_CAEN", "caen://V1718/0")
    try:
        bus = open_bus(url)
    except BusUrlError as err:
        pytest.skip(str(err))
    except LinkError as err:
        pytest.skip(f"no bridge at {url}: {err}")
    with bus:
        value = bus.read16(int(os.environ.get("PFMA_LAB_ADDR", "0x0100"), 0))
        assert 0 <= value <= 0xFFFF
        with pytest.raises(BusError):
            bus.read16(int(os.environ.get("PFMA_LAB_DEAD", "0x8000"), 0))

