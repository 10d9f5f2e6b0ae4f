"""Zenoh sessions the way the bridge uses them: peer mode, explicit endpoints, multicast
scouting off, a short lease (docs/bridge.md).

Keys: ``pfma/<buffer>/<area>`` (an area's body bytes), ``pfma/<buffer>/layout`` (the
layout JSON, a queryable), ``pfma/<buffer>/commands/set`` (a remote writer's command
body), ``pfma/<buffer>/writer/commands/<owner>`` (the remote writer's liveliness token).
"""

from __future__ import annotations

import re
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


def open_session(listen: list[str] | None = None, connect: list[str] | None = None) -> Any:
    """A peer session listening on / connecting to the given ``tcp/HOST:PORT`` endpoints
    (nothing else: no multicast scouting, no default listener on every interface)."""
    import zenoh
    listen = [check_endpoint(e) for e in listen or []]
    connect = [check_endpoint(e) for e in connect or []]
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    conf.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
    conf.insert_json5("transport/unicast/max_sessions", str(MAX_SESSIONS))
    conf.insert_json5("listen/endpoints", _json_list(listen))
    conf.insert_json5("connect/endpoints", _json_list(connect))
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
