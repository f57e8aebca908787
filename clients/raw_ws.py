"""A WebSocket client on a bare socket, for the hostile-client tests and benchmark: it reads
only when told to (a browser tab gone to sleep, a stalled game thread), with a small receive
buffer so a server's replies back up, and it can hold a connection open without a request."""

from __future__ import annotations

import base64
import os
import socket
import struct
import time

import numpy as np


class RawSocket:
    """A bare TCP connection to the server, with a small receive buffer so replies back up."""

    def __init__(self, base: str, rcvbuf: int = 4096) -> None:
        host, port = base.split("//")[1].split(":")
        self.host, self.port = host, int(port)
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.connect((self.host, self.port))

    def closed_by_server(self, timeout: float) -> bool:
        """Read (and discard) until the server drops the connection; False if it has not within
        `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                if not self.sock.recv(65536):
                    return True
            except TimeoutError:
                return False
            except OSError:  # reset: the server aborted
                return True
        return False

    def close(self) -> None:
        self.sock.close()


class HandshakeRefused(Exception):
    """The server answered the WebSocket handshake with something other than 101 (e.g. 429)."""

    def __init__(self, status_line: str, head: bytes) -> None:
        super().__init__(status_line)
        self.status = int(status_line.split()[1]) if len(status_line.split()) > 1 else 0
        self.head = head


class RawClient(RawSocket):
    """A WebSocket client that reads only when told to (a browser tab gone to sleep, a stalled
    game thread): the handshake by hand (with `token` in the query where the server has tokens),
    then masked text frames."""

    def __init__(self, base: str, rcvbuf: int = 4096, token: str | None = None) -> None:
        super().__init__(base, rcvbuf)
        key = base64.b64encode(os.urandom(16)).decode()
        path = "/v1/stream" if token is None else f"/v1/stream?token={token}"
        self.sock.sendall(
            (
                f"GET {path} HTTP/1.1\r\nHost: {self.host}:{self.port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            assert chunk, "connection closed during the handshake"
            head += chunk
        if not head.startswith(b"HTTP/1.1 101"):
            self.sock.close()
            raise HandshakeRefused(head.split(b"\r\n", 1)[0].decode(errors="replace"), head)

    def send_text(self, text: str) -> None:
        """One masked text frame (RFC 6455: clients mask)."""
        self.sock.sendall(self.text_frame(text))

    @staticmethod
    def text_frame(text: str) -> bytes:
        """A masked text frame's bytes, to send again and again without building it each time."""
        payload = text.encode()
        n = len(payload)
        if n < 126:
            length = bytes([0x80 | n])
        elif n < 65536:
            length = bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            length = bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        masked = (np.frombuffer(payload, np.uint8) ^ np.resize(np.frombuffer(mask, np.uint8), n)).tobytes()
        return bytes([0x81]) + length + mask + masked

    def recv_frame(self) -> tuple[int, bytes]:
        """The server's next frame as (opcode, payload) (servers do not mask); EOFError at the end
        of the stream. Fragmented messages are not joined: the service sends none."""
        first, second = self._recv_exactly(2)
        n = second & 0x7F
        if n == 126:
            (n,) = struct.unpack(">H", self._recv_exactly(2))
        elif n == 127:
            (n,) = struct.unpack(">Q", self._recv_exactly(8))
        return first & 0x0F, self._recv_exactly(n)

    def _recv_exactly(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise EOFError("the server ended the stream")
            data += chunk
        return data
