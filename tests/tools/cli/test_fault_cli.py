"""``pfma fault`` and the serve side of it (``--fault``, ``--scenario``, the control endpoint).

In-process: a SimRig's service with :func:`install_serve_faults`, the ``pfma fault`` client
in a thread while the test steps the loop's frames (the endpoint only queues; the loop
applies). One end-to-end case runs a real ``pfma serve`` subprocess (polling for its
socket with a time-out). Bad inputs: exit codes, one message, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from bit3.buffer import Bit3Buffer
from bit3.layout import LINK_STALE
from sim.rig import SimRig
from sim.scenario import load_scenario
from tools.cli import main
from tools.cli.fault import add_serve_fault_args, install_serve_faults
from tools.faultctl import MSG_FAULT_OFF, MSG_FAULT_ON, NO_ENDPOINT, request, socket_path

ROOT = Path(__file__).resolve().parents[3]


def serve_args(name, fault=(), scenario=None):
    return argparse.Namespace(fault=list(fault), scenario=scenario, buffer=name)


@pytest.fixture
def served():
    """A simulated service with its fault endpoint (what ``pfma serve`` builds), not yet running."""
    rig = SimRig(prefix="pfma-fcli-")
    try:
        yield rig
    finally:
        rig.close()


def while_stepping(rig, fn, wall_s=20.0):
    """Run ``fn`` in a thread while this thread steps the service's frames; its result."""
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("r", fn()), daemon=True)
    t.start()
    deadline = time.monotonic() + wall_s
    while t.is_alive() and time.monotonic() < deadline:
        rig.run_frames(1)
    t.join(1.0)
    assert not t.is_alive(), "the client did not finish"
    return out["r"]


def cli(rig, capsys, *argv):
    rc = while_stepping(rig, lambda: main(["fault", *argv, "--buffer", rig.name]))
    cap = capsys.readouterr()
    assert "Traceback" not in cap.out + cap.err
    return rc, cap.out, cap.err


def messages(rig):
    return [(m.code, m.text) for m in rig.reader.messages()]


def test_serve_faults_from_the_first_frame_posted_and_endpoint_0600(served, capsys):
    install_serve_faults(serve_args(served.name, ["ft-unplugged"]), served.svc, served.world)
    path = socket_path(served.name)
    assert stat.S_ISSOCK(os.stat(path).st_mode) and stat.S_IMODE(os.stat(path).st_mode) == 0o600
    served.run(0.5)
    s = served.reader.read_inputs()
    assert s.link_status[served.layout.slot("link", "ft_sensor")] & LINK_STALE
    assert (MSG_FAULT_ON, "simulated fault on: ft-unplugged") in messages(served)
    assert f"fault control on {path}" in capsys.readouterr().out
    served.close()
    assert not os.path.exists(path)  # removed when the service stops


def test_inject_list_clear_through_the_endpoint(served, capsys):
    install_serve_faults(serve_args(served.name), served.svc, served.world)
    served.run(0.2)
    rc, out, _ = cli(served, capsys, "inject", "resolver-los:shoulder_pitch_angle")
    assert rc == 0 and "injected resolver-los:shoulder_pitch_angle: loss of signal" in out
    served.run(0.1)
    s = served.reader.read_inputs()
    assert s.rtd_status[served.layout.slot("rtd", "shoulder_pitch_angle")] & 1
    rc, out, _ = cli(served, capsys, "inject", "serial-noise:ft_sensor")
    rc, out, _ = cli(served, capsys, "list", "--active", "--json")
    assert rc == 0
    specs = [f["spec"] for f in json.loads(out)["faults"]]
    assert specs == ["resolver-los:shoulder_pitch_angle", "serial-noise:ft_sensor"]
    rc, out, _ = cli(served, capsys, "list", "--active")
    assert rc == 0 and out.count("since frame") == 2
    rc, out, _ = cli(served, capsys, "clear", "resolver-los:shoulder_pitch_angle")
    assert rc == 0 and "cleared resolver-los:shoulder_pitch_angle" in out
    served.run(0.1)
    assert served.reader.read_inputs().rtd_status[served.layout.slot("rtd", "shoulder_pitch_angle")] == 0
    rc, out, _ = cli(served, capsys, "clear", "all")
    assert rc == 0 and "cleared serial-noise:ft_sensor" in out
    texts = messages(served)
    assert (MSG_FAULT_ON, "simulated fault on: resolver-los:shoulder_pitch_angle") in texts
    assert (MSG_FAULT_OFF, "simulated fault off: serial-noise:ft_sensor") in texts
    rc, out, _ = cli(served, capsys, "list", "--active")
    assert rc == 0 and "no simulated fault active" in out


