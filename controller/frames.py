"""Minor and major frames and the controller's scheduling table.

IRSS report 2.3.5 ("Framing"): minor frames of about 3 ms, 16 minor frames per major
frame, tasks staggered by frame number so that their relative phase repeats every
major frame; 2.2.1: "The frequency with which a task executes is determined within
a scheduling table indexed by the frame number." 2.2.3: the communications segment
opens every minor frame and takes "roughly 15% of the entire minor frame time".

Here the controller's minor frame is locked to the I/O service's frame (3.125 ms,
320 Hz by default): it runs right after each service frame. A task has a rate and a
phase; its rate must be the minor-frame rate divided by a divisor of 16, and the
tasks of any one minor frame, plus the decision tables, must fit the part of the
frame left after the communications segment. :meth:`FrameConfig.validate` reports
every task that cannot fit its period (a :class:`ScheduleError` lists them all).

Rate profiles (select with ``FrameConfig.profile(name)`` or ``pfma controller
--profile NAME``):

``layers`` (default)
    the report's layer section (2.2.1): multi-segment path planner 20 Hz, trajectory
    planner 40 Hz, Cartesian engine 40 and 80 Hz, joint planner 80 Hz, servo at the
    resolver rate (160 Hz; the I/O chassis refreshes resolvers at 160 Hz, 2.3.1), on
    320 Hz minor frames.
``overview``
    the report's overview figures (section 1): "Independent joint servos run at a 134
    Hz rate and position based impedance control functions at 67 Hz. Autonomous path
    generation and hand controller inputs are processed at a 33 Hz rate." With 16
    minor frames per major frame these are dividers 2, 4 and 8 of a 268 Hz minor frame
    (3.73 ms, "about 3 ms"): servo 134 Hz, joint planner and Cartesian engine 67 Hz,
    trajectory and path planners 33.5 Hz. Locked to the service, the I/O service must
    then run 268 Hz frames too (its resolvers at 134 Hz); the system simulator does this
    when asked. With the controller's own clock (below) the service keeps its rates.

Clocks (``FrameConfig.clock``, ``pfma controller --clock``; docs/controller.md "Two clocks"):

``locked`` (default)
    a minor frame runs right after each service frame; its number is the service's.
``own``
    the controller's own frame clock, as the report's computational chassis had its own
    frame interrupt (board 2) and the I/O chassis its own rates, meeting only in the Bit3
    RAM: minor frame k is due ``k`` periods after the controller's first frame, whatever
    the service does. Each frame reads the newest whole inputs; the commands still carry
    the service frame of the inputs they were computed from, so the service's freshness
    rule (ages in its own frames) is unchanged; missed frames are counted on this clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pfma.errors import ConfigError

MINOR_FRAMES_PER_MAJOR = 16  # IRSS report 2.3.5
#: service frames the controller may miss in a row before it is a Servo Control fault
#: (assumed; see FrameConfig.max_missed_run)
DEFAULT_MAX_MISSED_RUN = 2
#: the controller's frame clocks (see the module doc)
CLOCKS = ("locked", "own")
#: share of the minor frame the communications segment takes (report 2.2.3)
COMM_FRACTION = 0.15


class ScheduleError(ConfigError):
    """The controller's schedule is not valid; the message lists every problem."""


@dataclass(frozen=True)
class TaskSpec:
    """One periodic task of a layer.

    :param name: task name (unique)
    :param layer: layer key the task belongs to
    :param rate_hz: how often it runs
    :param phase: which minor frame of its period it runs in (0 .. divider-1)
    :param budget_s: the time it may take (worst case) - used to check the schedule fits
    """

    name: str
    layer: str
    rate_hz: float
    phase: int = 0
    budget_s: float = 100e-6
    doc: str = ""


#: task name -> (layer, doc) of the default tasks; rates and phases come from the profiles
TASK_DOCS = {
    "updown_requests": ("updown", "user requests -> Up/Down command; responses (request/response)"),
    "msp_planner": ("msp", "multi-segment path planner: path recording, files, playback segments"),
    "msp_requests": ("msp", "multi-segment path planner while not running: move requests refused at once"),
    "trajectory_planner": ("trajectory", "trajectory planner: one Cartesian segment, speed profile"),
    "cartesian_slow": ("cartesian", "Cartesian engine: trajectory and hand-controller composition"),
    "cartesian_fast": ("cartesian", "Cartesian engine: force/torque offsets"),
    "joint_planner": ("joint", "joint planner: commanded joint positions for the servo"),
    "servo_control": ("servo", "first-order compensators, limits: joint positions -> rate commands"),
    "gripper_control": ("servo", "the gripper (seventh amplifier): requests, stall detection, grip force"),
}

