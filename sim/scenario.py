"""Fault scenarios: a TOML file of timed steps, run on the service loop's frame count.

A scenario injects and clears faults (:mod:`sim.faults` specs) at given times since the
service's first frame, for CI runs and for training::

    name = "resolver-dropout"
    description = "the shoulder pitch resolver loses its signal for 3 s"

    [[step]]
    at_s = 2.0
    inject = "resolver-los:shoulder_pitch_angle"

    [[step]]
    at_s = 5.0
    clear = "resolver-los:shoulder_pitch_angle"     # or clear = "all"

Time is frame time: a step at ``at_s`` runs just before frame ``round(at_s * rate)`` of the
service loop (frame 0 is the first), so a run is the same on a simulated clock and in
real time, and a dropped frame does not move a step. Steps at the same time run in file
order. :func:`load_scenario` checks everything before anything runs: unknown keys, types,
every spec against the rack, and that each ``clear`` names a fault an earlier step
injected; an error names the file, the step's line and the field.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, NoReturn

import msgspec

from pfma import config
from pfma.errors import ConfigError, did_you_mean
from pfma.rack import RackConfig
from sim.faults import Fault, FaultSet, parse_fault

_TOP_KEYS = ("name", "description", "errors_seed", "step")
_STEP_KEYS = ("at_s", "inject", "clear")


@dataclass(frozen=True)
class Step:
    """One step: at ``at_s``, inject ``spec`` (``action == "inject"``) or clear it."""

    at_s: float
    action: str  #: "inject" or "clear"
    spec: str  #: a fault spec, or "all" for a clear
    line: int | None = None  #: the step's ``[[step]]`` line in its file

    def frame(self, rate_hz: float) -> int:
        """The loop frame this step runs before."""
        return int(round(self.at_s * rate_hz))

    def as_text(self) -> str:
        return f"t={self.at_s:g} s {self.action} {self.spec}"


@dataclass
class Scenario:
    name: str
    description: str = ""
    steps: list[Step] = field(default_factory=list)
    source: str = "<string>"
    #: the simulated rack's imperfections the scenario runs on (sim/errors.py; None: the
    #: service's own, ``--sim-errors``)
    errors_seed: int | None = None


class _StepEntry(msgspec.Struct, forbid_unknown_fields=True):
    at_s: Annotated[float, msgspec.Meta(ge=0)]
    inject: str | None = None
    clear: str | None = None


class _ScenarioFile(msgspec.Struct, forbid_unknown_fields=True):
    step: Annotated[list[_StepEntry], msgspec.Meta(min_length=1)]
    name: str | None = None
    description: str = ""
    errors_seed: Annotated[int, msgspec.Meta(ge=0)] | None = None


_NO_STEPS = "no steps; add [[step]] tables with at_s and inject or clear"
_AT_S = "at_s must be a number of seconds >= 0, not {value!r}"
_STRINGS = "name and description must be strings"
#: the scenario's wording per field (pfma.config.convert)
_MESSAGES: dict[str, Any] = {
    "*": lambda f: (f"unknown key {f['key']!r}"
                    + (did_you_mean(f["key"], _TOP_KEYS) or f"; keys: {', '.join(_TOP_KEYS)}")),
    "name": _STRINGS, "description": _STRINGS,
    "errors_seed": "errors_seed must be a whole number >= 0 (the seed of pfma serve --sim-errors), not {value!r}",
    "errors_seed?": "errors_seed must be a whole number >= 0 (the seed of pfma serve --sim-errors), not {value!r}",
    "step": _NO_STEPS, "step?": _NO_STEPS,
    "step[]": "a step is a [[step]] table",
    "step[].*": lambda f: (f"unknown field {f['key']!r}"
                           + (did_you_mean(f["key"], _STEP_KEYS) or f"; fields: {', '.join(_STEP_KEYS)}")),
    "step[].at_s": _AT_S, "step[].at_s?": _AT_S,
    "step[].inject": "inject must be a fault spec string, not {value!r}",
    "step[].clear": "clear must be a fault spec string, not {value!r}",
}


def parse_scenario(text: str, source: str = "<string>", rack: RackConfig | None = None) -> Scenario:
    """A scenario from TOML text, fully checked (see the module docstring).

    :raises ConfigError: naming ``source``, the step's line and the field
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"scenario {source}: not valid TOML: {err}") from None

    def error(p: config.Problem) -> ConfigError:
        if len(p.path) >= 2 and p.path[0] == "step" and isinstance(p.path[1], int):
            line = config.line_of(text, p.path[:2])
            where = f"scenario {source}" + (f" line {line}" if line else "") + f" (step {p.path[1] + 1})"
            return ConfigError(f"{where}: {p.message}")
        return ConfigError(f"scenario {source}: {p.message}")

    raw = config.convert(data, _ScenarioFile, source=source, text=text, messages=_MESSAGES, error=error)
    steps: list[Step] = []
    for i, st in enumerate(raw.step):
        def fail(msg: str) -> NoReturn:
            config.fail(source, text, ("step", i), msg, error=error)
        if not math.isfinite(st.at_s):
            fail(_AT_S.format(value=st.at_s))
        actions = [k for k in ("inject", "clear") if getattr(st, k) is not None]
        if len(actions) != 1:
            fail("give exactly one of inject = \"SPEC\" or clear = \"SPEC\"|\"all\"")
        action = actions[0]
        spec = getattr(st, action)
        if not spec.strip():
            fail(f"{action} must be a fault spec string, not {spec!r}")
        steps.append(Step(float(st.at_s), action, spec.strip(), config.line_of(text, ("step", i))))
    order = sorted(range(len(steps)), key=lambda j: steps[j].at_s)  # stable: file order on ties
    name = Path(source).stem if raw.name is None else raw.name
    scenario = Scenario(name, raw.description, [steps[j] for j in order], source, raw.errors_seed)
    _check_specs(scenario, rack)
    return scenario


