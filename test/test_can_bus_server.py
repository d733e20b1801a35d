"""The loopback CAN bus server (redarm-canbus): loopback-only bind, port announcement, two clients
exchanging frames through a server subprocess, malformed frames not killing delivery, signals."""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Iterator

import can
import pytest
from can_remote.websocket import WebSocket

from redarm_ros.can.bus import open_bus
from redarm_ros.can.bus_server import (
    BusServerProcess,
    LoopbackBusServer,
    check_loopback,
    client_config,
    main,
    start_bus_server,
)
from redarm_ros.errors import BusError, InvalidInputError

pytestmark = pytest.mark.usefixtures("no_open_buses")


@pytest.fixture
def server_proc(tmp_path) -> Iterator[BusServerProcess]:
    proc = start_bus_server(port_file=tmp_path / "canbus.port")
    yield proc
    proc.stop()


def _msg(arb_id: int, data: bytes = b"\x00") -> can.Message:
    return can.Message(arbitration_id=arb_id, data=data, is_extended_id=False, check=True)


def _drain_ids(bus: can.BusABC, quiet_s: float = 0.3) -> list[int]:
    out = []
    while (m := bus.recv(quiet_s)) is not None:
        out.append(m.arbitration_id)
    return out


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost", "127.0.0.2"])
def test_loopback_hosts_accepted(host: str) -> None:
    assert check_loopback(host).startswith("127.")


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.10", "::1", "::", "example.org", ""])
def test_non_loopback_hosts_refused(host: str) -> None:
    with pytest.raises(InvalidInputError):
        check_loopback(host)


