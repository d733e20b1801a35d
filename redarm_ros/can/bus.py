"""Open the CAN bus from python-can configuration only, and guard the known transport flaws.

The transport is never chosen in code. :func:`resolve_config` and :func:`open_bus` use
python-can's own configuration chain, with this precedence (python-can's, fixed):

1. explicit keyword arguments (e.g. node parameters ``interface``/``channel``, passed through),
2. ``can.rc``,
3. environment ``CAN_INTERFACE``, ``CAN_CHANNEL``, ``CAN_BITRATE``, ``CAN_CONFIG`` (JSON with
   any further keyword; with ``config_context="X"`` the ``_X``-suffixed variables come first),
4. config files (``~/can.conf``, ``/etc/can.conf``, ``~/.can``, ``~/.canrc``, or ``config_file``).

Errors are translated into :class:`~redarm_ros.errors.BusError` (cause kept) with a message that
says what to do. A configuration that can never work raises its subclass
:class:`~redarm_ros.errors.BusConfigError` (retrying does not help): no interface configured, an
unknown interface type or a missing backend, and for socketcan

* errno 97 ``EAFNOSUPPORT``: the kernel has no SocketCAN at all;
* errno 19 ``ENODEV``: the interface does not exist: for a ``vcan*`` name the ``ip link`` commands to
  create it (see ``setup_vcan.sh`` next to this file), for a real adapter (``can0``) what to check.

Transient failures stay plain :class:`~redarm_ros.errors.BusError`: the interface exists but is down
(errno 100 ``ENETDOWN``), the loopback bus server is not listening (yet, or again). This module holds
every piece of advice text about opening the bus (:func:`describe_open_error`, :data:`NO_ANSWER_ADVICE`).
* remote (python-can-remote 0.3.0): a dead server surfaces as ``WebsocketClosed`` or
  ``OSError`` rather than ``CanError``, clients do not reconnect, and ``shutdown()`` can raise
  ``OSError``. :class:`ReconnectingBus` converts the first, offers :meth:`ReconnectingBus.reopen`
  for the second and swallows (and logs) the third.

Messages sent through :class:`ReconnectingBus` are checked (11/29-bit id range, DLC matches
data, classic CAN at most 8 bytes) before they reach the transport, because one malformed frame
on the remote bus can stop delivery to other clients; build them with ``check=True`` anyway.
"""

from __future__ import annotations

import errno
import logging
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, runtime_checkable

import can

from redarm_ros.errors import BusConfigError, BusError, InvalidInputError

logger = logging.getLogger(__name__)

VCAN_RECIPE = "sudo ip link add dev {ch} type vcan && sudo ip link set up {ch}"
#: Bringing a real SocketCAN adapter up; 500 kbit/s is the bit rate deployed PowerCube arms use.
ADAPTER_UP_RECIPE = "sudo ip link set {ch} up type can bitrate 500000"
#: What to check when the bus is open but no module answers (a real arm).
NO_ANSWER_ADVICE = ("check the CAN cable and its 120 ohm termination, that the modules are powered, and "
                    "that the bit rate and module_ids match the modules")

# Errors that mean "the connection is gone": the bus must be reopened. python-can-remote's
# ``WebsocketClosed`` and ``http.client.HTTPException`` can only be raised once their modules are loaded
# (by a python-can-remote bus), so they join then: importing python-can-remote builds an SSL context
# (~35 ms of CPU in every process that imports this module), and the stack's buses never load it.
_BASE_LOST_ERRORS: tuple[type[BaseException], ...] = (OSError, EOFError)


def _lost_errors() -> tuple[type[BaseException], ...]:
    """The "connection gone" exception types (evaluated only when an ``except`` clause is reached)."""
    errors = _BASE_LOST_ERRORS
    ws = sys.modules.get("can_remote.websocket")
    if ws is not None:
        errors += (ws.WebsocketClosed,)
    http_client = sys.modules.get("http.client")
    if http_client is not None:
        errors += (http_client.HTTPException,)
    return errors


