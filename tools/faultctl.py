"""The fault control endpoint of a simulated service, and its client.

``pfma serve`` on the simulated rack opens a Unix-domain stream socket beside its Bit3
buffer (``/dev/shm/NAME.faults``, mode 0600; a stale one, left by a killed service, is
recognised and replaced): :class:`FaultEndpoint` takes one JSON line per connection and
queues it for :class:`FaultController`, which applies it in the service loop's thread just
before a frame. :func:`request` is the client (``pfma fault``, ``pfma hand``, the console).
The verb and its help are ``tools/cli/fault.py``; the specs are ``sim/faults.py``.
"""

from __future__ import annotations

import errno
import json
import os
import queue
import socket
import stat
import threading

from pfma.errors import ConfigError, PfmaError

#: message codes the service posts (``service_messages``)
MSG_FAULT_ON, MSG_FAULT_OFF, MSG_SCENARIO_STEP_FAILED = 180, 181, 182
#: a simulated hand controller deflected or released (``pfma hand --deflect``)
MSG_HAND = 183
#: the longest a deflection holds before the stick springs back (``pfma hand --for``), s
HAND_HOLD_MAX_S = 10.0
#: how long a request waits for the loop to take it (the loop takes it before its next
#: frame: 3.1 ms at 320 Hz; a stopped or stalled loop answers nothing)
REPLY_TIMEOUT_S = 2.0
#: the longest request line accepted (a spec is a few dozen bytes)
MAX_REQUEST_BYTES = 4096
#: the one message for a buffer with no fault endpoint
NO_ENDPOINT = "service {name} runs a real rack (or none): faults are only for the simulated rack"


def socket_path(buffer: str) -> str:
    """The control endpoint of the service on Bit3 buffer ``buffer`` (beside the buffer
    ``/dev/shm/NAME`` and its ring ``/dev/shm/NAME.ring``)."""
    return f"/dev/shm/{buffer}.faults"


# ----------------------------------------------------------------------------- the verb


# ----------------------------------------------------------------------------- the client
class NoEndpoint(PfmaError):
    """The buffer has no live fault endpoint (a real rack's service, or none)."""


def request(buffer: str, req: dict, timeout_s: float = REPLY_TIMEOUT_S + 3.0) -> dict:
    """Send one request to the service on ``buffer``; its reply.

    :raises NoEndpoint: no endpoint, or a stale one (its service is gone)
    """
    path = socket_path(buffer)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.settimeout(timeout_s)
        try:
            s.connect(path)
        except FileNotFoundError:
            raise NoEndpoint(NO_ENDPOINT.format(name=buffer)) from None
        except ConnectionRefusedError:
            raise NoEndpoint(f"service {buffer} is not running: its fault control socket {path} is "
                             f"stale: the service that made it is gone") from None
        except PermissionError:
            raise NoEndpoint(f"service {buffer}: no permission to use its control socket {path} "
                             f"(mode 0600: it runs as another user)") from None
        s.sendall(json.dumps(req).encode() + b"\n")
        data = _read_line(s)
    except (TimeoutError, socket.timeout):
        raise NoEndpoint(f"service {buffer} did not answer within {timeout_s:g} s "
                         f"(its loop is not running?)") from None
    except OSError as err:
        raise NoEndpoint(f"service {buffer}: control socket {path}: {err.strerror or err}") from None
    finally:
        s.close()
    try:
        reply = json.loads(data)
    except ValueError:
        raise NoEndpoint(f"service {buffer}: unreadable reply {data[:60]!r}") from None
    if not isinstance(reply, dict):
        raise NoEndpoint(f"service {buffer}: unreadable reply {data[:60]!r}")
    return reply


def _read_line(s: socket.socket) -> bytes:
    buf = b""
    while b"\n" not in buf and len(buf) <= MAX_REQUEST_BYTES * 16:
        chunk = s.recv(4096)
        if not chunk:
            break
        buf += chunk
    return buf.split(b"\n", 1)[0]


# ----------------------------------------------------------------------------- the service side
class _Pending:
    """A request waiting for the loop, and its reply."""

    def __init__(self, req: dict) -> None:
        self.req = req
        self.reply: dict | None = None
        self.done = threading.Event()
        self.lock = threading.Lock()
        self.abandoned = False  # the endpoint gave up waiting: the loop must not act on it


