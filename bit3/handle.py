"""A high-level handle on the rack for a short Python script (docs/python.md).

::

    from bit3.handle import Rack

    with Rack.open("pfma") as rack:                  # attach as the command writer
        rack.arm(current_limit_a=2.0)                 # a new re-arm number; waits for ARMED
        rack.rates(elbow_pitch=0.05)                  # rad/s; the others 0
        rack.sleep(1.0)                               # the keep-alive holds the heartbeat
        print(rack.read().angle("elbow_pitch"))      # a named input with its status
    # leaving the block (or an exception) disarms: rates 0, current limits 0, no arm request

What the handle does for the script (each rule once, here and in docs/python.md):

- **Attach** as the writer of the command area (owner name ``python-script`` unless
  given); a service that is not running is one :class:`RackError` line.
- **Arm**: zero rates, the current limits asked for, ``arm_request`` 1 and the next
  ``rearm_counter`` (read from the command area, never reused), then waits until the
  service says ARMED, or raises :class:`RackError` with the service's own reason.
- **Keep-alive**: while the handle is open a thread re-publishes the command area every
  :data:`KEEPALIVE_S` (the service's watchdog is 15 ms), so ``time.sleep`` in the script
  does not trip it.
- **Rate expiry**: a rate command lasts :data:`RATE_EXPIRY_S` (0.3 s) unless the script
  gives it again; then the keep-alive sends **zero rates**, never the last ones, and says
  so once. A script that hangs or forgets stops the arm within 0.3 s; a script that
  dies stops publishing and the service's 15 ms watchdog makes the outputs safe.
- **Breakaway**: a rate command (or a current limit) too small to beat a joint's Coulomb
  friction at rest (:attr:`pfma.arm.JointFacts.breakaway_rate_rad_s`; the nominal arm
  model, gravity not counted) is sent as asked, and said once per joint: the joint will
  not move.
- **Disarm** on ``close()``, at the end of the ``with`` block and on an exception in it.
- **Gripper**: ``gripper_open``/``gripper_close``/``gripper_stop``/``gripper_force`` drive the
  seventh amplifier (DAC channels 6 and 13) with the controller's own motion logic
  (:class:`pfma.gripper.GripperMotion`, run by the keep-alive at :data:`GRIPPER_UPDATE_S`): a
  move ends on a stall, a close holds at the grip force its current limit sets.
  ``gripper_wait`` waits for the end of the move. The gripper's command does not expire
  like a rate (a move ends on its stall or after ``pfma.gripper.MOVE_TIMEOUT_S``, a grip
  presses no harder than its force); a dead script stops it with the heartbeat.

Assumption (named once): the keep-alive thread needs the GIL every 3 ms; a script that
holds it more than about 10 ms (a long C call that does not release it) lets the heartbeat go stale and
the service trips to FAULT, which is the safe side.
"""

from __future__ import annotations

import atexit
import math
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

from bit3.client import Client, Snapshot
from bit3.layout import ServiceState, Severity, status_text
from bit3.seqlock import Bit3Error
from pfma.arm import GRIPPER, JOINTS, JointFacts
from pfma.gripper import (
    ACTIONS as GRIPPER_ACTIONS, COMPLETE, FAILED, MOVE_TIMEOUT_S, NOTE, REFUSED, GripperMotion, GripperRequest,
    GripperState, Outcome,
)
from pfma.rack import RackConfig, load_rack
from pfma.show import wrap_angle

#: a rate command lasts this long unless the script gives it again; then the keep-alive
#: sends zero rates (assumed: 0.3 s, long enough for a script that renews at 10-50 Hz,
#: short enough that a hung script moves a joint at most 0.3 s x its rate)
RATE_EXPIRY_S = 0.3
#: the keep-alive re-publishes the command area this often: about one service frame
#: (3.125 ms), so a stall of this process up to about 10 ms stays inside the service's
#: 15 ms watchdog (measured: about 2 % of a core on the 2-core dev VM)
KEEPALIVE_S = 0.003
#: how long :meth:`Rack.arm` waits for the service to say ARMED
ARM_WAIT_S = 1.0
#: how long :meth:`Rack.close` keeps the heartbeat going for the service to see the disarm
CLOSE_WAIT_S = 0.5
#: the keep-alive updates the gripper's motion this often while it moves or holds (as the
#: controller's gripper task: 40 Hz)
GRIPPER_UPDATE_S = 0.025


class RackError(Bit3Error):
    """A script's mistake or a refusal by the service, in one line."""


