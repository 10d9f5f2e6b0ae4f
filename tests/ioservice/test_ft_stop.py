"""Stopping the service ends the F/T stream with the sensor's own dialogue (CR, then the
prompt): on the simulated rack the stop reads the prompt from the MVME400 in the board's
time, instead of non-blocking reads that never drained the FIFO and timed out on the wall
clock (0.5 s at every stop, every simulator test)."""

from __future__ import annotations

from sim.rig import SimRig


def test_service_stop_reads_the_stream_stop_prompt():
    rig = SimRig(prefix="pfma-test-")
    try:
        rig.run(0.3)
        ft = rig.svc.ft.ft
        assert ft is not None and ft.streaming
        outcome: list[str] = []
        stop_stream = ft.stop_stream

        def watched():
            try:
                out = stop_stream()
            except Exception as err:  # the old path: PfmaTimeoutError, swallowed by stop()
                outcome.append(type(err).__name__)
                raise
            outcome.append("prompt")
            return out

        ft.stop_stream = watched
        t0 = rig.clock.now()
        rig.svc.stop()
        assert outcome == ["prompt"]
        assert not ft.streaming and not rig.world.ft.streaming  # both ends agree the stream ended
        assert rig.clock.now() - t0 < ft.reply_timeout_s  # a few character times of model time
    finally:
        rig.close()
