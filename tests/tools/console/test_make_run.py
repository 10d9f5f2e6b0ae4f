"""`make run` is the system the README describes (issue 29 item 6; docs/console.md "Names"):
it takes the buffer and world model every tool reads by default unless a live system has
one of them, then a private pair said in one line; a leftover of a dead run does not block
it; the console names what it reads on screen; the simulated system keeps the frame ring and
the fault socket `pfma serve --rack fake` keeps, and removes all of it when it ends.

The deterministic tests use unique names (tests run side by side). The two that take the
default name `pfma` start processes and are realtime (run alone); both leave `pfma` as they
found it. That both branches of `make run` take the defaults when free and every (service)
line of the README runs beside them: tests/tools/test_readme.py.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.ring import FrameRing
from controller.worldmodel import WorldModel
from pfma.errors import PfmaError
from sim.rig import SimRig
from sim.system import SystemSimulator
from tests.tools.console._pilot import screen_text
from tests.tools.console.test_sizes import run_at
from tools import runnames
from tools.runnames import claim

ROOT = Path(__file__).resolve().parents[3]
PFMA = str(Path(sys.executable).with_name("pfma"))


@pytest.fixture
def name():
    """A unique buffer name (and ``name + '_wm'`` for its world model); whatever a test left
    under either is removed."""
    n = f"pfma-mkrun-{uuid.uuid4().hex[:8]}"
    yield n
    assert not [f for f in os.listdir("/dev/shm") if f.startswith(n)], "a test left its names in /dev/shm"


def _shm(*names: str) -> list[str]:
    return [n for n in names if os.path.exists(f"/dev/shm/{n}")]


# --- the names ---------------------------------------------------------------------------------
def test_free_names_are_taken_as_asked(name):
    got = claim(name, f"{name}_wm")
    assert (got.buffer, got.wm, got.note, got.private) == (name, f"{name}_wm", None, False)
    assert got.reach() == f"--buffer {name} --wm {name}_wm"


def test_the_leftovers_of_a_dead_run_do_not_block_it(name):
    """A crashed run's buffer (its owner record names a pid, its claim lock is gone with the
    process) and its world model (owner gone) are not in use: the names are taken over them."""
    buf = Bit3Buffer.create(name)
    buf.claim("service", "pfma-ioservice", simulated=True)
    buf.close()  # no release, no unlink: what a killed service leaves (the lock goes with the fd)
    sim = SystemSimulator(wm_name=f"{name}_wm")
    sim.close()  # the world model stays, its owner gone (as after `pfma controller --sim`)
    assert _shm(name, f"{name}_wm") == [name, f"{name}_wm"]
    assert Bit3Buffer.owner_alive(name)[0] is False and runnames.wm_in_use(f"{name}_wm") is None
    got = claim(name, f"{name}_wm")
    assert (got.buffer, got.wm, got.note) == (name, f"{name}_wm", None)
    from tools.console.simrun import SimulatedSystem
    system = SimulatedSystem(buffer=name, wm=f"{name}_wm", power_up=False)  # the creates do not refuse
    try:
        assert Bit3Buffer.owner_alive(name)[0] is True
    finally:
        system.close()


def test_a_live_service_on_the_buffer_moves_the_pair_to_private_names_said_in_one_line(name):
    with SimRig(name=name):  # a live service holds the buffer's claim lock
        got = claim(name, f"{name}_wm")
        assert got.private and got.buffer.startswith(runnames.PRIVATE_PREFIX) and got.wm == f"{got.buffer}_wm"
        assert got.note is not None and "\n" not in got.note
        assert got.note.startswith(f"a service already runs on buffer {name!r} (owned by ")
        assert got.note.endswith(f"reach it with --buffer {got.buffer} --wm {got.wm}")
        assert not _shm(got.buffer, got.wm)  # named, not made: the caller makes them
        assert Bit3Buffer.owner_alive(name)[0] is True  # the live one untouched
        with pytest.raises(PfmaError) as err:
            claim(name, f"{name}_wm", fallback=False)
        assert "--buffer NAME" in str(err.value)


def test_a_live_controller_on_the_world_model_moves_the_pair_too(name):
    sim = SystemSimulator(wm_name=f"{name}_wm")  # this process owns it: alive
    try:
        got = claim(name, f"{name}_wm")
        assert got.private and got.note is not None
        assert got.note.startswith(f"a controller already runs on world model '{name}_wm'")
        with pytest.raises(PfmaError) as err:
            claim(name, f"{name}_wm", fallback=False)
        assert "--wm NAME" in str(err.value)
    finally:
        sim.close()
        WorldModel.remove_segment(f"{name}_wm")


def test_an_explicit_name_in_use_is_refused_in_one_line(name, capsys):
    from tools.cli import main
    with SimRig(name=name):
        rc = main(["console", "--sim", "--buffer", name, "--wm", f"{name}_wm"])
    out, err = capsys.readouterr()
    assert rc == 1 and out == "" and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert err.startswith(f"pfma console: a service already runs on buffer {name!r}") and "--buffer NAME" in err
    assert not _shm(f"{name}_wm")


def test_a_remote_buffer_for_the_simulated_system_is_one_message_exit_2(capsys):
    from tools.cli import main
    rc = main(["console", "--sim", "--buffer", "zenoh://127.0.0.1:7447/pfma"])
    out, err = capsys.readouterr()
    assert rc == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert err.startswith("pfma console: --sim runs the simulated system here") and "zenoh://" in err


# --- the simulated system on those names -------------------------------------------------------
def test_the_simulated_system_keeps_what_serve_keeps_and_removes_it_all(name):
    """The frame ring (pfma record, watch, scope), the fault socket (pfma fault) and a named
    world model (pfma wm, pfma console) beside the buffer; none of them after close."""
    from tools.faultctl import socket_path
    from tools.console.simrun import SimulatedSystem
    wm = f"{name}_wm"
    system = SimulatedSystem(buffer=name, wm=wm)
    try:
        assert system.name == name and system.fault_note is None
        assert _shm(name, f"{name}.ring", f"{name}.faults", wm) == [name, f"{name}.ring", f"{name}.faults", wm]
        assert socket_path(name) == f"/dev/shm/{name}.faults"
        system.sim.step(20)
        ring = FrameRing.attach(name)
        try:
            assert ring.count() >= 20
        finally:
            ring.close()
        c = Client.attach(name)  # another tool: the defaults of the layout, a reader
        try:
            assert c.read_inputs().frame >= 20
        finally:
            c.close()
        info = WorldModel.attach(wm).close_after(lambda m: m.info())
        assert info.owner_alive and info.owner_pid == os.getpid()
        system.stop()
    finally:
        system.close()
    assert not _shm(name, f"{name}.ring", f"{name}.faults", wm)


@pytest.mark.parametrize("size", [(80, 24), (120, 40)], ids=["80x24", "120x40"])
def test_the_console_names_the_buffer_and_world_model_it_reads(sim, reader, size):
    from tools.console import view
    from tools.console.app import ConsoleApp
    from tools.console.control import ControllerLink
    sources = view.Sources(reader, sim.rt.wm, rack="simulated")
    sources.names = f"buffer {sim.name}, world model pfma-sim-0123abcd_wm"
    app = ConsoleApp(sources, ControllerLink(sim.rt.wm), auto_refresh=False)

    async def body(pilot):
        await pilot.pause()
        assert f"World Status (buffer {sim.name}, world model pfma-sim-0123abcd_wm)" in screen_text(app)
    run_at(app, size, body)


# --- make run beside a live service on pfma (the default name: realtime) -----------------------
@pytest.fixture
def pfma_held():
    """A live service on the default buffer ``pfma`` (this process holds its claim lock), as
    a user's `pfma serve` would; a leftover there is cleared first, nothing is left after."""
    alive, who = Bit3Buffer.owner_alive(runnames.DEFAULT_BUFFER)
    if alive:
        pytest.skip(f"a live service owns /dev/shm/pfma ({who}); this test would disturb it")
    claim(runnames.DEFAULT_BUFFER, None, fallback=False)  # a dead run's leftover removed
    rig = SimRig(name=runnames.DEFAULT_BUFFER)
    try:
        yield rig
    finally:
        rig.close()
    assert not Bit3Buffer.owner_alive(runnames.DEFAULT_BUFFER)[0]