@dataclass(frozen=True)
class Reading:
    """One named input: its engineering value, units and status (``"ok"`` or what is wrong)."""

    name: str
    value: float
    units: str
    status: str

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def __str__(self) -> str:
        return f"{self.name} = {self.value:.4f} {self.units} ({self.status})"


class Inputs:
    """A copy of one frame of inputs with named, status-carrying readings."""

    def __init__(self, snap: Snapshot, state: ServiceState) -> None:
        self.snapshot = snap
        self.frame = int(snap.frame)
        self.t_s = float(snap.t_s)
        self.service_state = state  #: the service's state (a name: ``ServiceState.ARMED``)

    def __getitem__(self, signal: str) -> Reading:
        """A rack channel by its signal name, e.g. ``inputs["elbow_pitch_angle"]``."""
        try:
            c = self.snapshot.layout.channel(signal, "inputs")
        except KeyError:
            names = [c.name for c in self.snapshot.layout.channels
                     if c.area == "inputs" and c.kind in ("rtd", "adc") and not c.spare]
            raise RackError(f"no input {signal!r}; inputs: {', '.join(names)}") from None
        ch = self.snapshot.channel(signal)
        status = next((int(v) for k, v in ch.items() if k.endswith("_status")), 0)
        value = float(self.snapshot.value(signal))
        if c.kind == "rtd":  # the resolver's 0..2 pi in (-pi, pi], as every tool shows it (pfma/show.py)
            value = wrap_angle(value)
        return Reading(signal, value, c.units, status_text(c.kind, status))

    def _joint(self, kind: str, joint: str, quantity: str) -> Reading:
        try:
            entry = self.snapshot.layout.joint_entry(kind, joint, quantity)
        except KeyError as err:
            raise RackError(str(err).strip("'\"")) from None
        return self[entry.name]

    def angle(self, joint: str) -> Reading:
        """A joint's resolver angle (rad, in (-pi, pi]) with its status."""
        return self._joint("rtd", joint, "angle")

    def rate(self, joint: str) -> Reading:
        """A joint's tachometer rate (rad/s) with its status."""
        return self._joint("adc", joint, "rate")

    def current(self, joint: str) -> Reading:
        """A joint's motor current (A) with its status."""
        return self._joint("adc", joint, "motor_current")

    def __repr__(self) -> str:
        return f"<Inputs frame {self.frame} service {self.service_state.name}>"