def test_cli_refuses_non_loopback_bind(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--host", "0.0.0.0", "--port", "0"]) == 2
    assert "only 127.0.0.0/8" in capsys.readouterr().err


def test_client_config_shape() -> None:
    assert client_config(5555) == {"interface": "remote", "channel": "ws://127.0.0.1:5555/"}


def test_two_clients_through_server_subprocess(server_proc: BusServerProcess, tmp_path) -> None:
    assert int((tmp_path / "canbus.port").read_text()) == server_proc.port
    with open_bus(**server_proc.client_config()) as a, open_bus(**server_proc.client_config()) as b:
        for i in range(20):
            a.send(_msg(0x0E1, bytes([i])))
            b.send(_msg(0x0A1, bytes([i, 0])))
        got_b = [b.recv(2.0) for _ in range(20)]
        got_a = [a.recv(2.0) for _ in range(20)]
        assert [bytes(m.data) for m in got_b] == [bytes([i]) for i in range(20)]
        assert [bytes(m.data) for m in got_a] == [bytes([i, 0]) for i in range(20)]
        assert a.recv(0.05) is None and b.recv(0.05) is None  # no echo of own frames
    assert server_proc.stop() == 0
    assert not (tmp_path / "canbus.port").exists()


def test_shared_conftest_fixture_and_env_config(canbus_server, monkeypatch: pytest.MonkeyPatch) -> None:
    for k, v in canbus_server.env.items():
        monkeypatch.setenv(k, v)
    with open_bus() as a, open_bus(**canbus_server.kwargs) as b:  # env-configured and explicit
        a.send(_msg(0x0C3, b"\x0a\x1d"))
        m = b.recv(2.0)
        assert m is not None and (m.arbitration_id, bytes(m.data)) == (0x0C3, b"\x0a\x1d")


def _json_client(channel: str) -> WebSocket:
    """A foreign client speaking python-can-remote's JSON protocol (as the web page does)."""
    ws = WebSocket(channel, ["can.json.v1"])
    ws.send(json.dumps({"type": "bus_request", "payload": {"config": {}}}))
    assert json.loads(ws.read())["type"] == "bus_response"
    return ws


def test_malformed_frame_from_one_client_does_not_kill_delivery(server_proc: BusServerProcess) -> None:
    """Unguarded python-can-remote 0.3.0: a dlc-1000 frame from a JSON client silently kills the
    sender threads of every other client. The server drops such frames on entry."""
    cfg = server_proc.client_config()
    with open_bus(**cfg) as a, open_bus(**cfg) as b:
        a.send(_msg(0x0E1))
        assert b.recv(2.0).arbitration_id == 0x0E1
        ws = _json_client(server_proc.channel)
        try:
            for payload in (
                {"arbitration_id": 0x10, "is_extended_id": False, "dlc": 1000, "data": [1]},
                {"arbitration_id": -1, "is_extended_id": False, "data": [1]},
                {"arbitration_id": 0x800, "is_extended_id": False, "data": [1]},
            ):
                ws.send(json.dumps({"type": "message", "payload": payload}))
            # A raw python-can-remote client can also send a frame check=True would refuse.
            raw = can.Bus(ignore_config=True, **cfg)
            try:
                raw.send(can.Message(arbitration_id=0x11, data=bytes(20), is_extended_id=False))
                raw.send(_msg(0x0E7))  # a good frame from the same client still goes through
            finally:
                raw.shutdown()
            time.sleep(0.2)
            assert _drain_ids(b) == [0x0E7]  # none of the malformed frames arrived
            for i in range(5):  # and delivery to the others still works, both ways
                a.send(_msg(0x0E2, bytes([i])))
                b.send(_msg(0x0A2, bytes([i])))
            assert _drain_ids(b) == [0x0E2] * 5 and _drain_ids(a) == [0x0E7] + [0x0A2] * 5
        finally:
            ws.close()


def test_in_process_server_counts_dropped_frames() -> None:
    with LoopbackBusServer() as srv, open_bus(**srv.client_config()) as good:
        ws = _json_client(srv.channel)
        try:
            ws.send(
                json.dumps({"type": "message", "payload": {"arbitration_id": 0x10, "dlc": 999, "data": []}})
            )
            ws.send(json.dumps({"type": "message", "payload": {"arbitration_id": 0x10, "data": [1]}}))
            m = good.recv(2.0)
            assert m is not None and m.arbitration_id == 0x10 and bytes(m.data) == b"\x01"
            assert srv.dropped_frames == 1
        finally:
            ws.close()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_stops_server_cleanly_and_clients_see_it(sig: int) -> None:
    srv = start_bus_server()
    bus = open_bus(**srv.client_config())
    try:
        srv.process.send_signal(sig)
        assert srv.process.wait(10) == 0
        with pytest.raises(BusError, match="lost"):
            bus.recv(2.0)
    finally:
        bus.shutdown()
        srv.stop()


def test_frames_keep_their_sender_stamp_and_unstamped_ones_get_the_server_time() -> None:
    with LoopbackBusServer() as server:
        with open_bus(**server.client_config()) as a, open_bus(**server.client_config()) as b:
            stamped = _msg(0x0E1)
            stamped.timestamp = time.time() - 0.3  # sent 0.3 s ago (e.g. it waited in the sender)
            a.send(stamped)
            got = b.recv(5.0)
            assert got is not None and got.timestamp == pytest.approx(stamped.timestamp, abs=1e-6)
            t0 = time.time()
            a.send(_msg(0x0E2))  # timestamp 0: stamped by the server on receipt
            got = b.recv(5.0)
            assert got is not None and t0 - 0.5 <= got.timestamp <= time.time() + 0.5
            bogus = _msg(0x0E3)
            bogus.timestamp = 12.5  # not a wall-clock time (e.g. a monotonic stamp): replaced
            a.send(bogus)
            got = b.recv(5.0)
            assert got is not None and got.timestamp > t0 - 0.5


def test_a_flood_leaves_no_unbounded_backlog_for_a_slow_reader() -> None:
    # A reader that does not read during a flood afterwards finds a bounded backlog that ends with
    # the newest frames, not the whole flood queued behind its next reply. (What waits is the relay's
    # queue plus what the kernel buffers of the connection hold, ~10k frames: the flood is larger.)
    n = 40000
    with LoopbackBusServer() as server:
        with open_bus(**server.client_config()) as flood, open_bus(**server.client_config()) as slow:
            for k in range(n):
                flood.send(_msg(0x123, (k % 65536).to_bytes(2, "little")))
            flood.send(_msg(0x7FF, b"\x01"))  # the last frame of the flood
            got = []
            while (m := slow.recv(1.0)) is not None:
                got.append(m.arbitration_id)
            assert 0x7FF in got[-5:]  # the newest traffic got through
            assert len(got) < n // 2
            assert server.overflowed_frames + server.skipped_frames > 0


def test_a_vanished_client_leaves_no_thread_exception(monkeypatch: pytest.MonkeyPatch) -> None:
    """A client killed while frames flow to it (the driver's cycle process, SIGKILL) breaks the pipe under
    the server's send thread: that connection ends quietly and the others keep exchanging frames."""
    import threading

    errors: list[BaseException | None] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: errors.append(args.exc_value))
    with LoopbackBusServer() as srv, open_bus(**srv.client_config()) as a, \
            open_bus(**srv.client_config()) as b:
        ws = _json_client(srv.channel)
        ws.socket.close()  # gone without a close handshake, as a killed process
        for k in range(400):  # frames the server must try to deliver to the vanished client too
            a.send(_msg(0x100 + k % 16))
            if k % 50 == 0:
                time.sleep(0.01)
        time.sleep(0.5)
        a.send(_msg(0x0E1))
        assert 0x0E1 in _drain_ids(b)
    assert errors == []


def test_a_json_client_gets_binary_clients_frames_as_json() -> None:
    """The relay forwards raw frames to binary clients and builds the JSON form once for JSON ones."""
    with LoopbackBusServer() as srv, open_bus(**srv.client_config()) as a:
        ws = _json_client(srv.channel)
        try:
            sent = can.Message(arbitration_id=0x1234567, data=b"\x01\x02\x03", is_extended_id=True)
            sent.timestamp = time.time() - 0.1
            a.send(sent)
            assert ws.wait(5.0)
            event = json.loads(ws.read())
            assert event["type"] == "message"
            got = event["payload"]
            assert (got["arbitration_id"], got["is_extended_id"], got["dlc"], got["data"]) == (
                0x1234567, True, 3, [1, 2, 3])
            assert got["timestamp"] == pytest.approx(sent.timestamp, abs=1e-6)
        finally:
            ws.close()


def test_periodic_task_of_a_client_is_sent_by_the_server_until_stopped() -> None:
    with LoopbackBusServer() as srv, open_bus(**srv.client_config()) as rx:
        sender = can.Bus(ignore_config=True, **srv.client_config())
        try:
            task = sender.send_periodic(_msg(0x321, b"\x07"), 0.02)
            time.sleep(0.5)
            task.stop()
            time.sleep(0.2)
            ids = _drain_ids(rx, 0.3)
            assert 10 <= len(ids) <= 40 and set(ids) == {0x321}
            assert _drain_ids(rx, 0.3) == []  # stopped
        finally:
            sender.shutdown()
