"""The controller's layers distributed over processes by configuration (issue 19 item 3):
the distribution file and its mistakes, the sections and their ownership, and the
distributed simulator (every process's runtime in this process, simulated time): power-up,
a rack fault climbing to System Up/Down, a process lost, whole frames imported."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest

from controller.decision import Status
from controller.distributed import (
    ERR_PROCESS_STOPPING, ERR_SECTION_LOST, SECTION_LOST_FRAMES, DistributedConfigError, load_config, parse_config,
    section_owners,
)
from controller.layers import Request, Response
from controller.runtime import LAYER_KEYS
from controller.worldmodel import WorldModel, WorldModelError
from sim.distributed import DistributedSimulator
from sim.system import SystemSimulator
from tools.cli import main

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "distributed.toml"

TWO = {"process": {"planners": {"layers": ["updown", "msp", "trajectory", "cartesian"]},
                   "rack": {"layers": ["joint", "servo", "daq"]}}}
#: the Joint Planner moved beside the Cartesian engine, System Up/Down on its own: a change of the file
THREE = {"process": {"top": {"layers": ["updown"]},
                     "planners": {"layers": ["msp", "trajectory", "cartesian", "joint"]},
                     "rack": {"layers": ["servo", "daq"]}}}


def _resolver_los(world) -> None:  # as bench/bench_controller.py FAULTS
    world.bus["rtd1"].inject("loss_of_signal", channel=0)


# --- the distribution file ----------------------------------------------------------------
def test_the_example_file_is_two_processes():
    cfg = load_config(EXAMPLE)
    assert cfg.names == ("planners", "rack")
    assert cfg.process("rack").layers == ("joint", "servo", "daq")
    assert cfg.process_of("cartesian") == "planners" and cfg.transport == "shm" and cfg.wm == "pfma_wm"
    assert cfg.wm_name("base", "rack") == "base.rack"


def test_zenoh_endpoints_link_every_pair_on_loopback_by_default():
    cfg = parse_config({"distributed": {"transport": "zenoh"}, **THREE})
    assert cfg.transport == "zenoh"
    assert cfg.endpoints("top") == (("tcp/127.0.0.1:7460",), ())
    assert cfg.endpoints("planners") == (("tcp/127.0.0.1:7461",), ("tcp/127.0.0.1:7460",))
    assert cfg.endpoints("rack") == (("tcp/127.0.0.1:7462",), ("tcp/127.0.0.1:7460", "tcp/127.0.0.1:7461"))
    given = parse_config({"process": {"planners": {"layers": ["updown", "msp", "trajectory", "cartesian"],
                                                   "connect": ["tcp/10.0.0.2:7460"]},
                                      "rack": {"layers": ["joint", "servo", "daq"], "listen": ["tcp/10.0.0.2:7460"]}}})
    assert given.transport == "zenoh" and given.endpoints("planners") == ((), ("tcp/10.0.0.2:7460",))


MISTAKES = [
    ({"process": {"a": {"layers": ["updown", "msp", "trajectory", "cartesian", "joint"]},
                  "b": {"layers": ["joint", "servo", "daq"]}}}, "layer joint is in processes a and b"),
    ({"process": {"a": {"layers": ["updown", "trajectory", "cartesian"]},
                  "b": {"layers": ["joint", "servo", "daq"]}}}, "layer msp is in no process"),
    ({"process": {"a": {"layers": ["updown", "msp", "trajectory", "cartesian"]},
                  "b": {"layers": ["joint_planner", "joint", "servo", "daq"]}}},
     "unknown layer 'joint_planner' (layers: updown, msp, trajectory, cartesian, joint, servo, daq); "
     "joint_planner is a task of layer joint"),
    ({"process": {"a": {"layers": ["updown", "msp", "trajectory", "cartesian", "joint", "servo"]},
                  "b": {"layers": ["daq"]}}}, "servo is in process a but daq, the one writer of the Bit3 command area"),
    ({"process": {"a": {"layers": ["updown", "msp", "trajectory", "cartesian"], "layer": []},
                  "b": {"layers": ["joint", "servo", "daq"]}}}, "[process.a]: unknown key 'layer'"),
    ({"process": {"a": {"layers": ["updown", "msp", "trajectory", "cartesian"], "listen": ["127.0.0.1:7460"]},
                  "b": {"layers": ["joint", "servo", "daq"]}}}, "listen endpoint '127.0.0.1:7460' is not tcp/HOST:PORT"),
    ({"process": {"a": {"layers": []}, "b": {"layers": ["updown", "msp", "trajectory", "cartesian", "joint",
                                                          "servo", "daq"]}}}, "[process.a]: layers must be a non-empty"),
    ({"distributed": {"wm": "x"}}, "no processes"),
    ({"distributed": {"transport": "udp"}, **TWO}, "transport = 'udp'"),
]


@pytest.mark.parametrize("doc, text", MISTAKES, ids=[t.split(":")[0][:30] for _, t in MISTAKES])
def test_each_mistake_gets_one_message(doc, text):
    with pytest.raises(DistributedConfigError) as e:
        parse_config(doc, "d.toml")
    assert len(e.value.problems) == 1, e.value.problems
    assert text in e.value.problems[0]
    assert str(e.value).startswith("d.toml: ")


def test_two_mistakes_two_messages():
    with pytest.raises(DistributedConfigError) as e:
        parse_config({"process": {"a": {"layers": ["updown", "msp", "trajectory", "cartesian", "servo"]},
                                  "b": {"layers": ["joint", "servo"]}}})
    assert len(e.value.problems) == 2
    assert "layer servo is in processes a and b" in e.value.problems[0]
    assert "layer daq is in no process" in e.value.problems[1]


def test_a_file_that_is_not_toml(tmp_path):
    bad = tmp_path / "d.toml"
    bad.write_text("[process.a\nlayers = 1\n")
    with pytest.raises(DistributedConfigError, match=r"d.toml: not valid TOML"):
        load_config(bad)
    with pytest.raises(DistributedConfigError, match="cannot read it"):
        load_config(tmp_path / "missing.toml")


@pytest.mark.parametrize("argv, text", [
    (["--distribute", "BAD"], "layer joint is in processes planners and rack"),
    (["--distribute", "EXAMPLE", "--process", "rakc"], "no process 'rakc' (processes: planners, rack); did you mean rack?"),
    (["--process", "rack"], "--process needs --distribute FILE"),
    (["--distribute", "EXAMPLE", "--process", "rack", "--power-up"],
     "--power-up goes to the process that runs updown (System Up/Down): planners, not rack"),
    (["--distribute", "EXAMPLE"], "which process is this? --process NAME (processes in"),
    (["--distribute", "EXAMPLE", "--process", "rack", "--buffer", "zenoh://10.0.0.1:7447/pfma"],
     "process rack runs daq, the one writer of the Bit3 command area"),
    (["--distribute", "EXAMPLE", "--process", "rack", "--halt"], "--halt not with a distributed controller"),
])
def test_cli_mistakes_one_line_exit_2(tmp_path, capsys, argv, text):
    bad = tmp_path / "bad.toml"
    bad.write_text('[process.planners]\nlayers = ["updown", "msp", "trajectory", "cartesian", "joint"]\n'
                   '[process.rack]\nlayers = ["joint", "servo", "daq"]\n')
    argv = [str(bad) if a == "BAD" else str(EXAMPLE) if a == "EXAMPLE" else a for a in argv]
    assert main(["controller", *argv]) == 2
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and text in lines[0], cap.err
    assert "Traceback" not in cap.err and cap.out == ""


def test_cli_simulates_every_process(capsys):
    assert main(["controller", "--sim", "--distribute", str(EXAMPLE), "--wm", "none", "--power-up",
                 "--duration", "0.3", "--messages", "0"]) == 0
    out = capsys.readouterr().out
    assert "process planners: updown=START_UP_COMPLETE  msp=START_UP_COMPLETE" in out
    assert "process rack: joint=START_UP_COMPLETE  servo=START_UP_COMPLETE  daq=START_UP_COMPLETE" in out
    # 83 frames: the brake test waits for each tach to show the motion, 6 frames later behind
    # the anti-aliasing board (docs/simulated-arm.md) than the 77 without it
    assert "power-up: every layer START UP COMPLETE after 83 frames" in out


# --- sections and ownership -------------------------------------------------------------------
@pytest.fixture(scope="module")
def two():
    with DistributedSimulator(TWO) as sim:
        yield sim


def test_every_variable_in_one_section_by_its_writer(two):
    rt = two.rt("rack")
    owners = section_owners(rt.layers, two.config)
    specs = {s.name: s for s in rt.wm.specs}
    assert set(owners) == {n for n, s in specs.items() if s.writer != "runtime"}
    assert owners["servo.q_cmd_rad"] == "rack"  # written by the Joint Planner
    assert owners["daq.command"] == "rack"  # written by the servo, the layer above
    assert owners["joint.command"] == "planners"  # written by the Cartesian engine above the Joint Planner
    assert owners["cart.mode"] == "planners" and owners["servo.kp_per_s"] == "rack"  # user variables: declaring layer
    assert owners["ui.response"] == "planners"  # System Up/Down's request task
    # the sections' byte ranges: disjoint, and exactly the owned variables' bytes
    dp = two.processes["rack"]
    covered: dict[int, str] = {}
    for p, sec in dp.sections.items():
        for off, n, _ in sec.ranges:
            for b in range(off, off + n):
                assert b not in covered, (b, p, covered[b])
                covered[b] = p
    for name, p in owners.items():
        off, n = rt.wm.var_range(name)
        assert {covered.get(b) for b in range(off, off + n)} == {p}, name
    for s in specs.values():
        if s.writer == "runtime":
            off, n = rt.wm.var_range(s.name)
            assert all(b not in covered for b in range(off, off + n))


def test_posting_another_process_section_is_refused_naming_it(two):
    rack, planners = two.rt("rack"), two.rt("planners")
    with pytest.raises(WorldModelError, match=r"'cart.mode' \(writer 'user'\) is in the section of process 'planners'; process 'rack' may read it but not "
                                              r"post it \(a task writes only its local section\)"):
        rack.wm.post_task_outputs("user", {"cart.mode": 1})
    with pytest.raises(WorldModelError, match=r"'servo.q_cmd_rad' \(writer 'joint'\) is in the section of process 'rack'"):
        planners.wm.post_task_outputs("joint", {"servo.q_cmd_rad": np.zeros(6)})
    with pytest.raises(WorldModelError, match=r"'joint.status' \(writer 'joint'\) is in the section of process 'rack'"):
        planners.wm.post_state_variable("joint", "joint.status", 5)
    # a user write of another process's variable: refused at once ...
    with pytest.raises(WorldModelError, match=r"ui.request belongs to process planners \(distributed world model\)"):
        rack.request(Request.POWER_UP)
    # ... its own variables are fine, in its own process
    planners.wm.post_task_outputs("runtime", {"runtime.frames": 1})
    rack.wm.set_user("servo.kp_per_s", [8.0] * 6, rack.wm.access_key)


def test_halt_is_refused_when_distributed(two):
    two.step(2)
    code, text = two.request(Request.HALT)
    assert code == Response.REFUSED and "distributed" in text


# --- the distributed simulator ------------------------------------------------------------------
@pytest.mark.parametrize("config", [TWO, THREE], ids=["two", "three"])
def test_power_up_and_a_rack_fault_to_system_up_down_as_in_one_process(config):
    with SystemSimulator() as one:
        one.step(10)
        single = one.power_up(1000)
    with DistributedSimulator(config) as sim:
        sim.step(10)
        frames = sim.power_up(1000)
        assert frames == single  # a status climbs one layer per frame across a boundary too
        assert sim.all_status(Status.START_UP_COMPLETE)
        # the arm flies from the rack process's joint goal: DAC rates flowing, the joint moving
        q0 = sim.joint_angles_rad()
        sim.rt("joint").set_joint_goal(q0 + np.array([0.0, 0.05, 0, 0, 0, 0]))
        rates = []
        for _ in range(60):
            sim.step(1)
            rates.append(abs(sim.dac_volts()[1]))
        assert max(rates) > 0.5 and sim.joint_angles_rad()[1] - q0[1] > 0.02
        # a resolver loss of signal at the rack: System Up/Down ERROR in the top process
        k_inject = sim.daq.frame
        _resolver_los(sim.world)
        k_detect = sim.run_until(lambda: sim.daq.daq.fault_bits != 0, 20) and sim.daq.frame
        sim.run_until(lambda: sim.first_change("updown", Status.ERROR, k_inject) is not None, 20)
        k_up = sim.first_change("updown", Status.ERROR, k_inject)
        # an ERROR climbs every layer of one process in the frame it is decided, and crosses a
        # process boundary at the next frame's section import: one frame per boundary
        assert k_up - k_detect == len(config["process"]) - 1
        sim.step(4)
        assert np.all(sim.dac_volts()[:6] == 0.0)
        assert all(s == Status.ERROR for s in sim.statuses().values())


def test_two_simulators_give_the_same_traces():
    traces = []
    for _ in range(2):
        with DistributedSimulator(TWO) as sim:
            sim.step(10)
            sim.power_up(1000)
            sim.step(10)
            traces.append([(r.frame, r.layers, r.fault_bits, r.tasks) for p in ("planners", "rack")
                           for r in sim.rt(p).trace])
    assert traces[0] == traces[1]


def test_each_frame_imports_the_other_section_as_it_was_after_its_last_frame(two):
    rack, planners = two.processes["rack"], two.processes["planners"]
    sec = rack.section
    body = bytearray(planners.rt.wm.body_size)
    seen = []

    def record() -> None:
        seen.append(rack.payload()[16:])  # the rack's section after its frame
    two.after_step.append(record)
    try:
        for _ in range(6):
            two.step(1)
            planners.rt.wm.read_body_into(body)
            mine = bytearray(sec.size)
            sec.pack(body, mine)
            if len(seen) >= 2:
                assert bytes(mine) == seen[-2]  # imported at this frame's segment: the frame before's
    finally:
        two.after_step.remove(record)


def test_a_user_write_into_the_wrong_process_model_is_rejected_by_its_owner():
    base = "pt-dwm-" + uuid.uuid4().hex[:6]
    with DistributedSimulator(TWO, wm_base=base) as sim:
        sim.step(2)
        tool = WorldModel.attach(f"{base}.rack")  # what `pfma wm set --name BASE.rack` does
        try:
            rid = tool.set_user("cart.mode", 1, "pfma")  # the tool does not know the sections: the owner does
            sim.step(1)
            req = tool.request(rid)
            assert req is not None and req.state == "rejected"
            assert req.result == f"cart.mode belongs to process planners: set it in world model {base}.planners"
        finally:
            tool.close()


@pytest.mark.parametrize("victim", ["planners", "rack"])
def test_a_lost_process_stops_the_arm_or_reaches_system_up_down(victim):
    with DistributedSimulator(TWO) as sim:
        sim.step(10)
        sim.power_up(1000)
        sim.step(10)
        k = sim.daq.frame
        sim.stop(victim)
        if victim == "planners":  # the rack's Joint Planner faults; the servo's safe stop, the arm disarmed
            rack = sim.rt("rack")
            sim.run_until(lambda: rack.by_key["joint"].error_code == ERR_SECTION_LOST, SECTION_LOST_FRAMES + 2)
            assert rack.frame - k == SECTION_LOST_FRAMES + 1
            sim.run_until(lambda: rack.status("daq") == Status.SHUT_DOWN, 200)
            assert rack.status("joint") == Status.ERROR and np.all(sim.dac_volts()[:6] == 0.0)
            assert "process planners (superior Cartesian Engine) lost" in rack.messages.format(20)
        else:  # the planners' Cartesian engine faults; the ERROR climbs to System Up/Down in that frame
            top = sim.rt("planners")
            sim.run_until(lambda: top.first_change("updown", Status.ERROR, k) is not None, SECTION_LOST_FRAMES + 10)
            assert top.first_change("updown", Status.ERROR, k) == top.first_change("cartesian", Status.ERROR, k)
            assert top.by_key["cartesian"].error_code == ERR_SECTION_LOST


def test_a_process_leaving_stops_its_layers_safely():
    with DistributedSimulator(TWO) as sim:
        sim.step(10)
        sim.power_up(1000)
        rack = sim.processes["rack"]
        assert rack.leave()
        sim.run_until(rack.stopped, 200)
        assert rack.rt.by_key["joint"].error_code == ERR_PROCESS_STOPPING
        assert rack.rt.status("daq") == Status.SHUT_DOWN and np.all(sim.dac_volts()[:6] == 0.0)
        sim.run_until(lambda: sim.rt("planners").status("updown") == Status.ERROR, 20)
        assert not rack.leave()  # nothing left to stop


def test_layer_keys_are_the_runtime_layers(two):
    assert tuple(l.key for l in two.rt("rack").layers) == LAYER_KEYS
