"""`pfma bridge` end to end: a real `pfma serve` process, a `pfma bridge --commands`
process, a remote commander process on tcp/127.0.0.1 that is SIGKILLed. Nothing here is
timed: every wait is bounded polling for a state."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.layout import ServiceState
from tests.tools.bridge.test_bridge import free_port
from tools.cli import main

pytest.importorskip("zenoh")

ROOT = Path(__file__).resolve().parents[3]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
WAIT_S = 20.0


def pfma_proc(*argv: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "tools.cli", *argv], cwd=ROOT, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def until(cond, what: str, procs=()) -> None:
    end = time.monotonic() + WAIT_S
    while not cond():
        for p in procs:
            if p.poll() is not None:
                raise AssertionError(f"{what}: {p.args[3:5]} exited: {p.communicate()}")
        if time.monotonic() > end:
            raise AssertionError(f"not within {WAIT_S} s: {what}")
        time.sleep(0.01)


COMMANDER = textwrap.dedent("""
    import sys, time
    from tools.bridge.remote import RemoteBuffer, RemoteCommander
    from tools.bridge.session import open_session
    endpoint, name = sys.argv[1], sys.argv[2]
    remote = RemoteBuffer(open_session(connect=[endpoint]), name, timeout_s=20)
    remote.wait("inputs", timeout_s=20)
    cmd = RemoteCommander(remote, "far-commander")
    n = len(remote.layout.joint_names)
    cmd.write_commands(joint_rate_rad_s=[0.0] * n, arm_request=1, rearm_counter=1,
                       current_limit_a=[1.0] * len(remote.layout.current_limit_names))
    print("armed", flush=True)
    while True:  # a keep-alive every 2 ms until killed
        cmd.write_commands()
        time.sleep(0.002)