#: profile -> (minor-frame rate Hz, {task: (rate Hz, phase)})
PROFILES: dict[str, tuple[float, dict[str, tuple[float, int]]]] = {
    "layers": (320.0, {
        "updown_requests": (320.0, 0),
        "servo_control": (160.0, 0),  # the frames with fresh resolver data (service rtd phase 0)
        "joint_planner": (80.0, 1),
        "cartesian_fast": (80.0, 3),
        "cartesian_slow": (40.0, 5),
        "trajectory_planner": (40.0, 7),
        "msp_planner": (20.0, 9),
        "msp_requests": (20.0, 9),  # never with msp_planner: its table has one or the other
        "gripper_control": (40.0, 3),
    }),
    "overview": (268.0, {
        "updown_requests": (268.0, 0),
        "servo_control": (134.0, 0),
        "joint_planner": (67.0, 1),
        "cartesian_fast": (67.0, 3),
        "cartesian_slow": (67.0, 3),
        "trajectory_planner": (33.5, 5),
        "msp_planner": (33.5, 7),
        "msp_requests": (33.5, 7),
        "gripper_control": (33.5, 2),
    }),
}


#: worst-case time budget per task (s): about twice the median cost measured in the system
#: simulator on the development VM (joint planner step ~0.25 ms, Cartesian engine and
#: servo ~0.1 ms); the schedule check uses them to report tasks that cannot fit
TASK_BUDGETS_S = {
    "updown_requests": 50e-6, "servo_control": 250e-6, "joint_planner": 500e-6,
    "cartesian_fast": 300e-6, "cartesian_slow": 300e-6, "trajectory_planner": 200e-6,
    "msp_planner": 200e-6, "msp_requests": 50e-6, "gripper_control": 100e-6,
}


def default_tasks(profile: str = "layers") -> tuple[TaskSpec, ...]:
    try:
        _, table = PROFILES[profile]
    except KeyError:
        raise ScheduleError(f"no schedule profile {profile!r}; profiles: {', '.join(PROFILES)}") from None
    return tuple(TaskSpec(n, TASK_DOCS[n][0], hz, ph, budget_s=TASK_BUDGETS_S.get(n, 100e-6),
                          doc=TASK_DOCS[n][1]) for n, (hz, ph) in table.items())