def test_refusals_exit_codes_and_messages(served, capsys):
    install_serve_faults(serve_args(served.name, ["ft-noise"]), served.svc, served.world)
    rc, _, err = cli(served, capsys, "inject", "resolver-los:shoulder_pich_angle")
    assert rc == 2 and "did you mean shoulder_pitch_angle" in err  # refused before asking
    rc, _, err = cli(served, capsys, "inject", "serial-noise:ft_sensor")
    assert rc == 1 and "already active (as 'ft-noise')" in err
    rc, _, err = cli(served, capsys, "clear", "ft-unplugged")
    assert rc == 1 and "not active; active: ft-noise" in err
    # the service checks a spec too (another client may skip the check): exit 2 in the reply
    reply = while_stepping(served, lambda: request(served.name, {"op": "inject", "spec": "bus-error:adcc"}))
    assert reply["ok"] is False and reply["exit"] == 2 and "did you mean adc" in reply["error"]
    reply = while_stepping(served, lambda: request(served.name, {"op": "teleport"}))
    assert reply["exit"] == 2


def test_garbage_on_the_socket_gets_an_error_line(served):
    install_serve_faults(serve_args(served.name), served.svc, served.world)
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(5)
        s.connect(socket_path(served.name))
        s.sendall(b"not json\n")
        reply = json.loads(s.recv(4096).split(b"\n")[0])
    assert reply["ok"] is False and "not a JSON request" in reply["error"]


def test_a_request_the_loop_does_not_take_changes_nothing(served):
    install_serve_faults(serve_args(served.name), served.svc, served.world)
    reply = request(served.name, {"op": "inject", "spec": "ft-unplugged"})  # no frame runs
    assert reply["ok"] is False and "nothing was changed" in reply["error"]
    served.run_frames(2)  # the abandoned request is dropped, not applied late
    assert served.world.bus["sio"].peer(0).device is not None


