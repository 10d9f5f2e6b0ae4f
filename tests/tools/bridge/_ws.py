"""A minimal WebSocket client for the tests (RFC 6455: the handshake with a subprotocol,
masked text frames out, unfragmented frames in): enough to speak to the foxglove-sdk
server without a websocket package (foxglove-sdk pulls none)."""

from __future__ import annotations

import base64
import json
import os
import select
import socket
import struct

TEXT, BINARY = 1, 2


class WsClient:
    def __init__(self, port: int, protocols=("foxglove.sdk.v1", "foxglove.websocket.v1"),
                 timeout_s: float = 5.0) -> None:
        self.s = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.s.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                        f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                        f"Sec-WebSocket-Protocol: {', '.join(protocols)}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            got = self.s.recv(1)
            if not got:
                raise EOFError("the server closed the connection during the handshake")
            head += got
        self.head = head.decode()
        if " 101 " not in self.head.split("\r\n", 1)[0]:
            raise ConnectionError(self.head)

    def _exact(self, n: int) -> bytes:
        b = b""
        while len(b) < n:
            got = self.s.recv(n - len(b))
            if not got:
                raise EOFError("connection closed")
            b += got
        return b

    def ready(self, timeout_s: float = 0.0) -> bool:
        return bool(select.select([self.s], [], [], timeout_s)[0])

    def recv(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next frame."""
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        return b0 & 0x0F, self._exact(n)

    def recv_json(self) -> dict:
        op, data = self.recv()
        assert op == TEXT, (op, data[:40])
        return json.loads(data)

    def send_json(self, obj: dict) -> None:
        data = json.dumps(obj).encode()
        mask = os.urandom(4)
        n = len(data)
        size = bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
        self.s.sendall(bytes([0x81]) + size + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(data)))

    def close(self) -> None:
        try:  # a close frame (1000, normal), masked as a client's must be
            self.s.sendall(bytes([0x88, 0x82]) + b"\0\0\0\0" + b"\x03\xe8")
        except OSError:
            pass
        self.s.close()


def message_data(payload: bytes) -> tuple[int, int, bytes]:
    """A server's binary MessageData (opcode 1): (subscription id, log time ns, message)."""
    assert payload[0] == 1, payload[:1]
    sub, t_ns = struct.unpack_from("<IQ", payload, 1)
    return sub, t_ns, payload[13:]
