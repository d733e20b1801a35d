"""The client side of python-can-remote's protocol, for the loopback bus (``interface="remote"``).

:func:`redarm_ros.can.bus.open_bus` opens a ``remote`` channel with :class:`RelayBus`: the same wire
protocol as python-can-remote 0.3.0's client (WebSocket upgrade, ``bus_request`` / ``bus_response``,
binary ``can.binary+json.v1`` frames: a type byte of 1, then ``>dIBB`` timestamp, arbitration id,
DLC, flags, then the data), so it talks to ``redarm-canbus`` and to python-can-remote's own server
alike; only the work per frame differs, which at 250 cycles/s of 7 modules is most of a simulated
stack's CPU:

* reads take whatever the socket holds in one ``recv`` and parse every complete frame of it (a
  precompiled struct over the buffer); :meth:`RelayBus.recv` hands them out one by one without
  touching the socket again;
* :meth:`RelayBus.send_many` writes a batch of frames (a driver's cycle, a simulator's replies) in
  one ``send``, so the bus server and the reader wake once for it, not once per frame;
* a frame is masked with the all-zero key: RFC 6455 asks clients for a random key to keep caching
  proxies from being poisoned; the bus is loopback-only, no proxy stands between, and the zero key
  leaves the payload as it is (no per-byte work on either side).

A server that does not offer the binary protocol is refused (both servers offer it). A closed
connection raises :class:`ConnectionResetError` (an ``OSError``: the bus is lost, see
:class:`~redarm_ros.can.bus.ReconnectingBus`); python-can-remote's error event raises
:class:`can.CanError`.
"""

from __future__ import annotations

import base64
import collections
import hashlib
import json
import math
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Iterable
from typing import Any
from urllib.parse import urlparse

import can

from redarm_ros.can.bus import DirectRecv

__all__ = ["BINARY_MSG", "BINARY_PROTOCOL", "BINARY_TYPE", "JSON_PROTOCOL", "RelayBus", "binary_flags"]

#: Timestamp, arbitration id, DLC, flags of a binary frame message (after its type byte).
BINARY_MSG = struct.Struct(">dIBB")
BINARY_TYPE = 1
BINARY_PROTOCOL, JSON_PROTOCOL = "can.binary+json.v1", "can.json.v1"
F_EXT, F_RTR, F_ERR, F_FD, F_BRS, F_ESI = 0x1, 0x2, 0x4, 0x8, 0x10, 0x20
OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x1, 0x2, 0x8, 0x9, 0xA
WS_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"

# A masked final binary frame of at most 125 bytes: opcode, mask bit + length, the zero key, then the
# frame message's type byte and fields; the data follow.
_OUT = struct.Struct(">BB4sBdIBB")
_ZERO_KEY = b"\0\0\0\0"
_RECV_BYTES = 64 * 1024
_HANDSHAKE_TIMEOUT_S = 5.0
_CLOSE_WAIT_S = 0.5


#: The message fields of each flags byte (python-can keywords), looked up once per frame.
_FLAG_FIELDS: dict[int, dict[str, bool]] = {
    f: {"is_extended_id": bool(f & F_EXT), "is_remote_frame": bool(f & F_RTR),
        "is_error_frame": bool(f & F_ERR), "is_fd": bool(f & F_FD), "bitrate_switch": bool(f & F_BRS),
        "error_state_indicator": bool(f & F_ESI)}
    for f in range(256)
}


def binary_flags(msg: can.Message) -> int:
    """The flags byte of ``msg`` in a binary frame message."""
    return ((F_EXT if msg.is_extended_id else 0) | (F_RTR if msg.is_remote_frame else 0)
            | (F_ERR if msg.is_error_frame else 0) | (F_FD if msg.is_fd else 0)
            | (F_BRS if msg.bitrate_switch else 0) | (F_ESI if msg.error_state_indicator else 0))


def _masked_frame(opcode: int, payload: bytes) -> bytes:
    """A final client frame with the zero key (see the module docstring)."""
    n = len(payload)
    if n <= 125:
        head = bytes((0x80 | opcode, 0x80 | n))
    elif n <= 0xFFFF:
        head = bytes((0x80 | opcode, 0x80 | 126)) + n.to_bytes(2, "big")
    else:
        head = bytes((0x80 | opcode, 0x80 | 127)) + n.to_bytes(8, "big")
    return head + _ZERO_KEY + payload