def _private_line(text: str, verb: str) -> tuple[str, str]:
    """The one line saying the default is in use: (the whole line, the private buffer)."""
    lines = [ln for ln in text.splitlines() if ln.startswith(f"pfma {verb}: a service already runs")]
    assert len(lines) == 1, text[-3000:]
    m = re.fullmatch(rf"pfma {verb}: a service already runs on buffer 'pfma' \(owned by .*\); this system runs "
                     r"on the private buffer '(pfma-sim-[0-9a-f]{8})'.* instead: reach it with --buffer "
                     r"(pfma-sim-[0-9a-f]{8}).*", lines[0].strip())
    assert m and m.group(1) == m.group(2), lines[0]
    return lines[0], m.group(1)


@pytest.mark.realtime
def test_make_run_on_a_terminal_beside_a_service_on_pfma_runs_privately_names_it_and_leaves_nothing(pfma_held):
    from tests.tools.test_readme import _Pty
    term = _Pty([PFMA, "console", "--sim"])  # make run's terminal branch
    try:
        assert term.seen(b"World Status (buffer pfma-sim-", 60.0), term.out[-2000:]
        # reached as the line says, while it runs
        _, private = _private_line(term.out.decode(errors="replace").replace("\r", ""), "console")
        p = subprocess.run([PFMA, "read", "elbow_pitch_angle", "--buffer", private], capture_output=True,
                           text=True, timeout=60)
        assert p.returncode == 0 and "from the service" in p.stdout, p.stdout + p.stderr
        os.write(term.fd, b"q")
        status = term.wait(60)
    finally:
        term.close()
    assert status is not None and os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0, term.out[-2000:]
    assert f"buffer {private} and world model {private}_wm removed".encode() in term.out
    assert not _shm(private, f"{private}.ring", f"{private}.faults", f"{private}_wm")
    assert Bit3Buffer.owner_alive("pfma")[0] is True  # the live service's buffer untouched


@pytest.mark.realtime
def test_make_run_off_a_terminal_beside_a_service_on_pfma_runs_privately_and_says_so(pfma_held):
    recipe = re.search(r"else \$\(BIN\)/(pfma serve [^;]*);", (ROOT / "Makefile").read_text())
    assert recipe, "the Makefile's run target has no `pfma serve` branch"
    argv = [PFMA, *recipe.group(1).split()[1:], "--duration", "2"]  # the recipe, bounded
    assert "--private-if-busy" in argv
    p = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    out = p.stdout + p.stderr
    assert p.returncode == 0 and "Traceback" not in out, out[-3000:]
    _, private = _private_line(out, "serve")
    assert f"buffer /dev/shm/{private}, " in out  # its start line names it too
    assert not _shm(private, f"{private}.ring", f"{private}.faults")  # a private name is not left behind
    assert Bit3Buffer.owner_alive("pfma")[0] is True
