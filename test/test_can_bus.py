"""Bus opening from python-can configuration, error translation, the remote-bus guards, reopen."""

from __future__ import annotations

import errno
import json
import socket
import uuid
from collections.abc import Iterator
from unittest import mock

import can
import pytest

from redarm_ros.can import bus as busmod
from redarm_ros.can.bus import (
    ReconnectingBus,
    check_config,
    open_bus,
    open_bus_waiting,
    resolve_config,
    safe_shutdown,
)
from redarm_ros.can.bus_server import LoopbackBusServer
from redarm_ros.errors import BusConfigError, BusError, InvalidInputError
from redarm_ros.testing.leaks import OpenBusTracker

CAN_ENV = ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG")


pytestmark = pytest.mark.usefixtures("no_open_buses")


@pytest.fixture(autouse=True)
def _isolated_can_config(monkeypatch: pytest.MonkeyPatch) -> None:
    """No user/system python-can config and no CAN_* variables leak into these tests."""
    for k in CAN_ENV:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setattr(can.util, "CONFIG_FILES", [])
    monkeypatch.setattr(can, "rc", {})


def _channel() -> str:
    return f"test-bus-{uuid.uuid4().hex[:8]}"


def _msg(arb_id: int = 0x0E1, data: bytes = b"\x00") -> can.Message:
    return can.Message(arbitration_id=arb_id, data=data, is_extended_id=False, check=True)


# ------------------------------------------------------------------------------------------------
# Configuration
# ------------------------------------------------------------------------------------------------


def test_config_from_explicit_kwargs() -> None:
    cfg = resolve_config(interface="virtual", channel="abc", receive_own_messages=True)
    assert cfg["interface"] == "virtual" and cfg["channel"] == "abc" and cfg["receive_own_messages"] is True


def test_config_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "from-env")
    monkeypatch.setenv("CAN_CONFIG", json.dumps({"receive_own_messages": True}))
    cfg = resolve_config()
    assert (cfg["interface"], cfg["channel"], cfg["receive_own_messages"]) == ("virtual", "from-env", True)
    # unset node parameters (None / "") fall through to the environment, set ones win
    assert resolve_config(interface=None, channel="")["channel"] == "from-env"
    assert resolve_config(channel="explicit")["channel"] == "explicit"


def test_config_from_file(tmp_path) -> None:
    path = tmp_path / "can.ini"
    path.write_text("[default]\ninterface = virtual\nchannel = from-file\n\n[arm]\nchannel = arm-file\n")
    assert resolve_config(config_file=str(path))["channel"] == "from-file"
    assert resolve_config(config_file=str(path), config_context="arm")["channel"] == "arm-file"


def test_no_configuration_says_what_to_set() -> None:
    with pytest.raises(BusError, match="no CAN interface configured.*CAN_INTERFACE"):
        resolve_config()


def test_unknown_interface() -> None:
    with pytest.raises(BusError, match="invalid CAN configuration"):
        resolve_config(interface="no-such-backend", channel="x")


def test_open_virtual_send_recv_and_close() -> None:
    ch = _channel()
    with open_bus(interface="virtual", channel=ch) as a, open_bus(interface="virtual", channel=ch) as b:
        a.send(_msg(0x0E3, b"\x01"))
        got = b.recv(1.0)
        assert got is not None and (got.arbitration_id, bytes(got.data)) == (0x0E3, b"\x01")
        assert b.recv(0.01) is None
    assert a.inner is None


def test_software_filters_apply() -> None:
    ch = _channel()
    with (
        open_bus(interface="virtual", channel=ch) as a,
        open_bus(interface="virtual", channel=ch, can_filters=[{"can_id": 0x0A0, "can_mask": 0x7E0}]) as b,
    ):
        a.send(_msg(0x0E1))
        a.send(_msg(0x0A1))
        got = b.recv(0.5)
        assert got is not None and got.arbitration_id == 0x0A1
        assert b.recv(0.01) is None