def test_fault_list_names_the_targets_after_the_kinds(capsys):
    """Issue 32: the list names what each argument accepts (the errors always did), after
    the unchanged one-line-per-kind rows; --json gives each kind its targets."""
    from sim.faults import KINDS, kinds_help, targets_help
    assert main(["fault", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[:len(KINDS)] == kinds_help()
    assert lines[len(KINDS):] == targets_help()
    assert lines[len(KINDS)].startswith("targets in rack pfma")
    assert "  BOARD (bus-error): rtd1, rtd2, dac, adc, sio, pio_user, pio_video" in lines
    assert main(["fault", "list", "--json"]) == 0
    rows = {r["kind"]: r for r in json.loads(capsys.readouterr().out)}
    assert list(rows) == list(KINDS)
    assert rows["stuck-bit"]["targets"]["REG"]["dac"] == ["DAC[0..15]"]
    assert rows["serial-drop"]["targets"] == {"LINE": ["ft_sensor", "crl_hand_controller"]}
    assert rows["ft-unplugged"]["targets"] == {}
    assert main(["fault", "inject", "stuck-bit:dac@CTRL:8=1", "--buffer", "pfma-fcli-none"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "shares its address (+0x00) with DAC[0]" in err


def test_no_endpoint_real_rack_or_none(capsys):
    name = "pfma-fcli-none-" + uuid.uuid4().hex[:6]
    assert main(["fault", "inject", "ft-unplugged", "--buffer", name]) == 1
    cap = capsys.readouterr()
    assert cap.err.strip() == "pfma fault: " + NO_ENDPOINT.format(name=name)
    assert main(["fault", "list", "--active", "--buffer", name]) == 1
    assert "Traceback" not in capsys.readouterr().err


def test_stale_socket_is_named_by_the_client_and_replaced_by_serve(served, capsys):
    path = socket_path(served.name)
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(path)  # a killed service's socket: the file stays, nobody listens
    dead.close()
    assert main(["fault", "list", "--active", "--buffer", served.name]) == 1
    assert "is stale: the service that made it is gone" in capsys.readouterr().err
    install_serve_faults(serve_args(served.name), served.svc, served.world)
    rc, out, _ = cli(served, capsys, "list", "--active")
    assert rc == 0


def test_real_rack_opens_nothing_and_refuses_fault_flags(capsys):
    class Svc:  # a service on a real rack: install_serve_faults must not touch it
        pass
    install_serve_faults(serve_args("pfma-real"), Svc(), None)
    assert not os.path.exists(socket_path("pfma-real"))
    with pytest.raises(SystemExit) as e:
        install_serve_faults(serve_args("pfma-real", ["ft-noise"]), Svc(), None)
    assert e.value.code == 2 and "need the simulated rack" in capsys.readouterr().err


@pytest.mark.parametrize("argv, says", [
    (["--fault", "bus-eror:adc"], "did you mean bus-error"),
    (["--fault", "resolver-los:elbow_pich_angle"], "did you mean elbow_pitch_angle"),
    (["--scenario", "/nonexistent/s.toml"], "scenario /nonexistent/s.toml: No such file"),
])
def test_serve_flags_checked_while_parsing(argv, says, capsys):
    p = argparse.ArgumentParser(prog="pfma serve")
    add_serve_fault_args(p)
    with pytest.raises(SystemExit) as e:
        p.parse_args(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and says in err and "Traceback" not in err


def test_bad_scenario_file_refused_while_parsing_naming_the_line(tmp_path, capsys):
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\n\n[[step]]\nat_s = 1\ninject = "ft-nose"\n')
    p = argparse.ArgumentParser(prog="pfma serve")
    add_serve_fault_args(p)
    with pytest.raises(SystemExit):
        p.parse_args(["--scenario", str(f)])
    assert f"scenario {f} line 3 (inject at 1 s): fault 'ft-nose': unknown kind" in capsys.readouterr().err


def test_scenario_scheduled_on_the_loops_frames_and_posted(served, capsys):
    sc = load_scenario(ROOT / "scenarios" / "ft-unplug.toml")
    install_serve_faults(serve_args(served.name, scenario=sc), served.svc, served.world)
    served.run(1.5)
    s = served.reader.read_inputs()
    assert s.link_status[served.layout.slot("link", "ft_sensor")] & LINK_STALE
    served.run(3.0)
    texts = [t for c, t in messages(served) if c in (MSG_FAULT_ON, MSG_FAULT_OFF)]
    assert texts == ["simulated fault on: ft-unplugged", "simulated fault off: ft-unplugged",
                     "simulated fault on: serial-noise:ft_sensor", "simulated fault off: serial-noise:ft_sensor"]
    out = capsys.readouterr().out
    assert "scenario ft-unplug: 4 steps" in out and "frame 320: injected simulated fault ft-unplugged" in out


# -- end to end: a real `pfma serve` process ----------------------------------------------------------


@pytest.mark.realtime
def test_end_to_end_with_a_serve_process():
    name = "pfma-fcli-e2e-" + uuid.uuid4().hex[:6]
    path = socket_path(name)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "tools.cli", "serve", "--buffer", name, "--duration", "30",
                             "--fault", "resolver-los:wrist_yaw_angle"],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not os.path.exists(path) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # polling for the service to come up, bounded
        assert os.path.exists(path), proc.communicate(timeout=10) if proc.poll() is not None else "no socket"

        def pfma(*argv):
            r = subprocess.run([sys.executable, "-m", "tools.cli", "fault", *argv, "--buffer", name],
                               cwd=ROOT, env=env, capture_output=True, text=True, timeout=30)
            assert "Traceback" not in r.stderr
            return r
        r = pfma("inject", "ft-unplugged")
        assert r.returncode == 0 and "injected ft-unplugged" in r.stdout
        r = pfma("list", "--active", "--json")
        assert [f["spec"] for f in json.loads(r.stdout)["faults"]] == ["resolver-los:wrist_yaw_angle",
                                                                         "ft-unplugged"]
        r = pfma("inject", "bus-error:adcc")
        assert r.returncode == 2 and "did you mean adc" in r.stderr
        r = pfma("clear", "all")
        assert r.returncode == 0 and r.stdout.count("cleared") == 2
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        Bit3Buffer.unlink(name)
    assert proc.returncode == 0, err
    assert "injected simulated fault ft-unplugged" in out and "Traceback" not in err
    assert not os.path.exists(path)  # removed at exit


def test_an_unexpected_error_is_answered_and_the_loop_runs_on(served, monkeypatch):
    from sim.faults import FaultSet
    install_serve_faults(serve_args(served.name), served.svc, served.world)

    def boom(self, spec, since=None):
        raise RuntimeError("boom")
    monkeypatch.setattr(FaultSet, "inject", boom)
    reply = while_stepping(served, lambda: request(served.name, {"op": "inject", "spec": "ft-noise"}))
    assert reply == {"ok": False, "exit": 1, "error": "RuntimeError: boom"}
    k = served.svc.loop.k
    served.run_frames(3)
    assert served.svc.loop.k == k + 3


def test_checkout_sim_fault_takes_the_same_specs(capsys):
    from tools.checkout.target import SimTarget
    assert {"tach-reversed:JOINT", "adc-dead:SIGNAL=VOLTS", "ft-noise"} <= set(SimTarget.FAULTS)
    rc = main(["checkout", "--non-interactive", "-q", "--only", "links", "--sim-fault", "serial-drop:ft_sensor"])
    out = capsys.readouterr().out
    assert rc == 1 and "injected fault: 3 bytes lost every 300 on ft_sensor" in out
    assert "FAILED: ft_sensor (links, bad records)" in out


def test_a_buffer_name_too_long_for_a_socket_runs_without_the_endpoint(capsys):
    name = "pfma-fcli-" + "x" * 100  # /dev/shm/NAME.faults beyond the 108-byte socket path
    with SimRig(name=name) as rig:
        install_serve_faults(serve_args(name, ["ft-noise"]), rig.svc, rig.world)
        assert "no fault control endpoint" in capsys.readouterr().err
        assert rig.world.ft._noise_every is not None  # --fault applied all the same
    assert main(["fault", "list", "--active", "--buffer", name]) == 1
    assert "Traceback" not in capsys.readouterr().err


def test_hand_unplugged_also_pulls_a_simulated_usb_six_axis(served, capsys):
    """``pfma serve --hid fake``: the service's HID slot holds a HidSpaceMouse on a
    FakeHidDevice; install_serve_faults hands that fake to the faults."""
    from drivers.crl.hid import HidSpaceMouse
    from fakes.hid import FakeHidDevice
    dev = FakeHidDevice()
    assert served.svc.hand.wire_hid(HidSpaceMouse(opener=dev, clock=served.clock), "fake SpaceMouse",
                                    simulated=True, thread=False)
    install_serve_faults(serve_args(served.name), served.svc, served.world)
    hid = served.layout.slot("hc", "hid")
    served.run(0.3)
    assert served.reader.read_inputs().hc_valid[hid]
    rc, out, _ = cli(served, capsys, "inject", "hand-unplugged")
    served.run(0.5)
    assert rc == 0 and not dev.plugged and not served.reader.read_inputs().hc_valid[hid]
    rc, out, _ = cli(served, capsys, "clear", "hand-unplugged")
    served.run(2.0)  # the driver retries the open every second of the service's clock
    assert rc == 0 and dev.plugged and served.reader.read_inputs().hc_valid[hid]