@dataclass(frozen=True)
class FrameConfig:
    """Minor-frame rate, tasks, and the time budget of the decision tables.

    :param frame_rate_hz: minor frames per second (the service's frame rate)
    :param tasks: the periodic tasks
    :param tables_budget_s: time reserved each minor frame for the seven decision tables
        and the data-acquisition bridge
    :param clock: ``locked`` (default: each minor frame follows a service frame and has its
        number) or ``own`` (the controller's own frame clock; see the module doc)
    :param max_missed_run: minor frames the controller may miss in a row (their periodic
        tasks are caught up in the frame it wakes in); more is a fault of the Servo Control
        layer. Assumed default 2: with the servo at half the frame rate and Data Acquisition's
        output at the end of the frame, two missed frames make the service see a rate command
        at most 4 frames old, the service's default ``max_input_age_frames`` (docs/controller.md,
        "Missed frames and command freshness")
    """

    frame_rate_hz: float = 320.0
    tasks: tuple[TaskSpec, ...] = field(default_factory=default_tasks)
    tables_budget_s: float = 400e-6
    profile_name: str = "layers"
    max_missed_run: int = DEFAULT_MAX_MISSED_RUN
    #: ``locked`` (a minor frame after each service frame) or ``own`` (its own frame clock)
    clock: str = "locked"

    @classmethod
    def profile(cls, name: str = "layers", **kw) -> "FrameConfig":
        """The named rate profile (see the module doc)."""
        rate, _ = PROFILES.get(name, (None, None))
        if rate is None:
            raise ScheduleError(f"no schedule profile {name!r}; profiles: {', '.join(PROFILES)}")
        return cls(frame_rate_hz=rate, tasks=default_tasks(name), profile_name=name, **kw)

    @property
    def period_s(self) -> float:
        return 1.0 / self.frame_rate_hz

    def divider(self, task: TaskSpec) -> int:
        return int(round(self.frame_rate_hz / task.rate_hz))

    def problems(self) -> list[str]:
        """Everything wrong with this schedule (empty when it is valid)."""
        out: list[str] = []
        if not 1.0 <= self.frame_rate_hz <= 5000.0:
            out.append(f"minor-frame rate {self.frame_rate_hz} Hz outside 1..5000 Hz")
            return out
        if self.clock not in CLOCKS:
            out.append(f"clock {self.clock!r}: one of {', '.join(CLOCKS)}")
        if not 0 <= int(self.max_missed_run) <= MINOR_FRAMES_PER_MAJOR:
            out.append(f"max_missed_run {self.max_missed_run} outside 0..{MINOR_FRAMES_PER_MAJOR}")
        names = [t.name for t in self.tasks]
        for n in {n for n in names if names.count(n) > 1}:
            out.append(f"task {n} is listed more than once")
        usable = self.period_s * (1.0 - COMM_FRACTION) - self.tables_budget_s
        if usable <= 0:
            out.append(f"decision tables ({self.tables_budget_s * 1e6:.0f} us) and the communications "
                       f"segment leave no time in a {self.period_s * 1e3:.3f} ms minor frame")
        for t in self.tasks:
            out += self._task_problems(t, usable)
        if not out:
            out += self._frame_problems(usable)
        return out

    def _task_problems(self, t: TaskSpec, usable: float) -> list[str]:
        """What is wrong with one task's rate, phase and budget (``usable``: seconds of a
        minor frame left for tasks)."""
        if t.rate_hz <= 0:
            return [f"task {t.name}: rate {t.rate_hz} Hz must be positive"]
        ratio = self.frame_rate_hz / t.rate_hz
        div = int(round(ratio))
        if abs(ratio - div) > 1e-6 * ratio or div < 1 or MINOR_FRAMES_PER_MAJOR % div:
            ok = sorted({self.frame_rate_hz / d for d in (1, 2, 4, 8, 16)}, reverse=True)
            return [f"task {t.name}: {t.rate_hz:g} Hz cannot fit its period: on "
                    f"{self.frame_rate_hz:g} Hz minor frames a task runs every 1, 2, 4, 8 or 16 "
                    f"frames ({', '.join(f'{r:g}' for r in ok)} Hz)"]
        out: list[str] = []
        if not 0 <= t.phase < div:
            out.append(f"task {t.name}: phase {t.phase} not in 0..{div - 1} for {t.rate_hz:g} Hz")
        if t.budget_s > usable:
            out.append(f"task {t.name}: budget {t.budget_s * 1e6:.0f} us cannot fit its period: "
                       f"{usable * 1e6:.0f} us of a minor frame are left for tasks")
        return out

    def _frame_problems(self, usable: float) -> list[str]:
        """The minor frames whose tasks' budgets together exceed ``usable`` seconds (checked
        only once every task fits on its own: the table needs valid dividers)."""
        out: list[str] = []
        for k, frame in enumerate(self.table()):
            total = sum(t.budget_s for t in frame)
            if total > usable:
                out.append(f"minor frame {k}: tasks {', '.join(t.name for t in frame)} need "
                           f"{total * 1e6:.0f} us, {usable * 1e6:.0f} us available: move a phase")
        return out

    def validate(self) -> "FrameConfig":
        """Raise :class:`ScheduleError` listing every problem; return self when valid."""
        p = self.problems()
        if p:
            raise ScheduleError("controller schedule: " + "; ".join(p))
        return self

    def task(self, name: str) -> TaskSpec:
        for t in self.tasks:
            if t.name == name:
                return t
        raise KeyError(name)

    def last_slot(self, name: str, frame: int) -> int:
        """The latest minor frame <= ``frame`` in which task ``name`` is scheduled."""
        t = self.task(name)
        d = self.divider(t)
        return frame - ((frame - t.phase) % d)

    def table(self) -> tuple[tuple[TaskSpec, ...], ...]:
        """The scheduling table: the tasks of each of the 16 minor frames, in list order."""
        return tuple(tuple(t for t in self.tasks if k % self.divider(t) == t.phase)
                     for k in range(MINOR_FRAMES_PER_MAJOR))

    def describe(self) -> str:
        """The scheduling table as text (rates, phases, frames)."""
        lines = [f"minor frame {self.period_s * 1e3:.3f} ms ({self.frame_rate_hz:g} Hz), "
                 f"{MINOR_FRAMES_PER_MAJOR} per major frame ({MINOR_FRAMES_PER_MAJOR * self.period_s * 1e3:.1f} ms), "
                 f"profile {self.profile_name}, clock {self.clock}"]
        for t in self.tasks:
            lines.append(f"  {t.name:<20} layer {t.layer:<11} {t.rate_hz:>7g} Hz  every {self.divider(t):>2} "
                         f"frames, phase {t.phase}")
        for k, frame in enumerate(self.table()):
            lines.append(f"  frame {k:>2}: {' '.join(t.name for t in frame)}")
        return "\n".join(lines)
