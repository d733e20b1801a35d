"""``redarm-canbus``: a cross-process CAN bus on loopback (a relay speaking python-can-remote's protocol).

The kernels here have no SocketCAN, so processes share a bus through this server: every client
connects with python-can-remote 0.3.0 (python-can's ``remote`` interface, unchanged), and the server,
a single-threaded relay, forwards every frame a client sends to every other client, as raw bytes
(no per-frame python-can objects, queues or threads). A sender does not get its own frames back. The
server binds **127.0.0.1 only** (any other address is refused) on an ephemeral port by default, and
announces it::

    REDARM_CANBUS_PORT=<port>
    REDARM_CANBUS_CHANNEL=ws://127.0.0.1:<port>/

on stdout (and in ``--port-file``, written atomically). Clients reach it with the python-can
configuration ``interface="remote", channel="ws://127.0.0.1:<port>/"`` (see
:func:`client_config`), e.g. ``CAN_INTERFACE=remote CAN_CHANNEL=ws://127.0.0.1:<port>/``.

SIGINT/SIGTERM close every client connection (clients then see ``WebsocketClosed``) and exit 0.

Like a real bus, it never holds on to old traffic (a flood must not leave seconds of backlog
behind, during which the modules' replies would wait in line):

* every frame keeps the time its sender put it on the bus (``msg.timestamp``, wall time; an
  unstamped or implausible stamp is replaced by the server's receipt time), so receivers can judge
  when a frame was sent, not when it arrived;
* a client whose unread traffic in the server's socket exceeds :data:`INGRESS_BACKLOG_BYTES` (it
  sends faster than the bus forwards) has frames skipped until it is back under, as a CAN
  controller loses arbitration; skipped frames are counted;
* each receiving client has a bounded queue (:data:`EGRESS_QUEUE` frames; the oldest is dropped
  when it is full, counted) and a small socket send buffer, so a slow reader sees the latest
  traffic rather than a growing backlog;
* a malformed frame (id out of range, DLC not matching the data, too long) is dropped on entry and
  counted, as a CAN controller would refuse to transmit it.

Clients speaking python-can-remote's JSON protocol (``can.json.v1``) and its periodic tasks are
served too; a plain HTTP GET gets python-can-remote's trace page.

The server process asks for real-time scheduling (``--realtime-priority``, SCHED_FIFO, default
50, with a fallback and one log line when not permitted): it is the wire between the driver and
the (simulated) modules. At normal scheduling its relay thread asks for a short time slice
(``--slice-ms``, :func:`redarm_ros.can.realtime.request_slice`).

Python helpers: :class:`LoopbackBusServer` runs the server in a thread of this process (tests);
:func:`start_bus_server` starts ``python -m redarm_ros.can.bus_server`` as a subprocess and waits
until it is ready.
"""

from __future__ import annotations

import argparse
import base64
import collections
import contextlib
import fcntl
import hashlib
import ipaddress
import json
import logging
import math
import mimetypes
import os
import re
import selectors
import signal
import socket
import struct
import sys
import tempfile
import termios
import threading
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from redarm_ros.can import realtime
from redarm_ros.errors import BusError, InvalidInputError
from redarm_ros.procs import ChildDiedError, ManagedProcess, ReadinessTimeoutError, python_module_cmd

logger = logging.getLogger(__name__)

#: Unread bytes in a client's server-side socket beyond which its frames are skipped (~650 frames).
INGRESS_BACKLOG_BYTES = 16 * 1024
#: Frames a receiving client's queue holds; when full the oldest is dropped.
EGRESS_QUEUE = 512
#: Kernel receive buffer of each client connection (bytes): what a sender may have in flight.
SOCKET_BUFFER_BYTES = 64 * 1024
#: Kernel send buffer of each client connection (bytes): small, so no backlog hides in it (the
#: relay's own queue of :data:`EGRESS_QUEUE` frames is where a slow reader's frames wait).
SEND_BUFFER_BYTES = 4 * 1024
#: A sender stamp may be this old (s) and still be taken as the time the frame went on the bus.
MAX_STAMP_AGE_S = 1.0
#: A frame read this long (s) after its sender's stamp is logged (with the time) as a slow hop.
SLOW_HOP_S = 0.005
#: At most this many slow hops are logged per second.
SLOW_HOP_LOGS_PER_S = 20
DEFAULT_REALTIME_PRIORITY = 50

PORT_LINE = "REDARM_CANBUS_PORT"
CHANNEL_LINE = "REDARM_CANBUS_CHANNEL"
_PORT_RE = re.compile(rf"^{PORT_LINE}=(\d+)\s*$")


def client_config(port: int, host: str = "127.0.0.1") -> dict[str, Any]:
    """python-can keyword arguments for a client of the server on ``port``."""
    return {"interface": "remote", "channel": f"ws://{host}:{port}/"}


