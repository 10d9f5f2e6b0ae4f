"""An independent reader of the Bit3 buffer: standard library only, layout from JSON.

It knows nothing of the project's code: it is given the published layout (the output
of ``pfma layout --json``, saved to a file) and the shared-memory name, and follows
docs/bit3-layout.md "Attaching without the project's code": map /dev/shm/NAME
read-only, check the magic and layout hash, copy an area between two equal even
sequence counts, decode fields from the copy. It measures how often each input is
refreshed from the sample times (``t_rtd_s``, ``t_adc_s``, ``t_ft_s``, ``t_dac_s``)
and, for readers that poll slower than a device, from the stats area's
``device_samples`` counters.

    pfma layout --json > /tmp/layout.json
    pfma serve --rack fake --duration 12 --buffer pfma &
    python bench/independent_reader.py /tmp/layout.json --buffer pfma --seconds 10

Nothing here imports ``pfma``, ``ioservice`` or numpy (that is the point of it).
"""

from __future__ import annotations

import argparse
import json
import mmap
import os
import struct
import sys
import time

#: sample-time field -> the rate the IRSS schedule gives it (report 3.4.3)
SAMPLE_TIMES = {"t_rtd_s": 160.0, "t_adc_s": 160.0, "t_ft_s": 80.0, "t_dac_s": 320.0}
#: device slots in stats.device_samples (docs/bit3-layout.md, "What refreshes when")
DEVICE_SLOTS = {"rtd": 0, "adc": 1, "dac": 2, "ft": 3}


class LayoutMismatch(Exception):
    """The buffer is not the layout this reader was given."""


class IndependentReader:
    """Reads fields of a Bit3 buffer described by a layout JSON document.

    :param layout: the parsed ``pfma layout --json`` document
    :param path: the shared-memory file (``/dev/shm/NAME``)
    """

    def __init__(self, layout: dict, path: str, max_retries: int = 100000) -> None:
        self.layout = layout
        self.max_retries = max_retries
        self.areas = {a["name"]: a for a in layout["areas"]}
        self.fields = {(f["area"], f["name"]): f for f in layout["fields"]}
        fd = os.open(path, os.O_RDONLY)
        try:
            self.mem = mmap.mmap(fd, layout["size"], mmap.MAP_SHARED, mmap.PROT_READ)
        finally:
            os.close(fd)
        magic = self.mem[0:8]
        if magic != layout["magic"].encode():
            raise LayoutMismatch(f"{path}: magic {magic!r}, expected {layout['magic']!r}")
        h = self.fields[("header", "layout_hash")]
        got = self.mem[h["offset"]: h["offset"] + h["nbytes"]].hex()
        if got != layout["hash"]:
            raise LayoutMismatch(f"{path}: layout hash {got}, expected {layout['hash']}")
        self.retries = 0

    def close(self) -> None:
        self.mem.close()

    def copy_area(self, area: str) -> bytes:
        """One consistent copy of ``area``'s body (sequence lock, bounded retries)."""
        a = self.areas[area]
        lo, hi, seq_at = a["body_offset"], a["body_offset"] + a["body_size"], a["offset"]
        mem = self.mem
        for _ in range(self.max_retries):
            s1 = struct.unpack_from("<Q", mem, seq_at)[0]
            if s1 & 1:
                self.retries += 1
                continue
            body = mem[lo:hi]
            if struct.unpack_from("<Q", mem, seq_at)[0] == s1:
                return body
            self.retries += 1
        raise TimeoutError(f"area {area}: no stable copy in {self.max_retries} tries (writer died mid-write?)")

    def field(self, body: bytes, area: str, name: str):
        """Decode ``name`` from a copy of ``area``'s body (scalars and flat arrays)."""
        f = self.fields[(area, name)]
        code = {"<f8": "d", "<u8": "Q", "<i8": "q", "<f4": "f", "<u4": "I", "<i4": "i",
                "<u2": "H", "<i2": "h", "|u1": "B", "|i1": "b"}[f["dtype"]]
        n = 1
        for d in f["shape"]:
            n *= d
        vals = struct.unpack_from(f"<{n}{code}", body, f["offset"] - self.areas[area]["body_offset"])
        return vals[0] if not f["shape"] else list(vals)


