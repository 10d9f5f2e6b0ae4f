"""Zenoh sessions the way the bridge uses them: peer mode, explicit endpoints, multicast
scouting off, a short lease (docs/bridge.md).

Keys: ``pfma/<buffer>/<area>`` (an area's body bytes), ``pfma/<buffer>/layout`` (the
layout JSON, a queryable), ``pfma/<buffer>/commands/set`` (a remote writer's command
body), ``pfma/<buffer>/writer/commands/<owner>`` (the remote writer's liveliness token).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pfma.errors import PfmaError

#: Zenoh link lease, ms. Assumption: 1 s, the low end of the 1-2 s the eclipse-zenoh
#: reference notes advise (default 10 s); a silent partition is noticed after it.
LEASE_MS = 1000
#: the listening endpoint when neither --listen nor --connect is given: loopback only
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
#: the largest Zenoh message a session takes, bytes (Zenoh's default is 1 GiB: one peer could
#: make a session hold that much). Assumption: 4 MiB; the largest payloads here are a world-model
#: section (the whole model is ~200 KB) and the layout document (~64 KB for the report's rack).
#: A bigger message closes the link that carried it; the session goes on with its other peers.
MAX_MESSAGE_BYTES = 4 * 1024 * 1024
#: peers one session accepts at once (Zenoh's default is 1,000). Assumption: a lab's bridge
#: serves a few remote tools and controllers; 64 leaves room and bounds a connection flood.
MAX_SESSIONS = 64

_ENDPOINT = re.compile(r"^tcp/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


def check_endpoint(text: str) -> str:
    """``tcp/HOST:PORT`` or a :class:`PfmaError` saying what is expected."""
    m = _ENDPOINT.match(text)
    if not m or not 0 < int(m.group(2)) < 65536:
        raise PfmaError(f"endpoint {text!r} is not tcp/HOST:PORT (e.g. tcp/127.0.0.1:7447)")
    return text


def check_name(text: str, what: str = "buffer name") -> str:
    """A key-expression chunk: letters, digits, ``_ . -`` (no ``/ * $ ?``)."""
    if not _NAME.match(text):
        raise PfmaError(f"{what} {text!r} may hold only letters, digits, '_', '.' and '-'")
    return text


def key(buffer: str, *parts: str) -> str:
    return "/".join(("pfma", buffer) + parts)


#: environment variable naming a file that holds this side's ``user:password`` (one line):
#: every session opened without explicit credentials authenticates with it (so every tool
#: taking ``--buffer zenoh://...`` reaches a bridge started with ``--users``)
CREDENTIALS_ENV = "PFMA_ZENOH_CREDENTIALS"

#: what an authenticated peer may do on ``pfma/<buffer>/**`` (ingress at the bridge):
#: subscribe, query (the layout, a late joiner's bodies, the command holder) and watch tokens
_READ_MESSAGES = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
#: what an operator may do on top: put command bodies and hold the writer token
_COMMAND_MESSAGES = ["put", "liveliness_token"]
#: what the bridge's own session sends (egress): its bodies, replies, tokens, declarations
_EGRESS_MESSAGES = ["put", "reply", "query", "declare_subscriber", "liveliness_token",
                    "declare_liveliness_subscriber", "liveliness_query", "declare_queryable"]


@dataclass(frozen=True)
class ZenohAuth:
    """Zenoh user/password authentication (``transport/auth/usrpwd``).

    :param user: this side's user name (a peer connecting to a bridge that checks users)
    :param password: its password
    :param users_file: the ``user:password`` lines (one per user) of those allowed to
        connect to this session's listeners; with it, every peer must authenticate, and
        :func:`open_session` with a ``buffer`` adds access control
    """

    user: str | None = None
    password: str | None = None
    users_file: str | Path | None = None

    @classmethod
    def from_file(cls, path: str | Path) -> "ZenohAuth":
        """This side's credentials from a one-line ``user:password`` file, or a PfmaError."""
        user, password = read_credentials(Path(path))[0]
        return cls(user, password)


def read_credentials(path: Path) -> list[tuple[str, str]]:
    try:
        lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    except OSError as err:
        raise PfmaError(f"cannot read the Zenoh credentials {path}: {err.strerror}") from None
    out = []
    for n, ln in enumerate(lines, 1):
        user, sep, password = ln.partition(":")
        if not sep or not user or not password:
            raise PfmaError(f"{path}: line {n} is not user:password")
        check_name(user, "Zenoh user name")
        out.append((user, password))
    if not out:
        raise PfmaError(f"{path}: no user:password line")
    return out


