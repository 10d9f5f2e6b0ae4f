"""The checkout fault matrix (issue 32 item 3; tools/checkout/faultmatrix.py): the matrix
covers every fault kind on every target; its judge reads a report as a user does; and a
seeded sample of it, run through the real checkout on the simulated rack (simulated time),
finds and names every fault the checkout is meant to, while the ones it cannot are listed
with their reason (docs/checkout.md "The fault matrix"). The full matrix is
``pfma bench faults``."""

from __future__ import annotations

import pytest

from pfma.rack import load_rack
from sim.faults import KINDS
from tools.checkout.faultmatrix import (NEVER_ALTERED, SPARE_CHANNEL, Case, cases, judge, named_kind, run_case,
                                         run_matrix, sample)
from tools.checkout.runner import stuck_bits

RACK = load_rack()


def test_the_matrix_has_every_kind_and_every_data_bit_of_the_data_registers():
    every = cases(RACK)
    assert {c.kind for c in every} == set(KINDS)
    specs = {c.spec for c in every}
    assert "stuck-bit:rtd1@CH0:13=1" in specs and "stuck-bit:rtd1@CH0:14=1" not in specs  # 14-bit angles
    assert "stuck-bit:dac@DAC[15]:11=0" in specs and "stuck-bit:dac@DAC[0]:12=0" not in specs  # 12-bit latch
    assert "stuck-bit:adc@SCAN[31]:0=1" in specs and "stuck-bit:adc@DATA:11=1" in specs
    assert not any(s.startswith("stuck-bit:adc@CSR") for s in specs)  # a control register: another fault
    case = next(c for c in every if c.spec == "stuck-bit:dac@DAC[2]:3=1")
    assert case.board == "dac" and case.signals == {"elbow_pitch_command"}


def test_a_sample_is_the_same_for_the_same_seed_and_has_every_kind():
    every = cases(RACK)
    a, b = sample(every, 30, 5), sample(every, 30, 5)
    assert a == b and len(a) == 30 and {c.kind for c in a} == set(KINDS)
    assert sample(every, 30, 6) != a


def test_the_judge_reads_the_first_failure_and_its_diagnosis():
    c = Case("brake-held:shoulder_yaw", "brake-held", None, frozenset({"shoulder_yaw_rate", "shoulder_yaw_angle"}))
    rows = [{"channel": "shoulder_yaw_rate", "check": "open-loop rate +", "detail": "commanded +0.06 rad/s"},
            {"channel": "shoulder_yaw", "check": "drive and brake (diagnosis)",
             "detail": "brake not released (or a jam): check the joint's brake-release switch"}]
    v = judge(c, rows, RACK)
    assert v.detected and v.part_right and v.kind_right and v.named == "brake-held"
    v = judge(c, rows[:1], RACK)
    assert v.detected and v.part_right and not v.kind_right and v.named == ""
    v = judge(c, [{"channel": "elbow_pitch_rate", "check": "x", "detail": "TACH POLARITY REVERSED"}], RACK)
    assert v.detected and not v.part_right and not v.kind_right and v.named == "tach-reversed"
    assert not judge(c, [], RACK).detected
    board = Case("bus-error:rtd2", "bus-error", "rtd2")
    assert judge(board, [{"channel": "rtd2", "check": "board status", "detail": "the service: bus error"}],
                 RACK).kind_right
    assert named_kind("silent: no record in 2.00 s") == "serial-stall"


@pytest.mark.parametrize("codes, bits, want", [
    (list(range(0, 200, 2)), 14, [(0, 0)]),  # every code even over a dense sweep: bit 0 at 0
    ([x | 8 for x in range(100, 300)], 14, [(3, 1)]),  # blocks of 8 with 8 missing
    (list(range(100, 300)), 14, []),  # a healthy sweep
    ([0, 1, 2, 3, 4, 5, 6, 7, 2800, 2801, 2802, 2803], 14, []),  # two poses: no sweep across the higher bits
    ([2048, 2048 + 410, 2048 - 410, 2048 + 820, 2048 - 820, 4095, 0, 1000], 12, []),  # a few stimulus levels
    ([5, 5, 5], 12, []),  # too few codes to judge
])
def test_a_stuck_bit_is_told_only_from_a_dense_sweep(codes, bits, want):
    import numpy as np
    assert stuck_bits(np.array(codes), bits) == want