def client_env(port: int, host: str = "127.0.0.1") -> dict[str, str]:
    """Environment variables that make ``can.Bus()`` reach the server on ``port``."""
    cfg = client_config(port, host)
    return {"CAN_INTERFACE": cfg["interface"], "CAN_CHANNEL": cfg["channel"]}


def check_loopback(host: str) -> str:
    """Return the IPv4 loopback address for ``host``; refuse anything else.

    Raises:
        InvalidInputError: ``host`` is not ``localhost`` or an address in 127.0.0.0/8.
    """
    if host == "localhost":
        return "127.0.0.1"
    try:
        addr = ipaddress.ip_address(host)
    except ValueError:
        raise InvalidInputError(
            f"bus server host must be a loopback IPv4 address, got {host!r}", field="host", value=host
        ) from None
    if addr.version != 4 or not addr.is_loopback:
        raise InvalidInputError(
            f"refusing to bind the CAN bus server to {host!r}: only 127.0.0.0/8 is allowed",
            field="host",
            value=host,
        )
    return str(addr)


# --------------------------------------------------------------------------------------------------
# The relay: one thread, one selector, raw frames.
#
# python-can-remote's own server costs, per frame, three blocking recv calls, a can.Message built on
# entry, a virtual bus that copies it into a queue per receiver, and a sender thread per receiver that
# re-packs it: most of the stack's bus cost. The relay speaks the same protocol to its clients
# (WebSocket handshake, the bus_request / bus_response exchange, binary ``can.binary+json.v1`` or
# JSON ``can.json.v1`` frames, periodic_start / periodic_stop) but forwards each frame as bytes: a
# binary frame is checked and, if its stamp is implausible, re-stamped in place, then the same bytes
# go to every other binary client (a JSON client gets the JSON form, built once per frame).
#
# Hardening kept from the python-can-remote era: every frame a client sends is checked on entry and
# dropped (and counted) if malformed, as a CAN controller would refuse to transmit it (a frame with
# dlc 1000 used to kill delivery to everyone else).
# --------------------------------------------------------------------------------------------------

_WS_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
_OP_TEXT, _OP_BINARY, _OP_CLOSE, _OP_PING, _OP_PONG = 0x1, 0x2, 0x8, 0x9, 0xA
_BINARY_MSG = struct.Struct(">dIBB")  # timestamp, arbitration id, dlc, flags (after a type byte of 1)
_BINARY_TYPE = 1
_F_EXT, _F_RTR, _F_ERR, _F_FD, _F_BRS, _F_ESI = 0x1, 0x2, 0x4, 0x8, 0x10, 0x20
_ZERO_KEY = b"\0\0\0\0"
_MAX_REQUEST_BYTES = 16 * 1024  # an HTTP upgrade request larger than this is refused
_MAX_WS_PAYLOAD = 64 * 1024  # a WebSocket message larger than this ends the connection
_RECV_BYTES = 64 * 1024
_WEB_DIR = "web"  # python-can-remote's trace page, served to a browser as its server did


def _ws_header(opcode: int, length: int) -> bytes:
    """Header of an unmasked (server to client) final WebSocket frame."""
    if length <= 125:
        return bytes((0x80 | opcode, length))
    if length <= 0xFFFF:
        return bytes((0x80 | opcode, 126)) + length.to_bytes(2, "big")
    return bytes((0x80 | opcode, 127)) + length.to_bytes(8, "big")


def _ws_frame(opcode: int, payload: bytes) -> bytes:
    return _ws_header(opcode, len(payload)) + payload


