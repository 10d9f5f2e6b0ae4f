"""Bit3 buffer benchmark: seqlock cost, torn-read fuzz, write-to-visible latency.

Prints figures (asserts nothing); the targets are perf-limits.md section 8:

- consistent write and read of a whole 32 KB region: median <= 3 us each and within
  3x a plain 32 KB copy measured in the same run;
- zero torn reads against a flat-out writer in another process;
- write -> spin-polling reader in another process: p50 <= 50 us, p99 <= 500 us, and
  >= 3x better than a multiprocessing Pipe or a Unix socket carrying the same bytes.

Timing uses ``time.perf_counter_ns`` (CLOCK_MONOTONIC, comparable across processes on
Linux). Default run about 12 s; ``run(quick=True)`` / ``--quick`` about 4 s.
"""

from __future__ import annotations

import multiprocessing
import os
import socket
import time
import uuid

import numpy as np

from bit3.layout import SEQ_BLOCK
from bit3.buffer import Bit3Buffer, SeqLock

REGION = 32768


def _pct(ns: np.ndarray) -> dict:
    if len(ns) == 0:
        return {"p50_us": float("nan"), "p99_us": float("nan"), "max_us": float("nan"), "n": 0}
    p50, p99 = np.percentile(ns, [50, 99])
    return {"p50_us": p50 / 1e3, "p99_us": p99 / 1e3, "max_us": float(ns.max()) / 1e3, "n": len(ns)}


def _timer_overhead_ns(n: int = 20000) -> float:
    pc = time.perf_counter_ns
    d = np.empty(n, np.int64)
    for i in range(n):
        t0 = pc()
        d[i] = pc() - t0
    return float(np.median(d))


def _time_op(op, n: int, overhead: float) -> np.ndarray:
    pc = time.perf_counter_ns
    d = np.empty(n, np.int64)
    for _ in range(min(n, 1000)):  # warm up
        op()
    for i in range(n):
        t0 = pc()
        op()
        d[i] = pc() - t0
    return np.maximum(d - overhead, 0)


def _region(name: str, create: bool):
    from multiprocessing import resource_tracker, shared_memory
    shm = shared_memory.SharedMemory(name, create=create, size=SEQ_BLOCK + REGION if create else 0)
    resource_tracker.unregister(shm._name, "shared_memory")  # see bit3/buffer.py
    return shm


def _unlink(name: str) -> None:
    from multiprocessing import shared_memory
    shared_memory._posixshmem.shm_unlink("/" + name)  # the tracker was told to forget it


# --- 1. cost per operation ------------------------------------------------------------

def micro(n: int) -> dict:
    """Seqlocked 32 KB write/read against a plain 32 KB copy, same process, same run."""
    name = f"pfma_bench_{uuid.uuid4().hex[:8]}"
    shm = _region(name, True)
    try:
        lock = SeqLock(shm.buf, 0, REGION, "bench32k")
        src_b, dst_b = bytearray(os.urandom(REGION)), bytearray(REGION)
        src, dst = memoryview(src_b), memoryview(dst_b)
        a, b = np.frombuffer(src_b, np.uint8), np.frombuffer(dst_b, np.uint8)
        ov = _timer_overhead_ns()

        def plain() -> None:
            dst[:] = src

        def npcopy() -> None:
            np.copyto(b, a)

        out = {"timer_overhead_ns": ov,
               "plain_copy": _pct(_time_op(plain, n, ov)),
               "np_copyto": _pct(_time_op(npcopy, n, ov)),
               "seqlock_write": _pct(_time_op(lambda: lock.write(src), n, ov)),
               "seqlock_read": _pct(_time_op(lambda: lock.read_into(dst), n, ov))}
        del lock, src, dst, a, b
    finally:
        shm.close()
        _unlink(name)
    base = out["plain_copy"]["p50_us"]
    out["write_ratio"] = out["seqlock_write"]["p50_us"] / base
    out["read_ratio"] = out["seqlock_read"]["p50_us"] / base
    # the real areas through the public classes
    bname = f"pfma_bench_{uuid.uuid4().hex[:8]}"
    buf = Bit3Buffer.create(bname)
    try:
        buf.claim("service", "bench")
        buf.claim("controller", "bench")
        for area in ("inputs", "commands"):
            w, r = buf.writer(area), buf.reader(area)
            out[f"{area}_publish"] = _pct(_time_op(w.publish, n, ov))
            out[f"{area}_read"] = _pct(_time_op(r.read, n, ov))
            out[f"{area}_bytes"] = w.area.body_size
            del w, r
    finally:
        buf.close(unlink=True)
    return out


# --- 2. torn-read fuzz ----------------------------------------------------------------

