"""``redarm-canbus``: a cross-process CAN bus on loopback (python-can-remote over a virtual bus).

The kernels here have no SocketCAN, so processes share a bus through a python-can-remote 0.3.0
server: every client connection gets its own python-can ``virtual`` bus on one channel name,
and the virtual buses deliver each frame to all the others. The server binds **127.0.0.1
only** (any other address is refused) on an ephemeral port by default, and announces it::

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
  traffic rather than a growing backlog.

The server process asks for real-time scheduling (``--realtime-priority``, SCHED_FIFO, default
50, with a fallback and one log line when not permitted): it is the wire between the driver and
the (simulated) modules.

Python helpers: :class:`LoopbackBusServer` runs the server in a thread of this process (tests);
:func:`start_bus_server` starts ``python -m redarm_ros.can.bus_server`` as a subprocess and waits
until it is ready.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import ipaddress
import logging
import os
import queue
import re
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

from can_remote.server import ClientRequestHandler, RemoteServer, RemoteServerProtocol
from can_remote.websocket import WebSocket, get_accept_key

from redarm_ros.can import realtime
from redarm_ros.can.bus import check_message
from redarm_ros.errors import BusError, InvalidInputError
from redarm_ros.procs import ChildDiedError, ManagedProcess, ReadinessTimeoutError, python_module_cmd

logger = logging.getLogger(__name__)

#: Unread bytes in a client's server-side socket beyond which its frames are skipped (~650 frames).
INGRESS_BACKLOG_BYTES = 16 * 1024
#: Frames a receiving client's queue holds; when full the oldest is dropped.
EGRESS_QUEUE = 512
#: Kernel socket buffers of each client connection (bytes): small, so no backlog hides in them.
SOCKET_BUFFER_BYTES = 64 * 1024
#: A sender stamp may be this old (s) and still be taken as the time the frame went on the bus.
MAX_STAMP_AGE_S = 1.0
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
# Hardening: python-can-remote 0.3.0 re-packs every frame for every other client in a per-client
# sender thread. A frame it cannot pack (e.g. dlc 1000, sent by a JSON client) kills those threads
# silently: the other clients stay connected but never receive again (measured). So every frame a
# client sends is checked on entry and dropped (and counted) if malformed, as a CAN controller
# would refuse to transmit it.
# --------------------------------------------------------------------------------------------------


def _pending_bytes(sock: socket.socket) -> int:
    """Bytes received by the kernel on ``sock`` and not read yet."""
    try:
        return struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0]
    except OSError:
        return 0


class _DropOldestQueue(queue.Queue):  # type: ignore[type-arg]
    """A receiving client's frame queue: never blocks the sender; when full, the oldest frame goes."""

    def __init__(self, maxsize: int, server: _CheckedRemoteServer) -> None:
        super().__init__(maxsize)
        self._server = server

    def put(self, item: object, block: bool = True, timeout: float | None = None) -> None:
        with self.mutex:
            if 0 < self.maxsize <= self._qsize():
                self._get()
                self._server.note_overflow()
            self._put(item)
            self.unfinished_tasks += 1
            self.not_empty.notify()


class _CheckedBus:
    """Proxy for one client's server-side bus: ``send`` drops frames failing :func:`check_message`,
    skips frames while the client's unread backlog is too large, and stamps unstamped frames."""

    def __init__(self, bus: Any, server: _CheckedRemoteServer, sock: socket.socket | None = None) -> None:
        self._bus = bus
        self._server = server
        self._sock = sock

    def send(self, msg: Any, timeout: float | None = None) -> None:
        try:
            check_message(msg)
        except (InvalidInputError, AttributeError, TypeError) as exc:
            self._server.note_dropped(exc)
            return
        if self._sock is not None and _pending_bytes(self._sock) > INGRESS_BACKLOG_BYTES:
            self._server.note_skipped()
            return
        now = time.time()
        if not (now - MAX_STAMP_AGE_S <= msg.timestamp <= now + 0.001):
            msg.timestamp = now  # unstamped (or not a wall-clock stamp): on the bus now
        self._bus.send(msg, timeout)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._bus, name)


