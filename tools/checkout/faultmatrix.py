"""The checkout fault matrix (issue 32 item 3): every fault ``pfma fault list`` names, on
every board, register, bit, channel, line and joint it takes, injected into the simulated
rack; ``pfma checkout`` run on each (as a user runs it: stop at the first failure); its
first failure read as a user reads it.

Three questions per case, each a column of the figures:

- *detected*: the checkout failed;
- *part right*: its first failure names the faulted part: one of the fault's channels, or
  for a board-wide fault (a shared register, a dead board) the board, or any channel on it;
- *kind right*: the first failure's words name the right kind of fault
  (:data:`KIND_WORDS`); the words it names instead give the confusion matrix's column
  (:func:`named_kind`).

The full matrix is ``pfma bench checkout-faults`` (a few thousand cases, ~2 s each on the
simulated rack); ``make test`` runs a seeded sample (tests/tools/checkout/test_fault_matrix.py).
docs/checkout.md has the figures and every miss with its reason.
"""

from __future__ import annotations

import random
import re
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from pfma.rack import RackConfig, load_rack

#: the words that name each kind of fault in a checkout's failure (lower case; any one
#: counts). ASSUMED to be what a lab engineer reads as "this kind": the checkout's own
#: diagnoses (tools/checkout/runner.py) use these words.
KIND_WORDS: dict[str, tuple[str, ...]] = {
    "bus-error": ("bus error", "not answering", "no answer"),
    "stuck-bit": ("stuck bit", "stuck at"),
    "adc-busy-stuck": ("busy", "conversion"),
    "resolver-los": ("loss of signal",),
    "serial-noise": ("noise", "bad record", "checksum", "garbage"),
    "serial-drop": ("bytes lost", "bad record", "checksum", "short record"),
    "serial-stall": ("silent", "no record", "stale", "stalled", "nothing"),
    "serial-disconnect": ("silent", "no record", "stale", "disconnected", "nothing"),
    "ft-unplugged": ("silent", "no record", "stale", "unplugged", "nothing"),
    "hand-unplugged": ("silent", "no record", "stale", "unplugged", "nothing"),
    "tach-reversed": ("tach polarity reversed",),
    "amp-off": ("no motor current", "pwm stage", "amplifier"),
    "brake-held": ("brake not released", "brake held", "brake-release"),
    "adc-dead": ("does not follow", "dead input", "input stuck"),
    "ft-noise": ("noise", "bad record", "checksum", "garbage"),
    "load": ("load", "collision"),
    "switcher-silent": ("switcher", "acknowledge"),
    "panel-off:28v": ("+28 v", "panel"),
    "panel-off:15v": ("+/-15 v", "panel"),
    "panel-off:pwm": ("pwm stage switch", "panel"),
    "panel-off:brake": ("brake-release switch", "panel"),
}

#: value for the faults that take one: an A/D input held at 2.5 V (mid-range, not 0), a
#: snag of 300 N*m (the supervision tests' collision; the gripper's 300 N)
ADC_DEAD_VOLTS = 2.5
LOAD_NM = 300.0


@dataclass(frozen=True)
class Case:
    """One fault on one target: the spec, its kind, the board it is on (None: not a board's
    fault) and the channels a right answer may name (empty: any channel of the board)."""

    spec: str
    kind: str
    board: str | None = None
    signals: frozenset[str] = frozenset()


@dataclass
class Verdict:
    case: Case
    detected: bool
    part_right: bool
    kind_right: bool
    named: str  #: the kind the first failure's words name ("" none, "?" no failure)
    first: str  #: the first failure's line ("" when the checkout passed)
    seconds: float = 0.0
    #: why no checkout could have seen this case in this run ("" when one could): from the
    #: simulated rack's ground truth (:func:`undetectable`)
    undetectable: str = ""

    @property
    def right(self) -> bool:
        return self.detected and self.part_right and self.kind_right

    def as_dict(self) -> dict[str, Any]:
        return {"spec": self.case.spec, "kind": self.case.kind, "detected": self.detected,
                "part_right": self.part_right, "kind_right": self.kind_right, "named": self.named,
                "first": self.first, "seconds": round(self.seconds, 2), "undetectable": self.undetectable}