#: faults this checkout does not find or name, and why (docs/checkout.md "The fault matrix")
def _cannot(case: Case) -> str | None:
    if case.kind == "load" and "gripper" not in case.spec:
        return ("a snag is found (the joint does not follow) but named a drive fault: the open-loop test at its "
                "low current limit cannot tell a load from a drive that does not answer")
    return None


def test_a_seeded_sample_through_the_real_checkout():
    """One case of every kind and a few stuck bits (seed 3): every kind is found and named
    right (the board or channel and the kind) but those :func:`_cannot` names (found, if at
    all, as it says), an A/D input held dead (found on its channel; its kind is not told apart
    from a wrong value) and the stuck bits (a stuck bit is found only where the run swept
    across it; when found by its data bits, it is named right)."""
    which = sample(cases(RACK), len(KINDS) + 4, seed=3)
    figs = run_matrix(which, RACK)
    bad = []
    for v in figs.verdicts:
        if _cannot(v.case):
            continue
        if v.case.kind == "stuck-bit":
            if v.detected and "data bits" in v.first and not (v.part_right and v.kind_right):
                bad.append(f"{v.case.spec}: found by its data bits but named wrong: {v.first}")
            continue
        if v.case.kind == "adc-dead":  # found; its kind is not told apart from a wrong value (documented)
            ok = v.detected and v.part_right
        else:
            ok = v.detected and v.part_right and v.kind_right
        if not ok:
            bad.append(f"{v.case.spec}: detected {v.detected}, part {v.part_right}, kind {v.kind_right}: {v.first}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("spec, why", [
    ("stuck-bit:adc@DATA:11=1", NEVER_ALTERED),  # the driver reads SCAN: DATA's bits change no word read
    ("stuck-bit:dac@DAC[14]:5=1", SPARE_CHANNEL),  # 0x800 latched as 0x820 on a channel wired to nothing
    ("stuck-bit:dac@DAC[0]:11=1", ""),  # the rate command's D11: the DAC-bit check finds and names it
    ("stuck-bit:rtd2@CH1:13=1", ""),  # read as 210 deg, outside the stops: "within travel" names it
])
def test_the_matrix_tells_the_undetectable_cases_from_the_rack_s_ground_truth(spec, why):
    case = next(c for c in cases(RACK) if c.spec == spec)
    v = run_case(case, RACK)
    assert v.undetectable == why
    if why:
        assert not v.detected  # bit for bit a healthy run, or nothing measured it: the checkout passed
    else:
        assert v.right, v.first


def _stick(codes, bit: int, value: int):
    import numpy as np
    return (np.asarray(codes) & ~(1 << bit)) | (value << bit)


def test_a_quiet_inputs_noise_split_by_a_stuck_bit_names_the_bit_and_healthy_noise_never():
    """:func:`noise_split` on seeded Gaussian noise (the simulated rack's, 0.3..2 counts rms)
    about many idle values: no healthy group is ever named; a group about 0 V with a bit
    stuck (every bit of the 12, each value) is named that bit and no other."""
    import numpy as np
    from tools.checkout.runner import noise_split
    rng = np.random.default_rng(11)
    for centre in np.linspace(2040.0, 2070.0, 31):
        for sigma in (0.3, 0.8, 1.2, 2.0):
            for n in (32, 1000):
                codes = np.round(rng.normal(centre, sigma, n)).astype(np.int64)
                assert noise_split(codes, 12) == [], (centre, sigma, sorted(set(codes.tolist())))
    for bit in range(12):
        for value in (0, 1):
            # a group about 0 V (0x7FF | 0x800: every bit's block edge): a bit stuck moves
            # the codes on one side away from the other (0x7FC.. down with D2 at 0, 0x800.. up
            # with D2 at 1); stuck towards the group it folds onto it and shows no hole
            codes = np.round(rng.normal(2047.5, 1.0, 1000)).astype(np.int64)
            stuck = _stick(codes, bit, value)
            assert (stuck != codes).any()
            assert noise_split(stuck, 12) == [(bit, value)], (bit, value, sorted(set(stuck.tolist())))