class _CheckedProtocol(RemoteServerProtocol):
    def __init__(
        self, config: dict[str, Any], websocket: WebSocket, server: _CheckedRemoteServer, sock: socket.socket
    ) -> None:
        self._checked_server = server  # before the library's __init__, which answers the client
        super().__init__(config, websocket)
        self.bus = _CheckedBus(self.bus, server, sock)
        self.sock = sock

    # A client that went away (killed, crashed) breaks the pipe under the library's send thread: end
    # this connection quietly (its receive side sees the close and cleans up) instead of leaving an
    # unhandled exception in that thread.
    def send_msg(self, msg: Any) -> None:
        try:
            super().send_msg(msg)
        except OSError as exc:
            self._client_gone(exc)

    def send(self, event_type: str, payload: Any) -> None:
        try:
            super().send(event_type, payload)
        except OSError as exc:
            self._client_gone(exc)

    def _client_gone(self, exc: OSError) -> None:
        if getattr(self, "running", False):
            logger.info("client connection lost while sending (%s); closing it", exc)
        self.running = False

    def send_bus_response(self, channel_info: str) -> None:
        # The client may send as soon as it has this answer: bound our queue first.
        self._bound_queue(self.bus, self._checked_server)
        super().send_bus_response(channel_info)

    @staticmethod
    def _bound_queue(bus: Any, server: _CheckedRemoteServer) -> None:
        # python-can's virtual bus delivers into one unbounded, blocking queue per bus (listed in its
        # channel): swap in a bounded one that drops the oldest frame instead of growing or blocking.
        try:
            from can.interfaces.virtual import channels_lock

            with channels_lock:
                i = next(k for k, q in enumerate(bus.channel) if q is bus.queue)
                bounded = _DropOldestQueue(EGRESS_QUEUE, server)
                while not bus.queue.empty():  # nothing already delivered is lost
                    bounded.put(bus.queue.get_nowait())
                bus.channel[i] = bounded
                bus.queue = bounded
        except (ImportError, AttributeError, StopIteration) as exc:  # another python-can layout
            logger.warning("could not bound the client queue (%r): a slow client may build a backlog", exc)


class _CheckedHandler(ClientRequestHandler):
    """The library's handler with the checked protocol (same WebSocket handshake)."""

    def start_websocket(self) -> None:
        self.send_response(101)
        self.send_header("Upgrade", "WebSocket")
        self.send_header("Connection", "Upgrade")
        self.send_header("Sec-WebSocket-Accept", get_accept_key(self.headers["Sec-WebSocket-Key"]))
        offered = [p.strip() for p in self.headers.get("Sec-WebSocket-Protocol", "can.json.v1").split(",")]
        chosen = "can.binary+json.v1" if "can.binary+json.v1" in offered else "can.json.v1"
        self.send_header("Sec-WebSocket-Protocol", chosen)
        self.end_headers()
        for opt in (socket.SO_SNDBUF, socket.SO_RCVBUF):
            with contextlib.suppress(OSError):
                self.request.setsockopt(socket.SOL_SOCKET, opt, SOCKET_BUFFER_BYTES)
        server: _CheckedRemoteServer = self.server  # type: ignore[assignment]
        protocol = _CheckedProtocol(
            server.config, WebSocket(None, chosen, sock=self.request), server, self.request
        )
        server.clients.append(protocol)
        try:
            protocol.run()
        finally:
            server.clients.remove(protocol)


class _CheckedRemoteServer(RemoteServer):
    def __init__(self, host: str, port: int, **config: Any) -> None:
        super().__init__(host, port, **config)
        self.RequestHandlerClass = _CheckedHandler
        self.dropped = 0
        self.skipped = 0
        self.overflowed = 0
        self._drop_lock = threading.Lock()

    def _count(self, counter: str, log_every: int) -> int | None:
        """Add one to the counter attribute ``counter``; its new value when it is the first or a
        multiple of ``log_every`` (time to log it), else None."""
        with self._drop_lock:
            n = getattr(self, counter) + 1
            setattr(self, counter, n)
        return n if n == 1 or n % log_every == 0 else None

    def note_dropped(self, exc: BaseException) -> None:
        if (n := self._count("dropped", 100)) is not None:
            logger.warning("dropped malformed CAN frame from a client (%d so far): %s", n, exc)

    def note_skipped(self) -> None:
        if (n := self._count("skipped", 10000)) is not None:
            logger.warning("a client sends faster than the bus forwards: skipping its backlog "
                           "(%d frames so far)", n)

    def note_overflow(self) -> None:
        if (n := self._count("overflowed", 10000)) is not None:
            logger.warning("a client reads slower than the bus delivers: dropping its oldest frames "
                           "(%d so far)", n)