def _unmask(data: bytes, mask: bytes) -> bytes:
    n = len(data)
    if n == 0:
        return b""
    key = (mask * (n // 4 + 1))[:n]
    return (int.from_bytes(data, "big") ^ int.from_bytes(key, "big")).to_bytes(n, "big")


def _pending_bytes(sock: socket.socket) -> int:
    """Bytes received by the kernel on ``sock`` and not read yet."""
    try:
        return struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0]
    except OSError:
        return 0


def _binary_ok(payload: bytes) -> bool:
    """A binary frame message that :func:`check_message` would accept (same rules, on the bytes)."""
    if len(payload) < 1 + _BINARY_MSG.size or payload[0] != _BINARY_TYPE:
        return False
    _, arb_id, dlc, flags = _BINARY_MSG.unpack_from(payload, 1)
    n = len(payload) - 1 - _BINARY_MSG.size
    is_fd = bool(flags & _F_FD)
    return (
        arb_id <= (0x1FFFFFFF if flags & _F_EXT else 0x7FF)
        and dlc == n
        and n <= (64 if is_fd else 8)
        and not (flags & _F_RTR and is_fd)
    )


def _json_from_binary(payload: bytes) -> bytes:
    """The ``can.json.v1`` form of a checked binary frame message."""
    ts, arb_id, dlc, flags = _BINARY_MSG.unpack_from(payload, 1)
    msg: dict[str, Any] = {
        "timestamp": ts, "arbitration_id": arb_id, "is_extended_id": bool(flags & _F_EXT),
        "is_remote_frame": bool(flags & _F_RTR), "is_error_frame": bool(flags & _F_ERR), "dlc": dlc,
        "data": list(payload[1 + _BINARY_MSG.size:]),
    }
    if flags & _F_FD:
        msg.update(is_fd=True, bitrate_switch=bool(flags & _F_BRS),
                   error_state_indicator=bool(flags & _F_ESI))
    return json.dumps({"type": "message", "payload": msg}).encode()


def _binary_from_message(msg: Any) -> bytes:
    flags = ((_F_EXT if msg.is_extended_id else 0) | (_F_RTR if msg.is_remote_frame else 0)
             | (_F_ERR if msg.is_error_frame else 0) | (_F_FD if msg.is_fd else 0)
             | (_F_BRS if msg.bitrate_switch else 0) | (_F_ESI if msg.error_state_indicator else 0))
    head = _BINARY_MSG.pack(float(msg.timestamp), msg.arbitration_id, msg.dlc, flags)
    return bytes((_BINARY_TYPE,)) + head + bytes(msg.data)


class _Client:
    """One connection: its socket, read buffer, state (``http`` until upgraded, ``ws`` until its
    bus_request, then ``bus``), output queue and periodic tasks."""

    __slots__ = ("binary", "closing", "out", "partial", "peer", "periodic", "rbuf", "sock", "state",
                 "writing")

    def __init__(self, sock: socket.socket, peer: str) -> None:
        self.sock = sock
        self.peer = peer
        self.rbuf = bytearray()
        self.state = "http"
        self.binary = False
        self.out: collections.deque[bytes] = collections.deque()
        self.partial: memoryview | None = None
        self.writing = False
        self.periodic: dict[int, list[Any]] = {}  # arbitration id -> [payload, period, next, end]
        self.closing = False


class _Relay:
    """The single-threaded relay; :class:`LoopbackBusServer` drives it."""

    def __init__(self, host: str, port: int, channel: str, slice_ms: float = 0.0) -> None:
        self.channel = channel
        self.slice_ms = slice_ms
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.listener.bind((host, port))
            self.listener.listen(16)
        except OSError:
            self.listener.close()
            raise
        self.listener.setblocking(False)
        self.port: int = self.listener.getsockname()[1]
        self.sel = selectors.DefaultSelector()
        self.sel.register(self.listener, selectors.EVENT_READ, None)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self.sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self.clients: list[_Client] = []  # every connection
        self.on_bus: list[_Client] = []  # connections that made their bus_request
        self.dropped = 0
        self.skipped = 0
        self.overflowed = 0
        self.slow_hops = 0  # bursts read SLOW_HOP_S or more after their sender's stamp
        self.max_hop_ms = 0.0  # the longest sender-stamp-to-read time of a frame (ms)
        self._hop_stamp = 0.0  # the sender stamp of the last slow hop noted
        self._hop_logs = realtime.PerSecondLimit(SLOW_HOP_LOGS_PER_S)
        self._stop = False
        self._close_all = threading.Event()
        self._closed_all = threading.Event()

    # -- counters ------------------------------------------------------------------------------
    @staticmethod
    def _due(n: int, every: int) -> bool:
        return n == 1 or n % every == 0

    def _note_dropped(self, why: str) -> None:
        self.dropped += 1
        if self._due(self.dropped, 100):
            logger.warning("dropped malformed CAN frame from a client (%d so far): %s", self.dropped, why)

    def _note_skipped(self) -> None:
        self.skipped += 1
        if self._due(self.skipped, 10000):
            logger.warning("a client sends faster than the bus forwards: skipping its backlog "
                           "(%d frames so far)", self.skipped)

    def _note_overflow(self, n: int) -> None:
        before = self.overflowed
        self.overflowed += n
        if before == 0 or before // 10000 != self.overflowed // 10000:
            logger.warning("a client reads slower than the bus delivers: dropping its oldest frames "
                           "(%d so far)", self.overflowed)

    # -- loop ----------------------------------------------------------------------------------
    def wake(self) -> None:
        with contextlib.suppress(OSError):
            self._wake_w.send(b"\0")

    def request_stop(self) -> None:
        self._stop = True
        self.wake()

    def serve(self) -> None:
        """Run until :meth:`request_stop`; then close every connection."""
        realtime.name_thread("canbus-relay")
        if self.slice_ms > 0:  # this thread is the hop every frame takes: woken first
            got = realtime.request_slice(self.slice_ms, who="redarm-canbus relay")
            (logger.warning if got.refused else logger.info)("%s", got.message)
        try:
            while not self._stop:
                timeout = self._run_periodic()
                for key, events in self.sel.select(timeout):
                    if key.data is None:
                        self._accept()
                    elif key.data == "wake":
                        with contextlib.suppress(OSError):
                            self._wake_r.recv(4096)
                    else:
                        client: _Client = key.data
                        if events & selectors.EVENT_WRITE and not client.closing:
                            self._flush(client)
                        if events & selectors.EVENT_READ and not client.closing:
                            self._read(client)
                if self._close_all.is_set():
                    self._close_all.clear()
                    self.close_every_client()
                    self._closed_all.set()
        finally:
            self.close_every_client()
            self._closed_all.set()

    def close_every_client(self) -> None:
        """Send every connection a CLOSE frame and close it (loop thread, or with the loop stopped)."""
        for c in list(self.clients):
            if c.state != "http":
                with contextlib.suppress(OSError):
                    c.sock.setblocking(False)
                    c.sock.send(_ws_frame(_OP_CLOSE, struct.pack(">H", 1001) + b"server stopping"))
            self._drop_client(c)

    def close(self) -> None:
        self.close_every_client()
        for s in (self.listener, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError, KeyError, ValueError):
                self.sel.unregister(s)
            s.close()
        self.sel.close()

    # -- connections ---------------------------------------------------------------------------
    def _accept(self) -> None:
        while True:
            try:
                sock, addr = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                logger.warning("accept failed: %s", exc)
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            for opt, size in ((socket.SO_SNDBUF, SEND_BUFFER_BYTES), (socket.SO_RCVBUF, SOCKET_BUFFER_BYTES)):
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, opt, size)
            c = _Client(sock, f"{addr[0]}:{addr[1]}")
            self.clients.append(c)
            self.sel.register(sock, selectors.EVENT_READ, c)

    def _drop_client(self, c: _Client) -> None:
        if c.closing:
            return
        c.closing = True
        with contextlib.suppress(KeyError, ValueError, OSError):
            self.sel.unregister(c.sock)
        with contextlib.suppress(OSError):
            c.sock.close()
        if c in self.clients:
            self.clients.remove(c)
        if c in self.on_bus:
            self.on_bus.remove(c)
        c.out.clear()
        c.periodic.clear()

    def _read(self, c: _Client) -> None:
        try:
            chunk = c.sock.recv(_RECV_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            logger.info("client %s: connection lost (%s)", c.peer, exc)
            self._drop_client(c)
            return
        if not chunk:
            self._drop_client(c)
            return
        c.rbuf += chunk
        if c.state == "http":
            self._handshake(c)
            if c.state == "http" or c.closing:
                return
        # What is still unread (in our buffer and in the kernel): a client that sends faster than the
        # bus forwards has frames skipped while this is above the limit, as arbitration would lose them.
        # A read shorter than asked for took all the kernel held: no need to ask it (one system call
        # less per read, two reads a driver cycle).
        backlog = len(c.rbuf) + (_pending_bytes(c.sock) if len(chunk) >= _RECV_BYTES else 0)
        binary_frames: list[bytes] = []
        now = time.time()
        buf = c.rbuf
        pos = 0
        while not c.closing:
            n = len(buf) - pos
            if n < 2:
                break
            b1, b2 = buf[pos], buf[pos + 1]
            length = b2 & 0x7F
            head = 2
            if length == 126:
                if n < 4:
                    break
                length = int.from_bytes(buf[pos + 2:pos + 4], "big")
                head = 4
            elif length == 127:
                if n < 10:
                    break
                length = int.from_bytes(buf[pos + 2:pos + 10], "big")
                head = 10
            masked = b2 & 0x80
            if length > _MAX_WS_PAYLOAD:
                logger.warning("client %s sent a %d-byte message: closing it", c.peer, length)
                self._drop_client(c)
                return
            total = head + (4 if masked else 0) + length
            if n < total:
                break
            if masked and buf[pos + head:pos + head + 4] != _ZERO_KEY:
                mask = bytes(buf[pos + head:pos + head + 4])
                payload = _unmask(bytes(buf[pos + head + 4:pos + total]), mask)
            elif masked:  # the all-zero key (our own clients, see relay_client): nothing to undo
                payload = bytes(buf[pos + head + 4:pos + total])
            else:
                payload = bytes(buf[pos + head:pos + total])
            pos += total
            backlog -= total
            opcode = b1 & 0x0F
            if opcode == _OP_BINARY and c.state == "bus":
                if not _binary_ok(payload):
                    self._note_dropped("binary frame failing the frame check")
                elif backlog > INGRESS_BACKLOG_BYTES:
                    self._note_skipped()
                else:
                    binary_frames.append(self._stamped(payload, now))
            elif opcode == _OP_TEXT:
                self._text(c, payload, binary_frames, now, backlog)
            elif opcode == _OP_PING:
                self._queue(c, [_ws_frame(_OP_PONG, payload)], drop=False)
            elif opcode == _OP_CLOSE:
                with contextlib.suppress(OSError):
                    c.sock.send(_ws_frame(_OP_CLOSE, payload[:2]))
                self._drop_client(c)
        if not c.closing:
            del buf[:pos]
        if binary_frames:
            self._deliver(c, binary_frames)

    def _stamped(self, payload: bytes, now: float) -> bytes:
        # Every frame keeps the time its sender put it on the bus; an unstamped or implausible one is
        # on the bus now.
        ts = _BINARY_MSG.unpack_from(payload, 1)[0]
        if now - MAX_STAMP_AGE_S <= ts <= now + 0.001:
            if now - ts >= SLOW_HOP_S and ts != self._hop_stamp:  # once per burst of one stamp
                self._hop_stamp = ts
                self._note_slow_hop(now - ts, ts)
            return payload
        return payload[:1] + struct.pack(">d", now) + payload[9:]

    def _note_slow_hop(self, hop_s: float, stamp: float) -> None:
        # How long a frame waited between its sender and this relay (the sender or the relay not
        # running), with its time, so that a late reply can be traced to the hop that held it.
        self.slow_hops += 1
        self.max_hop_ms = max(self.max_hop_ms, hop_s * 1e3)
        if self._hop_logs.allow(stamp):
            logger.warning("slow hop: frames stamped at wall time %.4f were read %.1f ms later (%d so far)",
                           stamp, hop_s * 1e3, self.slow_hops)

    def _text(self, c: _Client, payload: bytes, frames: list[bytes], now: float, backlog: int) -> None:
        try:
            event = json.loads(payload)
            kind = event["type"]
        except (ValueError, TypeError, KeyError):
            error = {"type": "error", "payload": "message must be a JSON object with a 'type'"}
            self._queue(c, [_ws_frame(_OP_TEXT, json.dumps(error).encode())], drop=False)
            return
        if kind == "bus_request" and c.state == "ws":
            info = json.dumps({"type": "bus_response",
                               "payload": {"channel_info": f"Virtual bus channel {self.channel}"}})
            self._queue(c, [_ws_frame(_OP_TEXT, info.encode())], drop=False)
            c.state = "bus"
            self.on_bus.append(c)
            return
        if c.state != "bus":
            return
        if kind == "message":
            frame = self._frame_from_json(event.get("payload"), now)
            if frame is None:
                return
            if backlog > INGRESS_BACKLOG_BYTES:
                self._note_skipped()
            else:
                frames.append(frame)
        elif kind == "periodic_start":
            try:
                body = event["payload"]
                frame = self._frame_from_json(body["msg"], now)
                period = float(body["period"])
                duration = body.get("duration")
            except (KeyError, TypeError, ValueError):
                return
            if frame is None or not period > 0.0:
                return
            arb_id = _BINARY_MSG.unpack_from(frame, 1)[1]
            t = time.monotonic()
            c.periodic[arb_id] = [frame, period, t, t + float(duration) if duration else math.inf]
            self.wake()
        elif kind == "periodic_stop":
            c.periodic.pop(event.get("payload"), None)

    def _frame_from_json(self, fields: Any, now: float) -> bytes | None:
        """A checked binary frame message from a JSON client's message fields (None: dropped)."""
        # python-can costs ~0.2 s of CPU to import and only JSON frames need it (imported already when
        # a JSON client connected, see _handshake); binary clients (the stack's own) never do.
        import can  # noqa: PLC0415

        from redarm_ros.can.bus import check_message  # noqa: PLC0415

        try:
            fields = dict(fields)
            if not isinstance(fields.get("timestamp", 0.0), (int, float)):
                del fields["timestamp"]  # not a time: stamped on receipt
            msg = can.Message(**fields)
            check_message(msg)
        except (InvalidInputError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            self._note_dropped(str(exc))
            return None
        return self._stamped(_binary_from_message(msg), now)

    def _run_periodic(self) -> float | None:
        """Send the periodic frames that are due; the time (s) until the next one (None: no task)."""
        nxt = math.inf
        now = time.monotonic()
        for c in self.on_bus:
            for arb_id, task in list(c.periodic.items()):
                frame, period, due, end = task
                if now >= end:
                    del c.periodic[arb_id]
                    continue
                if now >= due:
                    unstamped = frame[:1] + struct.pack(">d", 0.0) + frame[9:]  # on the bus now
                    self._deliver(c, [self._stamped(unstamped, time.time())])
                    task[2] = due = max(due + period, now)
                nxt = min(nxt, due - now)
        return None if nxt == math.inf else max(nxt, 0.0)

    # -- out -----------------------------------------------------------------------------------
    def _deliver(self, sender: _Client, frames: list[bytes]) -> None:
        """Queue ``frames`` (binary frame messages) to every client on the bus but ``sender``."""
        bin_out: list[bytes] | None = None
        json_out: list[bytes] | None = None
        for c in self.on_bus:
            if c is sender or c.closing:
                continue
            if c.binary:
                if bin_out is None:
                    bin_out = [_ws_frame(_OP_BINARY, f) for f in frames]
                self._queue(c, bin_out)
            else:
                if json_out is None:
                    json_out = [_ws_frame(_OP_TEXT, _json_from_binary(f)) for f in frames]
                self._queue(c, json_out)

    def _queue(self, c: _Client, data: list[bytes], drop: bool = True) -> None:
        c.out.extend(data)
        excess = len(c.out) - EGRESS_QUEUE
        if drop and excess > 0:
            for _ in range(excess):
                c.out.popleft()
            self._note_overflow(excess)
        if not c.writing:
            self._flush(c)

    def _flush(self, c: _Client) -> None:
        while c.partial is not None or c.out:
            if c.partial is not None:
                data = c.partial
            else:
                data = memoryview(b"".join(c.out))
                c.out.clear()
            try:
                sent = c.sock.send(data)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError as exc:
                logger.info("client %s: connection lost while sending (%s); closing it", c.peer, exc)
                self._drop_client(c)
                return
            if sent < len(data):
                c.partial = data[sent:]
                if not c.writing:
                    c.writing = True
                    self.sel.modify(c.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, c)
                return
            c.partial = None
        if c.writing:
            c.writing = False
            self.sel.modify(c.sock, selectors.EVENT_READ, c)

    # -- handshake -----------------------------------------------------------------------------
    def _handshake(self, c: _Client) -> None:
        end = c.rbuf.find(b"\r\n\r\n")
        if end < 0:
            if len(c.rbuf) > _MAX_REQUEST_BYTES:
                self._drop_client(c)
            return
        head = bytes(c.rbuf[:end]).decode("latin-1")
        del c.rbuf[:end + 4]
        lines = head.split("\r\n")
        parts = lines[0].split()
        headers = {}
        for line in lines[1:]:
            k, _, v = line.partition(":")
            headers[k.strip().lower()] = v.strip()
        if len(parts) < 2 or parts[0] != "GET":
            self._http_reply(c, "405 Method Not Allowed", b"", "text/plain")
            return
        if headers.get("upgrade", "").lower() != "websocket" or "sec-websocket-key" not in headers:
            self._serve_page(c, parts[1])
            return
        key = headers["sec-websocket-key"].encode()
        accept = base64.b64encode(hashlib.sha1(key + _WS_GUID).digest()).decode()
        offered = [p.strip() for p in headers.get("sec-websocket-protocol", "can.json.v1").split(",")]
        chosen = "can.binary+json.v1" if "can.binary+json.v1" in offered else "can.json.v1"
        c.binary = chosen == "can.binary+json.v1"
        if not c.binary:  # its frames need python-can (_frame_from_json): import it now, not mid-relay
            import can  # noqa: F401, PLC0415

            import redarm_ros.can.bus  # noqa: F401, PLC0415
        reply = ("HTTP/1.1 101 Switching Protocols\r\nUpgrade: WebSocket\r\nConnection: Upgrade\r\n"
                 f"Sec-WebSocket-Accept: {accept}\r\nSec-WebSocket-Protocol: {chosen}\r\n\r\n")
        c.state = "ws"
        self._queue(c, [reply.encode("latin-1")], drop=False)

    def _serve_page(self, c: _Client, path: str) -> None:
        """python-can-remote's trace page (a browser client of the JSON protocol), as its server served it."""
        import can_remote  # noqa: PLC0415 - only for a browser

        root = Path(can_remote.__file__).resolve().parent / _WEB_DIR
        rel = path.split("?", 1)[0].lstrip("/") or "index.html"
        if rel.endswith("/"):
            rel += "index.html"
        target = (root / rel).resolve()
        gz = target.with_name(target.name + ".gz")
        body, encoding = None, None
        if root in target.parents:
            for f, enc in ((gz, "gzip"), (target, None)):
                if f.is_file():
                    body, encoding = f.read_bytes(), enc
                    break
        if body is None:
            self._http_reply(c, "404 Not Found", b"not found\n", "text/plain")
        else:
            ctype = mimetypes.guess_type(str(target), strict=False)[0] or "application/octet-stream"
            self._http_reply(c, "200 OK", body, ctype, encoding)

    def _http_reply(self, c: _Client, status: str, body: bytes, ctype: str,
                    encoding: str | None = None) -> None:
        head = (f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
                "Connection: close\r\n")
        if encoding:
            head += f"Content-Encoding: {encoding}\r\n"
        with contextlib.suppress(OSError):
            c.sock.setblocking(True)
            c.sock.settimeout(2.0)
            c.sock.sendall(head.encode("latin-1") + b"\r\n" + body)
        self._drop_client(c)


class LoopbackBusServer:
    """The loopback bus relay, served from a background thread of this process.

    Args:
        host: loopback address to bind (anything else is refused).
        port: TCP port, 0 for an ephemeral one (read :attr:`port` after construction).
        channel: the bus's name (reported to clients as their channel info); unique by default.
        slice_ms: time slice (ms) the relay thread asks for (:func:`redarm_ros.can.realtime.request_slice`;
            0: the kernel's default).

    Raises:
        InvalidInputError: non-loopback ``host``.
        BusError: the port cannot be bound.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, channel: str | None = None,
                 slice_ms: float = 0.0) -> None:
        self.host = check_loopback(host)
        self.virtual_channel = channel or f"redarm-canbus-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            self._relay = _Relay(self.host, port, self.virtual_channel, slice_ms)
        except OSError as exc:
            raise BusError(f"cannot bind CAN bus server to {self.host}:{port}: {exc}") from exc
        self.port: int = self._relay.port
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def channel(self) -> str:
        """The python-can ``remote`` channel of this server."""
        return client_config(self.port, self.host)["channel"]

    def client_config(self) -> dict[str, Any]:
        """python-can keyword arguments to connect to this server."""
        return client_config(self.port, self.host)

    @property
    def dropped_frames(self) -> int:
        """Malformed frames from clients that were dropped instead of reaching the bus."""
        return self._relay.dropped

    @property
    def skipped_frames(self) -> int:
        """Frames skipped because their sender's unread backlog was too large."""
        return self._relay.skipped

    @property
    def overflowed_frames(self) -> int:
        """Frames dropped from full receive queues (slow readers)."""
        return self._relay.overflowed

    @property
    def client_count(self) -> int:
        """Number of connected clients (that made their bus request)."""
        return len(self._relay.on_bus)

    def start(self) -> LoopbackBusServer:
        """Serve in a daemon thread; returns self."""
        if self._thread is None and not self._closed:
            self._relay._stop = False
            self._thread = threading.Thread(target=self._relay.serve, name="redarm-canbus", daemon=True)
            self._thread.start()
        return self

    def close_clients(self, wait_s: float = 5.0) -> None:
        """Close every client connection (clients see ``WebsocketClosed``); keep listening."""
        relay = self._relay
        if self._thread is None:
            relay.close_every_client()
            return
        relay._closed_all.clear()
        relay._close_all.set()
        relay.wake()
        relay._closed_all.wait(wait_s)

    def stop(self) -> None:
        """Stop serving, close all client connections and the listening socket (idempotent)."""
        if self._thread is not None:
            self._relay.request_stop()
            self._thread.join(5.0)
            self._thread = None
        if not self._closed:
            self._closed = True
            self._relay.close()

    def __enter__(self) -> LoopbackBusServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _write_port_file(path: Path, port: int) -> None:
    # Atomic: a reader never sees a half-written file.
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as f:
        f.write(f"{port}\n")
    os.replace(tmp, path)


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``redarm-canbus``."""
    ap = argparse.ArgumentParser(
        prog="redarm-canbus",
        description="Loopback CAN bus server (a relay for python-can-remote clients).",
    )
    ap.add_argument("--host", default="127.0.0.1", help="loopback address to bind (only 127.0.0.0/8)")
    ap.add_argument("--port", type=int, default=0, help="TCP port, 0 = ephemeral (default)")
    ap.add_argument("--port-file", type=Path, help="write the chosen port to this file")
    ap.add_argument("--channel", help="bus name reported to clients (default: unique per process)")
    ap.add_argument("--realtime-priority", type=int, default=DEFAULT_REALTIME_PRIORITY, metavar="N",
                    help="SCHED_FIFO priority (1..98, 0 = normal scheduling; default "
                    f"{DEFAULT_REALTIME_PRIORITY}); falls back to a raised nice level when not permitted")
    ap.add_argument("--slice-ms", type=float, default=realtime.DEFAULT_SLICE_MS, metavar="MS",
                    help="time slice of the relay thread at normal scheduling (0.1..100 ms, 0 = the "
                    f"kernel's default; default {realtime.DEFAULT_SLICE_MS:g}): woken sooner, same CPU share")
    ap.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Run the bus server until SIGINT/SIGTERM. Exit codes: 0 clean, 2 bad arguments/bind failure."""
    args = build_parser().parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    # python-can-remote logs every connection at INFO; keep it quiet unless asked.
    logging.getLogger("can_remote").setLevel(level if args.verbose >= 2 else logging.WARNING)
    try:
        server = LoopbackBusServer(args.host, args.port, args.channel, args.slice_ms)
    except (InvalidInputError, BusError) as exc:
        print(f"redarm-canbus: {exc}", file=sys.stderr)
        return 2
    # The wire between driver and modules must not be starved (threads created below inherit it).
    prio = realtime.raise_priority(args.realtime_priority, who="redarm-canbus")
    if not prio.realtime and args.realtime_priority > 0:
        print(f"redarm-canbus: {prio.message}", file=sys.stderr)
    else:
        logger.info("%s", prio.message)

    stop = threading.Event()

    def _on_signal(signum: int, _frame: object) -> None:
        logger.info("signal %d: stopping", signum)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _on_signal)

    server.start()
    # Start-up objects are never scanned again: no full collection pauses the relay for milliseconds.
    realtime.freeze_gc()
    if args.port_file is not None:
        _write_port_file(args.port_file, server.port)
    sys.stdout.write(f"{PORT_LINE}={server.port}\n{CHANNEL_LINE}={server.channel}\n")
    sys.stdout.flush()
    logger.info("CAN bus server on %s (bus %s)", server.channel, server.virtual_channel)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        server.stop()
        if args.port_file is not None:
            with contextlib.suppress(OSError):
                args.port_file.unlink()
    logger.info("CAN bus server stopped")
    return 0


# --------------------------------------------------------------------------------------------------
# Subprocess helper
# --------------------------------------------------------------------------------------------------


class BusServerProcess:
    """A ``redarm-canbus`` child process: :attr:`port`, :meth:`client_config`, :meth:`stop`.

    The child is a :class:`redarm_ros.procs.ManagedProcess` (own session, dies with its parent,
    staged stop); :attr:`process` is its ``Popen``.
    """

    def __init__(self, child: ManagedProcess, port: int) -> None:
        self.child = child
        self.process = child.popen
        self.port = port

    @property
    def channel(self) -> str:
        """The python-can ``remote`` channel of the server."""
        return client_config(self.port)["channel"]

    def client_config(self) -> dict[str, Any]:
        """python-can keyword arguments to connect to the server."""
        return client_config(self.port)

    def client_env(self) -> dict[str, str]:
        """CAN_INTERFACE / CAN_CHANNEL for child processes."""
        return client_env(self.port)

    def stop(self, timeouts: tuple[float, float, float] = (3.0, 2.0, 2.0)) -> int:
        """End the server: SIGINT, wait, SIGINT again, wait, then SIGKILL. Returns the exit code."""
        return self.child.stop(timeouts)

    def __enter__(self) -> BusServerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_bus_server(
    *,
    port: int = 0,
    port_file: Path | None = None,
    python: str | None = None,
    env: dict[str, str] | None = None,
    ready_timeout_s: float = 30.0,
) -> BusServerProcess:
    """Start ``python -m redarm_ros.can.bus_server`` on 127.0.0.1 and wait for its port line.

    Raises:
        BusError: the server exited or did not announce its port within ``ready_timeout_s``
            (the process is killed then).
    """
    cmd = python_module_cmd(
        "redarm_ros.can.bus_server", "--host", "127.0.0.1", "--port", str(port), python=python
    )
    if port_file is not None:
        cmd += ["--port-file", str(port_file)]
    child_env = dict(os.environ if env is None else env)
    # Make the package importable in the child even when it is not installed (run from a checkout).
    pkg_root = str(Path(__file__).resolve().parents[2])
    child_env["PYTHONPATH"] = os.pathsep.join(p for p in (pkg_root, child_env.get("PYTHONPATH", "")) if p)
    child = ManagedProcess("canbus", cmd, env=child_env, sink=logger.debug)
    try:
        m = child.wait_for_line(_PORT_RE, ready_timeout_s)
    except ReadinessTimeoutError as exc:
        child.kill()
        raise BusError(
            f"CAN bus server did not announce its port within {ready_timeout_s} s: {exc.tail}"
        ) from exc
    except ChildDiedError as exc:
        child.kill()
        raise BusError(
            f"CAN bus server exited with code {exc.returncode} before announcing its port"
        ) from exc
    except BaseException:
        child.kill()
        raise
    return BusServerProcess(child, int(m.group(1)))

if __name__ == "__main__":
    sys.exit(main())