# ------------------------------------------------------------------------------------------------
# socketcan errors
# ------------------------------------------------------------------------------------------------


def _kernel_has_socketcan() -> bool:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        return exc.errno != errno.EAFNOSUPPORT
    return True


@pytest.mark.skipif(_kernel_has_socketcan(), reason="this kernel has SocketCAN; errno 97 cannot happen")
def test_socketcan_missing_from_kernel_is_errno_97_for_real() -> None:
    with pytest.raises(BusError, match="no SocketCAN at all.*errno 97 EAFNOSUPPORT") as info:
        open_bus(interface="socketcan", channel="vcan0")
    assert isinstance(info.value.__cause__, OSError) and info.value.__cause__.errno == errno.EAFNOSUPPORT
    assert "redarm-canbus" in str(info.value)


def test_socketcan_missing_interface_is_errno_19_with_recipe(monkeypatch: pytest.MonkeyPatch) -> None:
    from can.interfaces.socketcan import socketcan

    fake_sock = mock.MagicMock(spec=socket.socket)
    monkeypatch.setattr(socketcan, "create_socket", lambda: fake_sock)

    def no_device(sock, channel):
        raise OSError(errno.ENODEV, "No such device")

    monkeypatch.setattr(socketcan, "bind_socket", no_device)
    with pytest.raises(BusError, match="'vcan0' does not exist \\(errno 19 ENODEV\\)") as info:
        open_bus(interface="socketcan", channel="vcan0")
    assert "sudo ip link add dev vcan0 type vcan && sudo ip link set up vcan0" in str(info.value)
    assert info.value.__cause__.errno == errno.ENODEV