def _expand(reg: str) -> list[str]:
    """``DAC[0..15]`` -> DAC[0] .. DAC[15]; a plain name as it is."""
    m = re.fullmatch(r"(\w+)\[(\d+)\.\.(\d+)\]", reg)
    return [f"{m[1]}[{i}]" for i in range(int(m[2]), int(m[3]) + 1)] if m else [reg]


#: the data registers of each device and the bits of their data field (the register
#: tables: drivers/rtd/registers.py ANGLE 14 bits right-justified, drivers/dac DAC latch
#: D11..D0, drivers/adc DATA and SCAN "code" 12 bits); a stuck bit elsewhere (a control or
#: status register) is another fault, not in this matrix
DATA_REGISTERS: dict[str, tuple[tuple[str, ...], int]] = {
    "rtd": (("CH",), 14), "dac": (("DAC[",), 12), "adc": (("DATA", "SCAN["), 12)}


def _data_bits(rack: RackConfig, board: str, reg: str) -> int:
    """The data bits of ``board``'s register ``reg`` (0: not a data register)."""
    prefixes, bits = DATA_REGISTERS.get(rack.board(board).device, ((), 0))
    return bits if reg.startswith(prefixes) else 0


def _board_signals(rack: RackConfig, board: str, reg: str) -> frozenset[str]:
    """The channels a register of ``board`` carries: CHn / DAC[n] its channel's signal, a
    shared register (A/D DATA, CSR, status) none (the board is named)."""
    m = re.fullmatch(r"(?:CH|DAC\[|SCAN\[)(\d+)\]?", reg)
    if not m:
        return frozenset()
    n = int(m[1])
    return frozenset(c.signal for c in rack.board(board).channels if c.channel == n)


def _joint_signals(rack: RackConfig, joint: str) -> frozenset[str]:
    return frozenset(c.signal for c in rack.channels() if c.joint == joint)


def cases(rack: RackConfig | None = None) -> list[Case]:
    """Every case of the matrix on ``rack`` (default: the report's), from
    ``sim.faults.fault_targets``: every kind on every target it takes; stuck bits on every
    data bit of every register, stuck at 0 and at 1."""
    from sim.faults import KINDS, fault_targets
    rack = rack if rack is not None else load_rack()
    t = fault_targets(rack)
    out: list[Case] = []
    for board in t["bus-error"]["BOARD"]:
        out.append(Case(f"bus-error:{board}", "bus-error", board))
    for board, regs in t["stuck-bit"]["REG"].items():
        for reg in (r for rr in regs for r in _expand(rr)):
            sig = _board_signals(rack, board, reg)
            for bit in range(_data_bits(rack, board, reg)):
                for v in (0, 1):
                    out.append(Case(f"stuck-bit:{board}@{reg}:{bit}={v}", "stuck-bit", board, sig))
    for board in t["adc-busy-stuck"]["BOARD"]:
        out.append(Case(f"adc-busy-stuck:{board}", "adc-busy-stuck", board))
    for sig in t["resolver-los"]["SIGNAL"]:
        out.append(Case(f"resolver-los:{sig}", "resolver-los", rack.channel(sig).board, frozenset({sig})))
    for sig in t["adc-dead"]["SIGNAL"]:
        out.append(Case(f"adc-dead:{sig}={ADC_DEAD_VOLTS:g}", "adc-dead", rack.channel(sig).board, frozenset({sig})))
    for kind in ("serial-noise", "serial-drop", "serial-stall", "serial-disconnect"):
        for line in t[kind]["LINE"]:
            out.append(Case(f"{kind}:{line}", kind, rack.channel(line).board, frozenset({line})))
    for kind in ("tach-reversed", "amp-off", "brake-held", "panel-off:pwm", "panel-off:brake"):
        for j in t[kind]["JOINT"]:
            out.append(Case(f"{kind}:{j}", kind, None, _joint_signals(rack, j)))
    for j in t["load"]["JOINT"]:
        out.append(Case(f"load:{j}={LOAD_NM:g}", "load", None, _joint_signals(rack, j)))
    out.append(Case("ft-unplugged", "ft-unplugged", None, frozenset({"ft_sensor"})))
    out.append(Case("hand-unplugged", "hand-unplugged", None, frozenset({"crl_hand_controller"})))
    out.append(Case("ft-noise", "ft-noise", None, frozenset({"ft_sensor"})))
    out.append(Case("switcher-silent", "switcher-silent", None, frozenset()))
    out.append(Case("panel-off:28v", "panel-off:28v"))
    out.append(Case("panel-off:15v", "panel-off:15v"))
    assert {c.kind for c in out} == set(KINDS), set(KINDS) ^ {c.kind for c in out}  # every kind, once a kind
    return out