class FaultController:
    """The faults of one simulated service: applied only in the loop's thread, just before
    a frame (:meth:`on_frame`, installed by :meth:`install` around the loop's body).

    :param svc: the :class:`ioservice.service.IoService`
    :param world: its :class:`fakes.world.FakeWorld`
    :param say: where lines for the operator go (stdout by default; None: nowhere)
    """

    def __init__(self, svc, world, say=lambda line: print(line, flush=True)) -> None:
        from sim.faults import FaultSet
        self.svc = svc
        self.world = world
        self.faults = FaultSet(world)
        self.requests: queue.SimpleQueue[_Pending] = queue.SimpleQueue()
        self.scenario = None  # a sim.scenario.ScenarioRunner
        self.say = say
        self.frame = 0
        #: frame at which the simulated CAE stick springs back to centre, deadman up (None: it is)
        self.hand_until: int | None = None

    def install(self) -> None:
        """Run :meth:`on_frame` before every frame of the service's loop."""
        body = self.svc.loop.body

        def frame(info) -> None:
            self.on_frame(info.index)
            body(info)
        self.svc.loop.body = frame

    def on_frame(self, k: int) -> None:
        """Between frames: the scenario's steps due, then the queued requests."""
        self.frame = k
        try:
            if self.hand_until is not None and k >= self.hand_until:
                self._hand_release("its time ran out")
            if self.scenario is not None:
                self.scenario.on_frame(k)
            requests = self.requests
            while not requests.empty():  # the usual frame: one cheap check, nothing queued
                p = requests.get_nowait()
                with p.lock:
                    if p.abandoned:
                        continue
                    try:
                        p.reply = self.handle(p.req)
                    except Exception as err:  # noqa: BLE001 - answered, never raised into the loop
                        p.reply = {"ok": False, "exit": 1, "error": f"{type(err).__name__}: {err}"}
                p.done.set()
        except Exception as err:  # noqa: BLE001 - a fault tool must never stop the service
            self.svc.post(_severity("ERROR"), MSG_SCENARIO_STEP_FAILED, f"fault control: {err}")

    def handle(self, req: dict) -> dict:
        """One request (``op`` inject, clear, list) -> reply (``ok``, ``faults`` or ``error``,
        ``exit``: 2 for a bad spec, 1 for a refusal)."""
        from sim.faults import parse_fault
        op = req.get("op")
        spec = req.get("spec")
        if op == "hand":
            return self.hand(req)
        try:
            if op == "list":
                from sim.errors import describe
                return {"ok": True, "faults": self.faults.listing(), "rack_errors": describe(self.world.sim.errors)}
            if op not in ("inject", "clear") or not isinstance(spec, str):
                return {"ok": False, "exit": 2, "error": f"bad request {req!r}"}
            if not (op == "clear" and spec.strip() == "all"):
                try:
                    parse_fault(spec, self.faults.rack)
                except ConfigError as err:
                    return {"ok": False, "exit": 2, "error": str(err)}
            if op == "inject":
                done = [self.inject(spec)]
            else:
                done = self.clear(spec)
            return {"ok": True, "faults": [_fault_dict(f, self.frame) for f in done]}
        except ConfigError as err:  # already active, not active
            return {"ok": False, "exit": 1, "error": str(err)}

    def hand(self, req: dict) -> dict:
        """``op`` hand: hold the simulated CAE stick (``volts``: its six axis voltages in
        ``fakes.sim_rack.CAE_AXIS_SIGNALS`` order, +-10 V full deflection; ``deadman``: discrete
        1 closed) for ``for_s`` seconds, after which it springs back to centre with the deadman
        up, as a hand let go does (renew to keep it; a new request replaces the old)."""
        volts, deadman, for_s = req.get("volts"), req.get("deadman"), req.get("for_s")
        ok = (req.get("source") == "cae" and isinstance(volts, list) and len(volts) == 6
              and all(isinstance(v, (int, float)) and abs(v) <= 10.0 for v in volts)
              and isinstance(deadman, bool) and isinstance(for_s, (int, float)) and 0 < for_s <= HAND_HOLD_MAX_S)
        if not ok:
            return {"ok": False, "exit": 2, "error": f"bad hand request {req!r}"}
        self.world.set_cae([float(v) for v in volts], (deadman, False, False))
        period = self.svc.schedule.period_s
        self.hand_until = self.frame + max(1, int(round(float(for_s) / period)))
        text = (f"simulated CAE stick held at {', '.join(f'{v:+.2f}' for v in volts)} V, deadman "
                f"{'pressed' if deadman else 'up'}, for {float(for_s):g} s")
        self.svc.post(_severity("INFO"), MSG_HAND, text)
        if self.say is not None:
            self.say(f"pfma serve: frame {self.frame}: {text}")
        return {"ok": True, "until_frame": self.hand_until, "text": text}

    def _hand_release(self, why: str) -> None:
        self.hand_until = None
        self.world.set_cae([0.0] * 6, (False, False, False))
        text = f"simulated CAE stick released: centred, deadman up ({why})"
        self.svc.post(_severity("INFO"), MSG_HAND, text)
        if self.say is not None:
            self.say(f"pfma serve: frame {self.frame}: {text}")

    def inject(self, spec: str):
        f = self.faults.inject(spec, since=self.frame)
        self._posted(MSG_FAULT_ON, "simulated fault on", f, "injected")
        return f

    def clear(self, spec: str):
        done = self.faults.clear(spec)
        for f in done:
            self._posted(MSG_FAULT_OFF, "simulated fault off", f, "cleared")
        return done

    def _posted(self, code: int, head: str, fault, verb: str) -> None:
        sev = _severity("WARNING" if code == MSG_FAULT_ON else "INFO")
        self.svc.post(sev, code, f"{head}: {fault.spec}")
        if self.say is not None:
            self.say(f"pfma serve: frame {self.frame}: {verb} simulated fault {fault.spec}: "
                     f"{fault.description}")

    def scenario_step(self, step, done, err) -> None:
        """A scenario step ran (``ScenarioRunner.say``)."""
        if err is not None:
            self.svc.post(_severity("ERROR"), MSG_SCENARIO_STEP_FAILED,
                          f"scenario step failed: {step.action} {step.spec}")
            if self.say is not None:
                self.say(f"pfma serve: frame {self.frame}: scenario step {step.as_text()} failed: {err}")
            return
        for f in done:
            if step.action == "inject":
                self._posted(MSG_FAULT_ON, "simulated fault on", f, "injected")
            else:
                self._posted(MSG_FAULT_OFF, "simulated fault off", f, "cleared")