def test_one_stray_sample_beyond_a_hole_is_noise_unless_a_failure_asks_why():
    import numpy as np
    from tools.checkout.runner import noise_split
    codes = np.array([2048] * 10 + [2049] * 12 + [2050] * 8 + [2051] * 3 + [2043])  # 0x7FB: 0x7FF with D2 at 0
    assert noise_split(codes, 12) == []  # one sample: no evidence the idle noise is split
    assert noise_split(codes, 12, evidence=1) == [(2, 0)]  # a failed row asks which bit explains it


def test_checkout_on_a_noisy_rack_names_a_low_a_d_bit_from_the_idle_noise():
    """On a seeded rack (its A/D noise), a motor-current monitor's D2 stuck at 0 splits the
    idle noise: the row that fails names the bit; the same rack healthy passes. Since the
    A/D noise limit is 9 counts (a 1.2 LSB rms rack's), the split passes the noise row and
    the first failure is the elbow's limit walk (the monitor reads its 2^2 step as none),
    which names the monitor's own bit beside the DAC's."""
    from tools.checkout import Checkout, load_checkout_config
    from tools.checkout.target import make_sim_target
    cfg = load_checkout_config(None)
    for fault in (None, "stuck-bit:adc@SCAN[3]:2=0"):
        t = make_sim_target(None, sim_errors=2)
        try:
            if fault:
                t.inject_fault(fault)
            rep = Checkout(t, cfg, interactive=False, say=lambda line: None).run()
        finally:
            t.close()
        fails = [r for r in rep.as_dict()["results"] if r["status"] == "FAIL"]
        if fault is None:
            assert fails == []
        else:
            assert fails and "elbow_pitch_motor_current" in fails[0]["channel"] + fails[0]["detail"]
            assert "data bit D2 stuck at 0" in fails[0]["detail"], fails[0]


def _resolver_rows(fault: str | None, *, operator: dict[str, str] | None = None) -> list[dict]:
    """The resolvers group's rows on seeded rack 1 with ``fault``; with ``operator`` (joint ->
    the answer typed) the stimulus is taken away and an operator is asked instead."""
    from tools.checkout import Checkout, load_checkout_config
    from tools.checkout.target import make_sim_target
    t = make_sim_target(None, sim_errors=1)
    asked: list[str] = []

    def ask(prompt: str) -> str:
        asked.append(prompt)
        return next((a for j, a in (operator or {}).items() if f"OPERATOR: {j}:" in prompt), "")
    try:
        if fault:
            t.inject_fault(fault)
        if operator is not None:
            t.stimulus = None
        rep = Checkout(t, load_checkout_config(None), only=["resolvers"], interactive=operator is not None,
                       say=lambda line: None, ask=ask, keep_going=True).run()
    finally:
        t.close()
    rows = [r for r in rep.as_dict()["results"] if r["check"] == "angle as seen on the arm"]
    assert operator is None or len(asked) == len(rows)
    return rows


def test_a_resolvers_high_bit_stuck_within_the_travel_is_found_by_the_angle_seen_on_the_arm():
    """D12 of the shoulder pitch's resolver stuck at 1 reads the joint 90 deg off (inside its
    travel: no other row can tell); the angle a person sees on the arm (here the simulated
    arm's true angle) finds it and names the bit; the healthy rack agrees within 5 deg."""
    healthy = _resolver_rows(None)
    assert len(healthy) == 6 and all(r["status"] == "PASS" for r in healthy), healthy
    rows = _resolver_rows("stuck-bit:rtd2@CH1:12=1")
    bad = [r for r in rows if r["status"] == "FAIL"]
    assert [r["channel"] for r in bad] == ["shoulder_pitch_angle"], rows
    assert "data bit D12 stuck at 1" in bad[0]["detail"] and "true angle (stimulus)" in bad[0]["detail"]