class ServiceStalled(RuntimeError):
    """The service stopped publishing before the measurement was complete."""


def measure(reader: IndependentReader, step, seconds: float, stall_s: float = 2.0,
            wall=time.monotonic) -> dict:
    """Poll the inputs after each ``step()`` for ``seconds`` of the service clock; return
    the refresh rate of each sample time and each device counter.

    ``step`` is whatever lets time pass: a short sleep against a live service, one
    simulated frame in a test.

    :raises ServiceStalled: the inputs' time stood still for ``stall_s`` of wall-clock
        time (the service stopped or hangs) - rather than waiting for ever; ``wall`` is
        that clock
    """
    seen: dict[str, list[float]] = {k: [] for k in SAMPLE_TIMES}
    stats0 = None
    t_start = None
    t_last, wall_last = None, wall()
    while True:
        step()
        body = reader.copy_area("inputs")
        t_now = reader.field(body, "inputs", "t_s")
        if t_now != t_last:
            t_last, wall_last = t_now, wall()
        elif wall() - wall_last > stall_s:
            got = 0.0 if t_start is None else t_now - t_start
            raise ServiceStalled(f"the service's inputs have not changed for {stall_s:g} s "
                                 f"(service stopped?) after {got:.1f} of {seconds:g} s measured")
        if t_start is None:
            t_start = t_now
            st = reader.copy_area("stats")
            stats0 = (reader.field(st, "stats", "t_s"), reader.field(st, "stats", "device_samples"))
        for name, times in seen.items():
            t = reader.field(body, "inputs", name)
            if t > 0 and (not times or t != times[-1]):
                times.append(t)
        if t_now - t_start >= seconds:
            break
    st = reader.copy_area("stats")
    stats1 = (reader.field(st, "stats", "t_s"), reader.field(st, "stats", "device_samples"))
    out = {}
    for name, times in seen.items():
        # drop the first change (it may be older than the start); rate over the changes seen
        ts = times[1:]
        out[name] = (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 2 and ts[-1] > ts[0] else 0.0
    dt = stats1[0] - stats0[0]
    for dev, slot in DEVICE_SLOTS.items():
        out[f"stats.{dev}"] = (stats1[1][slot] - stats0[1][slot]) / dt if dt > 0 else 0.0
    out["retries"] = reader.retries
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("layout", help="the output of 'pfma layout --json', saved to a file")
    p.add_argument("--buffer", default="pfma", help="shared-memory name (default pfma)")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--poll-s", type=float, default=0.0002, help="sleep between reads")
    a = p.parse_args(argv)
    with open(a.layout) as f:
        layout = json.load(f)
    r = IndependentReader(layout, f"/dev/shm/{a.buffer}")
    try:
        res = measure(r, lambda: time.sleep(a.poll_s), a.seconds)
    except ServiceStalled as err:
        print(f"independent reader: {err}", file=sys.stderr)
        return 2
    finally:
        r.close()
    print(f"independent reader, {a.seconds:g} s of /dev/shm/{a.buffer} (layout {layout['hash']}):")
    ok = True
    for name, want in SAMPLE_TIMES.items():
        dev = name[2:-2]
        got, by_stats = res[name], res[f"stats.{dev}"]
        within = abs(got - want) <= 0.01 * want
        ok &= within
        print(f"  {name:8s} refreshed at {got:7.2f} Hz (stats counter {by_stats:7.2f} Hz), "
              f"schedule {want:g} Hz: {'within 1 %' if within else 'OFF BY MORE THAN 1 %'}")
    print(f"  seqlock retries: {res['retries']}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
