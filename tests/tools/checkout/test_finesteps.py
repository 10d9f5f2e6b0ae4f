"""A DAC channel's lowest bits told from the monitor's noise (tools/checkout/finesteps.py):
the verdict of each step, the slope taken from the steps themselves, and a seeded check that
healthy steps read through noise are never called stuck while a stuck one is."""

import math

import numpy as np

from tools.checkout.finesteps import FINE_SIGMAS, Level, Step, judge_steps, level, summary


def test_a_step_is_ok_stuck_or_not_judged():
    assert Step(0, 0.9e-3, 0.1e-3, 1.0e-3).verdict == "ok"  # at least half its worth
    assert Step(0, 0.0, 0.1e-3, 1.0e-3).verdict == "stuck"  # 0.5 mA short, 5 standard errors
    assert Step(0, 0.0, 0.5e-3, 1.0e-3).verdict == "noise"  # 0.5 mA short, 1 standard error
    assert Step(0, 0.5e-3 - FINE_SIGMAS * 0.1e-3, 0.1e-3, 1.0e-3).verdict == "stuck"  # the edge


def test_the_slope_is_the_median_of_the_steps_so_one_stuck_bit_does_not_move_it():
    base = Level(0x800, 0x800, 0.0, 1e-4, 100)
    per = 2e-3
    healthy = [(b, Level(0x800 + (1 << b), 0x800 + (1 << b), (1 << b) * per, 1e-4, 100)) for b in range(4)]
    steps = judge_steps(base, healthy)
    assert [s.verdict for s in steps] == ["ok"] * 4
    assert all(math.isclose(s.want, (1 << s.bit) * per) for s in steps)
    d1_stuck = [(b, lv if b != 1 else Level(lv.code, lv.got, 0.0, 1e-4, 100)) for b, lv in healthy]
    stuck, unjudged = summary(judge_steps(base, d1_stuck))
    assert [s.bit for s in stuck] == [1] and unjudged == []


def test_seeded_noisy_reads_never_call_a_healthy_step_stuck_and_find_a_stuck_one():
    """Reads of 1.2 monitor codes of noise (the seeded rack's worst, 2.44 mA a code), 96
    of them a level (0.6 s at 160 Hz, ``dac_bits_fine_max_s``): 2,000 healthy D1 steps of
    4.9 mA are never called stuck; the same bit stuck is called stuck in at least 99.5 % (a
    stuck step reads over 3.3 standard errors above nothing 0.05 % of the time, and is then
    "not judged", never passed as ok)."""
    rng = np.random.default_rng(5)
    sigma, per, n = 1.2 * 2.44e-3, 2.44e-3, 96
    called, found, passed = 0, 0, 0
    for _ in range(2000):
        base = level(0x820, 0x820, list(rng.normal(0.0, sigma, n)))
        up = level(0x822, 0x822, list(rng.normal(2 * per, sigma, n)))
        flat = level(0x822, 0x822, list(rng.normal(0.0, sigma, n)))
        called += judge_steps(base, [(1, up)], per)[0].verdict == "stuck"
        v = judge_steps(base, [(1, flat)], per)[0].verdict
        found += v == "stuck"
        passed += v == "ok"
    assert called == 0 and found >= 1990 and passed == 0, (called, found, passed)


def test_a_step_under_one_and_a_half_monitor_codes_read_without_noise_is_not_judged():
    """Read without noise, a mean moves by whole codes: a healthy 0.95-code step can read as
    none, so it is not judged; the same step read through 0.5 codes of noise is, and a
    2-code step always is."""
    code = 2.44e-3
    base = Level(0x800, 0x800, 0.0, 0.0, 96)  # the same code every read
    flat = Level(0x801, 0x801, 0.0, 0.0, 96)
    assert judge_steps(base, [(0, flat)], 0.95 * code, code)[0].verdict == "noise"
    assert judge_steps(base, [(1, flat)], 1.0 * code, code)[0].verdict == "stuck"  # 2 codes' worth
    noisy = 0.5 * code / math.sqrt(96)  # the standard error of 96 reads of 0.5 codes of noise
    dithered = judge_steps(Level(0x800, 0x800, 0.0, noisy, 96), [(0, Level(0x801, 0x801, 0.0, noisy, 96))],
                           0.95 * code, code)[0]
    assert dithered.resolvable and dithered.verdict == "stuck"