""")


@pytest.mark.realtime
def test_a_killed_remote_commander_trips_the_services_watchdog():
    name = "pfma-bridge-e2e-" + uuid.uuid4().hex[:6]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    # a 300 ms watchdog: a loaded CI host must not trip it while the commander lives
    serve = pfma_proc("serve", "--buffer", name, "--duration", "60", "--watchdog-ms", "300")
    procs = [serve]
    try:
        until(lambda: Bit3Buffer.owner_alive(name)[0], "the service up", procs)
        bridge = pfma_proc("bridge", "--buffer", name, "--listen", endpoint, "--commands")
        procs.append(bridge)
        commander = subprocess.Popen([sys.executable, "-c", COMMANDER, endpoint, name], cwd=ROOT, env=ENV,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(commander)
        with Client.attach(name) as c:
            until(lambda: ServiceState(c.read_inputs().service_state) is ServiceState.ARMED,
                  "armed by the remote commander", procs)
            assert c.owners()["commands"].name == "pfma-bridge"
            commander.kill()  # SIGKILL: no goodbye
            commander.communicate(timeout=10)
            procs.remove(commander)
            until(lambda: ServiceState(c.read_inputs().service_state) is ServiceState.FAULT,
                  "the watchdog trip", procs)
            s = c.read_inputs()
            assert s.watchdog_tripped and np.abs(s.dac_value).max() == 0.0
            texts = [m.text for m in c.messages(queue="controller")]
            assert any("'far-commander' holds the command area" in t for t in texts), texts
            until(lambda: any("'far-commander' gone" in m.text for m in c.messages(queue="controller")),
                  "the bridge says the writer left (its session's close or the lease)", procs)
            texts = [m.text for m in c.messages(queue="controller")]
            assert sum(t.startswith("bridge:") for t in texts) == 2, texts  # said once each
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        outs = [p.communicate(timeout=30) for p in procs]
        Bit3Buffer.unlink(name)
    for p, (out, err) in zip(procs, outs):
        assert "Traceback" not in err, err


@pytest.mark.parametrize("argv, code, words", [
    (["bridge", "--listen", "127.0.0.1:7447"], 2, "is not tcp/HOST:PORT"),
    (["bridge", "--buffer", "a/b"], 2, "may hold only letters"),
    (["bridge", "--buffer", "pfma-no-such-bridge-buffer"], 1, "no I/O service runs on buffer"),
    (["bridge", "--operator", "ops"], 2, "--operator needs --users"),
    (["bridge", "--users", "/nonexistent/pfma-users"], 2, "cannot read the Zenoh credentials"),
    (["bridge", "--users", "/dev/null"], 2, "no user:password line"),
])
def test_bad_bridge_input_is_one_message(argv, code, words, capsys):
    assert main(argv) == code
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and err.count("\n") == 1


@pytest.mark.realtime
def test_bridge_commands_refused_while_a_local_controller_holds_the_area(capsys):
    """--commands claims the command area as a controller does: a live local controller
    refuses it, named, one line, exit 1; without --commands the bridge runs beside it."""
    from sim.rig import SimRig
    with SimRig(prefix="pfma-test-bridge-cli-") as rig:
        rig.controller("local-ctl")
        ep = f"tcp/127.0.0.1:{free_port()}"
        assert main(["bridge", "--buffer", rig.name, "--listen", ep, "--commands", "--duration", "0.1"]) == 1
        err = capsys.readouterr().err
        assert "'local-ctl'" in err and "Traceback" not in err and err.count("\n") == 1
        assert main(["bridge", "--buffer", rig.name, "--listen", ep, "--duration", "0.1"]) == 0
        assert "(read-only)" in capsys.readouterr().err


@pytest.mark.realtime
def test_sigterm_stops_the_bridge_in_order_and_releases_the_command_area():
    """SIGTERM (a process manager's stop; SIGINT ignored as a shell's background job has it)
    ends `pfma bridge --commands` through its orderly close: the summary line, exit 0, and
    the command area free for the next writer (before: killed at once, no summary)."""
    name = "pfma-test-brsig-" + uuid.uuid4().hex[:6]
    svc = pfma_proc("serve", "--rack", "fake", "--buffer", name, "--duration", "60")
    bridge = None
    try:
        until(lambda: os.path.exists(f"/dev/shm/{name}"), "the service's buffer", (svc,))
        time.sleep(0.5)
        bridge = subprocess.Popen([sys.executable, "-m", "tools.cli", "bridge", "--buffer", name, "--commands",
                                   "--listen", f"tcp/127.0.0.1:{free_port()}"], cwd=ROOT, env=ENV,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
        c = Client.attach(name)
        try:
            until(lambda: c.owners()["commands"].pid == bridge.pid, "the bridge's command claim", (svc, bridge))
            bridge.send_signal(signal.SIGTERM)
            _, err = bridge.communicate(timeout=WAIT_S)
            assert bridge.returncode == 0, err
            assert "pfma bridge: stopped; published" in err and "Traceback" not in err
            until(lambda: c.owners()["commands"].pid != bridge.pid, "the command area released")
        finally:
            c.close()
    finally:
        for p in (bridge, svc):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(WAIT_S)
                except subprocess.TimeoutExpired:
                    p.kill()
        Bit3Buffer.unlink(name)
        from bit3.ring import FrameRing
        FrameRing.unlink(name)


@pytest.mark.realtime
def test_a_bridge_with_users_serves_a_tool_with_credentials_and_not_one_without(tmp_path):
    """`pfma bridge --users FILE --operator ops` (processes, loopback): `pfma read` through
    it with $PFMA_ZENOH_CREDENTIALS of a user in the file reads the service's frame; the same
    tool without credentials gets one line and exit 1 (not connected: no layout answer)."""
    name = "pfma-test-brusr-" + uuid.uuid4().hex[:6]
    users = tmp_path / "users"
    users.write_text("ops:ops-pw\nviewer:viewer-pw\n")
    users.chmod(0o600)
    creds = tmp_path / "creds"
    creds.write_text("viewer:viewer-pw\n")
    creds.chmod(0o600)
    port = free_port()
    svc = pfma_proc("serve", "--rack", "fake", "--buffer", name, "--duration", "60")
    bridge = None
    try:
        until(lambda: os.path.exists(f"/dev/shm/{name}"), "the service's buffer", (svc,))
        bridge = pfma_proc("bridge", "--buffer", name, "--listen", f"tcp/127.0.0.1:{port}",
                           "--users", str(users), "--operator", "ops", "--duration", "60")
        url = f"zenoh://127.0.0.1:{port}/{name}"
        ok = None
        end = time.monotonic() + WAIT_S
        while time.monotonic() < end:  # the bridge may still be starting: ask again, bounded
            ok = subprocess.run([sys.executable, "-m", "tools.cli", "read", "elbow_pitch_angle", "--buffer", url],
                                cwd=ROOT, env=dict(ENV, PFMA_ZENOH_CREDENTIALS=str(creds)),
                                capture_output=True, text=True, timeout=60)
            if ok.returncode == 0:
                break
        assert ok is not None and ok.returncode == 0, ok
        assert "Traceback" not in ok.stderr
        env = {k: v for k, v in ENV.items() if k != "PFMA_ZENOH_CREDENTIALS"}
        no = subprocess.run([sys.executable, "-m", "tools.cli", "read", "elbow_pitch_angle", "--buffer", url],
                            cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
        assert no.returncode == 1, no
        assert "PFMA_ZENOH_CREDENTIALS" in no.stderr and "Traceback" not in no.stderr
        assert no.stderr.count("\n") == 1, no.stderr
    finally:
        for p in (bridge, svc):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(WAIT_S)
                except subprocess.TimeoutExpired:
                    p.kill()
        Bit3Buffer.unlink(name)
        from bit3.ring import FrameRing
        FrameRing.unlink(name)