class RelayBus(DirectRecv, can.BusABC):
    """A python-can bus on a ``ws://127.0.0.1:<port>/`` channel (see the module docstring).

    Args:
        channel: ``ws://host:port/`` (``host:port`` alone is taken as ``ws://``).
        **config: further bus keywords, passed to the server in the ``bus_request`` as
            python-can-remote's client does.

    Raises:
        OSError: no server listens there (``ConnectionRefusedError``) or the connection broke.
        can.CanInitializationError: the server did not speak the protocol.
    """

    def __init__(self, channel: str, can_filters: Any = None, **config: Any) -> None:
        url = channel if "://" in channel else f"ws://{channel}"
        parts = urlparse(url)
        if parts.scheme != "ws" or not parts.hostname:
            raise can.CanInitializationError(f"RelayBus needs a ws://host:port/ channel, got {channel!r}")
        port = parts.port or 80
        self.socket = socket.create_connection((parts.hostname, port), timeout=_HANDSHAKE_TIMEOUT_S)
        try:
            self.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._buf = bytearray()
            self._frames: collections.deque[can.Message] = collections.deque()
            self._send_lock = threading.Lock()
            self.ws_protocol = self._handshake(parts.hostname, port, parts.path or "/")
            if self.ws_protocol != BINARY_PROTOCOL:
                raise can.CanInitializationError(f"server speaks {self.ws_protocol!r} only")
            self._send_text({"type": "bus_request", "payload": {"config": config}})
            info = self._await_bus_response()
            self.socket.settimeout(None)
        except BaseException:
            self.socket.close()
            raise
        self._poll = select.poll()
        self._poll.register(self.socket, select.POLLIN)
        self.channel_info = f"{info} on {url}"
        self.channel = channel
        super().__init__(channel, can_filters=can_filters)

    # -- set-up --------------------------------------------------------------------------------
    def _handshake(self, host: str, port: int, path: str) -> str:
        key = base64.b64encode(os.urandom(16)).decode()
        request = (f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\n"
                   f"User-Agent: python-can/{can.__version__}\r\nUpgrade: WebSocket\r\n"
                   "Connection: Upgrade\r\n"
                   f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                   f"Sec-WebSocket-Protocol: {BINARY_PROTOCOL},{JSON_PROTOCOL}\r\n\r\n")
        self.socket.sendall(request.encode("latin-1"))
        while (end := self._buf.find(b"\r\n\r\n")) < 0:
            self._read_some()
        head = bytes(self._buf[:end]).decode("latin-1").split("\r\n")
        del self._buf[:end + 4]
        headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in head[1:])}
        accept = base64.b64encode(hashlib.sha1(key.encode() + WS_GUID).digest()).decode()
        status = head[0].split()
        if len(status) < 2 or status[1] != "101" or headers.get("sec-websocket-accept") != accept:
            raise can.CanInitializationError(f"not a CAN bus server (it answered {head[0]!r})")
        return headers.get("sec-websocket-protocol", "")

    def _await_bus_response(self) -> str:
        deadline = time.monotonic() + _HANDSHAKE_TIMEOUT_S
        while time.monotonic() < deadline:
            self._parse()
            info = getattr(self, "_bus_info", None)
            if info is not None:
                return info
            self._read_some()
        raise can.CanInitializationError("no response from the CAN bus server")

    # -- wire ----------------------------------------------------------------------------------
    def _read_some(self, flags: int = 0) -> bool:
        """Append what the socket holds to the buffer (blocking unless ``flags``); False: nothing there."""
        try:
            chunk = self.socket.recv(_RECV_BYTES, flags)
        except (BlockingIOError, InterruptedError):
            return False
        if not chunk:
            raise ConnectionResetError("the CAN bus server closed the connection")
        self._buf += chunk
        return True

    def _parse(self) -> None:
        """Turn every complete frame of the buffer into a message (or act on a control frame)."""
        buf = self._buf
        pos, end = 0, len(buf)
        unpack, frames = BINARY_MSG.unpack_from, self._frames
        while end - pos >= 2:
            b1, length = buf[pos], buf[pos + 1] & 0x7F
            head = 2
            if length == 126:
                if end - pos < 4:
                    break
                length, head = int.from_bytes(buf[pos + 2:pos + 4], "big"), 4
            elif length == 127:
                if end - pos < 10:
                    break
                length, head = int.from_bytes(buf[pos + 2:pos + 10], "big"), 10
            if end - pos < head + length:
                break
            start = pos + head
            pos = start + length
            opcode = b1 & 0x0F
            if opcode == OP_BINARY:
                if length >= 1 + BINARY_MSG.size and buf[start] == BINARY_TYPE:
                    ts, arb_id, dlc, flags = unpack(buf, start + 1)
                    # (a slice of the buffer is a bytearray of its own: the message keeps it as its data)
                    frames.append(can.Message(timestamp=ts, arbitration_id=arb_id, dlc=dlc,
                                              data=buf[start + 1 + BINARY_MSG.size:pos],
                                              **_FLAG_FIELDS[flags]))
            elif opcode == OP_TEXT:
                self._text(bytes(buf[start:pos]))
            elif opcode == OP_PING:
                self._send_raw(_masked_frame(OP_PONG, bytes(buf[start:pos])))
            elif opcode == OP_CLOSE:
                del buf[:pos]
                raise ConnectionResetError("the CAN bus server closed the connection")
        del buf[:pos]

    def _text(self, payload: bytes) -> None:
        try:
            event = json.loads(payload)
            kind, body = event["type"], event.get("payload")
        except (ValueError, TypeError, KeyError):
            return
        if kind == "bus_response":
            self._bus_info = str((body or {}).get("channel_info", ""))
        elif kind == "message":
            self._frames.append(can.Message(**body))
        elif kind == "error":
            raise can.CanOperationError(f"CAN bus server: {body}")

    def _send_raw(self, data: bytes) -> None:
        with self._send_lock:
            self.socket.sendall(data)

    def _send_text(self, event: dict[str, Any]) -> None:
        self._send_raw(_masked_frame(OP_TEXT, json.dumps(event).encode()))

    @staticmethod
    def _encode(msg: can.Message) -> bytes:
        data = bytes(msg.data)
        return _OUT.pack(0x80 | OP_BINARY, 0x80 | (1 + BINARY_MSG.size + len(data)), _ZERO_KEY, BINARY_TYPE,
                         float(msg.timestamp), msg.arbitration_id, msg.dlc, binary_flags(msg)) + data

    # -- python-can ----------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Put ``msg`` on the bus."""
        self._send_raw(self._encode(msg))

    def send_many(self, msgs: Iterable[can.Message]) -> None:
        """Put ``msgs`` on the bus in one write (the server forwards them together)."""
        self._send_raw(b"".join([self._encode(m) for m in msgs]))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        frames = self._frames
        if frames:
            return frames.popleft(), False
        if timeout is not None and timeout <= 0.0:
            if self._read_some(socket.MSG_DONTWAIT):
                self._parse()
            return (frames.popleft() if frames else None), False
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left_ms = None if deadline is None else max(0, math.ceil((deadline - time.monotonic()) * 1000.0))
            if self._poll.poll(left_ms) and self._read_some(socket.MSG_DONTWAIT):
                self._parse()
                if frames:
                    return frames.popleft(), False
            if deadline is not None and time.monotonic() >= deadline:
                return None, False

    def fileno(self) -> int:
        return self.socket.fileno()

    def shutdown(self) -> None:
        """Say goodbye to the server and close the connection (quietly if it is gone already)."""
        if self._is_shutdown:
            return
        try:
            self._send_raw(_masked_frame(OP_CLOSE, struct.pack(">H", 1000)))
            self.socket.shutdown(socket.SHUT_WR)
            # The server answers with its own CLOSE and hangs up: wait for that (briefly), as
            # python-can-remote's client does, so the server's side ends in order too.
            deadline = time.monotonic() + _CLOSE_WAIT_S
            while (left := deadline - time.monotonic()) > 0 and self._poll.poll(left * 1000.0) \
                    and self.socket.recv(_RECV_BYTES, socket.MSG_DONTWAIT):
                pass
        except OSError:
            pass
        finally:
            self.socket.close()
            super().shutdown()
