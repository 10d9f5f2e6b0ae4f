"""What a running ``pfma serve`` shows beside its frame loop: the live channel view
(``--live``), the messages it says as they happen (its trips, refusals, stalls), and the
lines it prints when it stops. Threads and text only; nothing here runs in the frame loop.
"""

from __future__ import annotations

import logging
import math
import threading
import time

from bit3.buffer import Bit3Error
from bit3.layout import ServiceState

log = logging.getLogger(__name__)

#: short labels of the command-area joints in the live view (layout.joint_names order)
JOINT_ABBREV = {"shoulder_pitch": "SP", "shoulder_yaw": "SY", "elbow_pitch": "EP",
                "wrist_yaw": "WY", "wrist_pitch": "WP", "wrist_roll": "WR"}
#: the live view's leading columns: time since start, frame, service state
_LIVE_LEAD = "{:>8} {:>7} {:<8}"
#: how often `pfma serve` looks for its own new messages to say (a thread beside the frame
#: loop, never in it): s
SAY_POLL_S = 0.1


def wrap_pi(a: float) -> float:
    """An angle (rad) wrapped to (-pi, pi]: the resolvers read 0..2 pi, so a joint near 0
    would jump between ~0 and ~2 pi."""
    from pfma.show import wrap_angle  # the one way an angle is shown
    return wrap_angle(a)


def _joint_label(name: str) -> str:
    return JOINT_ABBREV.get(name) or "".join(w[0] for w in name.split("_")).upper()[:3]


def live_header(joints) -> list[str]:
    """The column names, printed once above the live view's two-line updates."""
    return ["live view: t = s since the service started; joint angles in deg, (-180, 180]",
            _LIVE_LEAD.format("t[s]", "frame", "state") + " "
            + " ".join(f"{_joint_label(j):>7}" for j in joints) + "  deg",
            "  F/T force Fx Fy Fz [N]; device rates [Hz]; frame work time p50 [us]"]


def live_lines(t_since_start_s: float, frame: int, state: str, angles_rad, force_n,
               rates_hz, work_p50_us: float) -> list[str]:
    """One live-view update (two lines, each <= 80 columns); ``angles_rad`` in the
    command-area joint order of :func:`live_header`."""
    q = " ".join(f"{math.degrees(wrap_pi(a)):+7.1f}" for a in angles_rad)
    work = f"{work_p50_us:.0f} us" if math.isfinite(work_p50_us) else "--"
    r = "/".join(f"{x:.0f}" for x in rates_hz[:4])
    return [_LIVE_LEAD.format(f"{t_since_start_s:.2f}", frame, state) + " " + q,
            f"  F[N] {force_n[0]:+6.1f} {force_n[1]:+6.1f} {force_n[2]:+6.1f}  "
            f"rtd/adc/dac/ft {r} Hz  work p50 {work}"]


def live_message(m, t_start_s: float) -> str:
    """A service or controller message, its time since start, its text whole (a long text
    takes several Bit3 queue entries, joined by the reader)."""
    return (f"  > {m.t_s - t_start_s:9.2f} {m.queue.removesuffix('_messages')} "
            f"{m.severity.name} src={m.source} code={m.code}: {m.text}")


def live_view(buffer_name: str, stop: threading.Event, rack) -> None:
    """The live view (``--live``): twice a second, two lines of the newest frame and every
    new message, until ``stop`` is set. Runs in a thread of its own."""
    from bit3.client import Client
    try:
        c = Client.attach(buffer_name, rack=None if rack.source.endswith("rack_default.toml") else rack.source)
    except Bit3Error as err:
        log.warning("%s", err, extra={"prog": "live view"})
        return
    angles = {ch.joint: ch.name for ch in c.layout.channels if ch.kind == "rtd" and ch.quantity == "angle"}
    joints = [j for j in c.layout.joint_names if j in angles]
    t_start = None
    try:
        print("\n".join(live_header(joints)), flush=True)
        while not stop.wait(0.5):
            s = c.read_inputs()
            st = c.read_stats()
            if s.t_s == 0.0 and s.frame == 0:
                continue  # no frame published yet
            if t_start is None:  # the service's start: its frame 0 (if the viewer came late)
                t_start = s.t_s - s.frame * (st.period_s if st.period_s > 0 else 1 / 320)
            lines = live_lines(s.t_s - t_start, s.frame, ServiceState(s.service_state).name,
                               [s.value(angles[j]) for j in joints], s.ft_force_n,
                               st.device_rate_hz, st.work_p50_us)
            print("\n".join(lines), flush=True)
            for m in c.new_messages():
                print(live_message(m, t_start), flush=True)
    finally:
        c.close()


def say_line(m, t_start_s: float) -> str:
    """One service message as `pfma serve` says it when it happens."""
    text = m.text.replace("\n", " | ")
    return f"pfma serve: {m.t_s - t_start_s:9.2f} s  {m.severity.name:<7} {m.code}: {text}"


def start_saying(buffer_name: str, stop: threading.Event, t_start_s: float) -> threading.Thread | None:
    """Say the service's trips, refusals, stalls (every WARNING and ERROR of its own message
    queue) as they happen: a thread reading the Bit3 queue every SAY_POLL_S, rate-limited
    by :class:`controller.messages.LivePrinter` (at most LIVE_PER_SECOND lines a second,
    then one "... K more" line). Nothing of this runs in the frame loop; the attach and the
    imports are done here, before the loop starts, not in the thread beside it."""
    from bit3.client import Client
    from bit3.layout import Severity
    from controller.messages import LivePrinter
    try:
        c = Client.attach(buffer_name)
    except Bit3Error as err:
        log.warning("cannot say its messages: %s", err)
        return None
    say = LivePrinter(lambda line: print(line, flush=True), time.monotonic,
                      wanted=lambda m: m.queue == "service_messages" and m.severity >= Severity.WARNING,
                      fmt=lambda m: say_line(m, t_start_s), always=lambda m: False)
    c.new_messages()  # the start-up messages: said by the start lines

    def run() -> None:
        try:
            while True:
                stopping = stop.wait(SAY_POLL_S)
                for m in c.new_messages():
                    say(m)
                if stopping:
                    say.drain()
                    return
                say.flush()
        except (OSError, ValueError):
            pass  # no terminal any more
        finally:
            c.close()
    t = threading.Thread(target=run, name="pfma-serve-say", daemon=True)
    t.start()
    return t


def first_trip_line(svc) -> str:
    """The service's first trip or refusal since the last arm, one line (at exit)."""
    ft = svc.guard.first_trip
    if ft is None:
        return "pfma serve: first trip since the last arm: none"
    code, reason, _t = ft
    return f"pfma serve: first trip since the last arm: {reason} (code {code})"


def stopped_line(stats: dict) -> str:
    """The service's figures when it stops (``svc.publish_stats()``), one line."""
    loop = stats["loop"]
    return (f"pfma serve: stopped after {loop['frames']} frames, {loop['dropped']} dropped, "
            f"{loop['overruns']} overruns; work p50 {loop['work_s']['p50'] * 1e6:.0f} us, "
            f"p99 {loop['work_s']['p99'] * 1e6:.0f} us; wake latency p50 "
            f"{loop['wake_latency_s']['p50'] * 1e6:.0f} us; device rates "
            + ", ".join(f"{k} {v['rate_hz']:.1f} Hz" for k, v in stats["devices"].items() if v["samples"]))