def resolve_config(
    *, config_file: str | None = None, config_context: str | None = None, **kwargs: Any
) -> dict[str, Any]:
    """The python-can bus configuration that :func:`open_bus` would use (see module docstring).

    Keyword arguments whose value is ``None`` or ``""`` are dropped, so unset node parameters
    fall through to the environment.

    Raises:
        BusError: no interface is configured anywhere, or the interface name is unknown.
    """
    given = {k: v for k, v in kwargs.items() if v is not None and v != ""}
    try:
        cfg = can.util.load_config(path=config_file, config=given, context=config_context)
    except (can.CanInterfaceNotImplementedError, NotImplementedError, ValueError, TypeError) as exc:
        if not (given.get("interface") or given.get("bustype")) and "None" in str(exc):
            raise BusConfigError(
                "no CAN interface configured: pass interface/channel, or set CAN_INTERFACE and "
                "CAN_CHANNEL (e.g. CAN_INTERFACE=remote CAN_CHANNEL=ws://127.0.0.1:<port>/ for "
                "the redarm-canbus server, or CAN_INTERFACE=socketcan CAN_CHANNEL=vcan0)"
            ) from exc
        raise BusConfigError(f"invalid CAN configuration: {exc}") from exc
    return dict(cfg)


def _find_errno(exc: BaseException) -> int | None:
    """errno of ``exc`` or of anything in its cause/context chain (python-can wraps some)."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        code = getattr(cur, "errno", None)
        if isinstance(code, int):
            return code
        code = getattr(cur, "error_code", None)
        if isinstance(code, int) and code in errno.errorcode:
            return code
        cur = cur.__cause__ or cur.__context__
    return None


def is_virtual_channel(channel: str) -> bool:
    """True for a SocketCAN channel named like a virtual one (``vcan0``); ``can0`` counts as a real adapter
    (a vcan may be named ``can0`` too, so its messages give the vcan recipe as well)."""
    return channel.startswith("vcan")


def _socketcan_advice(ch: str, code: int | None) -> str | None:
    """What to do about errno ``code`` on SocketCAN channel ``ch`` (None: no advice for that code)."""
    if code == errno.EAFNOSUPPORT:
        return (
            "this kernel has no SocketCAN at all (errno 97 EAFNOSUPPORT: socket(AF_CAN) is not supported). "
            "Use a kernel with CAN/vcan modules (e.g. the User-Mode Linux guest in scripts/setup_uml.sh) or "
            "the loopback bus server: run redarm-canbus and set CAN_INTERFACE=remote "
            "CAN_CHANNEL=ws://127.0.0.1:<port>/"
        )
    if code == errno.ENODEV:
        if is_virtual_channel(ch):
            return (f"interface {ch!r} does not exist (errno 19 ENODEV). Create it with: "
                    f"{VCAN_RECIPE.format(ch=ch)} (or run redarm_ros/can/setup_vcan.sh {ch})")
        return (f"interface {ch!r} does not exist (errno 19 ENODEV): plug the CAN adapter in and check that "
                f"its kernel driver is loaded (`ip link show` lists the interfaces), then bring it up with: "
                f"{ADAPTER_UP_RECIPE.format(ch=ch)}; {NO_ANSWER_ADVICE}. (A virtual bus named {ch} "
                f"instead: {VCAN_RECIPE.format(ch=ch)})")
    if code == errno.ENETDOWN:
        up = f"sudo ip link set up {ch}" if is_virtual_channel(ch) else ADAPTER_UP_RECIPE.format(ch=ch)
        return f"interface {ch!r} is down (errno 100 ENETDOWN): {up}"
    return None


#: errno values that make a SocketCAN configuration fail for good (see the module docstring).
_PERMANENT_SOCKETCAN = (errno.EAFNOSUPPORT, errno.ENODEV)


def describe_open_error(cfg: dict[str, Any], exc: BaseException) -> str:
    """A message saying why opening ``cfg`` failed and what to do about it."""
    interface = cfg.get("interface")
    channel = cfg.get("channel")
    code = _find_errno(exc)
    where = f"CAN bus interface={interface!r} channel={channel!r}"
    if interface == "socketcan":
        advice = _socketcan_advice(str(channel or "vcan0"), code)
        if advice is not None:
            return f"cannot open {where}: {advice}"
    if isinstance(exc, (can.CanInterfaceNotImplementedError, ImportError)):
        return f"cannot open {where}: the python-can backend is not usable here ({exc})"
    if interface == "remote":
        if code == errno.ECONNREFUSED:
            return (
                f"cannot open {where}: no CAN bus server listens there (connection refused); "
                "start one with redarm-canbus --port-file PATH and use its port"
            )
        return f"cannot open {where}: the CAN bus server did not accept the connection ({exc!r})"
    return f"cannot open {where}: {exc!r}"


def is_permanent_open_error(cfg: dict[str, Any], exc: BaseException) -> bool:
    """True if opening ``cfg`` failed with ``exc`` for a reason that retrying cannot fix."""
    if isinstance(exc, (can.CanInterfaceNotImplementedError, ImportError)):
        return True
    return cfg.get("interface") == "socketcan" and _find_errno(exc) in _PERMANENT_SOCKETCAN


def _open_raw(cfg: dict[str, Any]) -> can.BusABC:
    try:
        if cfg.get("interface") == "remote":  # python-can-remote's protocol, our client (relay_client.py)
            from redarm_ros.can.relay_client import RelayBus  # noqa: PLC0415 - only for a remote bus

            return RelayBus(**{k: v for k, v in cfg.items() if k != "interface"})
        return can.Bus(ignore_config=True, **cfg)
    except BusError:
        raise
    except Exception as exc:  # any backend failure becomes a BusError with its cause
        kind = BusConfigError if is_permanent_open_error(cfg, exc) else BusError
        raise kind(describe_open_error(cfg, exc)) from exc


def safe_shutdown(bus: can.BusABC | None) -> None:
    """Shut ``bus`` down, swallowing and logging the errors a dead transport raises.

    python-can-remote's ``shutdown()`` raises ``OSError`` when the server is already gone; the
    bus is then marked shut down anyway (so its ``__del__`` stays quiet) and its socket closed.
    """
    if bus is None:
        return
    try:
        bus.shutdown()
        return
    except Exception as exc:  # shutdown must not fail the caller
        info = getattr(bus, "channel_info", bus)
        logger.info("ignoring error while shutting down CAN bus %s: %r", info, exc)
    try:
        can.BusABC.shutdown(bus)  # marks it shut down, stops periodic tasks
    except Exception:
        pass
    sock = getattr(bus, "socket", None)
    if sock is not None:
        try:
            sock.close()
        except OSError:
            pass


def check_message(msg: can.Message) -> None:
    """Refuse a frame that could upset other nodes (what ``can.Message(check=True)`` enforces).

    Raises:
        InvalidInputError: id out of range, DLC not matching the data, or too long.
    """
    id_max = 0x1FFFFFFF if msg.is_extended_id else 0x7FF
    n = len(msg.data)
    if (
        not 0 <= msg.arbitration_id <= id_max
        or msg.dlc != n
        or n > (64 if msg.is_fd else 8)
        or (msg.is_remote_frame and msg.is_fd)
    ):
        raise InvalidInputError(f"refusing to send malformed CAN frame: {msg}", field="msg", value=msg)


@runtime_checkable
class ReopenableBus(Protocol):
    """A bus that can reopen its transport in place after a failure (:class:`ReconnectingBus`)."""

    def reopen(self) -> None:
        """Open the same configuration again; raise :class:`BusError` if that fails."""


_CAN_RX_LOG = logging.getLogger("can.bus")  # python-can's log of received frames (BusABC.recv)


class DirectRecv:
    """Mixin for a :class:`can.BusABC` whose ``_recv_internal`` waits out the whole timeout: ``recv``
    returns what it gives when no software filter is set, without :meth:`can.BusABC.recv`'s loop
    around it (which then only re-checks the empty filter list, reads the clock twice and calls the
    logger: two layers of it per frame on a driver's cycle, 250 cycles a second). With filters, the
    base class's ``recv``. Received frames are logged as python-can does, when that level is on."""

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if self._filters is not None:  # type: ignore[attr-defined]
            return super().recv(timeout)  # type: ignore[misc]
        msg, _ = self._recv_internal(timeout)  # type: ignore[attr-defined]
        if msg is not None and _CAN_RX_LOG.isEnabledFor(can.BusABC.RECV_LOGGING_LEVEL):
            _CAN_RX_LOG.log(can.BusABC.RECV_LOGGING_LEVEL, "Received: %s", msg)
        return msg


class ReconnectingBus(DirectRecv, can.BusABC):
    """A python-can bus over a configuration, with typed errors and :meth:`reopen`.

    Every failure of the underlying transport surfaces as :class:`BusError` (cause kept). When
    the connection is gone (``WebsocketClosed``, ``OSError``), the bus is marked lost: later
    ``send``/``recv`` raise :class:`BusError` at once until :meth:`reopen` succeeds. The class
    does not reconnect on its own: the caller decides when (see :meth:`reopen_with_backoff`),
    so it can first make sure no stale command is sent.

    Thread-safety: ``send`` and ``recv`` may be called from different threads (as the
    transports allow); ``reopen`` and ``shutdown`` must not race with them.

    Args:
        config_file: python-can config file to read (else the default locations).
        config_context: python-can config context (``CAN_INTERFACE_<context>``, file section).
        can_filters: software filters applied by :class:`can.BusABC`.
        **kwargs: python-can bus keywords (``interface``, ``channel``, ``bitrate``, ...); unset
            ones (None/"") fall through to the environment and config files.

    Raises:
        BusError: the bus cannot be opened (see :func:`describe_open_error`).
    """

    def __init__(
        self,
        *,
        config_file: str | None = None,
        config_context: str | None = None,
        can_filters: can.typechecking.CanFilters | None = None,
        **kwargs: Any,
    ) -> None:
        self.config = resolve_config(config_file=config_file, config_context=config_context, **kwargs)
        self._bus: can.BusABC | None = _open_raw(self.config)
        self._lost: BaseException | None = None
        self._lock = threading.Lock()
        self.reopen_count = 0
        self.channel_info = f"{self._bus.channel_info} (redarm)"
        super().__init__(channel=self.config.get("channel"), can_filters=can_filters)

    # -- state ---------------------------------------------------------------------------------

    @property
    def is_lost(self) -> bool:
        """True after the transport failed, until :meth:`reopen` succeeds."""
        return self._lost is not None

    @property
    def inner(self) -> can.BusABC | None:
        """The python-can bus currently in use (None when lost or shut down)."""
        return self._bus

    def _mark_lost(self, exc: BaseException, during: str) -> BusError:
        if self._lost is None:
            logger.warning("CAN bus %s lost during %s: %r", self.config.get("channel"), during, exc)
        self._lost = exc
        bus, self._bus = self._bus, None
        safe_shutdown(bus)
        return BusError(
            f"CAN bus {self.config.get('interface')}:{self.config.get('channel')} lost during {during}: "
            f"{exc!r}; call reopen()"
        )

    def _live(self, during: str) -> can.BusABC:
        bus = self._bus
        if bus is None:
            if self._is_shutdown:
                raise BusError("CAN bus is shut down")
            raise BusError(f"CAN bus lost ({self._lost!r}); call reopen() before {during}")
        return bus

    # -- BusABC hooks --------------------------------------------------------------------------

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` (checked first).

        Raises:
            InvalidInputError: ``msg`` is malformed (nothing is sent).
            BusError: the transport failed (lost: reopen needed) or refused the frame.
        """
        check_message(msg)
        bus = self._live("send")
        try:
            bus.send(msg, timeout)
        except _lost_errors() as exc:
            raise self._mark_lost(exc, "send") from exc
        except can.CanError as exc:
            raise BusError(f"CAN send failed: {exc}") from exc

    def send_many(self, msgs: Sequence[can.Message]) -> None:
        """Send ``msgs`` in order, in one write where the transport allows (the loopback bus); all are
        checked before any is sent.

        Raises:
            InvalidInputError: one of ``msgs`` is malformed (nothing is sent).
            BusError: as :meth:`send`.
        """
        for msg in msgs:
            check_message(msg)
        bus = self._live("send")
        batch = getattr(bus, "send_many", None)
        try:
            if batch is not None:
                batch(msgs)
            else:
                for msg in msgs:
                    bus.send(msg)
        except _lost_errors() as exc:
            raise self._mark_lost(exc, "send") from exc
        except can.CanError as exc:
            raise BusError(f"CAN send failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        bus = self._bus
        if bus is None:
            bus = self._live("recv")  # raises: lost or shut down
        try:
            return bus.recv(timeout), False
        except _lost_errors() as exc:
            raise self._mark_lost(exc, "recv") from exc
        except can.CanError as exc:
            raise BusError(f"CAN receive failed: {exc}") from exc

    def shutdown(self) -> None:
        """Close the transport; never raises for a dead one (logged instead)."""
        bus, self._bus = self._bus, None
        safe_shutdown(bus)
        super().shutdown()

    # -- reconnection --------------------------------------------------------------------------

    def reopen(self) -> None:
        """Drop the current transport (if any) and open a new one with the same configuration.

        Frames queued on the old connection are lost; the caller must re-read the state of
        the devices before commanding them again.

        Raises:
            BusError: the bus cannot be opened now (try again later).
        """
        if self._is_shutdown:
            raise BusError("CAN bus is shut down; cannot reopen")
        with self._lock:
            old, self._bus = self._bus, None
            safe_shutdown(old)
            self._bus = _open_raw(self.config)
            self._lost = None
            self.reopen_count += 1
            logger.info("CAN bus %s reopened (%d)", self.config.get("channel"), self.reopen_count)

    def reopen_with_backoff(
        self,
        *,
        attempts: int = 10,
        initial_s: float = 0.05,
        max_s: float = 2.0,
        sleep: Callable[[float], None] = time.sleep,
    ) -> int:
        """Call :meth:`reopen` until it works, doubling the wait from ``initial_s`` up to ``max_s``.

        Returns:
            The number of failed attempts before success.

        Raises:
            BusError: still failing after ``attempts`` tries (the last error as cause).
        """
        for attempt, delay in enumerate(backoff_delays(initial_s, max_s)):
            try:
                self.reopen()
                return attempt
            except BusError as exc:
                if attempt + 1 >= attempts:
                    raise BusError(f"CAN bus could not be reopened after {attempts} attempts: {exc}") from exc
                logger.info("reopen attempt %d failed (%s); retrying in %.3f s", attempt + 1, exc, delay)
                sleep(delay)
        raise AssertionError("unreachable")  # pragma: no cover


def backoff_delays(initial_s: float = 0.05, max_s: float = 2.0) -> Iterator[float]:
    """Endless exponential backoff: initial_s, 2*initial_s, ... capped at max_s (seconds)."""
    delay = initial_s
    while True:
        yield delay
        delay = min(max_s, delay * 2.0)


def open_bus(
    *,
    config_file: str | None = None,
    config_context: str | None = None,
    can_filters: can.typechecking.CanFilters | None = None,
    **kwargs: Any,
) -> ReconnectingBus:
    """Open the configured CAN bus as a :class:`ReconnectingBus` (see that class for arguments).

    Raises:
        BusError: with the reason and the remedy (errno 97 / 19 for socketcan, refused
            connection for the remote server, no configuration at all).
    """
    return ReconnectingBus(
        config_file=config_file, config_context=config_context, can_filters=can_filters, **kwargs
    )


def check_config(*, config_file: str | None = None, config_context: str | None = None,
                 **kwargs: Any) -> dict[str, Any]:
    """Fail at once on a bus configuration that can never work; the resolved configuration otherwise.

    Resolves the configuration (see :func:`resolve_config`); a ``socketcan`` bus is also opened and
    closed once (cheap, touches no device), so a kernel without SocketCAN or a missing interface is
    found before any retry loop starts. Transient failures (an interface that is down, a bus server
    not listening yet) pass: the caller's retries are for them.

    Raises:
        BusConfigError: the configuration can never work; the message says what to do.
    """
    cfg = resolve_config(config_file=config_file, config_context=config_context, **kwargs)
    if cfg.get("interface") == "socketcan":
        try:
            safe_shutdown(_open_raw(cfg))
        except BusConfigError:
            raise
        except BusError:
            pass  # transient (e.g. down): the retries are for that
    return cfg


def open_bus_waiting(
    wait_s: float,
    *,
    log: Callable[[str], None] = logger.warning,
    sleep: Callable[[float], None] = time.sleep,
    clock: Callable[[], float] = time.monotonic,
    **kwargs: Any,
) -> ReconnectingBus:
    """:func:`open_bus`, retried with backoff for up to ``wait_s`` seconds while the failure is transient
    (a bus server that is still starting, an interface still down); ``log`` gets one line when the
    waiting starts. Keyword arguments as for :func:`open_bus`.

    Raises:
        BusConfigError: at once, for a configuration that can never work.
        BusError: still failing after ``wait_s`` (the last error, with its advice).
    """
    deadline = clock() + max(0.0, float(wait_s))
    delays = backoff_delays(0.05, 1.0)
    said = False
    while True:
        try:
            return open_bus(**kwargs)
        except BusConfigError:
            raise
        except BusError as exc:
            left = deadline - clock()
            if left <= 0:
                raise
            if not said:
                log(f"{exc}; waiting up to {wait_s:g} s for the CAN bus")
                said = True
            sleep(min(next(delays), left))