def _fuzz_writer(name: str, started, stop, max_s: float) -> None:
    shm = _region(name, False)
    lock = SeqLock(shm.buf, 0, REGION, "fuzz")
    lock.take_over()
    src_b = bytearray(REGION)
    src = memoryview(src_b)
    words = np.frombuffer(src_b, np.uint64)
    n = 0
    end = time.monotonic() + max_s
    while not stop.is_set() and time.monotonic() < end:
        for _ in range(100):
            n += 1
            words[:] = n
            lock.write(src)
        started.set()
    del lock, src, words
    shm.close()


def fuzz(seconds: float, ctx) -> dict:
    """Flat-out writer process; this process reads with the seqlock, then without it."""
    name = f"pfma_bench_{uuid.uuid4().hex[:8]}"
    shm = _region(name, True)
    started, stop = ctx.Event(), ctx.Event()
    p = ctx.Process(target=_fuzz_writer, args=(name, started, stop, seconds * 2 + 10), daemon=True)
    p.start()
    res = {}
    try:
        started.wait(30)
        lock = SeqLock(shm.buf, 0, REGION, "fuzz", timeout_s=1.0)
        dst_b = bytearray(REGION)
        dst = memoryview(dst_b)
        words = np.frombuffer(dst_b, np.uint64)
        reads = torn = 0
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            for _ in range(200):
                lock.read_into(dst)
                reads += 1
                if words[0] != words[-1] or words.min() != words.max():
                    torn += 1
        res["seqlock"] = {"reads": reads, "torn": torn, "retries": lock.retries,
                          "retries_per_read": lock.retries / max(reads, 1)}
        body = shm.buf[SEQ_BLOCK:SEQ_BLOCK + REGION]
        reads = torn = 0
        end = time.monotonic() + min(seconds, 1.0)
        while time.monotonic() < end:
            for _ in range(200):
                dst[:] = body
                reads += 1
                if words.min() != words.max():
                    torn += 1
        body.release()
        res["unprotected"] = {"reads": reads, "torn": torn}
        del lock, dst, words
    finally:
        stop.set()
        p.join(30)
        if p.is_alive():
            p.kill()
        shm.close()
        _unlink(name)
    return res


# --- 3. write -> visible latency ------------------------------------------------------

def _shm_reader(name: str, max_s: float, ready, out) -> None:
    """Spin-poll the inputs area; a stamp of 0 ends the run (a missed publish is not waited for)."""
    buf = Bit3Buffer.attach(name)
    r = buf.reader("inputs")
    stamp = np.frombuffer(r.raw, np.uint64, count=1)  # "frame" carries the writer's t_ns
    lat = []
    pc = time.perf_counter_ns
    r.read()
    ready.set()
    end = time.monotonic() + max_s
    while time.monotonic() < end:
        for _ in range(1000):
            if r.changed():
                break
        else:
            continue
        r.read()
        t = int(stamp[0])
        if t == 0:
            break
        lat.append(pc() - t)
    out.send_bytes(np.asarray(lat, np.int64).tobytes())
    del r, stamp
    buf.close()


def _stream_reader(recv_into, max_s: float, size: int, ready, out) -> None:
    b = bytearray(size)
    stamp = np.frombuffer(b, np.uint64, count=1)
    lat = []
    pc = time.perf_counter_ns
    ready.set()
    end = time.monotonic() + max_s
    while time.monotonic() < end:
        recv_into(b)
        t = int(stamp[0])
        if t == 0:
            break
        lat.append(pc() - t)
    out.send_bytes(np.asarray(lat, np.int64).tobytes())


def _pipe_reader(conn, max_s: float, size: int, ready, out) -> None:
    _stream_reader(conn.recv_bytes_into, max_s, size, ready, out)


def _sock_reader(sock, max_s: float, size: int, ready, out) -> None:
    _stream_reader(sock.recv_into, max_s, size, ready, out)