def _severity(name: str) -> int:
    from bit3.layout import Severity
    return int(Severity[name])


def _fault_dict(f, frame: int) -> dict:
    return {"spec": f.spec, "kind": f.kind, "description": f.description, "since": frame}


class FaultEndpoint:
    """The control socket: a small thread accepts connections, reads one JSON line, queues
    it for the loop (:class:`FaultController`) and writes the reply back. It touches no fake.

    :param path: the socket's path (:func:`socket_path`)
    :param controller: where requests are queued
    """

    def __init__(self, path: str, controller: FaultController) -> None:
        self.path = path
        self.controller = controller
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._ino: int | None = None

    def start(self) -> None:
        """Bind (replacing a stale socket; refusing a live one), mode 0600, listen, serve.

        :raises PfmaError: the path is a live endpoint or not a socket
        """
        _remove_stale(self.path)
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.bind(self.path)
            os.chmod(self.path, 0o600)  # before listen(): nobody can connect until then
            s.listen(8)
        except OSError as err:
            s.close()
            raise PfmaError(f"fault control socket {self.path}: {err.strerror or err}") from None
        self._ino = os.stat(self.path).st_ino
        self._sock = s
        self._thread = threading.Thread(target=self._serve, name="pfma-fault-endpoint", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return  # closed
            with conn:
                try:
                    self._one(conn)
                except OSError:
                    pass  # the client went away

    def _one(self, conn: socket.socket) -> None:
        conn.settimeout(REPLY_TIMEOUT_S)
        try:
            line = _read_line(conn)
        except (TimeoutError, socket.timeout):
            return
        try:
            req = json.loads(line)
            if not isinstance(req, dict):
                raise ValueError("not an object")
        except ValueError:
            reply: dict = {"ok": False, "exit": 2, "error": f"not a JSON request line: {line[:60]!r}"}
        else:
            p = _Pending(req)
            self.controller.requests.put(p)
            if not p.done.wait(REPLY_TIMEOUT_S):
                with p.lock:
                    if p.reply is None:
                        p.abandoned = True
                reply = p.reply or {"ok": False, "exit": 1,
                                    "error": f"the service loop took no request for {REPLY_TIMEOUT_S:g} s "
                                             f"(stopped or stalled); nothing was changed"}
            else:
                reply = p.reply or {"ok": False, "exit": 1, "error": "no reply"}
        conn.sendall(json.dumps(reply).encode() + b"\n")

    def close(self) -> None:
        """Stop serving and remove the socket (only if it is still ours). Idempotent."""
        self._stop.set()
        s, self._sock = self._sock, None
        if s is not None:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()
        if self._thread is not None:
            self._thread.join(REPLY_TIMEOUT_S + 1.0)
            self._thread = None
        try:
            if self._ino is not None and os.stat(self.path).st_ino == self._ino:
                os.unlink(self.path)
        except FileNotFoundError:
            pass
        self._ino = None


def _remove_stale(path: str) -> None:
    """Remove ``path`` if it is a socket nobody listens on; refuse a live one or a non-socket."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode):
        raise PfmaError(f"fault control socket {path}: exists and is not a socket; remove it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.settimeout(1.0)
        probe.connect(path)
    except OSError as err:
        if err.errno in (errno.ECONNREFUSED, errno.ENOENT):
            try:
                os.unlink(path)  # stale: its service is gone
            except FileNotFoundError:
                pass
            return
        raise PfmaError(f"fault control socket {path}: {err.strerror or err}") from None
    finally:
        probe.close()
    raise PfmaError(f"fault control socket {path} is in use by a live service")
