"""The scripted checkout: every channel of the rack, one PASS/FAIL row each.

Groups, in order (``[checkout] groups``; each is a method ``_group_<name>``):

``resolvers``  each resolver valid (status bits clear) and quiet (peak-to-peak counts);
``adc``        each ADC channel inside its idle range (per signal group) and quiet;
``links``      F/T and CRL serial links: record rate, bad records, resyncs, status;
``hand``       CAE axes and discretes, one operator action each ("deflect CAE up");
``pio``        user I/F box inputs, each operated alone (walking bit);
``matrix``     matrix-switcher routes written, read back as applied by the service;
``joints``     per joint an open-loop polarity and scaling test: arm with a low current
               limit, command a small rate each way, check tach and resolver, stop; then
               a diagnosis that names the drive or the brake from what the sensors showed.

Before the joints group the servo chassis' front panel (+28 V, +/-15 V, the PWM stage and
brake-release switches, IRSS 3.6) is asked of the operator, or taken as stated
(``panel``, ``pfma checkout --panel-off``), and recorded as such ("panel" rows: statements,
not measurements); a chassis supply stated off skips the joints, a joint's PWM stage or
brake switch stated off skips that joint.

Before the groups a preflight checks the service state and every board's status and
error counter. Operator actions go through the target's ``stimulus`` on the
simulated rack; on a real rack the operator is prompted and the checkout waits (with
a time-out) for the input to change. Outputs are made safe (rates 0, current limits
0, disarmed) however a joint test ends.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Callable

import numpy as np

from tools.checkout.config import CheckoutConfig
from tools.checkout.finesteps import (
    ADC_VOLTS_PER_CODE, DAC_VOLTS_PER_CODE, DAC_ZERO_CODE, FINE_SE_CODES, FINE_WORTHS, Level, Step, adc_offset_bit,
    bit_of_codes, judge_steps, place_code, read_fine, step_levels, steps_why, summary, worst_step,
)
from tools.checkout.limitbits import DRIVE_STILL, JAW_FIRST_BIT, JAW_PULSE_CHECK, JOINT_FIRST_BIT, PULSE_CHECK, \
    DAC_BITS, LimitPulses, limit_low_hint, monitor_excess, pulse_bits, zeroing_bits
from tools.checkout.panel import ASSUMED, GRIPPER, PANEL_CHECKS, SWITCH_TEXT, PanelState, ask_panel
from tools.checkout.report import FAIL, PASS, SKIP, Report, Result
from tools.checkout.target import ServiceLost, Target
from bit3.layout import (
    BOARD_FAULT, BOARD_OK, CHANNEL_BUS_ERROR, LINK_FAULT, LINK_OPEN, LINK_STALE, LINK_SYNCED, RTD_LOSS_OF_SIGNAL,
    RTD_NO_REFERENCE, ServiceState,
)
from pfma.errors import PfmaError
from pfma.show import wrap_angle
from controller.routes import ALL_ROUTES, route_text
from drivers.adc.registers import DVME611
from drivers.dac.registers import VMIVME4100

#: rtd_status bits (bit3.layout)
RTD_BITS = {RTD_LOSS_OF_SIGNAL: "loss of signal", RTD_NO_REFERENCE: "no reference",
            CHANNEL_BUS_ERROR: "board read failed"}
LINK_BITS = {LINK_OPEN: "open", LINK_SYNCED: "synced", LINK_FAULT: "fault", LINK_STALE: "stale"}
BOARD_BITS = {BOARD_OK: "ok", 2: "init", BOARD_FAULT: "fault"}
#: a tach whose samples span less than this fraction of the commanded rate while the
#: resolver shows the joint moving is reported as dead or stuck rather than reversed
STUCK_TACH_FRACTION = 0.1

GROUP_TITLES = {
    "resolvers": "resolvers valid and quiet",
    "adc": "ADC channels inside their idle ranges",
    "links": "serial links: rate and errors",
    "hand": "hand controller axes and discretes (operator)",
    "pio": "user I/F box inputs (operator)",
    "matrix": "matrix switcher outputs",
    "joints": "open-loop polarity and scaling, per joint",
}


def bits_text(value: int, names: dict[int, str]) -> str:
    """``"loss of signal|no reference"``; unknown bits as hex; ``"clear"`` for 0."""
    if not value:
        return "clear"
    parts = [n for b, n in names.items() if value & b]
    rest = value & ~sum(names)
    if rest:
        parts.append(f"0x{rest:X}")
    return "|".join(parts)


def _wrap(x: np.ndarray | float, period: float):
    return (np.asarray(x) + period / 2) % period - period / 2


class StopRun(Exception):
    """First failure and no ``keep_going``."""


class Checkout:
    """One checkout run against a :class:`Target`.

    :param keep_going: continue after a failure (``-k``)
    :param only: groups to run (default: ``[checkout] groups``)
    :param interactive: prompt an operator on a real rack; False skips operator steps there
    :param say: where progress and prompts go (default ``print``)
    :param progress: called with (groups started, groups, text) as each group starts and
        once at the end (``pfma checkout`` draws a bar with it on a terminal)
    :param panel: the servo chassis' front panel as stated (``--panel-off``); None: asked
        of the operator before the joints group when ``interactive`` on a rack without a
        stimulus, else assumed all on (and recorded as assumed)
    :param ask: shows a prompt and returns the operator's answer line (default ``input``)
    """

    def __init__(self, target: Target, config: CheckoutConfig, *, keep_going: bool = False,
                 only: list[str] | None = None, interactive: bool = True,
                 say: Callable[[str], None] = print,
                 progress: Callable[[int, int, str], None] | None = None,
                 panel: PanelState | None = None, ask: Callable[[str], str] | None = None) -> None:
        self.t = target
        self.progress = progress
        self.cfg = config
        self.keep_going = keep_going
        groups = list(config.get("checkout", "groups"))
        if only:
            unknown = [g for g in only if g not in groups]
            if unknown:
                raise PfmaError(f"unknown checkout group(s) {unknown}; groups: {', '.join(groups)}")
            groups = [g for g in groups if g in only]
        self.groups = groups
        self.interactive = interactive
        self.say = say
        self.ask: Callable[[str], str] = ask if ask is not None else input
        self.panel = panel
        self.lay = target.layout
        self.poll_s = config.num("checkout", "poll_s")
        self.report = Report(target.describe(), target.rack.name, groups, config=config.as_dict(),
                             config_source=config.source)
        self.interrupted = False
        #: every resolver and A/D code the run read (the data-bit diagnosis reads them)
        self.codes = CodeLog()
        self._capture: dict[str, np.ndarray] | None = None
        self._group = "service"

    # ------------------------------------------------------------------ plumbing
    def record(self, group: str, channel: str, check: str, ok: bool | None, measured=None,
               low=None, high=None, units: str = "", detail: str = "") -> Result:
        """Add one row (ok None = SKIP); stop the run on a failure unless ``keep_going``."""
        status = SKIP if ok is None else (PASS if ok else FAIL)
        r = Result(group, channel, check, status, measured, low, high, units, detail)
        self.report.results.append(r)
        self.say(r.line())
        if status == FAIL and not self.keep_going:
            raise StopRun(f"first failure: {channel} ({check}); -k keeps going")
        return r

    def inputs(self):
        s = self.t.inputs()
        self.codes.note(s)
        return s

    def value(self, signal: str) -> float:
        return float(self.inputs().value(signal))

    def volts(self, signal: str) -> float:
        return float(self.inputs().channel(signal)["adc_volts"])

    def operate(self, prompt: str, stimulate: Callable, cond: Callable[[], bool]) -> bool | None:
        """One operator action: the stimulus does it on the simulated rack, an operator on a
        real one. True = seen, False = timed out, None = skipped (non-interactive, no stimulus)."""
        st = self.t.stimulus
        if st is not None:
            self.say(f"    [stimulus] {prompt}")
            stimulate(st)
            timeout = self.cfg.num("checkout", "stimulus_timeout_s")
        elif not self.interactive:
            return None
        else:
            timeout = self.cfg.num("checkout", "operator_timeout_s")
            self.say(f">>> OPERATOR: {prompt}  (waiting up to {timeout:.0f} s)")
        return self.t.wait_until(cond, timeout, self.poll_s)

    # ------------------------------------------------------------------ run
    def run(self) -> Report:
        rep = self.report
        wall0 = time.perf_counter()
        t0 = self.t.now()
        try:
            self.say(f"pfma checkout: {self.t.describe()}; groups: {', '.join(self.groups)}; "
                     f"tolerances: {self.cfg.source}")
            self._preflight()
            for k, g in enumerate(self.groups):
                self._group = g
                self.say(f"== {g}: {GROUP_TITLES[g]}")
                if self.progress is not None:
                    self.progress(k, len(self.groups), f"{g}: {GROUP_TITLES[g]}")
                getattr(self, f"_group_{g}")()
            self._group = "data bits"
            self._data_bits(stopping=False)
            if self.progress is not None:
                self.progress(len(self.groups), len(self.groups), "done")
        except StopRun as stop:
            rep.stopped_early = str(stop)
            self._data_bits(stopping=True)
        except ServiceLost as err:
            rep.stopped_early = str(err)
            self._record_quiet(self._group, "service", "publishing", False, detail=str(err))
        except PfmaError as err:
            rep.stopped_early = f"{type(err).__name__}: {err}"
            self._record_quiet(self._group, self._group, "ran", False, detail=str(err))
        except KeyboardInterrupt:
            rep.stopped_early = "interrupted by the operator"
            self.interrupted = True
        finally:
            try:
                if self.t.stimulus is not None:
                    self.t.stimulus.release()
            finally:
                self.t.release_commands()
            rep.duration_s = time.perf_counter() - wall0
            rep.target_time_s = self.t.now() - t0
        return rep

    def _record_quiet(self, *args, **kw) -> None:
        try:
            self.record(*args, **kw)
        except StopRun:
            pass

    # ------------------------------------------------------------------ preflight
    def _preflight(self) -> None:
        """Service up, every board present and initialised, no errors while settling."""
        s = self.inputs()
        boards = [c for c in self.lay.channels if c.kind == "board"]
        before = {c.name: int(s.board_errors[c.slot]) for c in boards}
        self.t.wait(self.cfg.num("checkout", "settle_s"))
        s = self.inputs()
        state = ServiceState(s.service_state)
        self.record("service", "service", "state", state not in (ServiceState.STARTING, ServiceState.STOPPED),
                    state.name, detail="the I/O service must be running")
        said = self.service_said()
        for c in boards:
            st = int(s.board_status[c.slot])
            new = int(s.board_errors[c.slot]) - before[c.name]
            ok = bool(st & BOARD_OK) and not st & BOARD_FAULT and new == 0
            addr = int(s.board_last_error_addr[c.slot])
            why = said.get(c.name, "") if not ok else ""
            self.record("service", c.name, "board status", ok, new, None, 0, "errors",
                        f"status {bits_text(st, BOARD_BITS)}" +
                        (f", last error at A16 0x{addr:04X}" if addr else "") +
                        (f"; the service: {why}" if why else ""))

    def service_said(self) -> dict[str, str]:
        """The service's newest message about each board (its text begins with the board's
        name: ``adc: busy stuck scanning ...``, ``rtd2: bus error: ...``), the board's name
        cut off: the cause in the service's own words, for a failure's detail."""
        names = {c.name for c in self.lay.channels if c.kind == "board"}
        out: dict[str, str] = {}
        try:
            msgs = self.t.reader.messages()
        except Exception:  # noqa: BLE001 - the words are a courtesy; the check stands without them
            return out
        for m in msgs:
            head, sep, rest = m.text.partition(": ")
            if sep and head in names:
                out[head] = rest
                continue
            for name in names:  # said inside another message ("... (bus error: write16 dac DAC[0] ...")
                if f" {name} " in m.text and ("bus error" in m.text or "not answering" in m.text):
                    out[name] = m.text
        return out

    # ------------------------------------------------------------------ data bits
    def _stuck_found(self, c, codes: np.ndarray) -> list[tuple[int, int]]:
        """(bit, value) of every stuck data bit channel ``c``'s ``codes`` show, strongest first:
        a jump across a bit's edge (the bit one value on both sides of a 2^b jump), then a
        dense sweep's, then the noise's."""
        nbits = DATA_BITS[c.kind]
        found = angle_jumps(codes, nbits) if c.kind == "rtd" else adc_jumps(codes, nbits)
        found += stuck_bits(codes, nbits)
        found += noise_split(codes, nbits) + self._idle_split(c)
        for group in code_groups(codes):  # each level the input held (idle, deflected, driven)
            found += noise_split(group, nbits)
        if c.kind != "rtd":
            found += core_splits(codes, nbits) + noise_strays(codes, nbits)
        return found

    def monitor_stuck(self, signal: str) -> str:
        """What A/D input ``signal``'s codes read so far say of its own data bits, for a row
        that a stuck bit of that input would explain: "" when they show none."""
        c = next((c for c in self.lay.channels if c.name == signal and c.kind in DATA_BITS), None)
        found = self._stuck_found(c, self.codes.of(c.kind, c.slot)) if c is not None else []
        if not found:
            return ""
        b, v = found[0]
        return (f"; or the monitor {signal}: its codes so far never had a {1 - v} in bit {b} (its data bit D{b} "
                f"stuck at {v}?)")

    def _data_bits(self, *, stopping: bool) -> None:
        """The resolver and A/D channels' data bits over every code the run read: a bit that
        never changed while the channel's codes swept densely across where it must have
        (:func:`stuck_bits`) is stuck. After a failure (``stopping``) only a stuck bit is
        said, as that failure's diagnosis; at the end of a whole run a row per board."""
        seen: dict[str, tuple[int, int]] = {}
        for c in self.lay.channels:
            if c.kind not in DATA_BITS:
                continue
            codes = self.codes.of(c.kind, c.slot)
            found = self._stuck_found(c, codes)
            n, k = seen.get(c.board, (0, 0))
            seen[c.board] = (n + len(codes), k + bool(found))
            for bit, v in list(dict.fromkeys(found))[:1]:  # the first reading names it; one row a channel
                u = np.unique(codes)
                self._record_quiet("data bits", c.name, "data bits (diagnosis)" if stopping else "data bits",
                                   False, f"bit {bit} stuck at {v}", detail=(
                                       f"bit {bit} stuck at {v}: {len(u)} distinct codes {int(u[0])}..{int(u[-1])} "
                                       f"over the run, never a {1 - v} in bit {bit} (board {c.board} ch "
                                       f"{c.channel}; a data bit of the board or its cable)"))
        if stopping:
            return
        for board, (n, k) in seen.items():
            if not k:
                self.record("data bits", board, "data bits", True, n, detail=(
                    "no stuck bit seen: a bit is judged where a channel's codes swept across it densely "
                    "(low bits of moving joints and driven inputs; a bit no channel swept is not judged)"))

    def _idle_split(self, c, evidence: int | None = None) -> list[tuple[int, int]]:
        """:func:`noise_split` of channel ``c``'s codes in the idle capture (none taken: [])."""
        if self._capture is None or c.kind not in DATA_BITS:
            return []
        return noise_split(self._capture[f"{c.kind}_counts"][:, c.slot].astype(np.int64), DATA_BITS[c.kind],
                           evidence)

    def _split_why(self, c) -> str:
        """A quiet channel's idle noise split by a stuck data bit, said for its failing idle or
        noise row ("" when its noise shows none). The row has failed already, so one sample
        one bit away from the rest is reason enough to name the bit."""
        found = self._idle_split(c, evidence=1)
        if not found:
            return ""
        b, v = found[0]
        return (f"; data bit D{b} stuck at {v}: its idle noise reads in two groups {1 << b} codes apart "
                f"(D{b} the same in every code; with D{b} put back they join into one)")

    # ------------------------------------------------------------------ idle capture
    def capture(self) -> dict[str, np.ndarray]:
        """N input samples at the resolver/ADC rate, shared by the resolver and ADC groups."""
        if self._capture is None:
            n = int(self.cfg.num("capture", "samples"))
            dt = self.cfg.num("capture", "interval_s")
            keys = ("rtd_counts", "rtd_angle_rad", "rtd_status", "adc_counts", "adc_volts",
                    "adc_value", "adc_status")
            rows: dict[str, list] = {k: [] for k in keys}
            for _ in range(n):
                self.t.wait(dt)
                s = self.inputs()
                for k in keys:
                    rows[k].append(np.array(s[k], copy=True))
            self._capture = {k: np.array(v) for k, v in rows.items()}
        return self._capture

    # ------------------------------------------------------------------ resolvers
    def _group_resolvers(self) -> None:
        from drivers.rtd.registers import VMIVME4940
        lsb = VMIVME4940.constants["lsb_rad"]
        cap = self.capture()
        spares = bool(self.cfg.get("resolvers", "check_spares"))
        max_noise = self.cfg.num("resolvers", "max_noise_counts")
        must = int(self.cfg.num("resolvers", "status_must_be"))
        for c in (c for c in self.lay.channels if c.kind == "rtd"):
            if c.spare and not spares:
                self.record("resolvers", c.name, "valid", None, detail="spare channel, not cabled")
                continue
            status = int(np.bitwise_or.reduce(cap["rtd_status"][:, c.slot]))
            self.record("resolvers", c.name, "valid (status bits)", status == must, status, must, must,
                        "bits", f"{bits_text(status, RTD_BITS)} (board {c.board} ch {c.channel})")
            ang = np.unwrap(cap["rtd_angle_rad"][:, c.slot])
            pp = float((ang.max() - ang.min()) / lsb)
            self.record("resolvers", c.name, "noise (peak-peak)", pp <= max_noise, round(pp, 2), 0,
                        max_noise, "counts",
                        f"mean {wrap_angle(float(np.mean(ang))):.4f} rad over "
                        f"{len(ang)} samples" + ("" if pp <= max_noise else
                                                 _drifted(ang, lsb, c.name) or self._split_why(c)))
            self._within_travel(c.name, float(np.mean(ang)))
            self._as_seen(c, float(np.mean(ang)), int(np.median(cap["rtd_counts"][:, c.slot])))

    def _within_travel(self, signal: str, angle: float) -> None:
        """A resolver angle outside its joint's hard stops (pfma-model 8.2, ``pfma.arm``) is
        not where the joint can be: a high bit of the angle word stuck, a zero far off, or
        wiring. One row per joint's resolver (a rack's joint the nominal arm lacks: none)."""
        from pfma.arm import JOINTS
        joint = self.t.rack.channel(signal).joint
        jf = next((f for f in JOINTS if f.name == joint), None)
        if jf is None:
            return
        margin = math.radians(float(self.cfg.num("resolvers", "travel_margin_deg")))
        a = jf.centre_rad + wrap_angle(angle - jf.centre_rad)
        lo, hi = jf.hard_lo_rad - margin, jf.hard_hi_rad + margin
        ok = lo <= a <= hi
        self.record("resolvers", signal, "within travel (hard stops)", ok, round(math.degrees(a), 2),
                    round(math.degrees(lo), 1), round(math.degrees(hi), 1), "deg",
                    f"{joint}'s hard stops {math.degrees(jf.hard_lo_rad):g}..{math.degrees(jf.hard_hi_rad):g} deg "
                    f"(+/- {math.degrees(margin):g})" + ("" if ok else
                    ": the joint cannot be there: a stuck bit in the angle word (a high bit, stuck at the "
                    "other value), a resolver zero far off, or its wiring"))

    def _seen_angle(self, joint: str, reads_deg: float) -> tuple[float | None, str]:
        """The joint's angle as a person reads it on the arm (deg) and who read it: the
        simulated rack's stimulus (its true angle), the operator (interactive), or nobody."""
        st = self.t.stimulus
        if st is not None:
            q = st.joint_angle_rad(joint)
            return (None if q is None else math.degrees(wrap_angle(q))), "the simulated arm's true angle (stimulus)"
        if not self.interactive:
            return None, "not checked: no operator (non-interactive)"
        answer = self.ask(f">>> OPERATOR: {joint}: the resolver reads {reads_deg:+.1f} deg. Its angle on the "
                          "arm's scale in deg (Enter: skip): ").strip()
        if not answer:
            return None, "skipped by the operator"
        try:
            v = float(answer)
        except ValueError:
            return None, f"not checked: {answer!r} is not an angle in degrees"
        return (v if math.isfinite(v) else None), "read by the operator on the arm"

    def _as_seen(self, c, angle: float, code: int) -> None:
        """The resolver's angle against the joint's as a person sees it on the arm: a high
        data bit stuck at the other value moves the reading by 2^b counts and stays within
        the joint's travel, so only a look at the arm finds it (``seen_tolerance_deg``)."""
        from drivers.rtd.registers import VMIVME4940
        joint = self.t.rack.channel(c.name).joint
        if not joint:
            return
        reads = math.degrees(wrap_angle(angle))
        seen, who = self._seen_angle(joint, reads)
        tol = float(self.cfg.num("resolvers", "seen_tolerance_deg"))
        if seen is None:
            self.record("resolvers", c.name, "angle as seen on the arm", None, detail=who)
            return
        diff = math.degrees(wrap_angle(math.radians(reads - seen)))
        ok = abs(diff) <= tol
        why = ""
        if not ok:
            lsb = math.degrees(float(VMIVME4940.constants["lsb_rad"]))
            bits = [b for b in range(DATA_BITS["rtd"]) if abs(abs(diff) - (1 << b) * lsb) <= tol / 2
                    and (code >> b) & 1 == (diff > 0)]
            why = (f": {abs(diff):.1f} deg is {1 << bits[-1]} counts: data bit D{bits[-1]} stuck at {int(diff > 0)} "
                   f"(board {c.board} ch {c.channel}; or the resolver's zero is that far off)" if bits else
                   ": the resolver's zero is off, or its wiring (no one data bit explains it)")
        self.record("resolvers", c.name, "angle as seen on the arm", ok, round(diff, 2), -tol, tol, "deg",
                    f"the resolver reads {reads:+.2f} deg, {who} {seen:+.2f} deg{why}")

    # ------------------------------------------------------------------ ADC
    def _group_adc(self) -> None:
        cap = self.capture()
        spares = bool(self.cfg.get("adc", "check_spares"))
        max_noise = self.cfg.num("adc", "max_noise_counts")
        for c in (c for c in self.lay.channels if c.kind == "adc"):
            if c.spare and not spares:
                self.record("adc", c.name, "idle", None, detail="spare channel not checked")
                continue
            g = self.cfg.adc_group(c.name)
            where = f"board {c.board} ch {c.channel}"
            status = int(np.bitwise_or.reduce(cap["adc_status"][:, c.slot]))
            if status:
                self.record("adc", c.name, "read", False, status, 0, 0, "bits",
                            f"ADC read failed ({where})")
                continue
            if g is None:
                self.record("adc", c.name, "idle", None, detail=f"no [[adc.group]] matches ({where})")
            else:
                key, units = ("adc_value", c.units) if g["quantity"] == "value" else ("adc_volts", "V")
                x = cap[key][:, c.slot]
                lo, hi = float(g["low"]), float(g["high"])
                mean = float(np.mean(x))
                worst = float(x[np.argmax(np.abs(x - (lo + hi) / 2))])
                ok = bool(np.all((x >= lo) & (x <= hi)))
                why = "" if ok else self._split_why(c) or "; " + _idle_why(int(round(float(np.mean(cap["adc_counts"][:, c.slot])))),
                                                    lo, hi, self.t.rack.channel(c.name).scale
                                                    if g["quantity"] == "value" else 1.0)
                self.record("adc", c.name, f"idle: {g['name']}", ok, round(mean, 5), lo, hi, units,
                            f"worst sample {worst:.4g} {units}; {float(np.mean(cap['adc_volts'][:, c.slot])):.4f} V "
                            f"({where}){why}")
            counts = cap["adc_counts"][:, c.slot].astype(int)
            pp = int(counts.max() - counts.min())
            # within the limit, a split the idle capture alone shows (its default evidence:
            # never named in healthy seeded noise) still fails it: a low bit stuck splits a
            # noisy input's idle codes by 2^b, under the peak-to-peak a rack's noise may reach
            ok = pp <= max_noise and not self._idle_split(c)
            self.record("adc", c.name, "noise (peak-peak)", ok, pp, 0, max_noise, "counts",
                        f"{len(counts)} samples ({where})" + ("" if ok else self._split_why(c)))

    # ------------------------------------------------------------------ links
    def _group_links(self) -> None:
        links = [c for c in self.lay.channels if c.kind == "link"]
        conf = self.cfg.get("links")
        todo = [c for c in links if isinstance(conf.get(c.name), dict)]
        for c in links:
            if c not in todo:
                self.record("links", c.name, "link", None, detail="no [links.<name>] table: not checked")
        if not todo:
            return
        s = self.inputs()
        t0 = self.t.now()
        base = {c.name: (int(s.link_records[c.slot]), int(s.link_bad[c.slot]), int(s.link_resyncs[c.slot]))
                for c in todo}
        self.t.wait(self.cfg.num("links", "window_s"))
        s = self.inputs()
        dt = self.t.now() - t0
        for c in todo:
            lc = conf[c.name]
            r0, b0, y0 = base[c.name]
            rate = (int(s.link_records[c.slot]) - r0) / dt if dt > 0 else 0.0
            bad = int(s.link_bad[c.slot]) - b0
            resyncs = int(s.link_resyncs[c.slot]) - y0
            status = int(s.link_status[c.slot])
            mn = float(lc.get("min_rate_hz", 0.0))
            silent = (f"; silent: no record in {dt:.2f} s (the cable, the far end's power or its port; "
                      f"a bad line would still send bytes)" if rate == 0.0 else "")
            self.record("links", c.name, "record rate", rate >= mn, round(rate, 2), mn, None, "records/s",
                        f"over {dt:.2f} s; service figure {float(s.link_rate_hz[c.slot]):.1f}/s{silent}")
            mb = int(lc.get("max_bad", 0))
            self.record("links", c.name, "bad records", bad <= mb, bad, 0, mb, "records", f"over {dt:.2f} s")
            my = int(lc.get("max_resyncs", 0))
            self.record("links", c.name, "resyncs", resyncs <= my, resyncs, 0, my, "", f"over {dt:.2f} s")
            if lc.get("require_synced", True):
                ok = bool(status & LINK_OPEN and status & LINK_SYNCED) and not status & (LINK_FAULT | LINK_STALE)
                self.record("links", c.name, "link status", ok, status, None, None, "bits",
                            bits_text(status, LINK_BITS) + f"; age {float(s.link_age_s[c.slot]) * 1e3:.0f} ms")
            if c.name == "ft_sensor" and "max_status" in lc:
                st = int(s.ft_status)
                self.record("links", c.name, "sensor status word", st <= int(lc["max_status"]), st, 0,
                            int(lc["max_status"]), "bits",
                            f"F = {np.round(np.asarray(s.ft_force_n), 2).tolist()} N")

    # ------------------------------------------------------------------ hand controller
    def _hc(self):
        s = self.inputs()
        i = self.lay.slot("hc", "cae")
        return s.hc_axes[i].copy(), int(s.hc_buttons[i]), bool(s.hc_valid[i])

    def _group_hand(self) -> None:
        h = self.cfg.get("hand")
        thr = float(h["deflect_threshold_v"])
        tol = float(h["centre_tolerance_v"])
        on_v = float(h["discrete_on_v"])
        stim_v = float(h["stimulus_volts"])
        axes = [a["signal"] for a in h["axes"]]
        names = {c.name for c in self.lay.channels if c.kind == "adc"}
        for a in h["axes"]:
            self._hand_axis(a, axes, names, thr, tol, stim_v)
        for dsc in h["discretes"]:
            self._hand_discrete(dsc, names, on_v)

    def _hand_axis(self, a: dict, axes: list[str], names: set[str], thr: float, tol: float,
                   stim_v: float) -> None:
        """One CAE axis: deflected alone (no other axis moving), then back to centre."""
        sig, d = a["signal"], int(a.get("direction", 1))
        if sig not in names:
            self.record("hand", sig, "deflect", None, detail="not in this rack")
            return
        seen = self.operate(a["prompt"], lambda st, s_=sig, v=d * stim_v: st.cae_axis(s_, v),
                            lambda s_=sig, d_=d: d_ * self.volts(s_) >= thr)
        if seen is None:
            self.record("hand", sig, "deflect", None, detail="operator step skipped (non-interactive)")
            return
        v = self.volts(sig)
        others = {o: self.volts(o) for o in axes if o != sig and o in names}
        moved = {o: x for o, x in others.items() if abs(x) > tol}
        hc, _, valid = self._hc()
        detail = (f"hand-controller slot cae: axes {np.round(hc, 3).tolist()} (valid {valid})"
                  + (f"; ALSO MOVED: {', '.join(f'{o} {x:+.2f} V' for o, x in moved.items())}" if moved else ""))
        lo, hi = (thr, None) if d > 0 else (None, -thr)
        self.record("hand", sig, "deflect " + ("+" if d > 0 else "-"), bool(seen) and not moved,
                    round(v, 3), lo, hi, "V", detail if seen else "no deflection seen; " + detail)
        back = self.operate(f"Release the CAE stick ({sig})", lambda st, s_=sig: st.cae_axis(s_, 0.0),
                            lambda s_=sig: abs(self.volts(s_)) <= tol)
        self.record("hand", sig, "return to centre", bool(back), round(self.volts(sig), 3), -tol, tol, "V")

    def _hand_discrete(self, dsc: dict, names: set[str], on_v: float) -> None:
        """One CAE discrete: pressed, then released."""
        sig = dsc["signal"]
        if sig not in names:
            self.record("hand", sig, "press", None, detail="not in this rack")
            return
        seen = self.operate(dsc["prompt"], lambda st, s_=sig: st.cae_discrete(s_, True),
                            lambda s_=sig: self.volts(s_) >= on_v)
        if seen is None:
            self.record("hand", sig, "press", None, detail="operator step skipped (non-interactive)")
            return
        _, buttons, _ = self._hc()
        self.record("hand", sig, "press", bool(seen), round(self.volts(sig), 3), on_v, None, "V",
                    f"hand-controller buttons 0x{buttons:X}")
        off = self.operate(f"Release {sig}", lambda st, s_=sig: st.cae_discrete(s_, False),
                           lambda s_=sig: self.volts(s_) < on_v)
        self.record("hand", sig, "release", bool(off), round(self.volts(sig), 3), None, on_v, "V")

    # ------------------------------------------------------------------ PIO inputs
    def _group_pio(self) -> None:
        idle = int(self.cfg.num("pio", "idle_word"))
        nbits = int(self.cfg.num("pio", "bits"))
        ports = sorted((c for c in self.lay.channels if c.kind == "pio" and c.name.startswith("user_if_box_inputs")),
                       key=lambda c: c.channel)
        if not ports:
            self.record("pio", "user_if_box_inputs", "inputs", None, detail="not in this rack")
            return

        def word() -> int:
            return int(self.inputs().pio_user_inputs)

        w = word()
        self.record("pio", "user_if_box_inputs", "idle word", w == idle, f"0x{w:04X}", None, None, "bits",
                    f"expected 0x{idle:04X}")
        for k in range(nbits):
            want = idle ^ (1 << k)
            port = ports[min(k // 8, len(ports) - 1)]
            ch = f"{port.name}.{k % 8}"
            seen = self.operate(f"Operate user I/F input {k} alone (bit {k} to {(want >> k) & 1})",
                                lambda st, w_=want: st.user_inputs(w_), lambda w_=want: word() == w_)
            if seen is None:
                self.record("pio", ch, "operate", None, detail="operator step skipped (non-interactive)")
                continue
            got = word()
            back = self.operate(f"Return user I/F input {k}", lambda st: st.user_inputs(idle),
                                lambda: word() == idle) if seen else False
            self.record("pio", ch, "operate and return", bool(seen and back), f"0x{got:04X}", None, None, "bits",
                        f"expected 0x{want:04X} then 0x{idle:04X}" + ("" if seen else
                        f"; bits that differ: 0x{got ^ want:04X}"))

    # ------------------------------------------------------------------ matrix switcher
    def _group_matrix(self) -> None:
        """Every route of the switch-to-route table (controller/routes.py, named in words),
        then the configured port-line patterns that are not routes: each written, strobed and
        acknowledged (the service applies a route only after the switcher's acknowledge), and
        read back as applied; on the fake switcher also its latched byte and one new
        acknowledge. The route from before the group is put back at the end."""
        try:
            c = self.lay.channel("matrix_switcher_route", "inputs")
        except KeyError:
            self.record("matrix", "matrix_switcher_route", "routes", None, detail="not in this rack")
            return
        board = self.lay.slot("board", c.board)
        cmd = self.t.commander()
        timeout = self.cfg.num("matrix", "timeout_s")
        switcher = _fake_switcher(self.t, c.board)
        patterns = [int(r) for r in self.cfg.get("matrix", "routes") if int(r) not in ALL_ROUTES]
        before = int(self.inputs().matrix_route)
        # the service writes a route only when it changes: start after the route applied now,
        # so every route is a change (and the last one is the route from before, when it is one)
        k = ALL_ROUTES.index(before) + 1 if before in ALL_ROUTES else 0
        try:
            for route in list(ALL_ROUTES[k:] + ALL_ROUTES[:k]) + patterns:
                name = f"route {route_text(route)}" if route in ALL_ROUTES else f"port lines 0x{route:02X}"
                self._matrix_one(c, board, cmd, timeout, switcher, route, name)
        finally:
            cmd.set(matrix_route=before)
            self.t.wait_until(lambda: int(self.inputs().matrix_route) == before, timeout, self.poll_s)

    def _matrix_one(self, c, board: int, cmd, timeout: float, switcher, route: int, name: str) -> None:
        s = self.inputs()
        err0 = int(s.board_errors[board])
        acks0 = switcher.acks if switcher is not None else 0
        cmd.set(matrix_route=route)

        def applied(r=route) -> bool:
            x = self.inputs()
            return int(x.matrix_route) == r and int(x.pio_port_bits[c.slot]) == r

        ok = self.t.wait_until(applied, timeout, self.poll_s)
        s = self.inputs()
        errs = int(s.board_errors[board]) - err0
        got = int(s.matrix_route)
        detail = f"0x{route:02X} written; {errs} new board errors on {c.board}"
        if not ok:
            msgs = [m.text for m in self.t.reader.messages() if m.code == 141][-1:]
            detail += f"; not applied within {timeout:g} s" + (f": {msgs[0]}" if msgs else "")
        if switcher is not None:
            latched, acks = switcher.route, switcher.acks - acks0
            ok = ok and latched == route and acks >= 1
            detail += (f"; fake switcher latched {'nothing' if latched is None else f'0x{latched:02X}'}, "
                       f"{acks} acknowledge(s)")
        self.record("matrix", c.name, name, ok and errs == 0, f"0x{got:02X}", None, None, "bits", detail)

    # ------------------------------------------------------------------ joints
    def _group_joints(self) -> None:
        rack = self.t.rack
        panel = self._panel()
        if panel.chassis_off:
            what = " and ".join(SWITCH_TEXT[s] for s in panel.chassis_off)
            self.record("joints", "joints", "open-loop test", None,
                        detail=f"not run: {panel.who()} the servo chassis {what} is off: nothing can move "
                               "(no motor current on any joint, every brake set). Turn +28 VDC and "
                               "+/-15 V on, then run `pfma checkout --only joints`")
            return
        for j in self.lay.joint_names:
            roles = {q: rack.find(j, q) for q in ("rate", "angle", "current_limit")}
            missing = [q for q, c in roles.items() if c is None]
            if missing or roles["current_limit"].signal not in self.lay.current_limit_names:
                self.record("joints", j, "open-loop test", None,
                            detail=f"no {' or '.join(missing) or 'current_limit'} channel for {j} in this rack")
                continue
            off = [k for k in ("pwm", "brake") if panel.is_off(k, j)]
            if off:
                why = {"pwm": "its PWM output stage switch is off (no motor current)",
                       "brake": "its brake-release switch is off (the brake would stay set, the "
                                "amplifier driving against it)"}
                switches = " and ".join(f"{SWITCH_TEXT[k]} switch" for k in off)
                self.record("joints", j, "open-loop test", None,
                            detail=f"not run: {panel.who()} " + " and ".join(why[k] for k in off)
                                   + f". Turn its {switches} on, then run `pfma checkout --only joints`")
                continue
            self._open_loop(j, roles["rate"].signal, roles["angle"].signal, roles["current_limit"].signal)
        self._gripper(panel)

    def _gripper(self, panel: PanelState) -> None:
        """The gripper's open-loop test (``[gripper]``): open, then close by as much, at a
        bounded command and current limit, every joint's limit 0 (brakes set); the tach's
        sign and size against the command and the motor current's, one row per move, each
        failure with what the readings say (no current, tach reversed, a held jaw)."""
        rack = self.t.rack
        ch = {q: rack.find(GRIPPER, q) for q in ("gripper_command", "rate", "motor_current", "current_limit")}
        missing = [q for q, c in ch.items() if c is None]
        if missing or ch["current_limit"].signal not in self.lay.current_limit_names:
            self.record("joints", GRIPPER, "open-loop test", None,
                        detail=f"no {' or '.join(missing) or 'current_limit'} channel for the gripper in this rack")
            return
        if panel.is_off("pwm", GRIPPER):
            self.record("joints", GRIPPER, "open-loop test", None,
                        detail=f"not run: {panel.who()} its PWM output stage switch is off (no motor current). "
                               f"Turn its {SWITCH_TEXT['pwm']} switch on, then run `pfma checkout --only joints`")
            return
        g = lambda key: self.cfg.get("gripper", key)  # noqa: E731 - one table's lookups
        limit = ch["current_limit"].signal
        names = list(self.lay.current_limit_names)
        limits = [0.0] * len(names)
        i_lim = float(g("current_limit_fraction")) * float(self.cfg.joint(GRIPPER, "dac_full_scale_v")) \
            * float(rack.channel(limit).scale)
        limits[names.index(limit)] = i_lim
        cmd = self.t.commander()
        n_joints = len(self.lay.joint_names)
        try:
            cmd.keepalive = True
            if not self._arm(cmd, GRIPPER, [0.0] * n_joints, limits, None, gripper=0.0):
                return
            moved = [self._gripper_move(cmd, sign * float(g("command_v")), ch["rate"].signal,
                                        ch["motor_current"].signal, i_lim) for sign in (1, -1)]
            if all(moved):  # a drive that does not follow its command is not stepped further
                self._gripper_bits(cmd, ch["gripper_command"].signal, ch["rate"].signal)
                self._gripper_limit_bits(cmd, ch["rate"].signal, ch["motor_current"].signal, limits,
                                         names.index(limit), i_lim)
        finally:
            try:
                cmd.set(gripper=0.0)
                self._stop_outputs(cmd, n_joints, len(names))
                self.t.wait(0.02)
            except PfmaError:
                pass  # the service is gone: its watchdog has made the outputs safe
            finally:
                cmd.keepalive = False

    def _gripper_move(self, cmd, v: float, tach: str, current: str, i_lim: float) -> bool:
        """One gripper move at ``v`` volts, then the pause: its row, with the diagnosis when it
        fails; True when it passed."""
        g = lambda key: self.cfg.get("gripper", key)  # noqa: E731 - one table's lookups
        move_s = float(g("move_s"))
        cmd.set(gripper=v)
        t0, xs, peak = self.t.now(), [], 0.0
        while self.t.now() - t0 < move_s:
            self.t.wait(self.poll_s)
            s = self.inputs()
            if self.t.now() - t0 >= move_s * (1.0 - float(g("tach_window"))):
                xs.append(float(s.value(tach)))
            i = float(s.value(current))
            peak = i if abs(i) > abs(peak) else peak
        cmd.set(gripper=0.0)
        expected = v * float(g("tach_per_command"))
        mean = float(np.mean(xs)) if xs else float("nan")
        lo, hi = (float(r) * expected for r in g("rate_ratio"))
        lo, hi = min(lo, hi), max(lo, hi)
        ok = lo <= mean <= hi and abs(peak) >= float(g("min_current_fraction")) * i_lim
        tag = "open" if v > 0 else "close"
        why = "" if ok else "; " + self._gripper_why(mean, peak, expected, i_lim)
        self.record("joints", tach, f"gripper open-loop {tag}", ok, round(mean, 4), round(lo, 4), round(hi, 4), "V",
                    f"command {v:+.2f} V at a {i_lim:.2f} A limit: tach mean {mean:+.3f} V of {expected:+.2f} V, "
                    f"peak motor current {peak:+.3f} A ({current}){why}")
        self.t.wait(float(g("pause_s")))
        return ok

    def _gripper_why(self, tach: float, peak: float, expected: float, i_lim: float) -> str:
        """What a failed gripper move's tach and motor current say (the jaw has no position
        sensor: the current's sign is the drive's, the tach's the jaw's)."""
        g = lambda key: float(self.cfg.get("gripper", key))  # noqa: E731 - one table's lookups
        moved = abs(tach) >= 0.1 * abs(expected)
        if abs(peak) < g("no_current_fraction") * i_lim:
            return ("no motor current: check the gripper's PWM stage switch, +28 V and +/-15 V (the servo "
                    "chassis panel), and the amplifier" + ("" if not moved else "; yet the tach moved: its monitor?"))
        if moved and tach * expected < 0 and peak * expected > 0:
            return "TACH POLARITY REVERSED (the motor current pushes the commanded way, the tach reads the other)"
        over = max(abs(float(r)) for r in self.cfg.get("gripper", "rate_ratio")) * abs(expected)
        if abs(tach) > over:  # driven far past the command: its DAC output is not the command
            off = tach - expected
            b = round(math.log2(abs(off) / DAC_VOLTS_PER_CODE))
            bit = f"data bit D{b} stuck at {int(off > 0)} ({1 << b} codes)" if 0 <= b < 12 else "a data bit stuck"
            return (f"the jaw ran at {tach:+.2f} V for {expected:+.2f} V: the drive's input is not the command: "
                    f"{bit} on DAC channel {self.t.rack.find(GRIPPER, 'gripper_command').signal}, or the amplifier")
        if moved and tach * expected < 0:
            return "a reversed drive (motor current and tach both against the command: motor or amplifier wiring)"
        if not moved and abs(peak) >= g("stalled_current_fraction") * i_lim:
            return ("the jaw does not move with the motor current at its limit: held by a load (an object in "
                    "the jaws, a snag) or jammed")
        return self._gripper_bit(tach, expected) or \
            "the tach's size is off the command's: its scale, its filter card, or a data bit (the data-bit rows)"

    def _gripper_bit(self, tach: float, expected: float) -> str:
        """The jaw's command data bit (D5 and up) whose 2^b codes the tach is off by, when the
        command's code has that bit the other way (a stuck bit can only take it there): the
        tach reads the command's volts one for one (``tach_per_command``) less the friction's
        droop, so two bits may fit and both are said. "" when none does."""
        tpc = float(self.cfg.get("gripper", "tach_per_command")) or 1.0
        codes = (tach - expected) / tpc / DAC_VOLTS_PER_CODE
        code = DAC_ZERO_CODE + int(round(expected / tpc / DAC_VOLTS_PER_CODE))
        value = int(codes > 0)
        # the bits a stuck value could take that way, near 2^b codes; the jaw's friction droop
        # (about 0.1 V) is in the tach, so a wide band, all of them said
        bits = [b for b in range(5, 11) if (code >> b & 1) != value and 0.55 <= abs(codes) / (1 << b) <= 1.6]
        exact = bit_of_codes(codes, DAC_BITS)
        if exact in bits:
            bits = [exact]
        if not bits:
            return ""
        signal = self.t.rack.find(GRIPPER, "gripper_command").signal
        return (f"the jaw ran {codes:+.0f} codes' worth off its command (code 0x{code:03X}): data bit "
                f"{' or '.join(f'D{b}' for b in bits)} of DAC channel {signal} stuck at {value}?")

    def _gripper_limit_bits(self, cmd, tach: str, current: str, limits: list[float], li: int,
                            i_lim: float) -> None:
        """The jaw's current-limit data bits (``[gripper] dac_bits_limit``), the jaw closed on
        its stop and held there (:mod:`tools.checkout.limitbits`): the monitor's zero first,
        then closing at ``dac_bits_close_v`` until the tach stops, D0..D4 stepped, D5 and up
        pulsed, then opened back for as long as it closed. ASSUMED: nothing is in the jaw."""
        g = lambda key: self.cfg.get("gripper", key)  # noqa: E731 - one table's lookups
        if not bool(g("dac_bits_limit")):
            return
        v = float(g("dac_bits_close_v"))

        def set_limit(x: float) -> None:
            limits[li] = x
            cmd.set(current_limit_a=limits)
        lp = LimitPulses(self, GRIPPER, self.lay.current_limit_names[li], current, tach, v, set_limit,
                         lambda sign: cmd.set(gripper=sign * v), hold=True)
        lp.fine_max_s = float(g("dac_bits_limit_fine_max_s"))
        lp.read_zero()
        set_limit(i_lim)
        closed_s = self._close_on_stop(cmd, tach, v, float(g("dac_bits_close_max_s")))
        if closed_s is None:
            self.record("joints", lp.signal, JAW_PULSE_CHECK, None,
                        detail=f"not run: the jaw's tach {tach} did not stop within {g('dac_bits_close_max_s')} s "
                               f"of closing at {v:g} V (no stop reached)")
        else:
            lp.low_steps_row()
            ps = lp.pulses(pulse_bits(JAW_FIRST_BIT, i_lim / lp.per_code), lambda i: -1)
            set_limit(i_lim)
            lp.pulse_row(JAW_PULSE_CHECK, ps, f"the jaw held closed on its stop at {-v:+g} V")
        cmd.set(gripper=v)  # back about where it was
        self.t.wait(closed_s if closed_s is not None else float(g("dac_bits_close_max_s")))
        cmd.set(gripper=0.0)

    def _close_on_stop(self, cmd, tach: str, v: float, max_s: float) -> float | None:
        """Close the jaw at ``v`` volts until its tach stays under :data:`DRIVE_STILL` of the
        command for ``STOP_STILL_S``: how long it took, or None (the drive left on)."""
        cmd.set(gripper=-v)
        t0 = self.t.now()
        still = None
        while self.t.now() - t0 < max_s:
            self.t.wait(self.poll_s)
            if abs(self.value(tach)) >= DRIVE_STILL * v:
                still = None
            elif still is None:
                still = self.t.now()
            elif self.t.now() - still >= STOP_STILL_S:
                return self.t.now() - t0
        return None

    def _gripper_bits(self, cmd, signal: str, tach: str) -> None:
        """The jaw command's data bits (:data:`GRIPPER_BITS`), read through the tach while the
        jaw runs: each step of 2^b codes adds 2^b codes' worth of tach (the median step per
        code, :func:`judge_steps`), a stuck bit nothing, opening and closing alike. One row,
        each bit judged on the mean of its two steps (two reads of one step: half the
        variance; a stuck D0 read +1.3 and +0.6 mV of 4.9, +/-0.7 each, neither alone told)."""
        if not bool(self.cfg.get("gripper", "dac_bits")):
            return
        g = lambda key: float(self.cfg.get("gripper", key))  # noqa: E731 - one table's lookups
        tach_code = ADC_VOLTS_PER_CODE * float(self.t.rack.channel(tach).scale)
        worth = DAC_VOLTS_PER_CODE * g("tach_per_command")  # one command code's tach, nominal

        def at(code: int) -> Level:
            got = place_code(self, lambda x: cmd.set(gripper=x), signal, code, DAC_VOLTS_PER_CODE)
            self.t.wait(g("dac_bits_settle_s"))
            return read_fine(self, tach, code, got, max(FINE_SE_CODES * tach_code, worth / FINE_WORTHS),
                             g("dac_bits_window_s"), g("dac_bits_max_s"))

        series = []
        for base, sign in ((GRIPPER_BITS_OPEN, 1), (GRIPPER_BITS_CLOSE, -1)):
            levels = [at(c) for c in (base, *(base + sign * (1 << b) for b in GRIPPER_BITS))]
            if any(lv.got != lv.code for lv in levels):
                cmd.set(gripper=0.0)
                self.record("joints", signal, GRIPPER_BITS_CHECK, None,
                            detail=f"not run: the service wrote codes {[f'0x{lv.got:03X}' for lv in levels]} for "
                                   f"{[f'0x{lv.code:03X}' for lv in levels]} (its calibration of {signal})")
                return
            levels = [replace(lv, mean=sign * lv.mean) for lv in levels]  # closing: the steps' size
            series.append(judge_steps(levels[0], list(zip(GRIPPER_BITS, levels[1:])), None, tach_code))
        cmd.set(gripper=0.0)
        both = [Step(o.bit, 0.5 * (o.step + c.step), 0.5 * math.hypot(o.se, c.se), 0.5 * (o.want + c.want),
                     o.resolvable or c.resolvable) for o, c in zip(*series)]
        stuck, unjudged = (([st.bit for st in group]) for group in summary(both))
        said = "; ".join(f"{what} from 0x{base:03X}: " + ", ".join(st.text("mV") for st in steps)
                         for what, base, steps in (("opening", GRIPPER_BITS_OPEN, series[0]),
                                                   ("closing", GRIPPER_BITS_CLOSE, series[1])))
        why = steps_why(stuck, unjudged, signal, "added nothing to the jaw's rate", "the tach's noise hides the step")
        self.record("joints", signal, GRIPPER_BITS_CHECK, not stuck, round(worst_step(both), 3), 0.5, None,
                    "of a step",
                    f"tach {tach} while the jaw runs, each step against its base: {said}{why}")

    def _arm(self, cmd, who: str, rates: list[float], limits: list[float],
             disarmed: Callable[[], None] | None = None, **fields) -> bool:
        """Arm the service with these rates and current limits (and ``fields``), after
        ``disarmed`` ran with it disarmed (it may change ``limits``); a failed arm is a row
        naming ``who`` and the service's last words. True when armed."""
        cmd.set(joint_rate_rad_s=rates, current_limit_a=limits, arm_request=0, **fields)
        self.t.wait(0.05)
        rc = int(cmd.record["rearm_counter"]) + 1
        if disarmed is not None:
            disarmed()
        cmd.set(joint_rate_rad_s=rates, current_limit_a=limits, arm_request=1, rearm_counter=rc, **fields)
        if self.t.wait_until(lambda: self.inputs().service_state == ServiceState.ARMED,
                             float(self.cfg.joint(who, "arm_timeout_s")), self.poll_s):
            return True
        st = ServiceState(self.inputs().service_state).name
        last = [m.text for m in self.t.reader.messages()][-2:]
        self.record("joints", who, "arm", False, st, detail=f"service did not arm; messages: {last}")
        return False

    def _panel(self) -> PanelState:
        """The servo chassis' front panel before the arm moves: as stated, asked of the
        operator (interactive, a rack without a stimulus) or assumed all on; one "panel"
        row per group of switches, each marked as a statement (SKIP: nothing measured)."""
        if self.panel is None:
            if self.interactive and self.t.stimulus is None:
                self.panel = ask_panel(self.ask, self.say, self.t.rack.joints or self.lay.joint_names)
            else:
                self.panel = PanelState(frozenset(), ASSUMED)
        panel = self.panel
        joints = list(self.t.rack.joints or self.lay.joint_names)
        self.report.panel = panel.summary(joints)
        how = panel.how()
        for key, channel in (("28v", "servo_chassis_28v"), ("15v", "servo_chassis_15v")):
            self.record("panel", channel, PANEL_CHECKS[key], None,
                        "off" if panel.is_off(key) else "on", detail=how)
        for kind, channel, names in (("pwm", "pwm_stage_switches", [*joints, GRIPPER]),
                                     ("brake", "brake_release_switches", joints)):
            off = panel.off_joints(kind, names)
            self.record("panel", channel, PANEL_CHECKS[kind], None,
                        f"off: {', '.join(off)}" if off else "all on", detail=how)
        return panel

    def _stop_outputs(self, cmd, n_joints: int, n_limits: int) -> None:
        cmd.set(joint_rate_rad_s=[0.0] * n_joints, current_limit_a=[0.0] * n_limits, arm_request=0)

    def _open_loop(self, j: str, tach: str, angle: str, limit: str) -> None:
        cfg = self.cfg
        jn = list(self.lay.joint_names)
        ji = jn.index(j)
        li = list(self.lay.current_limit_names).index(limit)
        n_lim = len(self.lay.current_limit_names)
        fs_v = float(cfg.joint(j, "dac_full_scale_v"))
        i_max = fs_v * float(self.t.rack.channel(limit).scale)
        i_lim = float(cfg.joint(j, "current_limit_fraction")) * i_max
        rate = cfg.joint(j, "rate_rad_s")
        if not rate:  # a fraction of the full-scale rate: 10 V x the command channel's scale
            rate = float(cfg.joint(j, "rate_fraction")) * fs_v * float(self.t.rack.joint_channel(j, "rate_command").scale)
        rate = float(rate)
        # the joint's motor-current monitor must respond while the joint is driven: a dead
        # ADC input reads a constant (0 V passes the idle range) and only shows here
        found = self.t.rack.find(j, "motor_current")
        current = found.signal if found else f"{j} motor current"
        try:
            self.lay.channel(current)
        except KeyError:  # a rack without that monitor
            current = ""
        # peak-to-peak it must reach, a fraction of the test's current limit (the simulated
        # arm reaches the limit itself while accelerating)
        min_current = float(cfg.joint(j, "min_current_fraction")) * i_lim
        cmd = self.t.commander()
        rates = [0.0] * len(jn)
        limits = [0.0] * n_lim
        #: what each move showed, kept before its rows are recorded: the diagnosis reads it
        #: even when a row of the move stops the run
        moves: list[Move] = []
        try:
            cmd.keepalive = True
            bits = bool(cfg.joint(j, "dac_bits")) and bool(current)
            zero = [0.0]
            pulses: Callable[[], None] | None = None
            stall_a: float | None = None  # what the held drive draws at the moves' rate, unlimited

            def disarmed() -> None:
                # the monitor's reading while no current can flow (not armed, limits 0): the
                # DAC-bit check's zero, and a monitor fault named on the monitor, not the DAC
                if bits:
                    zero[0] = DacBits.monitor_zero(self, j, current, limit)
                # the DAC-bit check first, brake set; then the moves' limit
                limits[li] = float(cfg.joint(j, "dac_bits_limit_v")) * float(self.t.rack.channel(limit).scale) \
                    if bits else i_lim
            if not self._arm(cmd, j, rates, limits, disarmed):
                return
            if bits:
                db = DacBits(self, j, current, cmd, rates, limits, ji, li, zero[0])
                db.run()
                if db.amps_per_code:
                    stall_a = db.amps_per_code * abs(rate) / db.rate_per_code
                if bool(cfg.joint(j, "dac_bits_limit_pulses")):  # after the moves: polarity known
                    pulses = (lambda: self._limit_pulses(j, tach, current, cmd, rates, limits, ji, li, i_lim,
                                                         rate, db.drew))
                limits[li] = i_lim
                cmd.set(joint_rate_rad_s=rates, current_limit_a=limits)
            try:
                self._moves(j, tach, angle, current, cmd, rates, limits, ji, li, i_lim, rate, min_current,
                            moves, pulses, stall_a)
            except StopRun:
                # the run stops at this joint: its diagnosis still says drive or brake
                self._diagnose(j, moves, i_lim, current, quiet=True)
                raise
            self._diagnose(j, moves, i_lim, current)
        finally:
            try:
                self._stop_outputs(cmd, len(jn), n_lim)
                self.t.wait(0.02)
            except PfmaError:
                pass  # the service is gone: its watchdog has made the outputs safe
            finally:
                cmd.keepalive = False

    def _moves(self, j: str, tach: str, angle: str, current: str, cmd, rates: list[float],
               limits: list[float], ji: int, li: int, i_lim: float, rate: float, min_current: float,
               moves: list[Move], pulses: Callable[[], None] | None = None,
               stall_a: float | None = None) -> None:
        """The armed part of a joint's open-loop test: each move and its rows, the limit's
        ``pulses`` (its polarity known then), then stopped, held by brake, disarm (none of
        those after a runaway). Appends to ``moves``."""
        cfg = self.cfg
        p = _MoveParams(cfg, j)
        p.stall_a = stall_a
        self.t.wait(float(cfg.joint(j, "brake_release_s")))
        signs = (1, -1) if cfg.joint(j, "bidirectional") else (1,)
        for sign in signs:
            v = sign * rate
            expected = v * (p.move_s - p.lag)
            m = self._drive_move(tach, angle, current, cmd, rates, ji, v, expected, p, i_lim)
            tag = "+" if sign > 0 else "-"
            self._move_rows(j, tach, angle, current, tag, v, expected, m, i_lim, min_current, p, moves)
            if m.runaway:
                return
            self.t.wait(float(cfg.joint(j, "pause_s")))
        if pulses is not None:
            pulses()
        self._stop_and_hold(j, tach, angle, cmd, rates, limits, li)

    def _limit_pulses(self, j: str, tach: str, current: str, cmd, rates: list[float], limits: list[float],
                      ji: int, li: int, i_lim: float, rate: float, drew: bool) -> None:
        """The current limit's D6 and up, each pulsed alone after the moves (their polarity
        rows passed), the joint driven at the moves' rate each way in turn
        (:mod:`tools.checkout.limitbits`); the moves' limit written back after."""
        def set_limit(x: float) -> None:
            limits[li] = x
            cmd.set(current_limit_a=limits)

        def drive(sign: int) -> None:
            rates[ji] = sign * rate
            cmd.set(joint_rate_rad_s=rates)
        lp = LimitPulses(self, j, self.lay.current_limit_names[li], current, tach, rate, set_limit, drive, drew=drew)
        # a joint that cannot hold its weight at a pulse's limit keeps its brake: no pulse
        # over the brake-release cards' release threshold
        top = i_lim / lp.per_code if bool(self.cfg.joint(j, "dac_bits_pulse_release")) else \
            float(self.cfg.joint(j, "brake_release_v")) / DAC_VOLTS_PER_CODE
        lp.read_zero()
        ps = lp.pulses(pulse_bits(JOINT_FIRST_BIT, min(top, i_lim / lp.per_code)), lambda i: 1 - 2 * (i % 2))
        limits[li] = i_lim
        cmd.set(joint_rate_rad_s=rates, current_limit_a=limits)
        lp.pulse_row(PULSE_CHECK, ps, f"driven at {rate:.4g} rad/s each way in turn")

    def _drive_move(self, tach: str, angle: str, current: str, cmd, rates: list[float], ji: int,
                    v: float, expected: float, p: "_MoveParams", i_lim: float) -> "_Sampled":
        """One open-loop move at ``v`` rad/s for ``move_s``: what the resolver, tach and
        motor current showed; a runaway makes the outputs safe at once and ends it."""
        m = _Sampled()
        a_prev = self.value(angle)
        t0 = t_prev = self.t.now()
        x_prev = self.value(tach)
        rates[ji] = v
        cmd.set(joint_rate_rad_s=rates)
        while self.t.now() - t0 < p.move_s:
            self.t.wait(p.dt)
            s = self.inputs()
            now = self.t.now()
            a = float(s.value(angle))
            x = float(s.value(tach))
            m.travel += float(_wrap(a - a_prev, 2 * math.pi))
            m.tach_integral += 0.5 * (x + x_prev) * (now - t_prev)
            a_prev, x_prev, t_prev = a, x, now
            m.samples.append((now - t0, x))
            if current:
                m.currents.append(float(s.value(current)))
            if not m.left and s.service_state != ServiceState.ARMED:
                m.left = ServiceState(s.service_state).name
            if abs(m.travel) > p.max_factor * abs(expected):
                m.runaway = (f"runaway: {m.travel:+.4f} rad after {now - t0:.2f} s, more than "
                             f"{p.max_factor:g} x the expected {expected:+.4f} rad; outputs made safe"
                             + _runaway_cause(m.currents, m.travel, i_lim))
                self._stop_outputs(cmd, len(self.lay.joint_names), len(self.lay.current_limit_names))
                break
        rates[ji] = 0.0
        if not m.runaway:
            cmd.set(joint_rate_rad_s=rates)
        return m

    def _move_rows(self, j: str, tach: str, angle: str, current: str, tag: str, v: float, expected: float,
                   m: "_Sampled", i_lim: float, min_current: float, p: "_MoveParams",
                   moves: list[Move]) -> None:
        """The rows of one move (tach rate, motor current, travel, tach/resolver scale); the
        move appended to ``moves`` first (the diagnosis reads it even when a row stops the run)."""
        cfg = self.cfg
        travel, runaway = m.travel, m.runaway
        ts = np.array([t for t, _ in m.samples])
        xs = np.array([x for _, x in m.samples])
        win = xs[ts >= ts[-1] * (1.0 - float(cfg.joint(j, "tach_window")))] if len(xs) else xs
        mean_tach = float(np.mean(win)) if len(win) else math.nan
        span = float(np.ptp(m.currents)) if m.currents else 0.0
        peak = float(np.max(np.abs(m.currents))) if m.currents else 0.0
        moves.append(Move(tag, v, expected, travel, mean_tach, peak if current else None, m.left))
        t_lo, t_hi = sorted((v * p.r_lo, v * p.r_hi))
        x_lo, x_hi = sorted((expected * p.r_lo, expected * p.r_hi))
        diag = self._move_diag(j, tach, current, v, expected, m, mean_tach, float(np.ptp(xs)) if len(xs) else 0.0,
                               peak, i_lim, p, not t_lo <= mean_tach <= t_hi and x_lo <= travel <= x_hi)
        self.record("joints", tach, f"open-loop rate {tag}", t_lo <= mean_tach <= t_hi and not runaway,
                    round(mean_tach, 5), round(t_lo, 5), round(t_hi, 5), "rad/s",
                    f"commanded {v:+.4g} rad/s at a {i_lim:.2f} A limit" + diag
                    + (f"; {runaway}" if runaway else ""))
        if current and not runaway:
            self.record("joints", current, f"motor current responds {tag}", span >= min_current,
                        round(span, 4), round(min_current, 4), None, "A",
                        f"peak-to-peak while driven at {v:+.4g} rad/s (limit {i_lim:.2f} A)"
                        + ("" if span >= min_current else
                           "; MOTOR CURRENT NOT RESPONDING (dead input or amplifier monitor)"))
        self.record("joints", angle, f"open-loop travel {tag}", x_lo <= travel <= x_hi and not runaway,
                    round(travel, 5), round(x_lo, 5), round(x_hi, 5), "rad",
                    f"{p.move_s:g} s at {v:+.4g} rad/s" + ("; RESOLVER MOVED THE WRONG WAY"
                                                           if travel * v < 0 else ""))
        ratio = m.tach_integral / travel if travel else math.nan
        ok = abs(ratio - 1) <= p.agree
        self.record("joints", tach, f"tach/resolver scale {tag}", ok,
                    round(ratio, 4), round(1 - p.agree, 4), round(1 + p.agree, 4), "1",
                    f"tach integral {m.tach_integral:+.5f} rad vs resolver travel {travel:+.5f} rad"
                    + ("" if ok or not travel else self._tach_bit((m.tach_integral - travel) / p.move_s, tach)))

    def _move_diag(self, j: str, tach: str, current: str, v: float, expected: float, m: "_Sampled",
                   mean_tach: float, swing: float, peak: float, i_lim: float, p: "_MoveParams",
                   tach_only: bool) -> str:
        """What a move's rate row says of its cause: the tach's own reading (dead, stuck,
        reversed; ``swing``: its peak-to-peak while driven), its A/D bit when the joint moved
        as commanded and only the tach (``tach_only``) read otherwise, or the current limit's
        bit when the joint stalled with its current flat under the limit."""
        # a tach that does not change while the joint is driven is dead or stuck, not
        # reversed (a dead input held at a few mV would otherwise read "reversed")
        no_current = bool(current) and peak < float(self.cfg.joint(j, "diag_no_current_fraction")) * i_lim
        diag = _tach_diag(v, expected, m.travel, mean_tach, swing, no_current, p.r_lo)
        if diag or m.runaway:
            return diag
        # the joint moved as commanded and the tach reads otherwise: the tach's reading
        if tach_only and (bit := self._tach_bit(mean_tach - m.travel / max(p.move_s - p.lag, 1e-3), tach)):
            return bit
        if abs(mean_tach) < DRIVE_STILL * abs(v) and current and p.stall_a:
            # stalled, its current flat under the limit and under what the held drive draws:
            # the limit channel's own bit (a held brake draws the one or the other; a joint
            # that runs slow draws K_a x (V - V_tach), flat and under both)
            limit = self.t.rack.joint_channel(j, "current_limit").signal
            return limit_low_hint(m.currents, i_lim, min(i_lim, p.stall_a),
                                  DAC_VOLTS_PER_CODE * float(self.t.rack.channel(limit).scale), limit,
                                  float(self.cfg.joint(j, "dac_bits_tolerance")))
        return ""

    def _tach_bit(self, off_rad_s: float, tach: str) -> str:
        """The A/D data bit a tach's offset from the resolver's rate (``off_rad_s`` over the
        move) would be, when it is within 30 % of 2^b codes (D3 and up): said as a question,
        the tach's scale the other answer. "" when no bit fits."""
        codes, b = adc_offset_bit(self.t.rack, tach, off_rad_s)
        if b is None:
            return ""
        return (f"; the tach reads {codes:+.0f} A/D codes off the resolver's rate: data bit D{b} of its A/D channel "
                f"stuck at {int(codes > 0)}? (or the tach's scale or filter card)")

    def _stop_and_hold(self, j: str, tach: str, angle: str, cmd, rates: list[float],
                       limits: list[float], li: int) -> None:
        """After the moves: stopped by the servo, held by the brake, disarmed (their rows)."""
        cfg = self.cfg
        self.t.wait(float(cfg.joint(j, "stop_s")))
        mx = float(cfg.joint(j, "max_stopped_rate"))
        still = self.value(tach)
        self.record("joints", tach, "stopped (servo)", abs(still) <= mx, round(still, 5), -mx, mx,
                    "rad/s", "rate command 0, current limit on")
        limits[li] = 0.0
        cmd.set(joint_rate_rad_s=rates, current_limit_a=limits)
        self.t.wait(float(cfg.joint(j, "brake_s")))
        a0 = self.value(angle)
        self.t.wait(float(cfg.joint(j, "brake_s")))
        creep = float(_wrap(self.value(angle) - a0, 2 * math.pi))
        mc = float(cfg.joint(j, "max_brake_creep_rad"))
        self.record("joints", angle, "held by brake", abs(creep) <= mc, round(creep, 6), -mc, mc, "rad",
                    f"current limit 0 for {2 * float(cfg.joint(j, 'brake_s')):g} s")
        self._stop_outputs(cmd, len(self.lay.joint_names), len(self.lay.current_limit_names))
        safe = self.t.wait_until(lambda: self.inputs().service_state == ServiceState.SAFE,
                                 float(cfg.joint(j, "arm_timeout_s")), self.poll_s)
        self.record("joints", j, "disarm", safe, ServiceState(self.inputs().service_state).name,
                    detail="rates 0, current limits 0 (brakes set), arm request cleared")

    # ------------------------------------------------------------------ drive or brake
    def _diagnose(self, j: str, moves: list[Move], i_lim: float, current: str, *, quiet: bool = False) -> None:
        """One row per joint after its open-loop test naming the drive or the brake, from
        what the resolver, tach and motor-current monitor showed during its moves (never
        from the command): moved -> the drive answers and the brake released; did not move
        with the motor current at (near) the test's limit -> the brake (or a jam); did not
        move with no motor current -> the PWM stage, +28 V or the amplifier.

        ``quiet``: the run is stopping already (a row of this joint failed); a failing
        diagnosis does not stop it a second time."""
        if not moves:
            return
        lim = _DiagLimits(self.cfg, j, i_lim)
        record = self._record_quiet if quiet else self.record
        check = "drive and brake (diagnosis)"
        texts = [m.text(i_lim) for m in moves]
        seen = "; ".join(texts) + (f" ({len(moves)} of 2 moves: the run stopped)" if quiet and len(moves) < 2
                                   and self.cfg.joint(j, "bidirectional") else "")
        answered: list[Move] = []
        unknown: list[Move] = []  # moves the service stopped (it left ARMED): they show nothing
        for m in moves:
            if lim.answered(m):
                answered.append(m)
            elif m.left_armed:
                unknown.append(m)
            else:
                value, detail = lim.not_answered(m, j, seen)
                limit = self.t.rack.find(j, "current_limit")
                if value == "no current" and limit is not None and not lim.moved(m):  # (moved: brake released)
                    detail += (f" A current limit that never leaves 0 V reads the same: data bit "
                               f"{zeroing_bits(i_lim, limit.scale)} of DAC channel {limit.signal} stuck at 0.")
                record("joints", j, check, False, value, detail=detail)
                return
        stopped = "; ".join(f"the service was not ARMED ({m.left_armed}) in the {m.tag} move" for m in unknown)
        if not answered:
            record("joints", j, check, None, "not diagnosed",
                   detail=f"{stopped}: the motion seen is not the drive's answer; the service's messages "
                          f"say why. {seen}")
            return
        wrong = [m.tag for m in answered if m.against >= lim.f_move and m.along < lim.f_move]
        record("joints", j, check, True, "moved",
               detail="drive answers, brake released"
                      + (f" (it moved against the command in the {', '.join(wrong)} move: see the polarity "
                         "rows)" if wrong else "")
                      + (f" ({stopped}: that move shows nothing)" if unknown else "") + f". {seen}")


#: the channel kinds whose raw codes the data-bit diagnosis reads, and their data bits
#: (drivers/rtd ANGLE 14 bits, drivers/adc code 12 bits)
DATA_BITS = {"rtd": 14, "adc": 12}
#: samples of codes a run keeps (a whole checkout reads a few thousand)
CODE_LOG_KEEP = 50_000


#: the A/D's and the DAC's codes, from their register tables: 12-bit offset binary over
#: +-10 V, 0 V at half scale
ADC_BITS = int(DVME611.constants["adc_bits"])
ADC_ZERO_CODE = int(DVME611.constants["full_scale_counts"]) // 2
DAC_CODES = int(VMIVME4100.constants["full_scale_counts"])
#: a code that one flipped data bit puts this near the idle value's code is named a stuck
#: bit first (ASSUMED: 8 codes, 39 mV, above the idle noise of a healthy input)
IDLE_FLIP_CODES = 8


def one_bit_away(code: int, centre: float) -> int | None:
    """The highest A/D data bit (D3 and up) that, flipped, puts ``code`` within
    :data:`IDLE_FLIP_CODES` of ``centre``; None when no one bit does."""
    bits = [b for b in range(ADC_BITS - 1, 2, -1) if abs((code ^ (1 << b)) - centre) <= IDLE_FLIP_CODES]
    return bits[0] if bits else None


def _idle_why(code: int, lo: float, hi: float, scale: float) -> str:
    """Why an A/D input is not at its idle value, from its code: when flipping one data
    bit (D3 and up) would put the code within :data:`IDLE_FLIP_CODES` of the idle value
    (0 when the idle range ``lo``..``hi``, in engineering units at ``scale`` per volt, holds
    it, as every group's does: a CAE discrete's -0.5..1 V is released at 0 V, not at its
    centre; else the range's centre), that bit stuck is named first; a dead input (or its
    wiring, or the sensor) reads the same at rest."""
    idle = 0.0 if lo <= 0.0 <= hi else (lo + hi) / 2
    centre = ADC_ZERO_CODE + idle / (scale or 1.0) / ADC_VOLTS_PER_CODE
    b = one_bit_away(code, centre)
    if b is None:
        return (f"code 0x{code:03X}: not one data bit away from the idle value: a dead input, its "
                "wiring or the sensor")
    return (f"code 0x{code:03X} is the idle value's 0x{code ^ (1 << b):03X} with D{b} flipped: data bit D{b} "
            f"stuck at {(code >> b) & 1}? Or a dead input (or its wiring, or the sensor) reads the same at rest")


#: the rate command's test codes (12-bit offset binary, +-10 V): -1 LSB has D0..D10 at 1
#: and D11 at 0, 0 V the opposite, so every data bit is at 1 in one and at 0 in the other
DAC_BITS_CODES = (0x7FF, 0x800)
#: how far the two codes' mean current may sit off zero, in ``dac_bits_tolerance``s: the
#: channel's offset, the same at both codes (assumed: the DAC's +-10 mV, sim/errors.py, and
#: an amplifier's input offset, times K_a up to 3.3 A/V, stay under twice the tolerance)
DAC_BITS_OFFSET_FACTOR = 2.0


#: the current limit's walk (``[joints] dac_bits_limit_walk``): from 32 codes (0.156 V) up by
#: 4, 8 and 16 codes, at most 48 codes (0.234 V), below the brake-release cards' 0.3 V engage
#: threshold (pfma-model 8.4), so the brake stays set. D0 and D1 (1-2 codes, 2.4-4.9 mA) are
#: below what the monitor's noise lets a short window tell; D5 and up are the 0.2 V test
#: limit's (its code 0x829) and the moves'
LIMIT_WALK_BASE = DAC_ZERO_CODE + 0x20
LIMIT_WALK_BITS = (2, 3, 4)
#: each walk level is read to a standard error of its smallest step's worth over this (a
#: step's two levels then put half its worth over 4 standard errors; assumed)
WALK_WORTHS = 12.0
#: the bits stepped with the monitor's noise averaged out (``[joints] dac_bits_fine``,
#: tools/checkout/finesteps.py): the rate command's D0..D3, each alone from 0 V (8 codes at
#: most: K_a x 39 mV, 0.13 A on the shoulders, under the 0.2 A test limit with the channel's
#: offset), and the current limit's D0 and D1 from LIMIT_WALK_BASE
FINE_BITS = (0, 1, 2, 3)
LIMIT_FINE_BITS = (0, 1)
#: the jaw command's data bits (``[gripper] dac_bits``), stepped while the jaw moves (it has no
#: brake to push against): opening from 64 codes (0x840, 0.31 V: D6 at 1, D0..D5 at 0), each
#: bit set alone (at most 96 codes, 0.47 V), then closing from -65 codes (0x7BF: D0..D5 at 1,
#: D6 at 0), each bit cleared alone, back about where it was. ASSUMED: 64 codes is above the
#: jaw's breakaway, so it runs and the proportional rate loop's tach follows the command (the
#: simulated jaw breaks away between 16 and 32 codes and reads 1.0 V of tach per command volt
#: once running, its current then constant: the friction's). ASSUMED too: the jaw starts
#: more than ~10 mm from either stop (the ready pose's 50 mm of 100); a jaw that reached a
#: stop mid-steps would read its steps as adding nothing
GRIPPER_BITS = (0, 1, 2, 3, 4, 5)
GRIPPER_BITS_OPEN = DAC_ZERO_CODE + 0x40
GRIPPER_BITS_CLOSE = DAC_ZERO_CODE - 0x41
GRIPPER_BITS_CHECK = "DAC data bits: the jaw's command stepped while it runs"
#: the jaw is on its stop once its tach has stayed still this long (assumed)
STOP_STILL_S = 0.1
#: the rate steps are judged only below this fraction of the test limit (a current at the
#: limit does not follow the command: a limit bit stuck low, or a large offset; assumed)
FINE_SAT_FRACTION = 0.8


class DacBits:
    """One joint's rate-command DAC data-bit check, brake set (``[joints] dac_bits``): each
    test code placed exactly (the service's calibration between rad/s and code is read back
    from the buffer's ``dac_counts``, the code written) and the motor current it draws
    against the brake; one row, its diagnosis from the current's sign."""

    def __init__(self, co: "Checkout", j: str, current: str, cmd, rates: list[float], limits: list[float],
                 ji: int, li: int, zero: float = 0.0) -> None:
        self.co, self.j, self.current, self.cmd = co, j, current, cmd
        self.zero = zero  #: the monitor's reading with no current (:meth:`monitor_zero`)
        self.codes: list[int] = []  #: the monitor's mean A/D code at each step, in order
        self.limits, self.li = limits, li
        self.walk: list[tuple[int, int, float]] = []  #: the limit walk (:meth:`limit_walk`)
        self.fine_limit: tuple[Level, list[Step]] | None = None  #: its low bits (:meth:`limit_steps`)
        self.fine_saturated = False  #: the rate steps reached the test limit (:meth:`rate_steps`)
        #: the motor current per rate-command code, held (K_a x a code's volts), from the low
        #: bits' steps; None when they did not run
        self.amps_per_code: float | None = None
        self.rates, self.ji, self.limit_a = rates, ji, limits[li]
        rack = co.t.rack
        self.signal = rack.joint_channel(j, "rate_command").signal
        self.limit_signal = rack.joint_channel(j, "current_limit").signal
        #: rad/s per volt of the rate command (the command channel's scale)
        self.rate_per_volt = float(rack.joint_channel(j, "rate_command").scale)
        #: rad/s of one code step: 2 x full scale / 4096 codes x the rate per volt
        self.rate_per_code = 2.0 * float(co.cfg.joint(j, "dac_full_scale_v")) / DAC_CODES * self.rate_per_volt

    def place(self, code: int) -> int:
        """Command the rate whose code is ``code`` (a few corrections from the code read back);
        returns the code written."""
        return self._place(code, "joint_rate_rad_s", self.rates, self.ji, self.signal, self.rate_per_code)

    def _place(self, code: int, field: str, values: list[float], i: int, signal: str, per_code: float) -> int:
        """Write ``values[i]`` (command field ``field``) so that DAC channel ``signal`` latches
        ``code`` (:func:`place_code`); returns the code written."""
        def write(x: float) -> None:
            values[i] = x
            self.cmd.set(**{field: values})
        return place_code(self.co, write, signal, code, per_code)

    @staticmethod
    def sample(co: "Checkout", j: str, current: str) -> tuple[list[float], list[int]]:
        """The motor-current monitor's values and A/D codes over ``dac_bits_window_s``."""
        vals, codes = [], []
        end = co.t.now() + float(co.cfg.joint(j, "dac_bits_window_s"))
        while co.t.now() < end:
            ch = co.inputs().channel(current)
            vals.append(float(ch["adc_value"]))
            codes.append(int(ch["adc_counts"]))
            co.t.wait(co.poll_s)
        return vals, codes

    @staticmethod
    def monitor_zero(co: "Checkout", j: str, current: str, limit: str) -> float:
        """The motor-current monitor's reading while no current can flow (the service not
        armed, every current limit 0): its own zero. Beyond the DAC-bit tolerance it fails
        on the monitor's channel (with the data bit that, flipped, would zero it), so the
        DAC check that follows does not blame the DAC for it."""
        i0, codes = DacBits.sample(co, j, current)
        zero = float(np.mean(i0)) if i0 else 0.0
        scale = float(co.t.rack.channel(limit).scale)
        thr = float(co.cfg.joint(j, "dac_bits_tolerance")) * float(co.cfg.joint(j, "dac_bits_limit_v")) * scale
        ok = abs(zero) <= thr
        why = "" if ok else "; " + _idle_why(int(round(float(np.mean(codes)))), -thr, thr,
                                             float(co.t.rack.channel(current).scale))
        co.record("joints", current, "zero with no current (limits 0)", ok, round(zero, 4), -thr, thr, "A",
                  f"the monitor with the service not armed and every current limit at 0{why}")
        return zero

    def mean_current(self) -> float:
        """The motor current after ``dac_bits_settle_s``, averaged over ``dac_bits_window_s``,
        less the monitor's zero."""
        self.co.t.wait(float(self.co.cfg.joint(self.j, "dac_bits_settle_s")))
        vals, codes = self.sample(self.co, self.j, self.current)
        self.codes.append(int(round(float(np.mean(codes)))) if codes else -1)
        return float(np.mean(vals)) - self.zero if vals else float("nan")

    def current_at(self, code: int) -> tuple[int, float]:
        got = self.place(code)
        return got, self.mean_current()

    def saturated_current(self) -> float:
        """The current at ``dac_bits_drive_v`` (a bounded rate command whose K_a x V exceeds the
        test limit on every joint): the amplifier's limit itself, so the limit channel's bits
        show; brake set, the joint does not move."""
        v = float(self.co.cfg.joint(self.j, "dac_bits_drive_v"))
        self.rates[self.ji] = v * self.rate_per_volt
        self.cmd.set(joint_rate_rad_s=self.rates)
        i = self.mean_current()
        self.walk = self.limit_walk()
        self.rates[self.ji] = 0.0
        self.cmd.set(joint_rate_rad_s=self.rates)
        return i

    def fine_level(self, place: Callable[[int], int], code: int, worth: float) -> Level:
        """``code`` placed (``place``), then the motor current read once a frame until its
        mean's standard error is small enough to tell a step of one code's ``worth`` (A) from
        nothing (:data:`FINE_WORTHS`), or :data:`FINE_SE_CODES` of a monitor code; at least
        ``dac_bits_fine_window_s``, at most ``dac_bits_fine_max_s``."""
        g = (lambda k: float(self.co.cfg.joint(self.j, k)))
        got = place(code)
        self.co.t.wait(g("dac_bits_settle_s"))
        target = max(FINE_SE_CODES * self.monitor_code, abs(worth) / FINE_WORTHS)
        return read_fine(self.co, self.current, code, got, target, g("dac_bits_fine_window_s"),
                         g("dac_bits_fine_max_s"), self.zero)

    def rate_steps(self, one_code: float) -> list[Step] | None:
        """The rate command's lowest bits (:data:`FINE_BITS`), each 2^b codes stepped from 0 V
        (0x800: D0..D10 at 0) against the set brake at the test limit (K_a x 8 codes stays
        under it on every joint); [] when ``dac_bits_fine`` is off, None when the service
        wrote other codes or the current reached the limit (``fine_saturated``)."""
        if not bool(self.co.cfg.joint(self.j, "dac_bits_fine")):
            return []
        read = step_levels(lambda c: self.fine_level(self.place, c, one_code), DAC_ZERO_CODE, FINE_BITS)
        if read is None:
            return None
        base, steps = read
        if max(abs(lv.mean) for lv in (base, *(lv for _, lv in steps))) >= FINE_SAT_FRACTION * self.limit_a:
            self.fine_saturated = True  # the limit, not the command, bounds the current: not judged
            return None
        return judge_steps(base, steps, monitor_code=self.monitor_code)

    @property
    def monitor_code(self) -> float:
        """One A/D code of the motor-current monitor, in A."""
        return ADC_VOLTS_PER_CODE * float(self.co.t.rack.channel(self.current).scale)

    def limit_steps(self, per_code: float) -> tuple[Level, list[Step]] | None:
        """The current limit's D0 and D1 (:data:`LIMIT_FINE_BITS`), stepped from
        :data:`LIMIT_WALK_BASE` while the drive saturates against the brake (the current is
        the limit); None when off or the service wrote other codes."""
        if not bool(self.co.cfg.joint(self.j, "dac_bits_fine")):
            return None
        place = (lambda c: self.place_limit(c, per_code))
        read = step_levels(lambda c: self.fine_level(place, c, per_code), LIMIT_WALK_BASE, LIMIT_FINE_BITS)
        if read is None:
            return None
        base, steps = read
        return base, judge_steps(base, steps, per_code, self.monitor_code)

    def fine_row(self, signal: str, check: str, steps: list[Step] | None) -> None:
        """The row of a set of small steps: FAIL naming the first stuck bit, else PASS naming
        the bits the noise left unjudged."""
        if steps == []:
            return
        if steps is None:
            self.co.record("joints", signal, check, None, detail=(
                "not judged: the current reached the test limit (a step adds nothing there; the current "
                "limit's rows judge it)" if self.fine_saturated else "not run: the service wrote other codes"))
            return
        stuck, unjudged = ([s.bit for s in group] for group in summary(steps))
        said = ", ".join(s.text() for s in steps)
        why = steps_why(stuck, unjudged, signal,
                        "added nothing; the two values read alike but for a constant offset, which the channel's "
                        "own offset hides",
                        "the monitor's noise hides the step, or it is under 1.5 of its codes with too little noise "
                        "to average")
        self.co.record("joints", signal, check, not stuck, round(worst_step(steps), 3), 0.5, None, "of a step",
                       said + why)

    def place_limit(self, code: int, per_code: float) -> int:
        """Write the current-limit code ``code`` (corrected from the code read back, as
        :meth:`place`); returns the code written."""
        return self._place(code, "current_limit_a", self.limits, self.li, self.limit_signal, per_code)

    def limit_walk(self) -> list[tuple[int, int, float]]:
        """The current limit's middle bits, walked while the drive saturates against the set
        brake (:data:`LIMIT_WALK_BASE`, then that plus 2^b for each of
        :data:`LIMIT_WALK_BITS`, all below the brake-release cards' 0.3 V): (code asked, code
        written, current) each; the test limit is written back after."""
        if not bool(self.co.cfg.joint(self.j, "dac_bits_limit_walk")):
            return []
        per_code = DAC_VOLTS_PER_CODE * float(self.co.t.rack.channel(self.limit_signal).scale)
        # each level read until a step's half-worth is over 4 standard errors of a step (a
        # noisy monitor, 1.2 LSB rms, made the 0.05 s window's steps off by half their worth:
        # rack seed 16); at least the window, at most dac_bits_fine_max_s
        g = (lambda k: float(self.co.cfg.joint(self.j, k)))
        target = (1 << min(LIMIT_WALK_BITS)) * per_code / WALK_WORTHS
        out = []
        for code in (LIMIT_WALK_BASE, *(LIMIT_WALK_BASE + (1 << b) for b in LIMIT_WALK_BITS)):
            got = self.place_limit(code, per_code)
            self.co.t.wait(g("dac_bits_settle_s"))
            lv = read_fine(self.co, self.current, code, got, max(target, FINE_SE_CODES * self.monitor_code),
                           g("dac_bits_window_s"), g("dac_bits_fine_max_s"), self.zero)
            out.append((code, got, lv.mean))
        self.fine_limit = self.limit_steps(per_code)
        self.limits[self.li] = self.limit_a
        self.cmd.set(current_limit_a=self.limits)
        return out

    def walk_row(self) -> None:
        """The limit walk's row: each step's current above the base's must be 2^b codes' worth
        (within half of it, the drive saturated at the limit); a step that adds nothing is
        bit b stuck, its value from the base's current (stuck at 1 lifts it by 2^b)."""
        if not self.walk:
            return
        co = self.co
        per_code = DAC_VOLTS_PER_CODE * float(co.t.rack.channel(self.limit_signal).scale)
        if any(c != g for c, g, _ in self.walk):
            co.record("joints", self.limit_signal, "DAC data bits: the current limit walked (brake set)", None,
                      detail=f"not run: the service wrote codes {[f'0x{g:03X}' for _, g, _ in self.walk]} for "
                             f"{[f'0x{c:03X}' for c, _, _ in self.walk]}")
            return
        base = self.walk[0][2]
        steps = [(b, i - base, (1 << b) * per_code) for b, (_, _, i) in zip(LIMIT_WALK_BITS, self.walk[1:])]
        bad = [(b, d, want) for b, d, want in steps if abs(d - want) > 0.5 * want]
        said = ", ".join(f"+2^{b}: {d * 1e3:+.1f} mA of {want * 1e3:.1f}" for b, d, want in steps)
        why = ""
        if bad and bad[0][1] > bad[0][2]:  # more than the codes' worth: no stuck limit bit does that
            b, d, want = bad[0]
            why = (f": adding 2^{b} codes raised the current by more than their worth, which no stuck bit of DAC "
                   f"channel {self.limit_signal} does (it adds nothing): the motor-current monitor {self.current}'s "
                   f"reading (its data bits are judged from its codes){self.monitor_excess(d - want)}")
        elif bad:
            b, _, want = bad[0]
            lifted = base - (LIMIT_WALK_BASE - DAC_ZERO_CODE) * per_code > 0.5 * want
            why = (f": data bit D{b} of DAC channel {self.limit_signal} stuck at {int(lifted)} (adding 2^{b} codes "
                   f"did not raise the current){self.monitor_excess(bad[0][1] - want) if abs(bad[0][1]) > want else ''}"
                   f"{co.monitor_stuck(self.current)}")
        worst = max(abs(d - want) / want for _, d, want in steps)
        co.record("joints", self.limit_signal, "DAC data bits: the current limit walked (brake set)", not bad,
                  round(worst, 3), None, 0.5, "of a step",
                  f"the limit at 0x{LIMIT_WALK_BASE:03X} drew {base:+.4f} A; {said}{why}")

    def run(self) -> None:
        co, j = self.co, self.j
        thr = float(co.cfg.joint(j, "dac_bits_tolerance")) * self.limit_a
        seen = [self.current_at(c) for c in DAC_BITS_CODES]
        # the low bits' steps, unless a high bit already drives the current (nothing more to
        # learn, and no need to push against the brake longer)
        high = max(abs(seen[0][1]), abs(seen[1][1])) > 2.0 * thr
        fine_rate = [] if high else self.rate_steps(seen[1][1] - seen[0][1])  # one code's worth
        if fine_rate:  # the drive's current per rate code against the brake (the median step's)
            self.amps_per_code = fine_rate[0].want / (1 << fine_rate[0].bit)
        i_sat = self.saturated_current()
        self.drew = abs(i_sat) >= 0.5 * self.limit_a  #: a current flowed against the brake
        placed = all(got == c for (got, _), c in zip(seen, DAC_BITS_CODES))
        (_, i_lo), (_, i_zero) = seen
        # judged on the step between the two codes (1 LSB apart, K_a x 1 LSB healthy), so the
        # channel's own offset (the DAC's +-10 mV and the amplifier's, the same at both codes:
        # a seeded rack's shoulder pitch drew -0.051 A and -0.031 A) is not read as a bit; an
        # offset beyond DAC_BITS_OFFSET_FACTOR x the tolerance fails as the offset it is
        step, centre = i_zero - i_lo, 0.5 * (i_zero + i_lo)
        offset_ok = abs(centre) <= DAC_BITS_OFFSET_FACTOR * thr
        ok = bool(abs(step) <= thr and offset_ok) if placed else None
        co.record("joints", self.signal, "DAC data bits (brake set)", ok, round(step, 4), -thr, thr, "A",
                  self.bits_detail(seen, ok, thr, fine_rate))
        lim_ok = bool(abs(abs(i_sat) - self.limit_a) <= thr)
        drew = (f"a {float(co.cfg.joint(j, 'dac_bits_drive_v')):g} V rate command drew {i_sat:+.3f} A "
                f"against the set brake, the limit written is {self.limit_a:.3f} A")
        if lim_ok:
            why = ""
        elif abs(i_sat) < float(co.cfg.joint(j, "diag_no_current_fraction")) * self.limit_a:
            # no current at all: the drive, a dead monitor or a limit stuck at 0 V read the same
            # with the brake set; the moves tell them apart (their drive-and-brake row)
            lim_ok = None
            why = ": no motor current seen, so the limit's bits are not judged here: the moves say why"
        else:
            # which bit is not said: the drive's own K_a x V may bound the current first
            high = abs(i_sat) > self.limit_a
            why = (f": a data bit of DAC channel {self.limit_signal} stuck at {int(high)} (the current limit reads "
                   f"{'high' if high else 'low'}; or the amplifier's own current limit is off)"
                   f"{self.monitor_excess(abs(i_sat) - self.limit_a)}")
        co.record("joints", self.limit_signal, "DAC data bits: the current limit (brake set)", lim_ok,
                  round(i_sat, 4), self.limit_a - thr, self.limit_a + thr, "A", drew + why)
        if lim_ok:  # the limit holds what was written: the rate steps below it are the command's
            self.walk_row()
            self.limit_fine_row()
            self.fine_row(self.signal, "DAC data bits: the low bits stepped (brake set)", fine_rate)

    def bits_detail(self, seen: list[tuple[int, float]], ok: bool | None, thr: float,
                    fine_rate: list[Step] | None) -> str:
        """The detail of the brake-set bits row: what the two codes ``seen`` (code written,
        current) drew, and when the row fails, which bits (``fine_rate``: the low bits' steps,
        measured already, name one)."""
        (_, i_lo), (_, i_zero) = seen
        step, centre = i_zero - i_lo, 0.5 * (i_zero + i_lo)
        drew = (f"codes 0x{DAC_BITS_CODES[0]:03X} and 0x{DAC_BITS_CODES[1]:03X} drew {i_lo:+.3f} A and "
                f"{i_zero:+.3f} A against the set brake, a step of {step:+.3f} A (limit {self.limit_a:.3f} A, "
                f"healthy within +/-{thr:.3f} A, their offset within +/-{DAC_BITS_OFFSET_FACTOR * thr:.3f} A)")
        if ok is None:
            return (f"not run: the service wrote codes {[f'0x{g:03X}' for g, _ in seen]} for "
                    f"{[f'0x{c:03X}' for c in DAC_BITS_CODES]} (its calibration of {self.signal})")
        if ok:
            return drew
        if abs(step) <= thr:
            return (f"DAC channel {self.signal}: both codes drew {centre:+.3f} A: the amplifier draws current at "
                    f"a zero command, or the DAC's offset is that far off: {drew}")
        if stuck_low := (summary(fine_rate)[0] if fine_rate else []):
            b = stuck_low[0].bit
            return (f"data bit D{b} of DAC channel {self.signal} stuck at 0 or at 1 (its step of 2^{b} codes from "
                    f"0 V added nothing: the low bits stepped row): {drew}")
        if max(abs(i_lo), abs(i_zero)) <= thr:
            return (f"DAC channel {self.signal}: a low data bit of D0..D10 stuck (the step between the two codes "
                    f"is more than one code's worth)" + self.monitor_bit() + f": {drew}")
        lo_moved = abs(i_lo) >= abs(i_zero)  # the code whose current a stuck bit moved
        return f"{self.diagnosis(i_lo if lo_moved else 0.0, 0.0 if lo_moved else i_zero, thr)}: {drew}"

    def limit_fine_row(self) -> None:
        """The current limit's D0 and D1 row (:meth:`limit_steps`)."""
        if self.fine_limit is None:
            return
        _, steps = self.fine_limit  # its value is not said: the amplifier's gain spread (+-10 %) hides 1-2 codes
        self.fine_row(self.limit_signal, "DAC data bits: the current limit's low bits stepped (brake set)", steps)

    def diagnosis(self, i_lo: float, i_zero: float, thr: float) -> str:
        """Which way the output went, and so which bits: at 0x7FF a bit of D0..D10 stuck at 0
        lowers it, D11 stuck at 1 raises it to +10 V; at 0x800 a bit of D0..D10 stuck at 1
        raises it, D11 stuck at 0 lowers it to -10 V."""
        said = []
        if i_lo < -thr:
            said.append("a data bit of D0..D10 stuck at 0 (code 0x7FF drove the joint negative)")
        elif i_lo > thr:
            said.append("data bit D11 stuck at 1 (code 0x7FF drove the joint positive)")
        if i_zero > thr:
            said.append("a data bit of D0..D10 stuck at 1 (code 0x800 drove the joint positive)")
        elif i_zero < -thr:
            said.append("data bit D11 stuck at 0 (code 0x800 drove the joint negative)")
        where = f"DAC channel {self.signal}"
        return f"{where}: " + "; ".join(said) + " (or the amplifier draws current at a zero command)" \
            + self.monitor_bit()

    def monitor_excess(self, excess_a: float) -> str:
        return monitor_excess(self.co.t.rack, self.current, excess_a)

    def monitor_bit(self) -> str:
        """The other reading of a small current at the test codes: the monitor's own data bit
        (one flipped bit of its code puts it back near zero current; a saturated current is
        never one bit away, so it is the DAC's)."""
        for code in self.codes[:2]:
            b = one_bit_away(code, ADC_ZERO_CODE)
            if code >= 0 and b is not None and abs(code - ADC_ZERO_CODE) > IDLE_FLIP_CODES:
                return (f"; or the motor-current monitor {self.current}: its code 0x{code:03X} is "
                        f"0x{code ^ (1 << b):03X} with D{b} flipped (data bit D{b} stuck at {(code >> b) & 1}?)")
        return ""


class CodeLog:
    """Every resolver and A/D code a checkout read (its inputs' ``rtd_counts``, ``adc_counts``)."""

    def __init__(self) -> None:
        self._rows: dict[str, list[np.ndarray]] = {"rtd": [], "adc": []}
        self._last: int | None = None

    def note(self, s) -> None:
        frame = int(s.frame)
        if frame == self._last or len(self._rows["adc"]) >= CODE_LOG_KEEP:
            return  # the same frame read twice adds nothing
        if ServiceState(int(s.service_state)) in (ServiceState.STARTING, ServiceState.STOPPED):
            return  # no sample yet (the area's zeros), or none any more: no code read
        self._last = frame
        self._rows["rtd"].append(np.array(s["rtd_counts"], dtype=np.int64))
        self._rows["adc"].append(np.array(s["adc_counts"], dtype=np.int64))

    def of(self, kind: str, slot: int) -> np.ndarray:
        """One channel's codes, in the order read."""
        rows = self._rows[kind]
        return np.array([r[slot] for r in rows], dtype=np.int64) if rows else np.zeros(0, dtype=np.int64)


def stuck_bits(codes: np.ndarray, nbits: int) -> list[tuple[int, int]]:
    """The bits of ``codes`` (a channel's raw codes over a run) stuck at 0 or 1: (bit, value).

    A bit is judged only where the codes swept across it densely. With bit ``b`` stuck, a
    sweep reads in blocks of 2^b codes with the other 2^b missing: neighbouring distinct codes
    are at most :data:`SWEEP_STEP` apart inside a block and 2^b + 1 .. 2^b + SWEEP_STEP across
    a missing one. A run of such neighbours spanning 2^(b+1) + 2 codes or more is a sweep that
    must have had the bit both 0 and 1 (a healthy one would: every 2^(b+1) consecutive codes
    hold both); codes in clusters far apart (two poses, a few stimulus levels) are no sweep.
    At least :data:`MIN_DISTINCT` distinct codes are needed at all."""
    u = np.unique(codes)
    if len(u) < MIN_DISTINCT:
        return []
    gaps = np.diff(u)
    out = []
    for b in range(nbits):
        bit = (u >> b) & 1
        if bit.min() != bit.max():
            continue
        w = 1 << b
        joined = (gaps <= SWEEP_STEP) | ((gaps > w) & (gaps <= w + SWEEP_STEP))
        if _longest_run_span(u, joined) >= 2 * w + 2:
            out.append((b, int(bit[0])))
    return out


def noise_split(codes: np.ndarray, nbits: int, evidence: int | None = None) -> list[tuple[int, int]]:
    """The bits of a quiet input's ``codes`` stuck at 0 or 1: (bit, value), read from its noise.

    A quiet input's noise reads as one unimodal group of neighbouring codes. Where the group
    straddles the edge of a 2^b block, bit ``b`` stuck moves the codes on one side by 2^b:
    the group reads with a hole, bit ``b`` is the same in every code, and each code read
    could have been itself or itself with bit ``b`` flipped. The bit is named when (1) some
    window narrower than what was read holds one of the two for every code, and the codes it
    holds fill it with no hole but chance's (the group put back together), and (2) the hole is
    no chance: between two codes read ``n1`` and ``n2`` times, a healthy unimodal group has
    each missing code at least min(n1, n2) times on average, so their product with the
    missing codes must reach :data:`NOISE_EVIDENCE` (a stray tail sample beyond a hole is
    noise; ``evidence`` instead where a failure has already been judged and only its cause is
    asked: 1). A healthy group has no such hole, or no window narrower. A group wider than
    :data:`NOISE_SPAN` is no quiet input's noise and is not judged here."""
    u, n = np.unique(codes, return_counts=True)
    if len(u) < (NOISE_MIN_CODES if evidence is None else 2):
        return []  # too few codes to be noise: a signal held at two values is no split group
    if _hole_evidence(u, n) < (NOISE_EVIDENCE if evidence is None else evidence):
        return []
    out = []
    for b in range(nbits):
        bit = (u >> b) & 1
        if bit.min() != bit.max():
            continue
        alt = u ^ (1 << b)
        for lo in np.unique(np.concatenate([u, alt])):
            # the narrowest window from lo: each code's nearest reading at or above lo
            near = np.where(u >= lo, np.where(alt >= lo, np.minimum(u, alt), u), alt)
            if (near < lo).any():
                continue
            hi = int(near.max())
            if hi - lo >= int(u[-1] - u[0]) or hi - lo > NOISE_SPAN:
                continue
            if _hole_evidence(*_held(u, alt, n, lo, hi)) < NOISE_EVIDENCE:
                out.append((b, int(bit[0])))
                break
    return out


def noise_core(codes: np.ndarray) -> np.ndarray:
    """``codes`` without their passing reads: a code read fewer than :data:`CORE_READS` times
    with no neighbour (+-1) read that often is a transient or a tail sample, not a level's
    noise (a deflection's few reads on the way out and back, a tach settling at a move's
    start, which on the noiseless perfect rack reads a code or two twice). What
    is left is the levels' noise, which :func:`noise_split` judges whole: a transient's one
    read 7 codes off made a split group too wide to judge (``stuck-bit:adc@SCAN[12]:4=1``,
    the wrist pitch tach idling across 0x800 with D4 at 1, docs/checkout.md)."""
    c = np.asarray(codes, dtype=np.int64)
    u, n = np.unique(c, return_counts=True)
    many = set(u[n >= CORE_READS].tolist())
    keep = [int(x) for x in u.tolist() if x in many or x - 1 in many or x + 1 in many]
    return c[np.isin(c, keep)]


def core_splits(codes: np.ndarray, nbits: int) -> list[tuple[int, int]]:
    """:func:`noise_split` of an A/D input's levels again without their passing reads
    (:func:`noise_core`), cut only where more than 32 codes are left out (a D5 split stays one
    level), and only where the two pieces interleave in time as noise does
    (:data:`INTERLEAVE_MIN` switches between them): two levels an input rested at a few codes
    apart, one after the other, are no split (a healthy seeded rack's resolver rested so)."""
    out: list[tuple[int, int]] = []
    for group in code_groups(noise_core(codes), GROUP_GAP + 1):
        found = noise_split(group, nbits)
        if found and _switches(group) >= INTERLEAVE_MIN:
            out += found
    return out


def _switches(group: np.ndarray) -> int:
    """How often the reads of ``group`` (in the order read) cross its widest hole."""
    u = np.unique(group)
    if len(u) < 2:
        return 0
    above = group >= u[int(np.argmax(np.diff(u))) + 1]
    return int(np.count_nonzero(above[1:] != above[:-1]))


#: :func:`core_splits`: the fewest crossings of a split's hole in the order read (assumed:
#: noise crosses it at every read of the smaller piece, 15 or more in the cases it was made
#: for; an input resting at one level, then another, crosses a few times)
INTERLEAVE_MIN = 8

#: :func:`noise_core`: how often a code is read before it counts as a level's (assumed: a
#: transient passes a code at most two or three times; the stuck bits' split pieces it was
#: made for read 15 times and more)
CORE_READS = 5


def _hole_evidence(u: np.ndarray, n: np.ndarray) -> int:
    """How sure a hole in a group of codes ``u`` (read ``n`` times each) is no chance: the most,
    over its holes, of missing codes x the fewer reads of the codes either side (0: none)."""
    if len(u) < 2:
        return 0
    return int(((np.diff(u) - 1) * np.minimum(n[:-1], n[1:])).max())


def _held(u: np.ndarray, alt: np.ndarray, n: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """The codes in ``lo``..``hi`` that each read code could have been (itself or ``alt``), and
    how often each could have been read: the group put back together."""
    got: dict[int, int] = {}
    for x, y, k in zip(u.tolist(), alt.tolist(), n.tolist()):
        for c in {x, y}:
            if lo <= c <= hi:
                got[c] = got.get(c, 0) + k
    keys = sorted(got)
    return np.array(keys, dtype=np.int64), np.array([got[c] for c in keys], dtype=np.int64)


def code_groups(codes: np.ndarray, max_step: int | None = None) -> list[np.ndarray]:
    """The levels an input held over a run: its codes cut where neighbouring distinct codes
    are more than ``max_step`` (:data:`GROUP_GAP`) apart, each group with at least :data:`GROUP_SAMPLES`
    reads (a passing transient is no level). Each is one quiet input's noise for
    :func:`noise_split` (idle, a deflected stick, a joint driven at a steady rate)."""
    if len(codes) == 0:
        return []
    u = np.unique(codes)
    cuts = u[1:][np.diff(u) > (GROUP_GAP if max_step is None else max_step)]
    edges = [int(u[0])] + [int(c) for c in cuts] + [int(u[-1]) + 1]
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        g = codes[(codes >= lo) & (codes < hi)]
        if len(g) >= GROUP_SAMPLES:
            out.append(g)
    return out


#: levels are cut where the codes leave more than this many codes out (assumed: wider than
#: a quiet input's noise, ``NOISE_SPAN``, narrower than a stuck bit D6 and up moves a code,
#: which :func:`noise_split` judges on the whole run or the idle capture)
GROUP_GAP = 32
#: reads a level needs to be judged (a transient passes through in a few)
GROUP_SAMPLES = 40


def angle_jumps(codes: np.ndarray, nbits: int) -> list[tuple[int, int]]:
    """A resolver's data bits stuck, from its angle jumping as the joint moves (codes in the
    order read): crossing the edge of a 2^b block with bit ``b`` stuck, the reading jumps by
    2^b (plus the motion between two reads) and the bit is the same on both sides: the
    stuck value. A healthy angle moves a few counts a read (wrapping at a turn); only bits
    whose jump is well above that (D6 and up, 64 counts) are judged. [] when none."""
    return _jumps(codes, nbits, JUMP_MIN_BIT, wrap=True, evidence=1, slack=lambda w: JUMP_SLACK)


def adc_jumps(codes: np.ndarray, nbits: int) -> list[tuple[int, int]]:
    """An A/D input's high data bit stuck, from its reading jumping as the input sweeps across
    the bit's edge (codes in the order read; :func:`angle_jumps`' rule without the wrap): a
    tach driven through 0 V with D11 stuck at 0 reads 0x7FF, then 0x003 for 0x803. Only D8 and
    up (:data:`ADC_JUMP_MIN_BIT`: 256 codes, 1.25 V, in one read through the anti-aliasing
    filter), within an eighth of 2^b (a driven tach moves tens of codes a read), seen
    :data:`ADC_JUMP_EVIDENCE` times or more (across the edge and back), the bit one value over
    the whole run. Found for the tach's D11 at 0 (``stuck-bit:adc@SCAN[9]:11=0``,
    docs/checkout.md). [] when none."""
    return _jumps(codes, nbits, ADC_JUMP_MIN_BIT, wrap=False, evidence=ADC_JUMP_EVIDENCE,
                  slack=lambda w: max(JUMP_SLACK, w >> 3))


def _jumps(codes: np.ndarray, nbits: int, min_bit: int, *, wrap: bool, evidence: int,
           slack: Callable[[int], int]) -> list[tuple[int, int]]:
    """The bits b >= ``min_bit`` whose 2^b jumps (within ``slack(2^b)``) between consecutive
    reads keep the bit the same on both sides, at least ``evidence`` of them, and (no
    ``wrap``: an A/D input) the bit never took the other value in the run."""
    c = np.asarray(codes, dtype=np.int64)
    if len(c) < 2:
        return []
    full = 1 << nbits
    d = (np.diff(c) + full // 2) % full - full // 2 if wrap else np.diff(c)
    u = np.unique(c)
    out = []
    for b in range(min_bit, nbits):
        w = 1 << b
        at = np.flatnonzero(np.abs(np.abs(d) - w) <= slack(w))
        same = [(int(c[i]) >> b) & 1 for i in at if (int(c[i]) >> b) & 1 == (int(c[i + 1]) >> b) & 1]
        held = ((u >> b) & 1).min() == ((u >> b) & 1).max()
        if len(same) >= evidence and len(set(same)) == 1 and (wrap or held):
            out.append((b, same[0]))
    return out


def noise_strays(codes: np.ndarray, nbits: int) -> list[tuple[int, int]]:
    """An A/D data bit stuck, from the stray reads a quiet input's noise throws 2^b away (codes
    in the order read). Where a level's noise only touches the edge of a 2^b block (idle at
    0x7FE, its noise now and then reading 0x800), bit ``b`` stuck sends each read across the
    edge 2^b away (0x800 reads 0xA00 with D9 at 1): isolated reads, a read of the level just
    before and just after, which with bit ``b`` flipped back fall next to the level (within
    :data:`STRAY_REACH` codes). Named when at least :data:`STRAY_EVIDENCE` reads do so and the
    bit held one value in every code of the run (it never took the other). Only D6 and up
    (:data:`JUMP_MIN_BIT`: 64 codes, far beyond noise); a lower bit's split is
    :func:`noise_split`'s. Found as the only miss of the 200-case matrix the anti-aliasing
    board added (``stuck-bit:adc@SCAN[18]:9=1``, docs/checkout.md). [] when none."""
    c = np.asarray(codes, dtype=np.int64)
    if len(c) < 3:
        return []
    u = np.unique(c)
    out: list[tuple[int, int]] = []
    for g in code_groups(c):
        lo, hi = int(g.min()), int(g.max())
        if hi - lo > NOISE_SPAN:
            continue
        inside = (c >= lo) & (c <= hi)
        stray = c[np.flatnonzero(~inside[1:-1] & inside[:-2] & inside[2:]) + 1]
        if len(stray) < STRAY_EVIDENCE:
            continue
        for b in range(JUMP_MIN_BIT, nbits):
            bit = (u >> b) & 1
            if bit.min() != bit.max() or (b, int(bit[0])) in out:
                continue
            back = stray ^ (1 << b)
            if int(((back >= lo - STRAY_REACH) & (back <= hi + STRAY_REACH)).sum()) >= STRAY_EVIDENCE:
                out.append((b, int(bit[0])))
    return out


#: :func:`noise_strays`: how many stray reads must fall next to the level with the bit
#: flipped back, and how far beyond the level's codes "next to" reaches (assumed: a healthy
#: input's noise puts no read exactly 2^b (64 codes or more) away three times, each between
#: two reads of its level; its tail reaches a code or two past what the level read)
STRAY_EVIDENCE, STRAY_REACH = 3, 2

#: the lowest resolver bit judged from a jump, and how far from 2^b counts a jump may be (the
#: motion between two reads; the checkout's moves, a runaway's 0.25 rad/s at most, move under
#: 12 counts a read) (assumed)
JUMP_MIN_BIT, JUMP_SLACK = 6, 16

#: :func:`adc_jumps`: the lowest A/D bit judged from a jump, and how many jumps name it
#: (assumed: no healthy input jumps 2^b codes (256 or more) in one read twice, each time
#: over a whole block of the bit's other value, and never reads that value over the run)
ADC_JUMP_MIN_BIT, ADC_JUMP_EVIDENCE = 8, 2


#: the widest group of codes a quiet input's noise reads (assumed: +-8 codes, beyond any
#: healthy A/D's or resolver's noise, ``[adc] max_noise_counts``)
NOISE_SPAN = 16
#: how many samples a hole in a quiet input's codes must have missed before it counts as a
#: stuck bit's (missing codes x the fewer reads of the codes either side; assumed: a
#: healthy code read 8 times on average is missed in a run with probability e^-8, 0.03 %)
NOISE_EVIDENCE = 8
#: the fewest distinct codes a group must read to be judged as noise (a noiseless input that
#: sat at two values, 0x800 and a few codes below, is not a split group) (assumed)
NOISE_MIN_CODES = 3


def _longest_run_span(u: np.ndarray, joined: np.ndarray) -> int:
    """The largest ``u[j] - u[i]`` over runs of neighbours all ``joined``."""
    best, start = 0, 0
    for k, ok in enumerate(joined):
        if not ok:
            start = k + 1
            continue
        best = max(best, int(u[k + 1] - u[start]))
    return best


#: the largest step between neighbouring distinct codes of a sweep (a moving joint's resolver
#: advances about one count a sample; a driven tach or monitor a few) (assumed)
SWEEP_STEP = 3
#: distinct codes a channel needs before its bits are judged
MIN_DISTINCT = 8


def _tach_diag(v: float, expected: float, travel: float, mean_tach: float, swing: float, no_current: bool,
               r_lo: float) -> str:
    """What an open-loop rate row adds about the tach: a tach that does not change while the
    joint is driven is dead or stuck, not reversed (a dead input held at a few mV would
    otherwise read "reversed"); a tach against the resolver's motion (or, with no motion to
    compare, against the command) is reversed; a joint that moved against the command with
    the tach agreeing was moved by gravity or a load (no motor current: the drive does not
    answer) or is driven the wrong way. "" when none."""
    if abs(travel) >= r_lo * abs(expected) and swing < STUCK_TACH_FRACTION * abs(v):
        return (f"; TACH NOT RESPONDING (dead or stuck input: it moved {swing:.3g} rad/s "
                f"while the resolver travelled {travel:+.4f} rad)")
    moved = abs(travel) >= MOVED_FRACTION * abs(expected)
    # a tach reading below MOVED_FRACTION of the command is its noise about 0: no sign to judge
    against = mean_tach * v < 0 and abs(mean_tach) >= MOVED_FRACTION * abs(v)
    if (moved and mean_tach * travel < 0) or (not moved and against):
        return "; TACH POLARITY REVERSED"
    if not against:
        return ""
    if no_current:
        return ("; MOVED AGAINST THE COMMAND WITH NO MOTOR CURRENT (tach and resolver agree): the drive "
                "does not answer (its PWM stage switch, +28 V and +/-15 V, the amplifier); gravity or a load "
                "moved it")
    return ("; MOVED AGAINST THE COMMAND (tach and resolver agree, with motor current): a reversed "
            "drive (motor or amplifier wiring)")


def _drifted(ang: np.ndarray, lsb: float, signal: str) -> str:
    """A resolver that went one way over the idle capture (its end at least 80 % of its
    peak-to-peak from its start, over 16 counts): the joint moved with every brake set and no
    current, which noise never does. "" otherwise."""
    moved = float(ang[-1] - ang[0])
    if abs(moved) / lsb < 16 or abs(moved) < 0.8 * float(ang.max() - ang.min()):
        return ""
    return (f"; the joint moved {math.degrees(moved):+.1f} deg while idle (brakes set, no current): an "
            f"external load beyond the brake's hold (a snag, a collision held against the arm) or a slipping "
            f"brake ({signal})")


def _runaway_cause(currents: list[float], travel: float, i_lim: float) -> str:
    """What the motor current says of a runaway (while it flowed: the mean of the reads at
    least half the move's largest, at least a tenth of the test's limit ``i_lim``): against
    the motion, the amplifier holds back while something else drives the joint (a load);
    with it, the motor drives it on (the rate loop's feedback). Not its last reads: the
    service may already have made the outputs safe (a load on the shoulder pitch held back
    at the limit, then read 0 A once the service tripped). "" without a monitor or with no
    current to read."""
    c = np.asarray(currents, dtype=float)
    if len(c) == 0:
        return ""
    peak = c[int(np.argmax(np.abs(c)))]
    flowing = c[(np.sign(c) == np.sign(peak)) & (np.abs(c) >= 0.5 * abs(peak))]
    i = float(np.mean(flowing)) if len(flowing) else 0.0
    if abs(i) < 0.1 * i_lim:
        return ""
    if i * travel < 0:
        return (f"; the motor current holds back ({i:+.2f} A) while the joint runs on: an external load "
                "drives it (a snag, a collision held against the arm, a payload beyond the counterbalance)")
    return (f"; the motor drives it on ({i:+.2f} A): the rate loop's tach feedback (a dead or reversed tach) "
            "or the amplifier")


#: a move's resolver travel of at least this fraction of the expected counts as motion
#: when the tach's sign is compared with it (assumed: well above a resolver LSB, far below a
#: working joint's travel)
MOVED_FRACTION = 0.1


class _DiagLimits:
    """A joint's drive-or-brake diagnosis thresholds, for a test at current limit ``i_lim``."""

    def __init__(self, cfg: CheckoutConfig, j: str, i_lim: float) -> None:
        self.f_move = float(cfg.joint(j, "diag_moved_fraction"))
        self.f_none = float(cfg.joint(j, "diag_no_current_fraction"))
        self.f_brake = float(cfg.joint(j, "diag_brake_current_fraction"))
        self.i_lim = i_lim
        self.i_none, self.i_brake = self.f_none * i_lim, self.f_brake * i_lim

    def moved(self, m: Move) -> bool:
        """The resolver or the tach shows at least ``f_move`` of the command, either way
        (the wrong way is the polarity rows' business: the drive answered)."""
        return max(m.along, m.against) >= self.f_move

    def answered(self, m: Move) -> bool:
        """The move counts: it moved and, where the rack has the monitor, with motor
        current (else gravity or a load moved it)."""
        return self.moved(m) and (m.peak_a is None or m.peak_a >= self.i_none)

    def not_answered(self, m: Move, j: str, seen: str) -> tuple[str, str]:
        """The value and detail of the failing diagnosis row for a move that did not answer."""
        i_lim, i_none, i_brake = self.i_lim, self.i_none, self.i_brake
        if m.peak_a is None:
            return "not moved", (
                f"did not move in the {m.tag} move and this rack has no motor-current "
                f"monitor for {j}: drive and brake cannot be told apart: check its brake-release "
                f"switch and brake, its PWM stage switch, +28 V and the amplifier. {seen}")
        if m.peak_a < i_none:
            also = (f" (it moved {m.travel:+.4f} rad without current: gravity or a load, or the current "
                    "monitor is dead: see its \"motor current responds\" row)" if self.moved(m) else "")
            return "no current", (
                f"no motor current: check its PWM stage switch, +28 V and +/-15 V (the servo chassis panel), "
                f"and the amplifier{also}. "
                f"Peak |current| {m.peak_a:.3g} A < {i_none:.3g} A "
                f"({self.f_none:g} x the {i_lim:.2f} A limit). {seen}")
        if m.peak_a >= i_brake:
            return "brake held", (
                f"brake not released (or a jam): check the joint's brake-release switch and "
                f"brake. It did not move with the motor current at {m.peak_a:.3g} A >= "
                f"{i_brake:.3g} A ({self.f_brake:g} x the {i_lim:.2f} A limit). {seen}")
        return "unclear", (
            f"did not move with some motor current ({m.peak_a:.3g} A, between "
            f"{i_none:.3g} and {i_brake:.3g} A): check its brake-release switch and brake, "
            f"then the amplifier. {seen}")

class _MoveParams:
    """A joint's open-loop move settings from the checkout configuration."""

    def __init__(self, cfg: CheckoutConfig, j: str) -> None:
        self.move_s = float(cfg.joint(j, "move_s"))
        self.lag = float(cfg.joint(j, "travel_lag_s"))
        self.r_lo, self.r_hi = (float(x) for x in cfg.joint(j, "rate_ratio"))
        self.agree = float(cfg.joint(j, "tach_resolver_tolerance"))
        self.max_factor = float(cfg.joint(j, "max_travel_factor"))
        self.dt = cfg.num("capture", "interval_s")
        #: the current the held drive draws at the move's command (the brake-set low bits'
        #: K_a x V), None when not measured
        self.stall_a: float | None = None


class _Sampled:
    """What the resolver, tach and motor current showed during one move."""

    def __init__(self) -> None:
        self.travel = 0.0  #: resolver travel, rad
        self.tach_integral = 0.0  #: the tach integrated over the move, rad
        self.samples: list[tuple[float, float]] = []  #: (time into the move, tach)
        self.currents: list[float] = []  #: motor current samples (a monitor present)
        self.runaway = ""  #: why the move was cut short ("" = it was not)
        self.left = ""  #: the service state when first seen not ARMED ("" = armed throughout)


class Move:
    """What one open-loop move of a joint showed (the diagnosis reads it)."""

    def __init__(self, tag: str, v: float, expected: float, travel: float, mean_tach: float,
                 peak_a: float | None, left_armed: str) -> None:
        self.tag = tag  #: "+" or "-"
        self.v = v  #: the rate commanded, rad/s
        self.expected = expected  #: the travel expected, rad
        self.travel = travel  #: resolver travel, rad
        self.mean_tach = mean_tach  #: tach mean over the move's window, rad/s
        self.peak_a = peak_a  #: peak |motor current| while driven, A (None: no monitor)
        self.left_armed = left_armed  #: the service state first seen not ARMED ("" = armed throughout)

    def _fractions(self) -> tuple[float, float]:
        """(the largest motion along the command, the largest against it) as fractions of
        the command, from the resolver travel and the tach mean."""
        fr = []
        if self.expected:
            fr.append(self.travel / self.expected)
        if self.v and math.isfinite(self.mean_tach):
            fr.append(self.mean_tach / self.v)
        if not fr:
            return 0.0, 0.0
        return max(0.0, max(fr)), max(0.0, -min(fr))

    @property
    def along(self) -> float:
        return self._fractions()[0]

    @property
    def against(self) -> float:
        return self._fractions()[1]

    def text(self, i_lim: float) -> str:
        cur = "no current monitor" if self.peak_a is None else f"peak |current| {self.peak_a:.3g} A of {i_lim:.2f} A"
        return (f"{self.tag} move: resolver {self.travel:+.4f} rad of {self.expected:+.4f} expected, "
                f"tach {self.mean_tach:+.4g} rad/s of {self.v:+.4g} commanded, {cur}")


def _fake_switcher(target: Target, board: str):
    """The fake matrix switcher behind ``board`` when the target is the simulated rack
    (None on real hardware: there the service's applied read-back is the check)."""
    world = getattr(target, "world", None)
    if world is None:
        return None
    try:
        return getattr(world.bus[board], "switcher", None)
    except KeyError:
        return None