def latency(n: int, ctx, period_s: float = 0.001) -> dict:
    """Publisher at about 1 kHz here; reader in a child process records arrival - stamp."""
    res = {}
    name = f"pfma_bench_{uuid.uuid4().hex[:8]}"
    buf = Bit3Buffer.create(name)
    max_s = n * period_s * 5 + 10
    try:
        buf.claim("service", "bench-latency")
        w = buf.writer("inputs")
        size = w.area.body_size
        stamp = np.frombuffer(w.raw, np.uint64, count=1)
        pc = time.perf_counter_ns

        def drive(send, target, args) -> np.ndarray:
            ready, (back, out) = ctx.Event(), ctx.Pipe(duplex=False)
            full = (*args, max_s, ready, out) if target is _shm_reader else (*args, max_s, size, ready, out)
            child = ctx.Process(target=target, args=full, daemon=True)
            child.start()
            try:
                ready.wait(30)
                for _ in range(n):
                    time.sleep(period_s)
                    stamp[0] = pc()
                    send()
                for _ in range(3):  # end marker (repeated: a spin reader may miss one publish)
                    time.sleep(period_s)
                    stamp[0] = 0
                    send()
                data = back.recv_bytes() if back.poll(max_s + 10) else b""
                child.join(30)
            finally:
                if child.is_alive():
                    child.kill()
            return np.frombuffer(data, np.int64)

        res["shm_spin_poll"] = _pct(drive(w.publish, _shm_reader, (name,)))
        rx, tx = ctx.Pipe(duplex=False)
        payload = memoryview(w.raw)
        res["pipe"] = _pct(drive(lambda: tx.send_bytes(payload), _pipe_reader, (rx,)))
        s1, s2 = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        s1.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 * size)
        res["unix_seqpacket"] = _pct(drive(lambda: s1.send(payload), _sock_reader, (s2,)))
        s1.close()
        s2.close()
        del w, stamp, payload
        res["payload_bytes"] = size
    finally:
        buf.close(unlink=True)
    shm = res["shm_spin_poll"]
    for k in ("pipe", "unix_seqpacket"):
        res[f"{k}_ratio_p50"] = res[k]["p50_us"] / shm["p50_us"] if shm["p50_us"] else float("nan")
        res[f"{k}_ratio_p99"] = res[k]["p99_us"] / shm["p99_us"] if shm["p99_us"] else float("nan")
    return res


# --- report ---------------------------------------------------------------------------

def run(quick: bool = False, seconds: float | None = None) -> dict:
    """Measure and print; returns the figures. ``quick``: about 4 s instead of about 12 s.
    ``seconds`` (from ``pfma bench --seconds``): below 5 s means quick."""
    if seconds is not None:
        quick = quick or seconds < 5
    ctx = multiprocessing.get_context("spawn")
    n_ops = 5000 if quick else 20000
    fuzz_s = 1.0 if quick else 3.0
    n_lat = 500 if quick else 2000
    out = {"micro": micro(n_ops), "fuzz": fuzz(fuzz_s, ctx), "latency": latency(n_lat, ctx)}

    m = out["micro"]
    print(f"Bit3 buffer benchmark ({'quick' if quick else 'default'}; {os.cpu_count()} CPUs; "
          f"timer overhead {m['timer_overhead_ns']:.0f} ns subtracted)")
    print(f"{'operation (32 KB unless noted)':36} {'p50 us':>8} {'p99 us':>8}  notes")
    for key, label, note in (
            ("plain_copy", "plain copy (memoryview)", "reference"),
            ("np_copyto", "np.copyto", ""),
            ("seqlock_write", "seqlock write", f"{m['write_ratio']:.2f}x plain (goal <= 3x, <= 3 us)"),
            ("seqlock_read", "seqlock read (copy + validate)", f"{m['read_ratio']:.2f}x plain (goal <= 3x, <= 3 us)"),
            ("inputs_publish", f"inputs publish ({m['inputs_bytes']} B)", "AreaWriter + heartbeat"),
            ("inputs_read", f"inputs read ({m['inputs_bytes']} B)", "AreaReader"),
            ("commands_publish", f"commands publish ({m['commands_bytes']} B)", ""),
            ("commands_read", f"commands read ({m['commands_bytes']} B)", "")):
        print(f"{label:36} {m[key]['p50_us']:8.2f} {m[key]['p99_us']:8.2f}  {note}")
    f = out["fuzz"]
    print(f"torn-read fuzz, flat-out writer process, {fuzz_s:g} s: {f['seqlock']['reads']} seqlocked reads, "
          f"{f['seqlock']['torn']} torn (goal 0), {f['seqlock']['retries_per_read']:.2f} retries/read; "
          f"without the lock {f['unprotected']['torn']} of {f['unprotected']['reads']} torn")
    lat = out["latency"]
    print(f"write -> visible, {n_lat} messages of {lat['payload_bytes']} B at ~1 kHz, reader in another process:")
    print(f"{'transport':28} {'p50 us':>8} {'p99 us':>8} {'max us':>9}")
    for key, label in (("shm_spin_poll", "Bit3 shm, spin-poll reader"), ("pipe", "multiprocessing Pipe"),
                       ("unix_seqpacket", "Unix SOCK_SEQPACKET")):
        r = lat[key]
        extra = "" if key == "shm_spin_poll" else \
            f"  {lat[key + '_ratio_p50']:.1f}x / {lat[key + '_ratio_p99']:.1f}x shm (p50/p99; goal >= 3x)"
        print(f"{label:28} {r['p50_us']:8.1f} {r['p99_us']:8.1f} {r['max_us']:9.1f}{extra}"
              f"  ({r['n']} received)")
    print("goal for shm: p50 <= 50 us, p99 <= 500 us (perf-limits.md 8, tier A)")
    return out