def test_on_a_real_rack_the_operator_reads_the_angle_and_may_skip():
    """Without a stimulus the operator is asked each joint's angle: a reading that agrees
    passes, one 120 deg off fails naming no bit (none explains it), a blank is a skip."""
    rows = _resolver_rows(None, operator={"shoulder_yaw": "0", "shoulder_pitch": "150", "elbow_pitch": "x"})
    by = {r["channel"]: r for r in rows}
    assert by["shoulder_yaw_angle"]["status"] == "PASS", by["shoulder_yaw_angle"]
    assert by["shoulder_pitch_angle"]["status"] == "FAIL"
    assert "read by the operator" in by["shoulder_pitch_angle"]["detail"]
    assert "no one data bit explains it" in by["shoulder_pitch_angle"]["detail"]
    assert by["elbow_pitch_angle"]["status"] == "SKIP" and "not an angle" in by["elbow_pitch_angle"]["detail"]
    assert by["wrist_roll_angle"]["status"] == "SKIP" and "skipped by the operator" in by["wrist_roll_angle"]["detail"]


def test_a_resolver_bit_stuck_shows_as_a_jump_of_2_to_the_b_as_the_joint_moves():
    """A joint moving through 600 counts at 3 counts a read: healthy, no jump (a turn's wrap
    is no jump either); with D8 stuck at 1 (or D9 at 0 across its edge) the reading jumps by
    2^b with the bit the same on both sides, which names it."""
    import numpy as np
    from tools.checkout.runner import angle_jumps
    true = np.arange(16200, 16200 + 1800, 3) % (1 << 14)  # crosses the turn at 16384
    assert angle_jumps(true, 14) == []
    assert angle_jumps(_stick(true, 8, 1), 14) == [(8, 1)]
    assert angle_jumps(_stick(true, 9, 0), 14) == [(9, 0)]


def test_each_level_an_input_held_is_judged_for_its_noise():
    """Idle, then a stick held at +5 V, each with noise: two levels (a transient between them
    is none); D3 stuck at 1 splits the held level's noise, and only that level shows it."""
    import numpy as np
    from tools.checkout.runner import code_groups, noise_split
    rng = np.random.default_rng(4)
    idle = np.round(rng.normal(2048.3, 0.9, 400)).astype(np.int64)
    held = np.round(rng.normal(3071.6, 0.9, 400)).astype(np.int64)  # 0xBFF | 0xC00
    ramp = np.arange(2060, 3060, 50)
    codes = np.concatenate([idle, ramp, held])
    groups = code_groups(codes)
    assert len(groups) == 2 and all(noise_split(g, 12) == [] for g in groups)
    stuck = np.concatenate([idle, ramp, _stick(held, 3, 1)])
    assert [noise_split(g, 12) for g in code_groups(stuck)] == [[], [(3, 1)]]


