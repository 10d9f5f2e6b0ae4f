"""``pfma replay``: play a recording back, for tools or for regression tests.

    pfma replay FILE.mcap [--buffer NAME] [--speed X | --fast] [--loop]
    pfma replay FILE.mcap --through-fakes [--frames N]

Default (**re-publish**): create Bit3 buffer NAME, claim the service role and publish the
recorded inputs frames (``/pfma/inputs_raw``, byte for byte), the recorded statistics
and messages at the recorded pace (``--speed``, or ``--fast``), so ``pfma monitor``,
``pfma scope``, ``pfma stats`` or ``pfma record`` run against a recording as against a
live service. Refuses a buffer a live service owns.

``--through-fakes`` (**regression**): build the simulated rack (FakeWorld) on a private
buffer, run a real IoService on it in simulated time with the same frame numbers as the
recording, and before each frame set the fake boards' physical inputs from the recorded
frame: resolver angles (RTD boards), ADC input volts (ADC boards), the user I/F box bits
(PIO). Then compare what the service publishes with what was recorded, per channel
(RTD counts, ADC counts, PIO bits; exact), and report the mismatches. The F/T sensor,
the CRL hand controller and the DAC (which follows the controller's commands) are not
driven, so they are not compared. A frame the service skipped (``pfma record info``:
service skipped) is skipped in the replay too and said so, not a mismatch; exit 1 only
for a mismatch (or nothing compared).
"""

from __future__ import annotations

import argparse
import sys

from tools.replay import replay_through_fakes, republish
from tools.cli.args import positive_float, positive_int


def add_parser(sub):
    p = sub.add_parser("replay", help="play an MCAP recording back into a buffer, or through the fakes",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", help="recording (pfma record)")
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name to publish into (default pfma)")
    p.add_argument("--speed", type=positive_float, default=1.0, help="playback speed factor (1 = recorded pace)")
    p.add_argument("--fast", action="store_true", help="as fast as possible")
    p.add_argument("--loop", action="store_true", help="start again at the end (until Ctrl-C)")
    p.add_argument("--through-fakes", action="store_true",
                   help="drive the simulated rack from the recording, run the service, compare")
    p.add_argument("--frames", type=positive_int, default=None, help="--through-fakes: at most N frames")
    p.add_argument("--rack", default="fake", help="rack TOML of the recording")
    return p


def run(args) -> int:
    from tools.cli import check_mcap, mcap_errors
    from pfma.rack import load_rack
    check_mcap(args.file)  # before any buffer is made: a missing, foreign or unfinished file
    if args.through_fakes:
        rack = load_rack(args.rack)
        with mcap_errors(args.file):
            rep = replay_through_fakes(args.file, rack=rack, max_frames=args.frames)
        print(rep.describe())
        return 0 if rep.frames_compared and not rep.mismatches else 1
    import signal
    from bit3.layout import build_layout, default_layout
    from tools.attach import service_status
    from bit3.buffer import Bit3Buffer
    layout = default_layout() if args.rack in ("fake", "default") else build_layout(load_rack(args.rack))
    c, _why = service_status(args.buffer, layout)
    if c is not None:
        c.close()
        print(f"pfma replay: a live service publishes on /dev/shm/{args.buffer}; use --buffer OTHER",
              file=sys.stderr)
        return 1
    Bit3Buffer.unlink(args.buffer)
    buf = Bit3Buffer.create(args.buffer, layout)
    stop = {"flag": False}
    old = signal.signal(signal.SIGINT, lambda *_: stop.__setitem__("flag", True))
    total = 0
    try:
        print(f"pfma replay: {args.file} -> /dev/shm/{args.buffer} "
              f"({'fast' if args.fast else f'x{args.speed:g}'}; Ctrl-C stops)", flush=True)
        while True:
            with mcap_errors(args.file):
                n = republish(args.file, buf, speed=args.speed, fast=args.fast, stop=lambda: stop["flag"])
            total += n
            if not args.loop or stop["flag"] or n == 0:
                break
            buf.release()
        from bit3.layout import ServiceState
        if "inputs" in buf.claimed:
            buf.set_service_state(ServiceState.STOPPED)
        print(f"pfma replay: {total} frames published")
    finally:
        signal.signal(signal.SIGINT, old)
        buf.release()
        buf.close()
        Bit3Buffer.unlink(args.buffer)
    return 0