class LoopbackBusServer:
    """A python-can-remote server on loopback, served from a background thread of this process.

    Args:
        host: loopback address to bind (anything else is refused).
        port: TCP port, 0 for an ephemeral one (read :attr:`port` after construction).
        channel: virtual bus channel name; unique by default so two servers never share a bus.

    Raises:
        InvalidInputError: non-loopback ``host``.
        BusError: the port cannot be bound.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, channel: str | None = None) -> None:
        self.host = check_loopback(host)
        self.virtual_channel = channel or f"redarm-canbus-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            self._server = _CheckedRemoteServer(
                self.host, port, interface="virtual", channel=self.virtual_channel, preserve_timestamps=True
            )
        except OSError as exc:
            raise BusError(f"cannot bind CAN bus server to {self.host}:{port}: {exc}") from exc
        self.port: int = self._server.server_port
        self._thread: threading.Thread | None = None

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
        return self._server.dropped

    @property
    def skipped_frames(self) -> int:
        """Frames skipped because their sender's unread backlog was too large."""
        return self._server.skipped

    @property
    def overflowed_frames(self) -> int:
        """Frames dropped from full receive queues (slow readers)."""
        return self._server.overflowed

    @property
    def client_count(self) -> int:
        """Number of connected clients."""
        return len(self._server.clients)

    def start(self) -> LoopbackBusServer:
        """Serve in a daemon thread; returns self."""
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._server.serve_forever,
                kwargs={"poll_interval": 0.1},
                name="redarm-canbus",
                daemon=True,
            )
            self._thread.start()
        return self

    def close_clients(self, wait_s: float = 5.0) -> None:
        """Close every client connection (clients see ``WebsocketClosed``) and wait until each
        connection's server-side bus is shut down (at most ``wait_s``); keep listening."""
        for proto in list(self._server.clients):
            proto.running = False
            with contextlib.suppress(OSError):
                proto.close()  # a CLOSE frame, so a reading client learns why
            with contextlib.suppress(OSError):
                # Unblocks the handler even if the client never answers the CLOSE.
                proto.sock.shutdown(socket.SHUT_RDWR)
        deadline = time.monotonic() + wait_s
        while self._server.clients and time.monotonic() < deadline:
            time.sleep(0.01)

    def stop(self) -> None:
        """Stop serving, close all client connections and the listening socket (idempotent)."""
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join(5.0)
            self._thread = None
        self.close_clients()
        with contextlib.suppress(OSError):
            self._server.server_close()

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
        description="Loopback CAN bus server (python-can-remote over a python-can virtual bus).",
    )
    ap.add_argument("--host", default="127.0.0.1", help="loopback address to bind (only 127.0.0.0/8)")
    ap.add_argument("--port", type=int, default=0, help="TCP port, 0 = ephemeral (default)")
    ap.add_argument("--port-file", type=Path, help="write the chosen port to this file")
    ap.add_argument("--channel", help="virtual bus channel name (default: unique per process)")
    ap.add_argument("--realtime-priority", type=int, default=DEFAULT_REALTIME_PRIORITY, metavar="N",
                    help="SCHED_FIFO priority (1..98, 0 = normal scheduling; default "
                    f"{DEFAULT_REALTIME_PRIORITY}); falls back to a raised nice level when not permitted")
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
        server = LoopbackBusServer(args.host, args.port, args.channel)
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
    if args.port_file is not None:
        _write_port_file(args.port_file, server.port)
    sys.stdout.write(f"{PORT_LINE}={server.port}\n{CHANNEL_LINE}={server.channel}\n")
    sys.stdout.flush()
    logger.info("CAN bus server on %s (virtual channel %s)", server.channel, server.virtual_channel)
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