def _idle_then_deflected(rng, centre: float, sigma: float, n: int = 600):
    """A quiet input's idle noise, a deflection out and back (a ramp through a 4-pole filter
    at 160 Hz: a few reads on the way), then idle again."""
    import numpy as np
    idle = np.round(rng.normal(centre, sigma, n)).astype(np.int64)
    out = np.array([2500, 3300, 3750, 3840], dtype=np.int64)
    held = np.round(rng.normal(3847.0, sigma, 200)).astype(np.int64)
    back = np.array([3700, 2900, 2300, 2080], dtype=np.int64)
    return np.concatenate([idle[: n // 2], out, held, back, idle[n // 2:]])


def test_a_quiet_input_s_noise_thrown_2_to_the_b_away_names_a_high_stuck_bit_and_healthy_noise_never():
    """:func:`noise_strays`: idle at 0x7FE, its noise now and then reading 0x800; with D9 stuck
    at 1 those reads come 512 codes away (0xA00), each between two idle reads, and D9 is 1 in
    every code of the run: named (the matrix's SCAN[18]:9=1). Healthy seeded noise about many
    idle values, with a deflection out and back, is never named; nor is a stuck input whose
    strays are fewer than three."""
    import numpy as np
    from tools.checkout.runner import STRAY_EVIDENCE, noise_strays
    rng = np.random.default_rng(18)
    codes = _idle_then_deflected(rng, 2046.0, 0.8)
    assert (codes == 2048).sum() >= STRAY_EVIDENCE and noise_strays(codes, 12) == []
    assert noise_strays(_stick(codes, 9, 1), 12) == [(9, 1)]
    few = codes.copy()
    few[np.flatnonzero(few == 2048)[STRAY_EVIDENCE - 1:]] = 2047  # two strays left
    assert noise_strays(_stick(few, 9, 1), 12) == []
    for centre in np.linspace(2040.0, 2070.0, 31):
        for sigma in (0.3, 0.8, 1.2, 2.0):
            c = _idle_then_deflected(rng, centre, sigma)
            assert noise_strays(c, 12) == [], (centre, sigma)


def test_an_a_d_input_swept_across_a_high_bit_s_edge_jumps_2_to_the_b_with_the_bit_stuck():
    """A tach idling just below 0 V (0x7FD), then driven to +80 codes and back at up to 30
    codes a read: healthy, no jump; with D11 stuck at 0 the reading jumps between 0x7FF and
    0x003 on the way up and back (the bit 0 on both sides, never 1 in the run), which names
    it. A current stepping 600 codes in three reads is no jump, nor one step of 2^b whose bit
    changes."""
    import numpy as np
    from tools.checkout.runner import adc_jumps
    ramp = np.concatenate([np.full(50, 0x7FD), np.arange(0x7FD, 0x850, 30), np.full(20, 0x850),
                           np.arange(0x850, 0x7FD, -30), np.full(50, 0x7FD)])
    assert adc_jumps(ramp, 12) == []
    assert adc_jumps(_stick(ramp, 11, 0), 12) == [(11, 0)]
    step = np.concatenate([np.full(40, 0x800), [0x8C8, 0x990, 0xA58], np.full(40, 0xA58)])
    assert adc_jumps(step, 12) == []
    assert adc_jumps(np.array([0x700] * 5 + [0x800] * 5 + [0x700] * 5), 12) == []  # D8 changes


def test_a_level_s_passing_reads_do_not_hide_its_split_noise():
    """Idle noise about 0 V (0x7FF | 0x800) with D4 stuck at 1 splits into 0x7FF and 0x810..;
    a tach's few passing reads 7 codes beyond each side made the group too wide to judge (the
    matrix's SCAN[12]:4=1). Without the reads read fewer than CORE_READS times and not next to
    one that is, it is named; healthy seeded noise with the same passing reads never is, nor
    the noiseless rack's settling reads (a code or two read twice)."""
    import numpy as np
    from tools.checkout.runner import noise_core, noise_split
    rng = np.random.default_rng(11)
    passing = np.array([0x7F8, 0x7F9, 0x80C, 0x80E])
    for k in range(200):
        sigma = rng.uniform(0.4, 1.2)
        idle = np.clip(np.rint(rng.normal(0x7FF + rng.uniform(0, 3), sigma, 1500)), 0, 4095).astype(np.int64)
        group = np.concatenate([idle, passing + rng.integers(-1, 2, 4)])
        assert noise_split(noise_core(group), 12) == [], (k, sigma)
    idle = np.clip(np.rint(rng.normal(0x800, 0.8, 1500)), 0, 4095).astype(np.int64)
    stuck = _stick(np.concatenate([idle, passing]), 4, 1)
    assert noise_split(stuck, 12) == []  # the passing reads: too wide to judge whole
    assert noise_split(noise_core(stuck), 12) == [(4, 1)]
    settling = np.array([0x723] * 67 + [0x724] * 5 + [0x714, 0x714, 0x716, 0x716, 0x70F])
    assert noise_split(noise_core(settling), 12) == []


@pytest.mark.parametrize("spec, channel, words", [
    ("stuck-bit:rtd2@CH0:7=1", "shoulder_yaw_angle", "bit 7 stuck at 1"),  # moves cross a D7 edge
    ("stuck-bit:adc@SCAN[9]:11=0", "shoulder_pitch_rate", "bit 11 stuck at 0"),  # the tach's jump
    ("stuck-bit:adc@SCAN[12]:4=1", "wrist_pitch_rate", "bit 4 stuck at 1"),  # split idle, passing reads
    ("stuck-bit:adc@SCAN[17]:5=0", "cae_forward_backward", "bit 5 stuck at 0"),
    ("stuck-bit:adc@SCAN[23]:5=0", "cae_discrete_2", "bit 5 stuck at 0"),
    # the current held back at the limit, then read 0 A once the service made outputs safe
    ("load:shoulder_pitch=300", "shoulder_pitch_rate", "an external load drives it"),
    # the jaw's command, read through its tach while it runs (it has no brake to push against)
    ("stuck-bit:dac@DAC[6]:0=0", "gripper_command", "data bit D0 of DAC channel gripper_command stuck"),
    ("stuck-bit:dac@DAC[6]:5=1", "gripper_command", "data bit D5 of DAC channel gripper_command stuck"),
    # current-limit bits no brake holds: the wrist pitch's D7 pulsed alone after its moves,
    # the jaw's D5 on its stop (tools/checkout/limitbits.py)
    ("stuck-bit:dac@DAC[11]:7=0", "wrist_pitch_current_limit",
     "data bit D7 of DAC channel wrist_pitch_current_limit stuck at 0"),
    ("stuck-bit:dac@DAC[13]:5=1", "gripper_current_limit",
     "data bit D5 of DAC channel gripper_current_limit stuck at 1"),
])
def test_the_former_misses_of_the_200_case_matrix_are_found_and_named(spec, channel, words):
    """Nine stuck bits and a load the 200-case matrix (seed 7, rack errors seed 1) passed or
    named no cause for (docs/checkout.md): found, the channel and the bit (the cause) named."""
    case = next(c for c in cases(RACK) if c.spec == spec)
    v = run_case(case, RACK, sim_errors=1)
    assert v.right, v.first
    assert channel in v.first and words in v.first, v.first


def test_a_split_counts_only_where_its_pieces_interleave_as_noise_does():
    """:func:`core_splits`: idle noise about 0x7FF | 0x800 with D5 stuck at 0 reads 0x7DF and
    0x800.. in turn, read by read: named. An input that rested at 0x7DF, then at 0x800, with
    the same codes and counts but one after the other (two levels, as a healthy seeded
    rack's resolver rested) is no split."""
    import numpy as np
    from tools.checkout.runner import core_splits
    rng = np.random.default_rng(3)
    idle = np.clip(np.rint(rng.normal(0x800, 0.8, 1500)), 0, 4095).astype(np.int64)
    stuck = _stick(idle, 5, 0)
    assert core_splits(stuck, 12) == [(5, 0)]
    rested = np.sort(stuck)  # the same reads, the low level's first
    assert core_splits(rested, 12) == []


def test_a_runaway_s_cause_is_read_while_the_current_flowed_not_after_the_trip():
    """A load runs the shoulder pitch away: the amplifier holds back at its -5 A limit, then
    the service makes the outputs safe and the monitor reads 0 A; the cause is the current
    while it flowed (a load), not the last reads. A drive that pushes with the motion is the
    rate loop's, and no current at all says nothing."""
    from tools.checkout.runner import _runaway_cause
    held_then_tripped = [-4.97] * 5 + [-3.7, -0.9, 0.5, 0.25] + [0.0, 0.005] * 15
    assert "an external load drives it" in _runaway_cause(held_then_tripped, +0.10, 5.0)
    assert "the motor drives it on" in _runaway_cause([0.5, 2.0, 4.9, 4.9, 0.0], +0.10, 5.0)
    assert _runaway_cause([0.0, 0.01, 0.0], +0.10, 5.0) == ""