def _check_specs(scenario: Scenario, rack: RackConfig | None) -> None:
    """Every spec parses against ``rack``; a clear names a fault active at its time."""
    active: dict[tuple, str] = {}
    for st in scenario.steps:
        where = (f"scenario {scenario.source}" + (f" line {st.line}" if st.line else "")
                 + f" ({st.action} at {st.at_s:g} s)")
        if st.action == "clear" and st.spec == "all":
            active.clear()
            continue
        try:
            f = parse_fault(st.spec, rack)
        except ConfigError as err:
            raise ConfigError(f"{where}: {err}") from None
        if st.action == "inject":
            if f.key in active:
                raise ConfigError(f"{where}: {st.spec!r} is already injected (as {active[f.key]!r})")
            active[f.key] = st.spec
        elif f.key not in active:
            raise ConfigError(f"{where}: {st.spec!r} is not injected by an earlier step; active then: "
                              f"{', '.join(active.values()) or 'none'}")
        else:
            del active[f.key]


def load_scenario(path: str | Path, rack: RackConfig | None = None) -> Scenario:
    """Read and check a scenario file (OSError for a missing or unreadable file)."""
    data = Path(path).read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(f"scenario {path}: not UTF-8 text (byte {err.start})") from None
    return parse_scenario(text, str(path), rack)


class ScenarioRunner:
    """Runs a scenario's steps on a :class:`FaultSet` as the loop's frames go by.

    :param scenario: the checked scenario
    :param faults: the world's fault set
    :param rate_hz: the loop's frame rate (a step at ``at_s`` runs before frame
        ``round(at_s * rate_hz)``)
    :param say: called with ``(step, faults applied or cleared, error or None)`` after each step
    """

    def __init__(self, scenario: Scenario, faults: FaultSet, rate_hz: float,
                 say: Callable[[Step, list[Fault], Exception | None], None] | None = None) -> None:
        self.scenario = scenario
        self.faults = faults
        self.rate_hz = rate_hz
        self.say = say
        self._due = [(st.frame(rate_hz), st) for st in scenario.steps]
        self._next = 0
        self.done: list[tuple[int, Step]] = []  #: (frame, step) of every step run

    @property
    def finished(self) -> bool:
        return self._next >= len(self._due)

    def on_frame(self, k: int) -> None:
        """Run the steps due before frame ``k`` (call before each frame, in the loop's thread).
        A step that fails (its fault not active any more, say) is reported, not raised."""
        while self._next < len(self._due) and self._due[self._next][0] <= k:
            _, st = self._due[self._next]
            self._next += 1
            err: Exception | None = None
            done: list[Fault] = []
            try:
                if st.action == "inject":
                    done = [self.faults.inject(st.spec, since=k)]
                else:
                    done = self.faults.clear(st.spec)
            except ConfigError as e:
                err = e
            self.done.append((k, st))
            if self.say is not None:
                self.say(st, done, err)


__all__ = ["Scenario", "ScenarioRunner", "Step", "load_scenario", "parse_scenario"]
