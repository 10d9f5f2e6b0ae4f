"""``pfma read SIGNAL...``: read channels by signal name, in engineering units.

Signal names, scales and units come from the rack file (``pfma channels``). RTD
angles are radians in (-pi, pi] (the resolver reads 0..2 pi); analog inputs are
``scale * volts + offset``; the DAC is write-only, so its value is the driver's shadow
(what this process last wrote, the board's reset value when nothing was); PIO ports are
the port byte. Each value has its channel's status beside it: ok, or what is wrong (LOS:
the resolver lost its signal; NOREF: no reference; BUSERR: the board did not answer, the
value is the last good sample; CLIPPED, SAFE, SLEWED, ENVELOPE for an output).
"""

from __future__ import annotations

import argparse
import json
import sys

from tools.cli import add_bus_arguments
from tools.regs import UsageError, close_bus, is_fake_bus, open_cli_bus
from bit3.layout import RTD_NO_REFERENCE, RTD_LOSS_OF_SIGNAL, status_text
from pfma.errors import PfmaError
from pfma.rack import load_rack
from pfma.show import wrap_angle
from drivers.rackio import RackIO

READ_NOTE = ("Without --bus the values come from the I/O service running on --buffer (start it "
             "with `pfma serve`); with no live service there the command says so and exits 1. "
             "--bus URL reads the registers instead; --bus fake reads a fresh simulated rack in its "
             "power-up state (every line says so).")


def add_parser(sub):
    p = sub.add_parser("read", help="read channels by signal name (engineering units)",
                       description=__doc__.split("\n\n")[1] + "\n\n" + READ_NOTE,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("signals", nargs="+", metavar="SIGNAL", help="signal name(s), see `pfma channels`")
    p.add_argument("--json", action="store_true",
                   help="one JSON list with an object per signal (status: the status word, status_name: its name)")
    add_bus_arguments(p)
    p.set_defaults(bus=None)  # None: the running service's buffer; registers only with an explicit --bus
    p.add_argument("--buffer", default="pfma",
                   help="read the latest values the service running on this Bit3 buffer published "
                        "(default pfma; the service must be running: `pfma serve`). With --bus the "
                        "registers are read instead (--bus fake: the simulated rack)")
    return p


def _service_client(name: str, rack: str | None):
    """A read-only client of the live service on buffer ``name``.

    :raises PfmaError: no live service there (the message says why), or its layout differs
    """
    from tools.attach import attach_reader
    return attach_reader(name, rack)  # shared memory, or zenoh://HOST:PORT/NAME through a bridge


def _read_buffer(client, signals, as_json: bool) -> int:
    from tools.checkout.view import entry_status, entry_units, entry_value
    snap = client.read_inputs()
    simulated = client.header().rack_kind == "simulated"  # the service's SIMULATED flag
    rows, failures = [], 0
    for signal in signals:
        row: dict = {"signal": signal}
        try:
            entry = next(e for e in client.layout.channels if e.name == signal and e.area == "inputs")
            value = entry_value(snap, entry)  # an angle in (-pi, pi]; a board's errors, a link's records
            value = value.tolist() if hasattr(value, "tolist") else value
            bits = next((int(snap.record[f][i]) for f, i, _ in entry.fields if f.endswith("_status")), 0)
            row.update(board=entry.board, channel=entry.channel, value=value, units=entry_units(entry),
                       status=bits, status_name=entry_status(snap, entry) or "-",
                       note=f"from the service (frame {snap.frame})")
            if simulated:
                row["source"] = "simulated rack"
        except StopIteration:
            failures += 1
            row["error"] = f"no channel named {signal!r} in the service's Bit3 layout"
            if not as_json:
                print(f"pfma read: {signal}: {row['error']}", file=sys.stderr)
        rows.append(row)
    if as_json:
        print(json.dumps(rows, indent=1))
    else:
        for row in rows:
            if "error" not in row:
                v = row["value"]
                shown = f"{v:.6g}" if isinstance(v, float) else str(v)
                sim = "(simulated rack) " if simulated else ""
                where = f"{row['board']} ch {row['channel']}" if row["channel"] >= 0 else row["board"] or "-"
                print(f"{row['signal']:32} {shown:>14} {row['units']:6} {row['status_name']:8} "
                      f"{where}  {sim}{row['note']}")
    return 1 if failures else 0


def _status(kind: str, bits: int) -> str:
    """A channel's status by name (bit3.layout.status_text); ``-`` for a kind without one (PIO)."""
    return "-" if kind == "pio" else status_text(kind, bits)


def _rtd_status(io: RackIO, ch) -> int:
    """A resolver channel's status bits as the service publishes them (bit3 ``rtd_status``:
    the board's loss-of-signal bit for the channel, no reference for all), read from the
    board's STATUS register."""
    st = io.driver(ch.board).status()
    return (RTD_LOSS_OF_SIGNAL if st.faults[ch.channel] else 0) | (0 if st.reference_present else RTD_NO_REFERENCE)


def run(args) -> int:
    if args.bus is None:
        client = _service_client(args.buffer, None if args.rack in ("fake", "default") else args.rack)
        try:
            return _read_buffer(client, args.signals, args.json)
        finally:
            client.close()
    simulated = is_fake_bus(args.bus)
    rack = load_rack(args.rack)
    try:
        bus = open_cli_bus(args.bus, rack)
    except UsageError as err:
        print(f"pfma read: {err}", file=sys.stderr)
        return 2
    io = RackIO(bus, rack)
    rows: list[dict] = []
    failures = 0
    try:
        for signal in args.signals:
            row: dict = {"signal": signal}
            try:
                ch = io.channel(signal)
                row.update(board=ch.board, channel=ch.channel, address=ch.address)
                r = io.read_signal(signal)
                bits = _rtd_status(io, ch) if ch.device == "rtd" else 0
                row.update(value=wrap_angle(r.value) if ch.device == "rtd" else r.value, units=r.units, raw=r.raw,
                           status=bits, status_name=_status(ch.device, bits), note=r.note)
                if simulated:
                    row["source"] = "simulated rack"
            except PfmaError as err:
                failures += 1
                row["error"] = str(err)
                if not args.json:
                    print(f"pfma read: {signal}: {err}", file=sys.stderr)
            rows.append(row)
    finally:
        close_bus(bus)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        for row in rows:
            if "error" in row:
                continue
            value = row["value"]
            shown = f"{value:.6g}" if isinstance(value, float) else f"{value} (0x{value:02X})"
            sim = "(simulated rack) " if simulated else ""
            print(f"{row['signal']:32} {shown:>14} {row['units']:6} {row['status_name']:8} raw {row['raw']:<6} "
                  f"{row['board']} ch {row['channel']}  {sim}{row['note']}".rstrip())
    return 1 if failures else 0
