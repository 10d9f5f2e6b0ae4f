"""Shared pieces of the world-model tests: specs, unique shm names, spawned-process bodies
(spawned children import this module, so everything here is module level)."""

from __future__ import annotations

import hashlib
import json
import mmap
import os
import struct
import time
import uuid

import numpy as np

from controller.worldmodel import (
    HEADER_FIELDS,
    PENDING,
    SLOT_FIELDS,
    SLOT_HEADER,
    VarSpec,
    WorldModel,
)


def unique_name() -> str:
    return f"pfma_wmt{os.getpid()}_{uuid.uuid4().hex[:8]}"


def sample_specs() -> list[VarSpec]:
    """One or more variables in every area, the shapes and types a controller uses."""
    return [
        VarSpec("servo.q_cmd_rad", "task_io", "f8", (6,), "trajectory", [0.0] * 6, "rad",
                doc="joint position command to the servo layer"),
        VarSpec("servo.q_rad", "task_io", "f8", (6,), "servo", [0.0, 0.1, 0.2, 0.3, 0.4, 0.5], "rad",
                doc="measured joint angles"),
        VarSpec("servo.integrator", "task_status", "f8", (6,), "servo", [0.0] * 6, "rad*s",
                doc="position-loop integrator state (recorded, not a task input)"),
        VarSpec("updown.command", "command_input", "i2", (), "user_interface", 0,
                doc="command to the System Up/Down layer"),
        VarSpec("updown.status", "status_output", "i2", (), "updown", 0,
                doc="System Up/Down layer status"),
        VarSpec("servo.kp_1_s", "control_flags", "f8", (6,), "user", [10.0] * 6, "1/s", protected=True,
                doc="position-loop gains (control-law parameter)"),
        VarSpec("hc.enable", "control_flags", "b1", (), "user", False, user="always",
                doc="hand controller connected to the arm"),
        VarSpec("servo.frames", "response_output", "u4", (), "servo", 0, doc="servo frames run"),
        VarSpec("servo.error_code", "error_reports", "i4", (), "servo", 0, doc="last servo error (0 none)"),
        VarSpec("tool.T_base", "task_io", "f4", (4, 4), "kinematics", np.eye(4).tolist(), "m",
                doc="tool frame in base coordinates"),
    ]


# ----------------------------------------------------------------------------------------
# bodies of spawned processes


TORN_SPECS_N = 512


def torn_specs() -> list[VarSpec]:
    return [VarSpec("big", "task_io", "f8", (TORN_SPECS_N,), "w1", [0.0] * TORN_SPECS_N),
            VarSpec("small", "status_output", "i4", (64,), "w2", [0] * 64),
            VarSpec("count", "response_output", "i8", (), "w1", 0)]


def flat_out_owner(name: str, started, stop, max_s: float, result) -> None:
    """Create the model and run communications segments as fast as possible; in frame k
    every element of every variable equals k (self-consistent frames)."""
    wm = WorldModel.create(torn_specs(), name=name, owner="flat-out-writer")
    big = np.zeros(TORN_SPECS_N)
    small = np.zeros(64, np.int32)
    k = 0
    t_end = time.monotonic() + max_s  # bound: never outlive the test
    try:
        while not stop.is_set() and time.monotonic() < t_end:
            for _ in range(100):
                k += 1
                big[:] = k
                small[:] = k
                wm.post_task_outputs("w1", {"big": big, "count": k})
                wm.post_task_outputs("w2", {"small": small})
                wm.communications_segment()
            if k == 200:
                started.set()
    finally:
        result.put(k)
        wm.close()
        wm.unlink()


def inspect_model(name: str, conn) -> None:
    """Attach from another process and send back what the segment says (no specs given)."""
    wm = WorldModel.attach(name)
    try:
        conn.send({"names": wm.names(),
                   "specs": [s.to_json() for s in wm.specs],
                   "values": {n: np.asarray(v).tolist() for n, v in wm.snapshot().items()},
                   "frame": wm.frame, "powered_up": wm.powered_up, "owner": wm.info().owner,
                   "owner_pid": wm.info().owner_pid})
        if conn.poll(20.0):  # parent asks for a user write from this process
            name_, value, key = conn.recv()
            try:
                conn.send(("ok", wm.set_user(name_, value, key)))
            except Exception as err:
                conn.send(("error", f"{type(err).__name__}: {err}"))
    finally:
        wm.close()


def forge_request(name: str, var: str, value, key: str, user: str = "forger") -> int:
    """Write a user request straight into segment ``name``'s request ring, as any process
    that can map /dev/shm/<name> could, using only the documented layout (header fields,
    spec JSON, slot fields) and skipping every check ``set_user`` makes. Returns its id."""
    fd = os.open(f"/dev/shm/{name}", os.O_RDWR)
    try:
        mm = mmap.mmap(fd, 0)
    finally:
        os.close(fd)
    try:
        def hget(fld):
            off, fmt = HEADER_FIELDS[fld]
            return struct.unpack_from("<" + fmt, mm, off)[0]

        doc = json.loads(mm[hget("spec_offset"):hget("spec_offset") + hget("spec_len")])
        i = [v["name"] for v in doc["variables"]].index(var)
        raw = np.asarray(value, dtype=doc["variables"][i]["dtype"]).tobytes()
        rid = hget("req_next_id") + 1
        base = hget("req_offset") + (rid - 1) % hget("req_slots") * hget("req_slot_size")
        for fld, v in (("var_index", i), ("req_id", rid), ("submit_ns", time.time_ns()),
                       ("pid", os.getpid()), ("nbytes", len(raw)), ("applied_frame", 0),
                       ("key_hash", hashlib.sha256(hget("key_salt") + key.encode()).digest()),
                       ("user", user.encode()), ("result", b"")):
            off, fmt = SLOT_FIELDS[fld]
            struct.pack_into("<" + fmt, mm, base + off, v)
        mm[base + SLOT_HEADER:base + SLOT_HEADER + len(raw)] = raw
        struct.pack_into("<I", mm, base + SLOT_FIELDS["state"][0], PENDING)
        struct.pack_into("<Q", mm, HEADER_FIELDS["req_next_id"][0], rid)
        return rid
    finally:
        mm.close()