def _no_device(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_device(**cfg):
        raise OSError(errno.ENODEV, "No such device")

    monkeypatch.setattr(can, "Bus", no_device)


def test_socketcan_missing_real_adapter_gets_adapter_advice(monkeypatch: pytest.MonkeyPatch) -> None:
    """errno 19 on can0 (a real adapter's name): plug it in, bring it up at the arm's bit rate, check the
    cable and the power; the vcan recipe only as the alternative. vcan0 keeps the vcan recipe alone."""
    _no_device(monkeypatch)
    with pytest.raises(BusConfigError) as info:
        open_bus(interface="socketcan", channel="can0")
    text = str(info.value)
    assert "'can0' does not exist (errno 19 ENODEV)" in text
    assert "sudo ip link set can0 up type can bitrate 500000" in text
    assert "cable" in text and "powered" in text
    assert text.index("bitrate 500000") < text.index("type vcan")
    with pytest.raises(BusConfigError) as info:
        open_bus(interface="socketcan", channel="vcan0")
    assert "sudo ip link add dev vcan0 type vcan" in str(info.value)
    assert "bitrate" not in str(info.value) and "cable" not in str(info.value)


@pytest.mark.parametrize(("channel", "advice"), [("can0", "sudo ip link set can0 up type can bitrate 500000"),
                                                 ("vcan0", "sudo ip link set up vcan0")])
def test_socketcan_interface_down_is_enetdown(monkeypatch: pytest.MonkeyPatch, channel: str,
                                              advice: str) -> None:
    def down(**cfg):
        raise can.CanOperationError("down", error_code=errno.ENETDOWN)

    monkeypatch.setattr(can, "Bus", down)
    with pytest.raises(BusError, match="is down") as info:
        open_bus(interface="socketcan", channel=channel)
    assert advice in str(info.value)
    assert not isinstance(info.value, BusConfigError)  # down is transient: retried


# ------------------------------------------------------------------------------------------------
# configurations that can never work vs. transient failures
# ------------------------------------------------------------------------------------------------


def test_never_working_configurations_are_bus_config_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(BusConfigError, match="no CAN interface configured"):
        check_config()
    with pytest.raises(BusConfigError, match="invalid CAN configuration"):
        check_config(interface="no_such_interface", channel="x")
    _no_device(monkeypatch)
    with pytest.raises(BusConfigError, match="errno 19"):
        check_config(interface="socketcan", channel="can0")


@pytest.mark.skipif(_kernel_has_socketcan(), reason="this kernel has SocketCAN; errno 97 cannot happen")
def test_no_socketcan_in_the_kernel_is_a_bus_config_error() -> None:
    with pytest.raises(BusConfigError, match="errno 97"):
        check_config(interface="socketcan", channel="can0")


def test_transient_failures_pass_the_check(monkeypatch: pytest.MonkeyPatch) -> None:
    # a bus server not listening yet: the driver's retries are for that (nothing is opened by the check)
    cfg = check_config(interface="remote", channel=f"ws://127.0.0.1:{_free_port()}/")
    assert cfg["interface"] == "remote"

    def down(**cfg):
        raise can.CanOperationError("down", error_code=errno.ENETDOWN)

    monkeypatch.setattr(can, "Bus", down)
    assert check_config(interface="socketcan", channel="can0")["channel"] == "can0"


def test_open_bus_waiting_retries_transient_failures_until_its_deadline() -> None:
    now = [0.0]
    slept: list[float] = []
    said: list[str] = []

    def sleep(s: float) -> None:
        slept.append(s)
        now[0] += s

    with pytest.raises(BusError, match="no CAN bus server listens there"):
        open_bus_waiting(3.0, log=said.append, sleep=sleep, clock=lambda: now[0], interface="remote",
                         channel=f"ws://127.0.0.1:{_free_port()}/")
    assert len(said) == 1 and "waiting up to 3 s for the CAN bus" in said[0]
    assert len(slept) > 2 and sum(slept) == pytest.approx(3.0)
    slept.clear()
    with pytest.raises(BusConfigError):  # never waited for
        open_bus_waiting(3.0, sleep=sleep, clock=lambda: now[0], interface="no_such_interface", channel="x")
    assert slept == []


def test_open_bus_waiting_returns_the_bus_once_it_opens(monkeypatch: pytest.MonkeyPatch) -> None:
    real_bus = can.Bus
    calls = [0]

    def late(**cfg):
        calls[0] += 1
        if calls[0] < 3:
            raise OSError(errno.ECONNREFUSED, "refused")
        return real_bus(**cfg)

    monkeypatch.setattr(can, "Bus", late)
    bus = open_bus_waiting(10.0, sleep=lambda s: None, interface="virtual", channel=_channel())
    try:
        assert calls[0] == 3
    finally:
        bus.shutdown()


# ------------------------------------------------------------------------------------------------
# Remote bus (python-can-remote) guards
# ------------------------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_remote_without_server_says_connection_refused() -> None:
    with pytest.raises(BusError, match="no CAN bus server listens there"):
        open_bus(interface="remote", channel=f"ws://127.0.0.1:{_free_port()}/")


@pytest.fixture
def server() -> Iterator[LoopbackBusServer]:
    srv = LoopbackBusServer().start()
    yield srv
    srv.stop()


def _recv_id(bus: can.BusABC, timeout: float = 2.0) -> int | None:
    msg = bus.recv(timeout)
    return None if msg is None else msg.arbitration_id


def test_remote_exchange_and_refuse_malformed(server: LoopbackBusServer) -> None:
    with open_bus(**server.client_config()) as a, open_bus(**server.client_config()) as b:
        a.send(_msg(0x0E1))
        assert _recv_id(b) == 0x0E1
        bad = can.Message(arbitration_id=0x800, data=b"\x00", is_extended_id=False)  # check=False
        with pytest.raises(InvalidInputError, match="malformed"):
            a.send(bad)
        bad_dlc = can.Message(arbitration_id=0x10, data=b"\x00", dlc=5, is_extended_id=False)
        with pytest.raises(InvalidInputError):
            a.send(bad_dlc)
        a.send(_msg(0x0E2))
        assert _recv_id(b) == 0x0E2  # nothing malformed went out before it
        assert not a.is_lost


def test_dead_server_becomes_bus_error_then_reopen(server: LoopbackBusServer) -> None:
    port = server.port
    bus = open_bus(**server.client_config())
    try:
        server.stop()  # the server closes the connection: the library raises WebsocketClosed
        with pytest.raises(BusError, match="lost during recv") as info:
            bus.recv(2.0)
        assert info.value.__cause__ is not None and not isinstance(info.value.__cause__, can.CanError)
        assert bus.is_lost and bus.inner is None
        with pytest.raises(BusError, match="call reopen"):
            bus.send(_msg())
        with pytest.raises(BusError, match="no CAN bus server"):
            bus.reopen()  # still no server
        with LoopbackBusServer(port=port) as again:
            bus.reopen()
            assert not bus.is_lost and bus.reopen_count == 1
            with open_bus(**again.client_config()) as peer:
                bus.send(_msg(0x0E5))
                assert _recv_id(peer) == 0x0E5
    finally:
        bus.shutdown()


def test_send_to_dead_server_is_bus_error(server: LoopbackBusServer) -> None:
    bus = open_bus(**server.client_config())
    try:
        server.stop()
        with pytest.raises(BusError):
            # The first sends may still land in the socket buffer; the loss shows within a few.
            for _ in range(200):
                bus.send(_msg())
                bus.recv(0.01)
        assert bus.is_lost
    finally:
        bus.shutdown()


def test_reopen_with_backoff_counts_and_gives_up(server: LoopbackBusServer) -> None:
    bus = open_bus(**server.client_config())
    port = server.port
    slept: list[float] = []
    try:
        server.stop()
        with pytest.raises(BusError, match="after 4 attempts"):
            bus.reopen_with_backoff(attempts=4, initial_s=0.01, max_s=0.03, sleep=slept.append)
        assert slept == [0.01, 0.02, 0.03]
        with LoopbackBusServer(port=port):
            assert bus.reopen_with_backoff(attempts=3, sleep=slept.append) == 0
    finally:
        bus.shutdown()


def test_safe_shutdown_swallows_oserror() -> None:
    class Flaky(can.BusABC):
        def __init__(self) -> None:
            super().__init__(channel="flaky")
            self.socket = mock.MagicMock()

        def send(self, msg, timeout=None) -> None:  # pragma: no cover - not used
            pass

        def _recv_internal(self, timeout):  # pragma: no cover - not used
            return None, False

        def shutdown(self) -> None:
            raise OSError(errno.ENOTCONN, "Transport endpoint is not connected")

    bus = Flaky()
    safe_shutdown(bus)  # must not raise
    assert bus._is_shutdown and bus.socket.close.called


def test_shutdown_of_client_after_server_death_does_not_raise(server: LoopbackBusServer) -> None:
    raw = can.Bus(ignore_config=True, **server.client_config())
    server.stop()
    safe_shutdown(raw)
    assert raw._is_shutdown


def test_open_bus_tracker_catches_a_leak() -> None:
    with OpenBusTracker() as tracker:
        leaky = can.Bus(interface="virtual", channel=_channel())
    assert tracker.leaked() == [leaky]
    assert tracker.close_leaked() and leaky._is_shutdown
    assert tracker.leaked() == []


def test_backoff_sequence() -> None:
    gen = busmod.backoff_delays(0.1, 0.5)
    assert [next(gen) for _ in range(5)] == [0.1, 0.2, 0.4, 0.5, 0.5]


def test_reconnecting_bus_is_a_python_can_bus() -> None:
    with ReconnectingBus(interface="virtual", channel=_channel()) as bus:
        assert isinstance(bus, can.BusABC)
        assert "Virtual" in bus.channel_info
