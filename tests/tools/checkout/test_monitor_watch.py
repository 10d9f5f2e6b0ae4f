"""`pfma monitor --once`, `pfma watch --count` against a running (simulated-time) service;
waiting for a service that is not up, reattaching after a restart, never hanging."""

import math
import re
import uuid

import pytest

from tools.checkout import Checkout, LiveTarget
from tools.attach import ServiceLink, attach_waiting
from bit3.client import Client
from tools.cli import main
from pfma.errors import PfmaTimeoutError
from pfma.show import wrap_angle
from sim.rig import SimRig as Rig


def test_monitor_once_shows_every_channel_with_units_status_and_links(rig, capsys):
    rig.run(1.0)
    rig.svc.publish_stats()
    assert main(["monitor", "--buffer", rig.name, "--once"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert "state SAFE" in lines[0] and f"buffer {rig.name}" in lines[0]
    for c in rig.reader.layout.channels:
        if c.area == "inputs":
            assert any(line.startswith(c.name) for line in lines), c.name
    row = next(line for line in lines if line.startswith("elbow_pitch_angle "))
    angle = wrap_angle(rig.reader.read_inputs().value("elbow_pitch_angle"))  # 0..2 pi shown in (-pi, pi]
    assert angle < 0 < rig.reader.read_inputs().value("elbow_pitch_angle")  # the rig's elbow: just below 0
    assert f"{angle:+.4f}" in row and " rad " in row and "160.0" in row  # value, units, rate
    assert row.split()[4] == "ok" and f"{math.degrees(angle):+.1f} deg" in row  # status; degrees labelled
    ft = next(line for line in lines if line.startswith("ft_sensor "))
    assert ft.split()[4] == "ok" and re.search(r"bad \d+ resyncs \d+", ft)  # open and synced: ok
    assert "messages:" in out and "service started" in out


def _row_names(out: str) -> list[str]:
    """The channel names of a monitor snapshot: the rows between the column header and the
    blank line before the messages."""
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("name ")) + 1
    rows = lines[start:]
    rows = rows[:rows.index("")] if "" in rows else rows
    return [r.split()[0] for r in rows]


def test_monitor_filter(rig, capsys):
    rig.run(0.2)
    assert main(["monitor", "--buffer", rig.name, "--once", "--filter", "wrist"]) == 0
    names = _row_names(capsys.readouterr().out)
    assert names and all("wrist" in n for n in names)
    assert "wrist_roll_angle" in names and "shoulder_yaw_angle" not in names
    assert main(["monitor", "--buffer", rig.name, "--once", "--filter", "*_motor_current"]) == 0
    names = _row_names(capsys.readouterr().out)
    assert "elbow_pitch_motor_current" in names and "elbow_pitch_rate" not in names


def test_watch_count_prints_one_line_per_sample(rig, capsys):
    rig.world.set_cae([5.0, 0, 0, 0, 0, 0])
    rig.run(0.3)
    assert main(["watch", "elbow_pitch_angle", "cae_up_down", "ft_force_n[2]", "service_state",
                 "--buffer", rig.name, "--count", "3", "--rate", "500"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3
    s = rig.reader.read_inputs()
    for line in lines:
        assert line.startswith(f"t={s.t_s:.4f} s")
        assert f"elbow_pitch_angle={wrap_angle(s.value('elbow_pitch_angle')):+.4f} rad [ok]" in line
        # 5 V through the anti-aliasing filter, read by the A/D: within one code of it
        assert f"cae_up_down={s.value('cae_up_down'):+.4f} V [ok]" in line
        assert abs(s.value("cae_up_down") - 5.0) <= 10.0 / 2048
        assert "service_state=SAFE (1)" in line and "ft_force_n[2]=" in line and "ft_force_n[2]=[" not in line


def test_read_watch_and_monitor_show_a_resolver_in_loss_of_signal_beside_its_value(rig, capsys):
    """A resolver in loss of signal read as a plain angle "from the service" (issue 29): each
    tool now shows the channel's status beside the value, numbers and names in --json."""
    import json

    from sim.faults import FaultSet
    rig.run(0.2)
    assert main(["read", "elbow_pitch_angle", "wrist_yaw_angle", "--buffer", rig.name]) == 0
    assert [ln.split()[3] for ln in capsys.readouterr().out.splitlines()] == ["ok", "ok"]
    FaultSet(rig.world).inject("resolver-los:elbow_pitch_angle")
    rig.run(0.05)
    rig.svc.publish_stats()
    assert main(["read", "elbow_pitch_angle", "wrist_yaw_angle", "rtd1", "--buffer", rig.name]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split()[0] for ln in lines] == ["elbow_pitch_angle", "wrist_yaw_angle", "rtd1"]
    assert lines[0].split()[2:4] == ["rad", "LOS"] and lines[1].split()[3] == "ok"
    assert lines[2].split()[1:4] == ["0", "err", "ok"]  # a board: its error count and status
    assert main(["read", "elbow_pitch_angle", "--buffer", rig.name, "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["status"] == 1 and row["status_name"] == "LOS" and -math.pi < row["value"] <= math.pi
    assert main(["watch", "elbow_pitch_angle", "wrist_yaw_angle", "--buffer", rig.name, "--count", "1"]) == 0
    line = capsys.readouterr().out
    assert re.search(r"elbow_pitch_angle=[-+]\d\.\d{4} rad \[LOS\]", line) and "rad [ok]" in line
    assert main(["watch", "elbow_pitch_angle", "service_state", "--buffer", rig.name, "--count", "1", "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["status"] == {"elbow_pitch_angle": "LOS"} and rec["values"]["service_state"] == 1
    assert rec["names"] == {"service_state": "SAFE (1)"}
    assert main(["monitor", "--buffer", rig.name, "--once", "--filter", "elbow_pitch_angle"]) == 0
    row_line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("elbow_pitch_angle "))
    assert row_line.split()[4] == "LOS"


def test_watch_unknown_signal_names_close_matches(rig, capsys):
    assert main(["watch", "elbow_pitch_angel", "--buffer", rig.name, "--count", "1"]) == 1
    err = capsys.readouterr().err
    assert "elbow_pitch_angel" in err and "did you mean elbow_pitch_angle" in err


class FakeTime:
    """Injected clock for the waiting loops: sleeping advances it, nothing really waits."""

    def __init__(self, on_sleep=None):
        self.t = 0.0
        self.on_sleep = on_sleep
        self.slept = 0

    def now(self):
        return self.t

    def sleep(self, dt):
        self.t += dt
        self.slept += 1
        if self.on_sleep:
            self.on_sleep(self)


def test_attach_waits_with_messages_then_gives_up_clearly():
    ft = FakeTime()
    said = []
    name = "pfma-nobody-" + uuid.uuid4().hex[:6]
    with pytest.raises(PfmaTimeoutError, match=f"no I/O service on buffer '{name}' after 10 s"):
        attach_waiting(name, wait_s=10, notice_s=3, say=said.append, sleep=ft.sleep, now=ft.now)
    assert 3 <= len(said) <= 5 and all("waiting for the I/O service" in s for s in said)
    assert "is the I/O service running?" in said[0]


def test_attach_waits_until_the_service_comes_up():
    name = "pfma-cotest-" + uuid.uuid4().hex[:8]
    rigs = []

    def start(ft):
        if ft.t >= 4 and not rigs:
            rigs.append(Rig(name=name))
    ft = FakeTime(start)
    said = []
    try:
        c = attach_waiting(name, wait_s=30, notice_s=3, say=said.append, sleep=ft.sleep, now=ft.now)
        assert c.service_state.name == "SAFE"
        assert said[-1] == f"attached to the I/O service on buffer {name!r}"
        assert any("waiting" in s for s in said)
        c.close()
    finally:
        for r in rigs:
            r.close()


def test_link_reattaches_after_the_service_restarts():
    name = "pfma-cotest-" + uuid.uuid4().hex[:8]
    first = Rig(name=name)
    rigs = []
    said = []
    link = ServiceLink(name, wait_s=30, notice_s=3, say=said.append,
                       sleep=lambda dt: rigs.append(Rig(name=name)) if not rigs else None)
    try:
        c1 = link.client()
        first.run(0.1)
        assert link.client() is c1  # healthy: the same attachment
        first.close()  # the service stops and its buffer goes away
        c2 = link.client()  # waits (one injected sleep starts a new service), reattaches
        assert c2 is not c1 and link.reattachments == 1
        rigs[0].run(0.1)
        assert c2.read_inputs().frame > 0
        assert any("lost the I/O service" in s for s in said) and said[-1].startswith("reattached")
    finally:
        link.close()
        for r in rigs:
            r.close()


def test_live_checkout_stops_with_a_message_when_the_service_stops_publishing(rig, cfg):
    rig.run(0.1)  # then the service never runs again: no new frames
    client = Client.attach(rig.name)
    target = LiveTarget(client, rig.svc.rack, service_timeout_s=0.2)
    lines = []
    try:
        rep = Checkout(target, cfg, only=["links"], say=lines.append).run()
    finally:
        target.close()
    assert not rep.passed
    assert "published no frame" in rep.stopped_early
    assert rep.failures()[-1].channel == "service"
    assert rep.target_time_s < 5


def test_link_invalidated_after_a_failed_read_reattaches(rig):
    said = []
    link = ServiceLink(rig.name, wait_s=5, say=said.append, sleep=lambda dt: None)
    try:
        c1 = link.client()
        link.invalidate("read timed out")
        c2 = link.client()
        assert c2 is not c1 and link.reattachments == 1
        rig.run(0.05)
        assert c2.read_inputs().frame > 0
        assert "read timed out" in said[0]
    finally:
        link.close()


def test_stats_shows_board_and_link_status_and_the_service_state_by_name(rig, capsys):
    """``pfma stats`` showed a healthy board as ``3 OK|INIT`` (issue 29): now ``ok``, a
    failing one ``FAULT``; --json keeps the numbers beside the names."""
    import json

    from sim.faults import FaultSet
    rig.run(0.3)
    FaultSet(rig.world).inject("bus-error:rtd2")
    rig.run(0.05)
    rig.svc.publish_stats()
    assert main(["stats", "--buffer", rig.name, "--wm", "none"]) == 0
    lines = capsys.readouterr().out.splitlines()
    boards = {ln.split()[0]: ln.split()[1] for ln in lines[lines.index("boards") + 2:lines.index("links")]}
    assert boards["rtd2"] == "FAULT" and boards["rtd1"] == "ok" and boards["dac"] == "ok"
    links = {ln.split()[0]: ln.split()[1] for ln in lines[lines.index("links") + 2:] if ln.split()
             and ln.split()[0].endswith(("_sensor", "_controller"))}
    assert links["ft_sensor"] == "ok" and links["hid_hand_controller"] == "CLOSED"
    assert lines[0].startswith("state FAULT ")  # the failed input board made the outputs safe
    assert "service fault INPUT BOARD" in next(ln for ln in lines if ln.startswith("commands: "))
    assert main(["stats", "--buffer", rig.name, "--wm", "none", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["boards"]["rtd2"]["status_name"] == "FAULT" and d["boards"]["rtd2"]["status"] & 4
    assert d["boards"]["rtd1"] == {"status": 3, "status_name": "ok", "errors": 0}
    assert d["service_state"] == "FAULT" and d["service_state_code"] == 3
    assert d["commands"]["fault_name"] == "INPUT BOARD" and d["commands"]["fault_code"] == 3