def sample(all_cases: list[Case], n: int, seed: int) -> list[Case]:
    """``n`` cases (at least one of every kind), drawn with ``seed``: the same sample for the
    same seed and matrix."""
    rng = random.Random(seed)
    by_kind: dict[str, list[Case]] = {}
    for c in all_cases:
        by_kind.setdefault(c.kind, []).append(c)
    picked = [rng.choice(v) for v in by_kind.values()]
    rest = [c for c in all_cases if c not in picked]
    picked += rng.sample(rest, max(0, min(n - len(picked), len(rest))))
    return picked


def named_kind(text: str) -> str:
    """The kind a failure's words name (the first of :data:`KIND_WORDS` whose word it has, in
    that table's order), or "" when none does."""
    low = text.lower()
    return next((k for k, words in KIND_WORDS.items() if any(w in low for w in words)), "")


def judge(case: Case, failures: list[dict], rack: RackConfig) -> Verdict:
    """A verdict on the checkout's failures (report rows: ``channel``, ``check``,
    ``detail``...) for ``case``: the rows a run that stops at its first failure reports,
    that failure and the diagnosis row it adds (a joint's drive-or-brake row), as the user
    reads them in the summary."""
    if not failures:
        return Verdict(case, False, False, False, "?", "")
    rows = [" ".join(str(f.get(k) or "") for k in ("channel", "check", "detail")) for f in failures]
    text = " | ".join(rows)
    low = text.lower()
    chans = {str(f.get("channel") or "") for f in failures}
    if case.signals:
        part = bool(chans & case.signals) or any(s in low for s in case.signals)
    elif case.board is not None:
        on_board = {c.signal for c in rack.board(case.board).channels}
        part = bool(chans & on_board) or case.board.lower() in low
    else:  # a whole-chassis fault (a panel supply): any joint's failure points at it
        part = True
    kind_ok = any(w in low for w in KIND_WORDS[case.kind])
    # the kind the report names: its last row that names one (a diagnosis explains the failure)
    named = next((k for k in (named_kind(r) for r in reversed(rows)) if k), "")
    return Verdict(case, True, part, kind_ok, named, text)


#: why a stuck bit could not be seen, by what the simulated rack knows of the run
NEVER_ALTERED = ("its stuck value was the true value every time the bit was read or latched "
                 "in this run: the run was bit for bit a healthy rack's")
SPARE_CHANNEL = "nothing is wired to a spare DAC channel: its output reaches nothing the rack measures"
UNCABLED_RESOLVER = ("a spare resolver channel is not cabled: its angle word means nothing (the checkout "
                     "does not read it, `[resolvers] check_spares`)")