class Rack:
    """The handle (see the module docstring). Use :meth:`open`, or wrap a :class:`Client`
    that owns the command area.

    :param client: a writer of the command area
    :param now: the clock rate expiry is judged on (default: ``time.monotonic``)
    :param sleep: how :meth:`sleep` and :meth:`arm` wait (a simulated rig passes its own)
    :param keepalive: start the keep-alive thread (tests on a simulated clock call
        :meth:`keepalive_step` themselves instead)
    :param say: where the handle's notes go (default: one line on stderr each)
    """

    def __init__(self, client: Client, *, rack: RackConfig | None = None,
                 now: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 keepalive: bool = True, say: Callable[[str], None] | None = None,
                 rate_expiry_s: float = RATE_EXPIRY_S) -> None:
        if client.role != "controller":
            raise RackError("the handle needs a client that owns the command area")
        self.client = client
        self.joints: tuple[str, ...] = tuple(client.layout.joint_names)
        self.facts: dict[str, JointFacts] = {j.name: j for j in JOINTS}
        rack = rack or load_rack(None)
        self._rate_limit: dict[str, float] = {}
        for name in self.joints:
            ch = rack.find(name, "rate_command")
            if ch is not None and ch.limit is not None:
                self._rate_limit[name] = float(ch.limit)
        #: current limits' own limits (A), in command order: the rack file's, as the service checks them
        self._current_max: list[float | None] = []
        for name in (*self.joints, "gripper"):
            ch = rack.find(name, "current_limit")
            self._current_max.append(float(ch.limit) if ch is not None and ch.limit is not None else None)
        self.rate_expiry_s = float(rate_expiry_s)
        self._now = now
        self._sleep = sleep
        self._say = say or (lambda text: print(f"rack: {text}", file=sys.stderr, flush=True))
        self._lock = threading.RLock()
        self._rates = [0.0] * len(self.joints)
        self._limits = [0.0] * len(client.command["current_limit_a"])
        self._rates_until = -math.inf
        self._said: set[tuple[str, str]] = set()  #: (joint, what) notes already said
        self.expired = 0  #: rate commands the keep-alive replaced by zero rates
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        # the gripper (pfma/gripper.py): its tach (volts on the default rack) and current channels
        self.gripper = GripperMotion()  #: the gripper's motion (state, force_n, jaw_m ...)
        self._grip_ch = self._gripper_channels(client)
        self._grip_t = -math.inf  # the last gripper update
        self._grip_last: Outcome | None = None  # the end of the last move
        self._publish(rates=self._rates, current_limit_a=self._limits, gripper=0.0, arm_request=0)
        if keepalive:
            self._thread = threading.Thread(target=self._keepalive_loop, name="rack-keepalive", daemon=True)
            self._thread.start()
            # a script that never calls close() (no ``with``) still disarms when it ends, not
            # by the service's watchdog tripping to FAULT
            atexit.register(self.close)

    @classmethod
    def open(cls, buffer: str = "pfma", *, owner: str = "python-script", rack: str | None = None,
             **kw: Any) -> "Rack":
        """Attach to the service on buffer ``buffer`` as the command writer ``owner``.

        :raises RackError: no service on that buffer, or another writer holds the commands
        """
        from bit3.buffer import Bit3Buffer
        alive, why = Bit3Buffer.owner_alive(buffer)
        if not alive:
            raise RackError(f"no I/O service runs on buffer {buffer!r} ({why}); start it with "
                            f"`pfma serve{'' if buffer == 'pfma' else ' --buffer ' + buffer}`")
        try:
            client = Client.attach(buffer, writer="commands", owner=owner, rack=rack)
        except Bit3Error as err:
            raise RackError(str(err)) from None
        try:
            return cls(client, rack=load_rack(rack), **kw)
        except BaseException:
            client.close()
            raise

    # --- what the script calls ----------------------------------------------------------

    @property
    def state(self) -> ServiceState:
        """The service's state by name (``ServiceState.ARMED``, ``.SAFE``, ``.FAULT`` ...)."""
        return ServiceState(self.client.service_state)

    def arm(self, current_limit_a: float | Iterable[float] | Mapping[str, float] = 0.0,
            wait_s: float = ARM_WAIT_S) -> None:
        """Arm the outputs: rates 0, these current limits (A; one number for every joint, a
        list in command order, or ``{joint: amps}``; 0 keeps a joint's brake set), a new
        re-arm number. Waits until the service is ARMED.

        :raises RackError: the service refused (its reason), or did not arm within ``wait_s``
        """
        limits = self._limit_list(current_limit_a)
        seen = self._last_service_seq()
        with self._lock:
            self._rates = [0.0] * len(self.joints)
            self._limits = limits
            counter = int(self.client.command["rearm_counter"]) + 1
            self._publish(rates=self._rates, current_limit_a=limits, gripper=0.0, arm_request=1,
                          rearm_counter=counter)
        self._check_limits_move()
        t_end = self._now() + wait_s
        while self.state != ServiceState.ARMED:
            if self._now() >= t_end:
                why = self._service_reason(seen)
                raise RackError(f"the service did not arm within {wait_s:g} s (state "
                                f"{self.state.name}){': ' + why if why else ''}")
            self._sleep(0.01)
        with self._lock:
            self.gripper.power(False, self._now())  # a new arming: the gripper starts STOPPED, limit as asked
            self.gripper.power(True, self._now())

    def rates(self, rates: Iterable[float] | Mapping[str, float] | None = None, **by_joint: float) -> None:
        """Command joint rates (rad/s): ``rates(elbow_pitch=0.05)``, ``rates({"wrist_roll": 0.4})``
        or a list in joint order; joints not named get 0. The command lasts
        :data:`RATE_EXPIRY_S` unless given again.

        :raises RackError: an unknown joint, a value that is not finite or is beyond the
            joint's rate limit, or a non-zero rate while the service is not ARMED (a trip:
            its reason is given); nothing is sent
        """
        values = self._per_joint(rates, by_joint, "rate")
        if any(values) and self.state != ServiceState.ARMED:
            why = self._service_reason(0, warnings_only=True)
            raise RackError(f"the service is {self.state}, not ARMED: rates not sent"
                            f"{' (' + why + ')' if why else ''}; rack.arm(...) arms it again")
        for name, v in zip(self.joints, values):
            lim = self._rate_limit.get(name)
            if lim is not None and abs(v) > lim:
                raise RackError(f"{name}: {v:g} rad/s is beyond its rate limit {lim:g} rad/s (nothing sent)")
        with self._lock:
            self._rates = values
            self._rates_until = self._now() + self.rate_expiry_s
            self._publish(rates=values)
        self._check_rates_move()

    def stop(self) -> None:
        """Zero rates now (stays armed)."""
        self.rates()

    def current_limits(self, limits: float | Iterable[float] | Mapping[str, float] | None = None,
                       **by_joint: float) -> None:
        """Command current limits (A): one number for every joint, a list in command order,
        ``{joint: amps}`` or keywords; the others keep theirs. A limit of 0 sets the brake."""
        if by_joint and limits is not None and not isinstance(limits, Mapping):
            raise RackError("give current limits as one value or list, or by joint name, not both")
        with self._lock:
            if by_joint or isinstance(limits, Mapping):
                merged = dict(zip(self.joints, self._limits))
                if len(self._limits) > len(self.joints):
                    merged["gripper"] = self._limits[len(self.joints)]
                if isinstance(limits, Mapping):
                    merged.update(limits)
                merged.update(by_joint)
                values = self._limit_list(merged)
            else:
                values = self._limit_list(0.0 if limits is None else limits)
            self._limits = values
            self._publish(current_limit_a=values)
        self._check_limits_move()

    def read(self) -> Inputs:
        """The newest frame of inputs (a copy), with named readings and their status."""
        return Inputs(self.client.read_inputs().copy(), self.state)

    def sleep(self, seconds: float) -> None:
        """Wait (the keep-alive holds the heartbeat; a rate command still expires)."""
        self._sleep(seconds)

    def disarm(self) -> None:
        """Rates 0, current limits 0 (brakes set), the gripper off, no arm request."""
        with self._lock:
            self._rates = [0.0] * len(self.joints)
            self._limits = [0.0] * len(self._limits)
            self._rates_until = -math.inf
            self.gripper.power(False, self._now())
            self._publish(rates=self._rates, current_limit_a=self._limits, gripper=0.0, arm_request=0)

    # --- the gripper (pfma/gripper.py) ---------------------------------------------------
    def gripper_open(self, force_n: float | None = None) -> str:
        """Open the jaw (``force_n``: a new grip force, N); the move ends at the open stop
        (:meth:`gripper_wait`). Returns the answer.

        :raises RackError: not ARMED, or the request refused (a force outside its range ...)
        """
        return self._gripper_request("open", force_n)

    def gripper_close(self, force_n: float | None = None) -> str:
        """Close the jaw; on contact it holds with the grip force (``force_n``, N; else the one
        in force: 40 N until set). Returns the answer; :meth:`gripper_wait` waits for the grip."""
        return self._gripper_request("close", force_n)

    def gripper_stop(self) -> str:
        """Stop the jaw (a grip is released)."""
        return self._gripper_request("stop", None)

    def gripper_force(self, force_n: float) -> str:
        """Set the grip force (N; the gripper's current limit at 40 N/A), in force at once."""
        return self._gripper_request("force", force_n)

    def gripper_wait(self, timeout_s: float = MOVE_TIMEOUT_S + 1.0) -> str:
        """Wait until the gripper's move ends; returns how (``"GRIPPING after 2.10 s: ..."``).

        :raises RackError: the move failed (the drive did not answer, no stall), or it did not
            end within ``timeout_s``
        """
        t_end = self._now() + timeout_s
        while self.gripper.moving:
            if self._now() >= t_end:
                raise RackError(f"the gripper is still {self.gripper.state.name} after {timeout_s:g} s")
            self._sleep(GRIPPER_UPDATE_S)
        last = self._grip_last
        if last is not None and last.code == FAILED:
            raise RackError(f"gripper: {last.text}")
        return last.text if last is not None else f"gripper {self.gripper.state.name}"

    @property
    def gripper_state(self) -> GripperState:
        """The gripper's state (``GripperState.GRIPPING`` ...)."""
        return self.gripper.state

    def close(self) -> None:
        """Disarm, stop the keep-alive, detach. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        try:
            self.disarm()
            # the heartbeat goes on until the service has seen the disarm: a writer that
            # stopped at once could be judged stale before the service's next frame
            t_end = self._now() + CLOSE_WAIT_S
            while self.state == ServiceState.ARMED and self._now() < t_end:
                self._sleep(0.005)
        finally:
            self._stop.set()
            if self._thread is not None:
                self._thread.join(timeout=1.0)
            self.client.close()

    def __enter__(self) -> "Rack":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the keep-alive ---------------------------------------------------------------

    def keepalive_step(self) -> None:
        """One keep-alive: expire an old rate command (zero rates, said once), update the
        gripper's motion (every :data:`GRIPPER_UPDATE_S` while it moves or holds), then publish
        the command area (a new heartbeat). The thread calls it every :data:`KEEPALIVE_S`."""
        with self._lock:
            if self._stop.is_set():  # detached (close() keeps the heartbeat until it sets this)
                return
            if self._gripper_update():
                return
            if self._now() >= self._rates_until and any(self._rates):
                self._rates = [0.0] * len(self.joints)
                self.expired += 1
                self._publish(rates=self._rates)
                self._say(f"rate command expired after {self.rate_expiry_s:g} s without renewal: "
                          f"rates set to 0 (give rack.rates() again within {self.rate_expiry_s:g} s "
                          f"to keep moving)")
                return
            self.client.publish_commands()

    def _keepalive_loop(self) -> None:
        while not self._stop.wait(KEEPALIVE_S):
            try:
                self.keepalive_step()
            except Exception as err:  # the buffer is gone: the service's watchdog makes it safe
                self._say(f"keep-alive stopped: {err}")
                return

    # --- helpers -----------------------------------------------------------------------

    @staticmethod
    def _gripper_channels(client: Client) -> tuple[int, float, int] | None:
        """(tach slot, m/s per unit, current slot) of the gripper, None without them."""
        lay = client.layout
        try:
            tach = lay.joint_entry("adc", "gripper", "rate")
            cur = lay.joint_entry("adc", "gripper", "motor_current")
        except KeyError:
            return None
        return tach.slot, (1.0 / GRIPPER.k_w_v_per_m_s if tach.units == "V" else 1.0), cur.slot

    def _gripper_request(self, action: str, force_n: float | None) -> str:
        kind = GRIPPER_ACTIONS[action]
        if kind in (GripperRequest.OPEN, GripperRequest.CLOSE) and self.state != ServiceState.ARMED:
            raise RackError(f"the service is {self.state}, not ARMED: gripper {action} not sent; rack.arm(...) first")
        if self._grip_ch is None:
            raise RackError("this rack has no gripper tach and current channels (joint gripper: rate, motor_current)")
        with self._lock:
            out = self.gripper.request(kind, force_n or 0.0, self._now())
            if out.code == REFUSED:
                raise RackError(f"gripper {action}: {out.text} (nothing sent)")
            if out.code == COMPLETE:
                self._grip_last = out
            self._gripper_publish()
        return out.text

    def _gripper_publish(self) -> None:
        g = self.gripper
        if len(self._limits) > len(self.joints) and g.powered:
            self._limits[len(self.joints)] = g.current_limit_a
        self._publish(gripper=g.rate_cmd_m_s * GRIPPER.k_w_v_per_m_s, current_limit_a=self._limits)

    def _gripper_update(self) -> bool:
        """The keep-alive's gripper sample (under the lock); True when it published."""
        g = self.gripper
        if self._grip_ch is None or g.state not in (GripperState.OPENING, GripperState.CLOSING,
                                                     GripperState.GRIPPING, GripperState.CLOSED):
            return False
        t = self._now()
        if t - self._grip_t < GRIPPER_UPDATE_S - 1e-9:
            return False
        self._grip_t = t
        if self.state != ServiceState.ARMED:  # tripped or disarmed under the script: the drive is off
            out = g.power(False, t)
        else:
            tach, scale, cur = self._grip_ch
            adc = self.client.read_inputs().record["adc_value"]
            before = (g.rate_cmd_m_s, g.current_limit_a)
            out = g.update(t, float(adc[tach]) * scale, float(adc[cur]))
            if (g.rate_cmd_m_s, g.current_limit_a) != before:
                self._gripper_publish()
                if out is not None:
                    self._gripper_outcome(out)
                return True
        if out is not None:
            self._gripper_outcome(out)
        return False

    def _gripper_outcome(self, out: Outcome) -> None:
        if out.code != NOTE:
            self._grip_last = out
        if out.code in (FAILED, NOTE):
            self._say(f"gripper: {out.text}")

    def _publish(self, rates: list[float] | None = None, **fields: Any) -> None:
        if rates is not None:
            fields["joint_rate_rad_s"] = rates
        self.client.write_commands(**fields)

    def _per_joint(self, values: Iterable[float] | Mapping[str, float] | None, by_joint: Mapping[str, float],
                   what: str) -> list[float]:
        out = [0.0] * len(self.joints)
        named = dict(values) if isinstance(values, Mapping) else {}
        named.update(by_joint)
        if values is not None and not isinstance(values, Mapping):
            seq = [float(v) for v in values]
            if len(seq) != len(self.joints):
                raise RackError(f"{len(seq)} {what}s given, {len(self.joints)} joints: "
                                f"{', '.join(self.joints)}")
            out = seq
        for name, v in named.items():
            if name not in self.joints:
                raise RackError(f"no joint {name!r}; joints: {', '.join(self.joints)}")
            out[self.joints.index(name)] = float(v)
        for name, v in zip(self.joints, out):
            if not math.isfinite(v):
                raise RackError(f"{name}: {what} {v!r} is not finite (nothing sent)")
        return out

    def _limit_list(self, limits: float | Iterable[float] | Mapping[str, float]) -> list[float]:
        n = len(self.client.command["current_limit_a"])
        if isinstance(limits, (int, float)):
            out = [float(limits)] * len(self.joints) + [0.0] * (n - len(self.joints))
        elif isinstance(limits, Mapping):
            out = list(self._per_joint(None, {k: v for k, v in limits.items() if k in self.joints},
                                       "current limit"))
            out += [float(limits.get("gripper", 0.0))] + [0.0] * (n - len(self.joints) - 1)
            extra = set(limits) - set(self.joints) - {"gripper"}
            if extra:
                raise RackError(f"no joint {sorted(extra)[0]!r}; joints: {', '.join(self.joints)}, gripper")
        else:
            out = [float(v) for v in limits]
            if len(out) == len(self.joints):
                out += [0.0] * (n - len(out))
            if len(out) != n:
                raise RackError(f"{len(out)} current limits given: {len(self.joints)} joints "
                                f"(or {n} with the gripper)")
        names = (*self.joints, "gripper")
        for i, v in enumerate(out[:n]):
            what = names[i] if i < len(names) else f"current limit {i}"
            if not math.isfinite(v) or v < 0:
                raise RackError(f"{what}: current limit {v!r} A: a limit is a finite number >= 0 (nothing sent)")
            top = self._current_max[i] if i < len(self._current_max) else None
            if top is not None and v > top:
                raise RackError(f"{what}: current limit {v:g} A is beyond its limit {top:g} A (nothing sent)")
        return out[:n]

    def _note_once(self, joint: str, what: str, text: str) -> None:
        if (joint, what) not in self._said:
            self._said.add((joint, what))
            self._say(text)

    def _check_rates_move(self) -> None:
        for name, u, lim in zip(self.joints, self._rates, self._limits):
            jf = self.facts.get(name)
            if jf is None or u == 0.0:
                continue
            if lim <= 0.0:
                self._note_once(name, "brake", f"{name}: current limit 0 A (brake set): a rate "
                                f"command will not move it; give rack.current_limits({name}=...)")
            elif abs(u) <= jf.breakaway_rate_rad_s:
                self._note_once(name, "breakaway", f"{name}: {abs(u):g} rad/s is below its breakaway rate "
                                f"{jf.breakaway_rate_rad_s:.3g} rad/s (Coulomb friction {jf.coulomb_nm:g} "
                                f"N*m, nominal arm model): the joint will not move from rest")

    def _check_limits_move(self) -> None:
        for name, lim in zip(self.joints, self._limits):
            jf = self.facts.get(name)
            if jf is not None and 0.0 < lim <= jf.breakaway_current_a:
                self._note_once(name, "current", f"{name}: current limit {lim:g} A is below its "
                                f"breakaway current {jf.breakaway_current_a:.3g} A (Coulomb friction "
                                f"{jf.coulomb_nm:g} N*m, nominal arm model): the joint will not move from rest")

    def _last_service_seq(self) -> int:
        msgs = self.client.messages(0, "service")
        return msgs[-1].seq if msgs else 0

    def _service_reason(self, since_seq: int, warnings_only: bool = False) -> str:
        """The service's newest message since ``since_seq`` (a WARNING or worse if asked)."""
        msgs = self.client.messages(since_seq, "service")
        if warnings_only:
            msgs = [m for m in msgs if m.severity >= Severity.WARNING]
        return msgs[-1].text if msgs else ""

    def __repr__(self) -> str:
        return f"<Rack {self.client.buffer.name} {self.state.name}>"
