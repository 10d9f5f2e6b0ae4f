"""Data Acquisition (layer 7): the bridge between the world model and the Bit3 buffer.

IRSS report 2.2.1: "the layer through which all I/O data (other than user keyboard
input) comes ... This layer also controls the DACs that command joint motions and
control motor current limits." Here the I/O chassis is the data-acquisition service
(:mod:`ioservice`); this layer talks to it only through
:class:`bit3.client.Client`:

* **acquire** (first thing in every minor frame, before the communications segment):
  the service's latest input snapshot -> world-model variables ``daq.*`` (resolver
  angles unwrapped to each joint's range, tach rates, F/T, hand controllers, service
  state and brake/arm bits), and the hardware checks -> the layer's fault flag;
* **output** (right after the decision tables): ``servo.rate_cmd_rad_s`` and
  ``servo.current_limit_cmd_a`` -> ``write_commands`` with a new heartbeat every
  minor frame. Rates are forced to 0 unless the layer is START UP COMPLETE, and
  everything is 0 (arm request off) while SHUT DOWN.

Hardware checks (``daq.fault_bits``; any of them, once the layer is initialised,
raises its fault flag, which its decision table turns into ERROR in the same frame):

=====  ======================================================================
bit    meaning
=====  ======================================================================
1      resolver fault on a joint channel (loss of signal / BIT, no reference,
       or the board did not answer)
2      tach ADC sample failed (bus error)
4      F/T link stale or faulted for FT_BAD_FRAMES frames in a row while the wrench
       drives the arm (impedance control on, or CRL force reflection); otherwise one
       WARNING says the force data are not valid and the arm goes on (disable the
       check entirely with ``require_ft=False``)
8      a board the controller needs reports a fault (bus error, init failure)
16     the service is STOPPED, or in FAULT while this layer requests the outputs, or not
       ARMED while it should be
32     the service has not published a new frame for ``STALE_FRAMES`` frames
64     the service refused this controller's command: its ``command_status``
       shows stale inputs (rates driven at 0 V because the command was computed
       from inputs older than the service's ``max_input_age_frames``), a refused
       value, or a foreign writer; or its stale/refused/foreign counters went up
       since the last frame (a refusal between two controller frames)
128    no servo output: the servo's rates were not there for the current servo
       period in more than STALE_OUTPUT_RUN frames in a row, so this layer sent 0 V
       (its own output check, not a reading; an event, so it stays until the layer's
       command is ERROR RESET)
=====  ======================================================================

Freshness of the rate commands (docs/controller.md, "Missed frames and command
freshness"): every write carries ``inputs_frame`` (the service frame of the inputs the
rates were computed from: the servo's stamp ``servo.rate_cmd_frame``, or this frame for
zero rates, which depend on no inputs) and ``controller_frame`` (this layer's write
counter). A servo output is sent only if it belongs to the current servo period
(:attr:`LayerContext.servo_oldest_frame`); otherwise the rates are 0 and it is this layer's
own fault (bit 128, no servo output), reported through its status like the hardware checks
(report 2.3.2: a layer never sets another's flag) - except in the
one frame that catches up a servo slot missed with the controller's frame
(:attr:`LayerContext.servo_catch_up`), which sends 0 rates without a fault.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from controller.decision import Command, Status, TaskState
from controller.force import FORCE
from controller.gripper import GRIP
from controller.layers import ERR_INVALID_VALUE, ERROR_NAMES, UI, Layer
from controller.messages import Level
from controller.relays import at
from controller.params import GRIPPER, JOINTS, N_CURRENT_LIMITS, N_JOINTS
from controller.servo import SERVO
from controller.teleop import TELEOP
from controller.variables import (  # noqa: F401  (the fault bits re-exported)
    DAQ, FAULT_BOARD, FAULT_COMMAND, FAULT_FT, FAULT_NAMES, FAULT_NO_OUTPUT, FAULT_RESOLVER, FAULT_SERVICE,
    FAULT_STALE, FAULT_TACH,
)
from controller.worldmodel import VarSpec, WorldModelValueError
from controller.routes import box_selections, route_text, set_monitor
from bit3.layout import (
    BOARD_FAULT, CHANNEL_BUS_ERROR, CMD_FOREIGN, CMD_REFUSED, CMD_STALE, CMD_STATUS_NAMES, HAND_CONTROLLERS, LINK_FAULT, LINK_STALE, MODE_HALTED, ServiceState,
)

if TYPE_CHECKING:  # pragma: no cover
    from controller.context import LayerContext
    from bit3.client import Client
    from bit3.layout import ChannelEntry, Layout

_PI, _TAU = math.pi, 2 * math.pi

#: command_status bits that make FAULT_COMMAND (CMD_ABSENT is the service keeping the last
#: good copy of a torn write: the heartbeat watchdog covers a writer that stopped)
COMMAND_FAULT_STATUS = CMD_STALE | CMD_REFUSED | CMD_FOREIGN
#: the service's counters of refused commands (inputs area), with what each one counts
COMMAND_COUNTERS = (("stale_commands", "stale"), ("refused_commands", "refused"), ("foreign_writes", "foreign"))
#: controller frames without a new service frame before the service counts as lost
STALE_FRAMES = 4
#: a host stall "explains" an F/T gap when it lasted at least this fraction of the gap
#: (assumed: half; the rest is the sensor's period and the resync after the stall)
STALL_EXPLAINS = 0.5
#: consecutive frames the service must flag the F/T link stale/faulted before it counts
#: (assumed: 4 frames = 12.5 ms on top of the service's 100 ms stale age, so that one late
#: record on a busy host does not stop the arm; a dead link still trips in 62.5 ms)
FT_BAD_FRAMES = 4
#: time the init task waits for healthy inputs, the start-up task for ARMED (assumed)
INIT_TIMEOUT_S = 0.5
ARM_TIMEOUT_S = 0.2
#: time the shut-down task waits for the servo's safe stop (current limits 0) before
#: disarming anyway (assumed: the servo's 0.5 s safe stop plus margin)
SHUTDOWN_WAIT_S = 1.0
#: frames in a row whose servo output is not of the current servo period, each sent as 0 V,
#: before it is this layer's fault (bit 128): as many as the controller may miss in a row
#: (frames.DEFAULT_MAX_MISSED_RUN; assumed: a burst of late inputs after a host or link
#: stall sends 0 V for a frame or two, a servo that stays behind stops the arm)
STALE_OUTPUT_RUN = 2
#: boards whose faults matter to the controller (the rest are reported only)


#: what Data Acquisition reads of the layers further up, as Servo Control passes it on
#: (controller/relays.py): the force loop's state and the reflection to the hand controller
#: (the Cartesian engine's), the operator's camera route request (System Up/Down's)
FORCE_STATE, REFLECT_ENABLED, REFLECT_FORCE, REFLECT_TORQUE, ROUTE_REQUEST, ROUTE_REQUEST_SEQ = (
    at("daq", n) for n in (FORCE.state, TELEOP.reflect_enabled, TELEOP.reflect_force_n,
                           TELEOP.reflect_torque_nm, UI.route_request, UI.route_request_seq))


class DataAcquisitionLayer(Layer):
    """Data Acquisition (layer 7, the bottom).

    :param client: a Client attached as the command writer of the service's buffer
    :param require_ft: a stale F/T link is a fault (True on the simulated rack)
    """

    key = "daq"
    title = "Data Acquisition"
    short = "DAQ "
    #: other layers' variables read (controller/neighbours.py; the far ones are listed there)
    reads = (
        "gripper.rate_cmd_m_s", "servo.current_limit_cmd_a", "servo.error", "servo.force_state",
        "servo.rate_cmd_frame", "servo.rate_cmd_rad_s", "servo.teleop_reflect_enabled",
        "servo.teleop_reflect_force_n", "servo.teleop_reflect_torque_nm", "servo.updown_route_request",
        "servo.updown_route_request_seq",
    )
    #: ``daq.error``: the lowest hardware-check bit that tripped (FAULT_NAMES), or every layer's
    error_names = {**ERROR_NAMES, **FAULT_NAMES}

    def __init__(self, client: "Client", require_ft: bool = True) -> None:
        super().__init__()
        self.client = client
        self.require_ft = require_ft
        lay = client.layout
        servo_entries = self._map_joints(lay)
        self._acq: dict = {}  # the acquire post, refilled every frame (same keys, same order)
        self._map_gripper(lay)
        self._map_boards(lay, servo_entries, require_ft)
        self.monitoring = False  #: faults count once initialised
        self.fault_bits = 0
        self.fault_detail = ""
        self.no_output = ""  #: the latched "no servo output" event (its text), until ERROR RESET
        self.snapshot = None
        self._last_frame = -1
        self._same_frames = 0
        self._ft_bad_run = 0
        self.ft_in_use = True  #: force control or force reflection uses the F/T (see _force_in_use)
        self._force_vars: tuple[str, ...] | None = None
        self._ft_warned = False
        self._ft_warning = ""
        self._invalid_said = ""  # the refused-input text last reported (said once, not every frame)
        self._stalls = np.zeros((8, 2))  #: the last 8 host stalls the service published: end time, length (s)
        self._stall_n = 0
        self._stall_seen_t = 0.0
        self.arm_request = 0
        self.rearm_counter = int(client.command["rearm_counter"])
        self._t_phase = 0.0
        self._phase = 0
        self.writes = 0  #: command writes (the controller_frame stamp of the next write)
        self._cmd_counts: list[int] | None = None  # the service's refusal counters last frame
        self._svc_msg_seq = 0  # newest service message looked at for a refusal's reason
        self._zeros = np.zeros(N_JOINTS)
        self._zero_limits = np.zeros(N_CURRENT_LIMITS)
        self._zero3 = np.zeros(3)
        if getattr(client, "role", None) == "controller":
            # a claimed command area the service has never seen written looks like a foreign
            # writer's: publish a safe command (0 rates, 0 limits, no arm request) at once
            client.write_commands(joint_rate_rad_s=self._zeros, gripper=0.0, current_limit_a=self._zero_limits,
                                  arm_request=0, controller_frame=0)
        #: the runtime is halted (docs/console.md): every write is the halted safe command
        self.halted = False
        self.stale_outputs = 0  #: frames whose servo output was not of the current servo period
        self._stale_run = 0  # such frames in a row (0 V each; a fault beyond STALE_OUTPUT_RUN)
        self.catch_up_zeros = 0  #: frames with 0 rates while a missed servo slot was caught up
        self.sent_input_frame = -1  #: inputs_frame of the last write
        # camera routes (docs/cameras.md): this layer is the one writer of commands.matrix_route;
        # it starts from what the command area holds (0, both monitors blank, on a new buffer)
        self.route = int(client.command["matrix_route"])  #: the route this layer commands
        self._route_dirty = False  # the route changed: the next write carries it
        self._box_word = -1  # the user I/F box word last looked at
        self._box_sel: tuple[int | None, ...] = (None, None)  # each monitor's box selection
        self._route_req_seq = 0  # the newest console route request applied (updown.route_request_seq)
        self._route_applied = -1  # the service's applied route last posted
        self._has_route_req: bool | None = None

    def _map_joints(self, lay: "Layout") -> list["ChannelEntry"]:
        """The joints' channels by their role in the rack (channel keys joint, quantity): the
        slots of the angles, tachs and motor currents. Returns the entries the servo depends
        on (angles, tachs, rate commands, in that order) for :meth:`_map_boards`."""
        self.joint_order = tuple(lay.joint_names)
        if self.joint_order != tuple(j.name for j in JOINTS):
            raise ValueError(f"Bit3 command joints {self.joint_order} differ from controller.params "
                             f"{tuple(j.name for j in JOINTS)}")
        angles = [lay.joint_entry("rtd", j, "angle") for j in self.joint_order]
        tachs = [lay.joint_entry("adc", j, "rate") for j in self.joint_order]
        currents = [lay.joint_entry("adc", j, "motor_current") for j in self.joint_order]
        rates = [lay.joint_entry("dac", j, "rate_command") for j in self.joint_order]
        self.rtd_slots = np.array([e.slot for e in angles], dtype=np.intp)
        self.tach_slots = np.array([e.slot for e in tachs], dtype=np.intp)
        self.current_slots = np.array([e.slot for e in currents], dtype=np.intp)
        self.centre = np.array([j.centre_rad for j in JOINTS])
        self._joint_centres = tuple((k, float(c)) for k, c in zip(self.rtd_slots.tolist(), self.centre.tolist()))
        return angles + tachs + rates

    def _map_gripper(self, lay: "Layout") -> None:
        """The gripper (controller/gripper.py): its tach (volts on the default rack: converted
        with the nominal 10 V / omega_fs) and motor current; None where the rack has no such
        channel."""
        self.gripper_tach_slot, self.gripper_current_slot = self._gripper_slot(lay, "rate"), \
            self._gripper_slot(lay, "motor_current")
        self.gripper_tach_scale = 1.0 / GRIPPER.k_w_v_per_m_s if self._gripper_units(lay, "rate") == "V" else 1.0
        self.gripper_cmd_scale = GRIPPER.k_w_v_per_m_s  #: volts per m/s of the gripper command (DAC channel 6)

    def _map_boards(self, lay: "Layout", servo_entries: list["ChannelEntry"], require_ft: bool) -> None:
        """The boards the servo depends on: those carrying ``servo_entries`` (the joints'
        angles, tachs and rate commands), and the F/T sensor's serial board when force
        sensing is required; and the F/T link's slot (None: the rack has none)."""
        ft = next((c for c in lay.channels if c.kind == "link" and c.quantity == "force_torque"), None)
        need = list(dict.fromkeys(e.board for e in servo_entries))
        if require_ft and ft is not None:
            need.append(ft.board)
        self.board_slots = np.array([lay.slot("board", b) for b in need], dtype=np.intp)
        self.board_names = need
        self.ft_slot = ft.slot if ft is not None else None

    def specs(self) -> list[VarSpec]:
        return self.state_specs() + DAQ.specs()

    # --- acquire -------------------------------------------------------------------------
    def acquire(self, rt: "LayerContext") -> int:
        """Read the service's inputs, post them, run the hardware checks. Returns the
        service frame number of the inputs."""
        snap = self.client.read_inputs()
        self.snapshot = snap
        frame = int(snap.frame)
        rt.frame = frame  # messages of this frame carry its number
        if frame == self._last_frame:
            self._same_frames += 1
        else:
            self._same_frames = 0
            self._last_frame = frame
        rec = snap.record  # the client's preallocated copy: fields read directly, not by name lookup
        # unwrapped to each joint's range in plain Python (six floats: cheaper than numpy's
        # small-array calls; Python's float % is numpy's mod, so the values are the same)
        ang = rec["rtd_angle_rad"].tolist()
        q = [c + (ang[k] - c + _PI) % _TAU - _PI for k, c in self._joint_centres]
        st = int(rec["service_state"])
        nh = len(HAND_CONTROLLERS)
        out = self._acq
        out[DAQ.joint_angle_rad] = q
        adc = rec["adc_value"]
        out[DAQ.joint_rate_rad_s] = adc[self.tach_slots]
        out[DAQ.motor_current_a] = adc[self.current_slots]
        out[DAQ.ft_force_n] = rec["ft_force_n"]
        out[DAQ.ft_torque_nm] = rec["ft_torque_nm"]
        out[DAQ.hc_axes] = rec["hc_axes"][:nh]
        out[DAQ.hc_deadman] = rec["hc_deadman"][:nh].astype(bool)
        if self.gripper_tach_slot is not None:
            out[DAQ.gripper_rate_m_s] = adc[self.gripper_tach_slot] * self.gripper_tach_scale
        if self.gripper_current_slot is not None:
            out[DAQ.gripper_current_a] = adc[self.gripper_current_slot]
        out[DAQ.service_frame] = frame
        out[DAQ.service_state] = st
        out[DAQ.brakes_released] = bool(rec["brakes_released"])
        out[DAQ.outputs_enabled] = bool(rec["outputs_enabled"])
        invalid = ""
        try:
            rt.wm.post_task_outputs("daq", out)
        except WorldModelValueError as err:  # rule 4: not posted, the inputs keep their last valid values
            invalid = f"inputs refused: {err}"
        self.ft_in_use = self._force_in_use(rt)
        self._camera_routes(rt, rec)
        if self.no_output and rt.wm.get_state_variable(self.v_command) == Command.ERROR_RESET:
            rt.post(self.key, Level.INFO, "error reset: no servo output was an event; cleared")
            self.no_output = ""
        bits, detail = self.check(snap, st)
        if self._ft_warning:
            rt.post(self.key, Level.WARNING, f"{self._ft_warning}: force data not valid (force control off: "
                                             f"the arm goes on)")
            self._ft_warning = ""
        if bits != self.fault_bits:
            names = [n for b, n in FAULT_NAMES.items() if bits & b]
            rt.wm.post_task_outputs("daq", {DAQ.fault_bits: bits})
            if bits:
                rt.post(self.key, Level.WARNING if not self.monitoring else Level.ERROR,
                        f"hardware check: {', '.join(names)}: {detail}")
            else:
                rt.post(self.key, Level.INFO, "hardware checks clear")
        self.fault_bits, self.fault_detail = bits, detail
        if self.monitoring and bits:
            code = next(b for b in FAULT_NAMES if bits & b)
            self.set_fault(rt, code, detail)
        elif self.monitoring and invalid:  # a published input outside its valid range: a fault, named
            self.set_fault(rt, ERR_INVALID_VALUE, invalid)
        elif self.fault and not bits and not invalid:
            self.clear_fault(rt)  # the flag follows the hardware; ERROR itself is latched by the table
        if invalid and invalid != self._invalid_said and not self.monitoring:
            rt.post(self.key, Level.WARNING, invalid)
        self._invalid_said = invalid
        return frame

    # --- camera routes (docs/cameras.md) ------------------------------------------------------
    def _camera_routes(self, rt: "LayerContext", rec) -> None:
        """The user I/F box's switches and the console's route requests -> the route this
        layer writes to ``commands.matrix_route`` (with the next command write). A box
        selection acts when it changes (controller/routes.py); a console request arrives
        from System Up/Down's request task (``updown.route_request``, passed on by the layers
        between: ``servo.updown_route_request``)."""
        word = int(rec["pio_user_inputs"])
        route = self.route
        if word != self._box_word:
            first = self._box_word < 0
            self._box_word = word
            sel = box_selections(word)
            for m, (cam, was) in enumerate(zip(sel, self._box_sel), 1):
                if cam is not None and cam != was:
                    route = set_monitor(route, m, cam)
            self._box_sel = sel
            rt.wm.post_task_outputs("daq", {DAQ.user_inputs: word, DAQ.camera_route: self.route} if first
                                    else {DAQ.user_inputs: word})
            if route != self.route:
                self._set_route(rt, route, "user I/F box")
        if self._has_route_req is None:
            self._has_route_req = ROUTE_REQUEST_SEQ in set(rt.wm.names())
        if self._has_route_req:
            seq = int(rt.wm.get(ROUTE_REQUEST_SEQ))
            if seq != self._route_req_seq:
                self._route_req_seq = seq
                monitor, camera = divmod(int(rt.wm.get(ROUTE_REQUEST)), 16)
                try:
                    self._set_route(rt, set_monitor(self.route, monitor, camera), f"console request {seq}")
                except ValueError as err:  # System Up/Down checked it; a bad one is a message, not a crash
                    rt.post(self.key, Level.WARNING, f"console request {seq}: {err}")
        applied = int(rec["matrix_route"])
        if applied != self._route_applied:
            self._route_applied = applied
            rt.wm.post_task_outputs("daq", {DAQ.camera_route_applied: applied})

    def _set_route(self, rt: "LayerContext", route: int, why: str) -> None:
        self.route = route
        self._route_dirty = True
        rt.wm.post_task_outputs("daq", {DAQ.camera_route: route})
        rt.post(self.key, Level.INFO, f"camera route {route_text(route)} ({why})")

    def _route_field(self, fields: dict) -> dict:
        """``fields`` plus ``matrix_route`` when the route changed since the last write."""
        if not self._route_dirty:
            return fields
        self._route_dirty = False
        return {**fields, "matrix_route": self.route}

    def status_value(self, rt) -> int:
        return rt.wm.get_state_variable(self.v_status)

    def _force_in_use(self, rt) -> bool:
        """The wrench drives the arm now: impedance control (``force.state`` not OFF) or
        force reflection to the CRL. A stale F/T link is then a fault; otherwise it only
        makes the force data invalid (a WARNING), so a host stall that starves the F/T line
        for 100 ms does not stop an arm that is not using it. Without the force layer's
        variables (a bare runtime) the F/T is taken to be in use."""
        if self._force_vars is None:  # which of them this model has: looked up once, not every frame
            names = set(rt.wm.names())
            self._force_vars = tuple(n for n in (FORCE_STATE, REFLECT_ENABLED) if n in names)
        if FORCE_STATE not in self._force_vars:
            return True
        v = rt.wm.get_task_inputs(self._force_vars)
        return int(v[FORCE_STATE]) != 0 or bool(v.get(REFLECT_ENABLED, False))

    def _note_stalls(self, rec) -> None:
        """Keep each host stall the service publishes (its measured length and end time; the
        inputs area holds only the latest, so a short stall after a long one would hide it)."""
        t_end = float(rec["host_stall_t_s"])
        if t_end != self._stall_seen_t:  # a new stall (rare): nothing allocated otherwise
            self._stall_seen_t = t_end
            dur = float(rec["host_stall_s"])
            if dur > 0:
                row = self._stalls[self._stall_n % len(self._stalls)]
                row[0], row[1] = t_end, dur
                self._stall_n += 1

    def service_dropped(self, t_from: float, t_to: float, period_s: float) -> int:
        """Frames the service itself did not run between two frames it published at
        ``t_from`` and ``t_to`` (service clock): those of every host stall it measured that
        ended in (t_from, t_to], a stall of d seconds dropping int(d / period) frames
        (issue 29 item 1: the controller is not charged with frames the service never
        published)."""
        if self.snapshot is not None:  # the stall of this very frame may not be noted yet
            self._note_stalls(self.snapshot.record)
        n = min(self._stall_n, len(self._stalls))
        dropped = 0
        for t_end, dur in self._stalls[:n]:
            if t_from < t_end <= t_to + period_s:
                dropped += int(float(dur) / period_s)
        return dropped

    def _stall_note(self, t_s: float, age_s: float) -> str:
        """What the measured host stalls say about an F/T gap of ``age_s`` seen at ``t_s``:
        " after a host stall of N ms" when the longest stall that overlapped the gap covers
        at least STALL_EXPLAINS of it; "; a host stall of N ms in that time does not explain
        it" when it is shorter; "" when the service measured none in the gap. Never a stall
        the gap did not contain (issue 29 item 8: a 1,045 ms gap was blamed on a 17 ms stall)."""
        n = min(self._stall_n, len(self._stalls))
        longest = 0.0
        for t_end, dur in self._stalls[:n]:
            if t_end <= t_s and t_end > t_s - age_s:  # it ended inside the gap
                longest = max(longest, float(dur))
        if longest <= 0:
            return ""
        if longest >= STALL_EXPLAINS * age_s:
            return f" after a host stall of {longest * 1e3:.0f} ms"
        return f"; a host stall of {longest * 1e3:.0f} ms in that time does not explain it"

    def check(self, snap, service_state: int) -> tuple[int, str]:
        """The hardware checks of one snapshot: (fault bits, description)."""
        bits, why = 0, []
        rec = snap.record
        self._note_stalls(rec)
        rs = rec["rtd_status"][self.rtd_slots]
        if rs.any():
            bits |= FAULT_RESOLVER
            why += [f"{self.joint_order[i]} resolver status 0x{int(rs[i]):X}" for i in np.nonzero(rs)[0]]
        ts = rec["adc_status"][self.tach_slots]
        if (ts & CHANNEL_BUS_ERROR).any():
            bits |= FAULT_TACH
            why.append("tach ADC sample failed")
        if self.require_ft and self.ft_slot is not None:
            ls = int(rec["link_status"][self.ft_slot])
            bad = bool(ls & (LINK_STALE | LINK_FAULT) or not ls)
            self._ft_bad_run = self._ft_bad_run + 1 if bad else 0
            if self._ft_bad_run >= FT_BAD_FRAMES:
                age = float(rec["link_age_s"][self.ft_slot])  # measured by the service
                what = (f"F/T link {'stale' if ls & LINK_STALE else 'faulted' if ls & LINK_FAULT else 'not open'}"
                        f" (age {age * 1e3:.0f} ms){self._stall_note(float(rec['t_s']), age)}")
                if self.ft_in_use:
                    bits |= FAULT_FT
                    why.append(what)
                elif not self._ft_warned:  # nothing uses the wrench now: force data invalid, arm fine
                    self._ft_warned = True
                    self._ft_warning = what
            elif not bad:
                self._ft_warned = False
        bs = rec["board_status"][self.board_slots]
        if (bs & BOARD_FAULT).any():
            bits |= FAULT_BOARD
            why += [f"board {self.board_names[i]} fault (errors {int(snap.board_errors[self.board_slots[i]])})"
                    for i in np.nonzero(bs & BOARD_FAULT)[0]]
        # a service in FAULT matters while this layer wants the outputs; once it has withdrawn
        # its arm request (the safe task), the latched FAULT only waits for the next arm
        # request (power up's start-up task): else an error reset could never finish. While
        # that request is on its way (start-up phase 1: sent, not yet answered; a link's
        # latency or a command that landed after the service's next frame began), FAULT is
        # the last episode's, not a new one: the start-up task times out after ARM_TIMEOUT_S
        # naming the state (tests/controller/test_arm_latency.py)
        if service_state == ServiceState.STOPPED or \
                (service_state == ServiceState.FAULT and self.arm_request and self._phase != 1) or \
                (self.arm_request and self._phase == 2 and service_state != ServiceState.ARMED
                 and not (self.halted and service_state == ServiceState.HALTED)):
            bits |= FAULT_SERVICE
            why.append(f"service {ServiceState(service_state).name}")
        if self._same_frames >= STALE_FRAMES:
            bits |= FAULT_STALE
            why.append(f"service frame {self._last_frame} unchanged for {self._same_frames} frames")
        cmd = self._command_check(snap)
        if cmd:
            bits |= FAULT_COMMAND
            why.append(cmd)
        if self.no_output:
            bits |= FAULT_NO_OUTPUT
            why.append(self.no_output)
        return bits, "; ".join(why)

    def _command_check(self, snap) -> str:
        """The service's verdict on our commands: '' when it took them, else its reason."""
        rec = snap.record
        cs = int(rec["command_status"]) & COMMAND_FAULT_STATUS
        counts = [int(rec[f]) for f, _ in COMMAND_COUNTERS]
        last, self._cmd_counts = self._cmd_counts, counts
        if not cs and (last is None or counts == last):  # the healthy frame: nothing refused, no counter up
            return ""
        up = [(n, c - c0) for (_, n), c, c0 in zip(COMMAND_COUNTERS, counts, last or counts) if c > c0]
        if not cs and not up:
            return ""
        parts = [CMD_STATUS_NAMES[b] for b in (CMD_STALE, CMD_REFUSED, CMD_FOREIGN) if cs & b]
        parts += [f"{n} +{d}" for n, d in up if n not in parts]
        text = (f"service: command {', '.join(parts)} (computed from inputs frame {int(snap.command_inputs_frame)}, "
                f"{int(snap.command_input_age_frames)} frames old)")
        reason = self._service_reason()
        return f"{text}: {reason}" if reason else text

    def _service_reason(self) -> str:
        """The newest WARNING/ERROR the service posted since the last look (only read when
        a refusal is seen, never in a healthy frame)."""
        try:
            msgs = self.client.messages(self._svc_msg_seq, "service")
        except Exception:  # noqa: BLE001 - the reason is a courtesy
            return ""
        if msgs:
            self._svc_msg_seq = msgs[-1].seq
        bad = [m for m in msgs if int(m.severity) >= 2]
        return bad[-1].text if bad else ""

    @staticmethod
    def _gripper_slot(lay, quantity: str) -> int | None:
        try:
            return lay.joint_entry("adc", "gripper", quantity).slot
        except KeyError:
            return None

    @staticmethod
    def _gripper_units(lay, quantity: str) -> str:
        try:
            return lay.joint_entry("adc", "gripper", quantity).units
        except KeyError:
            return ""

    # --- output --------------------------------------------------------------------------
    _OUT = (SERVO.rate_cmd_rad_s, SERVO.rate_cmd_frame, SERVO.current_limit_cmd_a, "servo.error",
            GRIP.rate_cmd_m_s)

    def output(self, rt: "LayerContext", status: int) -> None:
        """Write this frame's commands with a new heartbeat, ``inputs_frame`` and
        ``controller_frame``.

        Zero rates depend on no inputs: they carry this frame (``rt.frame``). Servo rates
        carry the servo's stamp and are sent only while START UP COMPLETE and only if the
        stamp is at least :attr:`LayerContext.servo_oldest_frame` (this frame minus the
        servo divider: the output of its latest slot) and the servo reports no error;
        otherwise the rates are 0 and, unless this frame catches up a missed servo slot or
        the servo already has a fault, it is this layer's own (bit 128, latched: the table
        reads it next frame)."""
        frame = rt.frame
        if self.halted:  # a single step while halted: the outputs stay in the halted safe state
            self.hold_output(frame)
            return
        rates, stamp, grip = self._zeros, frame, 0.0
        if status == Status.SHUT_DOWN:
            limits = self._zero_limits
        else:
            v = rt.wm.get_task_inputs(self._OUT)
            limits = v[SERVO.current_limit_cmd_a]
            if status in (Status.INITIALIZATION_IN_PROGRESS, Status.INITIALIZATION_COMPLETE, Status.START_UP):
                limits = self._zero_limits
            if status == Status.START_UP_COMPLETE:
                s = int(v[SERVO.rate_cmd_frame])
                servo_ok = not int(v["servo.error"])  # the neighbour's own report, not its flag
                if servo_ok:  # the seventh amplifier (controller/gripper.py)
                    grip = float(v[GRIP.rate_cmd_m_s]) * self.gripper_cmd_scale
                if s < 0:
                    self._stale_run = 0  # a sequence task's constant zero (a new start-up)
                elif s >= rt.servo_oldest_frame and servo_ok:
                    rates, stamp = v[SERVO.rate_cmd_rad_s], s
                    self._stale_run = 0
                elif rt.servo_catch_up and servo_ok:
                    self.catch_up_zeros += 1  # the missed slot runs in this frame: 0 for one frame
                else:
                    self.stale_outputs += 1
                    self._stale_run += 1
                    if servo_ok and not self.no_output and self._stale_run > STALE_OUTPUT_RUN:
                        self.no_output = (f"no servo output for the servo period of frame {rt.servo_oldest_frame} "
                                          f"at frame {frame}: the last was computed from frame {s} "
                                          f"({frame - s} frames old); rates 0")
                        self.set_fault(rt, FAULT_NO_OUTPUT, self.no_output)
        reflect = self._reflection(rt, status)
        self.client.write_commands(joint_rate_rad_s=rates, gripper=grip, current_limit_a=limits,
                                   arm_request=self.arm_request, rearm_counter=self.rearm_counter,
                                   inputs_frame=stamp, controller_frame=self.writes, **self._route_field(reflect))
        self.sent_input_frame = stamp
        self.writes += 1

    # --- halted (IRSS halt / single step, docs/console.md) ---------------------------------
    def hold_acquire(self, rt: "LayerContext"):
        """Between frames while halted: read the service's newest inputs (not posted: the
        world model keeps the halted frame's values) so that the hold follows the service's
        frames and a later step does not count the halted frames as missed or stale.
        Returns the snapshot."""
        snap = self.client.read_inputs()
        self.snapshot = snap
        self._last_frame = int(snap.frame)
        self._same_frames = 0
        return snap

    def hold_output(self, frame: int, resume: bool = False) -> None:
        """The halted safe command with a new heartbeat: 0 rates, 0 current limits (brakes
        set), no CRL force, ``mode`` HALTED and no arm request; the service holds HALTED
        without a watchdog trip. ``resume``: the resume's command instead (mode cleared, and
        if this layer had armed the outputs, an arm request with its ``rearm_counter``, which
        the runtime has made new; still 0 rates and limits)."""
        self.client.write_commands(joint_rate_rad_s=self._zeros, gripper=0.0, current_limit_a=self._zero_limits,
                                   arm_request=self.arm_request if resume else 0, rearm_counter=self.rearm_counter,
                                   mode=0 if resume else MODE_HALTED, inputs_frame=frame,
                                   controller_frame=self.writes, **self._route_field(self._no_reflection()))
        self.sent_input_frame = frame
        self.writes += 1

    def _no_reflection(self) -> dict:
        if "crl_reflect_enable" not in (self.client.command.dtype.names or ()):
            return {}
        return {"crl_reflect_force_n": self._zero3, "crl_reflect_torque_nm": self._zero3, "crl_reflect_enable": 0}

    _REFLECT = (REFLECT_FORCE, REFLECT_TORQUE, REFLECT_ENABLED)

    def _reflection(self, rt: "LayerContext", status: int) -> dict:
        """CRL force reflection (the Cartesian engine's teleop output) for the command area;
        zero and disabled unless the layer is START UP COMPLETE. The service sends it to the
        CRL only while armed."""
        if getattr(self, "_has_reflect", None) is None:
            self._has_reflect = self._REFLECT[0] in rt.wm.names()
        if not self._has_reflect:
            return {}
        v = rt.wm.get_task_inputs(self._REFLECT)
        on = status == Status.START_UP_COMPLETE and bool(v[REFLECT_ENABLED])
        zero = self._zero3  # write_commands copies it into the command record
        return {"crl_reflect_force_n": v[REFLECT_FORCE] if on else zero,
                "crl_reflect_torque_nm": v[REFLECT_TORQUE] if on else zero,
                "crl_reflect_enable": int(on)}

    # --- sequence tasks ------------------------------------------------------------------
    def seq_init(self, rt: "LayerContext") -> TaskState:
        """Wait (at most INIT_TIMEOUT_S) for a SAFE service with clean hardware checks (or
        one still in FAULT from before an error reset: the start-up's new arm request is its
        explicit re-arm)."""
        if self.task_frames == 0:
            self._t_phase = rt.now
        st = int(self.snapshot.service_state) if self.snapshot is not None else -1
        # halted (a power-up stepped frame by frame): the service holds HALTED for us, safe
        safe = st in (ServiceState.SAFE, ServiceState.FAULT) or (self.halted and st == ServiceState.HALTED)
        if safe and not self.fault_bits:
            self.monitoring = True
            return TaskState.DONE
        if rt.now - self._t_phase > INIT_TIMEOUT_S:
            why = self.fault_detail or f"service state {st}"
            self.set_fault(rt, FAULT_SERVICE if not self.fault_bits else self.fault_bits & -self.fault_bits,
                           f"inputs not healthy after {INIT_TIMEOUT_S} s: {why}")
            return TaskState.FAILED
        return TaskState.RUNNING

    def seq_startup(self, rt: "LayerContext") -> TaskState:
        """Arm the service: a new arm request with all rates 0; wait for ARMED (at most
        ARM_TIMEOUT_S). While the runtime is halted (a power-up single-stepped) the outputs
        stay in the halted safe state: the arm request waits for the resume's explicit
        re-arm (``pfma controller resume --rearm``), and the time-out counts from the first
        frame after it."""
        if self.task_frames == 0:
            self.rearm_counter += 1
            self.arm_request = 1
            self._phase = 1
            self._t_phase = rt.now
            if self.halted:
                rt.post(self.key, Level.INFO, "START UP: halted, so the outputs stay safe; arming waits for "
                                              "resume --rearm (console: a, then r)")
            return TaskState.RUNNING
        if self.halted:
            self._t_phase = rt.now
            return TaskState.RUNNING
        if int(self.snapshot.service_state) == ServiceState.ARMED:
            self._phase = 2
            rt.post(self.key, Level.INFO, f"service ARMED (request {self.rearm_counter}) after "
                                          f"{(rt.now - self._t_phase) * 1e3:.1f} ms")
            return TaskState.DONE
        if rt.now - self._t_phase > ARM_TIMEOUT_S:
            rt.post(self.key, Level.ERROR, f"service did not arm within {ARM_TIMEOUT_S} s "
                                           f"(state {ServiceState(int(self.snapshot.service_state)).name})")
            return TaskState.FAILED
        return TaskState.RUNNING

    def seq_shutdown(self, rt: "LayerContext") -> TaskState:
        """Keep bridging until the servo's safe stop has set the current limits to 0 (or
        SHUTDOWN_WAIT_S), then withdraw the arm request (the service goes SAFE: 0 V)."""
        if self.task_frames == 0:
            self._t_phase = rt.now
        if self.arm_request:
            limits = np.asarray(rt.wm.get(SERVO.current_limit_cmd_a), dtype=float)
            if np.any(limits != 0) and rt.now - self._t_phase < SHUTDOWN_WAIT_S:
                return TaskState.RUNNING
            self.arm_request = 0
            self._phase = 0
            rt.post(self.key, Level.INFO, f"arm request withdrawn after {(rt.now - self._t_phase) * 1e3:.1f} ms")
        self.monitoring = self.status_value(rt) == Status.ERROR  # an error stays monitored
        return TaskState.DONE

    def seq_safe(self, rt: "LayerContext") -> TaskState:
        return self.seq_shutdown(rt)

    def seq_reset(self, rt: "LayerContext") -> TaskState:
        if self.fault_bits:
            return TaskState.RUNNING  # the table refuses a reset while the fault is present
        self.monitoring = False
        self.clear_fault(rt)
        return TaskState.DONE