def undetectable(case: Case, target, rack: RackConfig) -> str:
    """Why no software could have told ``case`` from a healthy rack in the run just made on
    ``target`` (a :class:`SimTarget`), or "" when something could: a stuck bit that never
    changed a word (the fake counts, ``FakeBoard.stuck_bits_altered``), or one on a spare
    DAC channel (wired to nothing) or a spare resolver channel (not cabled). Every other case
    counts as detectable. A resolver's loss of signal on a spare channel is the uncabled
    channel's own state, so it is no fault to find either."""
    if case.kind == "resolver-los" and case.signals and all(rack.channel(sg).spare for sg in case.signals):
        return UNCABLED_RESOLVER
    if case.kind != "stuck-bit" or case.board is None:
        return ""
    if not target.world.bus[case.board].stuck_bits_altered:
        return NEVER_ALTERED
    if rack.board(case.board).device == "dac" and case.signals and all(
            rack.channel(sg).spare for sg in case.signals):
        return SPARE_CHANNEL
    if rack.board(case.board).device == "rtd" and case.signals and all(
            rack.channel(sg).spare for sg in case.signals):
        return UNCABLED_RESOLVER
    return ""


def run_case(case: Case, rack: RackConfig, config=None, sim_errors: int = 0) -> Verdict:
    """Checkout (stop at the first failure, non-interactive) on a simulated rack with
    ``case`` injected; ``sim_errors``: the seed of the rack's imperfections (sim/errors.py;
    0: the perfect rack)."""
    from tools.checkout import Checkout, load_checkout_config
    from tools.checkout.target import SimTarget
    cfg = config if config is not None else load_checkout_config(None)
    t0 = time.monotonic()
    target = SimTarget(rack, sim_errors=sim_errors)
    try:
        target.inject_fault(case.spec)
        report = Checkout(target, cfg, interactive=False, say=lambda line: None).run()
        why = undetectable(case, target, rack)
    finally:
        target.close()
    fails = [r for r in report.as_dict()["results"] if r.get("status") == "FAIL"]
    v = judge(case, fails, rack)
    v.undetectable = why
    v.seconds = time.monotonic() - t0
    return v


@dataclass
class Figures:
    """The matrix's figures: counts per kind and the confusion (injected kind -> named)."""

    verdicts: list[Verdict] = field(default_factory=list)

    def per_kind(self) -> dict[str, dict[str, int]]:
        out: dict[str, dict[str, int]] = {}
        for v in self.verdicts:
            k = out.setdefault(v.case.kind, {"cases": 0, "detected": 0, "part_right": 0, "kind_right": 0})
            k["cases"] += 1
            k["detected"] += v.detected
            k["part_right"] += v.detected and v.part_right
            k["kind_right"] += v.detected and v.part_right and v.kind_right
        return out

    def confusion(self) -> dict[str, dict[str, int]]:
        out: dict[str, dict[str, int]] = {}
        for v in self.verdicts:
            row = out.setdefault(v.case.kind, {})
            col = v.named if v.detected else "(passed)"
            row[col or "(no kind named)"] = row.get(col or "(no kind named)", 0) + 1
        return out

    def as_dict(self) -> dict[str, Any]:
        n = len(self.verdicts)
        det = sum(v.detected for v in self.verdicts)
        right = sum(v.right for v in self.verdicts)
        can = [v for v in self.verdicts if not v.undetectable]
        can_det = sum(v.detected for v in can)
        return {"cases": n, "detected": det, "named_right": right,
                "detected_fraction": round(det / n, 4) if n else None,
                "named_right_fraction_of_detected": round(right / det, 4) if det else None,
                "detectable": len(can), "detectable_detected": can_det,
                "detected_fraction_of_detectable": round(can_det / len(can), 4) if can else None,
                "undetectable": [v.as_dict() for v in self.verdicts if v.undetectable],
                "per_kind": self.per_kind(), "confusion": self.confusion(),
                "misses": [v.as_dict() for v in can if not v.right]}


def run_matrix(which: list[Case], rack: RackConfig | None = None,
               progress: Callable[[int, int, Verdict], None] | None = None, sim_errors: int = 0) -> Figures:
    """Checkout on every case of ``which`` (on the rack with the imperfections of seed
    ``sim_errors``); the figures."""
    from tools.checkout import load_checkout_config
    rack = rack if rack is not None else load_rack()
    cfg = load_checkout_config(None)
    figs = Figures()
    for i, c in enumerate(which):
        v = run_case(c, rack, cfg, sim_errors)
        figs.verdicts.append(v)
        if progress is not None:
            progress(i + 1, len(which), v)
    return figs
