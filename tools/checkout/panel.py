"""The servo control chassis' front panel (IRSS report 3.6) as the checkout knows it.

The panel has, in the centre, the +28 VDC On/Off switch and the +/-15 V DC-DC converter
On/Off switch; on the left seven PWM output stage On/Off switches (the six joints and the
gripper); on the right six brake-release switches, one per joint. The rack reads none of
them: what the checkout knows of the panel is what the operator answers when asked, or
what the command line states (``pfma checkout --panel-off``), never a measurement.

A panel state is the set of switches that are off, each named as ``sim.faults`` names the
simulated chassis' switches (``panel-off:SWITCH``): ``28v``, ``15v``, ``pwm:JOINT`` (a joint
or ``gripper``) and ``brake:JOINT``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

from pfma.errors import ConfigError, PfmaError, did_you_mean

GRIPPER = "gripper"
#: the switches of the panel, by kind: what each is called in a record, a question, a message
SWITCH_TEXT = {
    "28v": "+28 VDC",
    "15v": "+/-15 V DC-DC converter",
    "pwm": "PWM output stage",
    "brake": "brake-release",
}
#: the check of each "panel" row (one per group of switches)
PANEL_CHECKS = {
    "28v": "+28 VDC switch (stated)",
    "15v": "+/-15 V switch (stated)",
    "pwm": "PWM stages x7 (stated)",
    "brake": "brake releases x6 (stated)",
}
#: ``--panel-off`` grammar, for messages and help
SYNTAX = "28v, 15v, pwm:JOINT, brake:JOINT, pwm:all, brake:all (comma-separated), or none"

#: where a panel state came from
OPERATOR, COMMAND_LINE, ASSUMED = "operator", "command line", "assumed"
#: an operator's answer that is not understood is asked again, this many times in all
MAX_TRIES = 3

YES = ("y", "yes", "on")
NO = ("n", "no", "off")


@dataclass(frozen=True)
class PanelState:
    """Which front-panel switches are off, and who says so (``source``: OPERATOR,
    COMMAND_LINE or ASSUMED). ``off`` holds ``"28v"``, ``"15v"``, ``"pwm:JOINT"``,
    ``"brake:JOINT"``; an empty set is every switch on."""

    off: frozenset[str] = frozenset()
    source: str = ASSUMED

    def is_off(self, kind: str, joint: str = "") -> bool:
        return (f"{kind}:{joint}" if joint else kind) in self.off

    def off_joints(self, kind: str, order: Sequence[str] = ()) -> list[str]:
        """The joints (and the gripper, for ``pwm``) whose ``kind`` switch is off, in ``order``."""
        names = [s.split(":", 1)[1] for s in self.off if s.startswith(kind + ":")]
        rank = {n: i for i, n in enumerate(order)}
        return sorted(names, key=lambda n: (rank.get(n, len(rank)), n))

    @property
    def chassis_off(self) -> list[str]:
        """``"28v"`` and/or ``"15v"`` when either chassis supply is off: nothing can move."""
        return [s for s in ("28v", "15v") if s in self.off]

    def how(self) -> str:
        """Who says so, in words, for every panel record and the report."""
        if self.source == OPERATOR:
            return "the operator's answer, not measured by the checkout"
        if self.source == COMMAND_LINE:
            return "stated on the command line (--panel-off), not checked by a person"
        return "assumed (no operator asked and no --panel-off given), not checked by a person"

    def who(self) -> str:
        """``"the operator says"`` / ``"the command line (--panel-off) states"`` / ``"assumed"``."""
        return {OPERATOR: "the operator says", COMMAND_LINE: "the command line (--panel-off) states"}.get(
            self.source, "assumed")

    def summary(self, joints: Sequence[str] = ()) -> str:
        """One line: ``"all switches on"`` or ``"off: +28 VDC; PWM output stage of wrist_roll"``,
        then who says so."""
        if not self.off:
            what = "all switches on"
        else:
            parts = [SWITCH_TEXT[s] for s in self.chassis_off]
            for kind in ("pwm", "brake"):
                names = self.off_joints(kind, [*joints, GRIPPER])
                if names:
                    parts.append(f"{SWITCH_TEXT[kind]} of {', '.join(names)}")
            what = "off: " + "; ".join(parts)
        return f"{what}; {self.how()}"


def _joints_of(kind: str, joints: Sequence[str]) -> list[str]:
    """The names a ``kind`` switch can belong to: six joints, and the gripper for PWM."""
    return [*joints, GRIPPER] if kind == "pwm" else list(joints)


def parse_panel_off(values: Iterable[str], joints: Sequence[str]) -> frozenset[str]:
    """The switches named off by ``--panel-off`` values (each comma-separated; the option
    may be given more than once).

    :param joints: the rack's joints (``RackConfig.joints``)
    :raises ConfigError: one message naming the bad item, the closest known names and the grammar
    """
    off: set[str] = set()
    none = False
    items = [x.strip() for v in values for x in v.split(",")]
    for item in items:
        if not item:
            raise ConfigError(f"--panel-off: an empty item in {','.join(items)!r}; give {SYNTAX}")
        kind, sep, name = item.partition(":")
        kind = kind.lower()
        if kind == "none" and not sep:
            none = True
        elif kind in ("28v", "15v"):
            if sep:
                raise ConfigError(f"--panel-off: {kind} takes no joint (one switch for the whole "
                                  f"chassis), got {item!r}")
            off.add(kind)
        elif kind in ("pwm", "brake"):
            known = _joints_of(kind, joints)
            if not name:
                raise ConfigError(f"--panel-off: {kind} needs a joint ({kind}:JOINT or {kind}:all); "
                                  f"joints: {', '.join(known)}")
            if name == "all":
                off.update(f"{kind}:{n}" for n in known)
            elif name in known:
                off.add(f"{kind}:{name}")
            elif kind == "brake" and name == GRIPPER:
                raise ConfigError("--panel-off: the gripper has no brake: the six brake-release "
                                  "switches are the joints' (IRSS 3.6)")
            else:
                raise ConfigError(f"--panel-off: no joint {name!r} for {kind}"
                                  + (did_you_mean(name, known) or "") + f"; joints: {', '.join(known)}")
        else:
            raise ConfigError(f"--panel-off: unknown switch {item!r}"
                              + (did_you_mean(kind, ["28v", "15v", "pwm", "brake", "none"]) or "")
                              + f"; give {SYNTAX}")
    if none and off:
        raise ConfigError(f"--panel-off: 'none' (every switch on) given together with switches off "
                          f"({', '.join(sorted(off))})")
    return frozenset(off)


class _Asker:
    """The panel questions, asked through ``ask`` (``input`` on a terminal)."""

    def __init__(self, ask: Callable[[str], str], say: Callable[[str], None]) -> None:
        self.ask = ask
        self.say = say

    def _answer(self, question: str) -> str:
        try:
            return self.ask(f">>> OPERATOR: {question} ").strip()
        except EOFError:
            raise PfmaError(f"no answer to {question!r} (input closed): state the panel with "
                            "--non-interactive --panel-off SWITCHES (or --panel-off none)") from None

    def yes_no(self, question: str) -> bool:
        for _ in range(MAX_TRIES):
            a = self._answer(f"{question} [y/n]").lower()
            if a in YES:
                return True
            if a in NO:
                return False
            self.say(f">>> OPERATOR: not understood: {a!r}; answer y (on) or n (off)")
        raise PfmaError(f"no valid answer to {question!r} after {MAX_TRIES} tries")

    def names(self, a: str, known: Sequence[str]) -> list[str] | str:
        """The names listed in ``a`` (``all`` = every one), or why not (a str)."""
        if a.lower() == "all":
            return list(known)
        got = [x for x in a.replace(",", " ").split() if x]
        bad = [x for x in got if x not in known]
        if not got or bad:
            return (f"not understood: {a!r}" + (did_you_mean(bad[0], known) if bad else "")
                    + f"; names: {', '.join(known)}, or all")
        return got

    def group(self, question: str, known: Sequence[str], which: str) -> list[str]:
        """A group of switches: y = all on, or the names of those off (n asks which)."""
        tries = 0
        while tries < MAX_TRIES:
            a = self._answer(f"{question} [y = all on / n / the ones off, e.g. {known[-1]}]")
            low = a.lower()
            if low in YES:
                return []
            if low in NO:
                a = self._answer(f"{which} (comma-separated: {', '.join(known)}; or all)")
            got = self.names(a, known)
            if isinstance(got, list):
                return got
            self.say(f">>> OPERATOR: {got}")
            tries += 1
        raise PfmaError(f"no valid answer to {question!r} after {MAX_TRIES} tries")


def ask_panel(ask: Callable[[str], str], say: Callable[[str], None], joints: Sequence[str]) -> PanelState:
    """Ask the operator for the servo chassis' panel, one question per group of switches.

    :param ask: shows a prompt and returns the answer line (``input``)
    :param say: where "not understood" goes
    :param joints: the rack's joints, in panel order (``RackConfig.joints``)
    :raises PfmaError: no answer (input closed), or none understood after ``MAX_TRIES``
    """
    q = _Asker(ask, say)
    say(">>> OPERATOR: the joints test moves the arm: the servo chassis' front panel, please")
    off: set[str] = set()
    if not q.yes_no("servo chassis +28 VDC switch (centre) on?"):
        off.add("28v")
    if not q.yes_no("servo chassis +/-15 V DC-DC converter switch (centre) on?"):
        off.add("15v")
    pwm = _joints_of("pwm", joints)
    off.update(f"pwm:{n}" for n in q.group(f"PWM output stage switches (left) on, all {len(pwm)}?",
                                             pwm, "Which PWM stages are off?"))
    brake = _joints_of("brake", joints)
    off.update(f"brake:{n}" for n in q.group(f"brake-release switches (right) on, all {len(brake)}?",
                                               brake, "Which brake-release switches are off?"))
    return PanelState(frozenset(off), OPERATOR)


__all__ = ["ASSUMED", "COMMAND_LINE", "GRIPPER", "OPERATOR", "PANEL_CHECKS", "PanelState", "SWITCH_TEXT", "SYNTAX",
           "ask_panel", "parse_panel_off"]