def access_control(buffer: str, users: list[str], operators: list[str]) -> dict:
    """Zenoh ``access_control`` for a bridge of ``buffer`` (issue 28 item 6): deny by default;
    every authenticated user (``users``) may read the areas (subscribe, query, watch
    tokens); only ``operators`` may put on ``pfma/<buffer>/commands/set`` and declare the
    writer token. Nobody may put on an area's key but the bridge itself (egress)."""
    unknown = sorted(set(operators) - set(users))
    if unknown:
        raise PfmaError(f"operator {', '.join(unknown)} is not in the users file")
    rules = [
        {"id": "bridge-out", "permission": "allow", "flows": ["egress"], "messages": _EGRESS_MESSAGES,
         "key_exprs": [key(buffer, "**")]},
        {"id": "read", "permission": "allow", "flows": ["ingress"], "messages": _READ_MESSAGES,
         "key_exprs": [key(buffer, "**")]},
    ]
    subjects = [{"id": "users", "usernames": users}]
    policies = [{"rules": ["bridge-out", "read"], "subjects": ["users"]}]
    if operators:
        rules.append({"id": "command", "permission": "allow", "flows": ["ingress"], "messages": _COMMAND_MESSAGES,
                      "key_exprs": [key(buffer, "commands", "set"), key(buffer, "writer", "commands", "*")]})
        subjects.append({"id": "operators", "usernames": operators})
        policies.append({"rules": ["command"], "subjects": ["operators"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def open_session(listen: list[str] | None = None, connect: list[str] | None = None, *,
                 auth: ZenohAuth | None = None, buffer: str | None = None,
                 operators: list[str] | None = None) -> Any:
    """A peer session listening on / connecting to the given ``tcp/HOST:PORT`` endpoints
    (nothing else: no multicast scouting, no default listener on every interface).

    :param auth: user/password authentication (default: the file named by
        ``$PFMA_ZENOH_CREDENTIALS``, if set); with ``auth.users_file`` every peer connecting
        to this session must authenticate as one of its users
    :param buffer: with ``auth.users_file``: the buffer whose keys the access control
        guards (:func:`access_control`; ``operators`` may command)
    """
    import zenoh
    listen = [check_endpoint(e) for e in listen or []]
    connect = [check_endpoint(e) for e in connect or []]
    if auth is None and os.environ.get(CREDENTIALS_ENV):
        auth = ZenohAuth.from_file(os.environ[CREDENTIALS_ENV])
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    conf.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
    conf.insert_json5("transport/unicast/max_sessions", str(MAX_SESSIONS))
    conf.insert_json5("listen/endpoints", _json_list(listen))
    conf.insert_json5("connect/endpoints", _json_list(connect))
    if auth is not None:
        usrpwd: dict[str, str] = {}
        if auth.user:
            usrpwd.update(user=auth.user, password=auth.password or "")
        if auth.users_file is not None:
            users = [u for u, _ in read_credentials(Path(auth.users_file))]
            usrpwd["dictionary_file"] = str(Path(auth.users_file).resolve())
            if buffer is not None:
                conf.insert_json5("access_control", json.dumps(access_control(buffer, users, operators or [])))
        conf.insert_json5("transport/auth/usrpwd", json.dumps(usrpwd))
    try:
        return zenoh.open(conf)
    except zenoh.ZError as err:
        raise PfmaError(f"cannot open a Zenoh session (listen {listen or '-'}, connect "
                        f"{connect or '-'}): {zenoh_error_text(err)}") from err


#: where in Zenoh's Rust sources an error was raised (" at /root/.cargo/.../tcp.rs:61."): noise
#: to the person reading the message
_RUST_WHERE = re.compile(r"\s+at\s+/\S+?\.rs:\d+\.?")


def zenoh_error_text(err: BaseException) -> str:
    """A Zenoh error without the Rust source locations it carries."""
    text = _RUST_WHERE.sub("", str(err))
    return re.sub(r"\[(.*)\]\s*$", r"\1", text).strip()


def _json_list(items: list[str]) -> str:
    return "[" + ",".join(f'"{e}"' for e in items) + "]"
