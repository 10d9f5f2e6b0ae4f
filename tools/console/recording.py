"""The console's record start/stop (``c``): a ``pfma record`` process beside the console,
recording the service's Bit3 topics and, with a world model, the layers' statuses and the
servo's variables and the shoulder-roll index (``--wm NAME --var``), to ``pfma-console-<time>.mcap`` in the working
directory (assumed: where the operator started the console). Ctrl-C (SIGINT) ends it
cleanly with its summary written, as at a terminal."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

#: world-model variables the console records beside the Bit3 topics (docs/console.md)
WM_VARS = ("*.status", "servo.*", "joint.shoulder_roll_*")
#: how long a stopping recorder may take to write its summary before it is killed
STOP_TIMEOUT_S = 10.0


class ConsoleRecording:
    """At most one ``pfma record`` process at a time.

    :param buffer: the service's Bit3 buffer name
    :param wm: the controller's world-model name, or None (Bit3 topics only)
    """

    def __init__(self, buffer: str, wm: str | None) -> None:
        self.buffer, self.wm = buffer, wm
        self.proc: subprocess.Popen | None = None
        self.path = ""

    @property
    def active(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def start(self) -> str:
        """Start recording; returns the line to show."""
        if self.active:
            return f"already recording to {self.path}"
        self.path = time.strftime("pfma-console-%Y%m%d-%H%M%S.mcap")
        argv = [sys.executable, "-m", "tools.cli", "record", self.path, "--buffer", self.buffer, "--quiet"]
        if self.wm:
            argv += ["--wm", self.wm] + [a for v in WM_VARS for a in ("--var", v)]
        self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)
        return f"recording to {self.path}" + (f" (Bit3 topics + {', '.join(WM_VARS)})" if self.wm else "")

    def stop(self) -> str:
        """Stop recording cleanly; returns the line to show (the recorder's error if it failed)."""
        p = self.proc
        if p is None:
            return "not recording"
        self.proc = None
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
                return f"recording {self.path}: the recorder did not stop within {STOP_TIMEOUT_S:g} s; killed " \
                       f"(pfma record recover {self.path})"
        err = (p.stderr.read() if p.stderr else "").strip().splitlines()
        if p.returncode not in (0, -signal.SIGINT):
            return f"recording {self.path} failed (exit {p.returncode}): {err[-1] if err else 'no message'}"
        return f"recording stopped: {self.path}"
