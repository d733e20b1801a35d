"""The loopback bus's client (redarm_ros/can/relay_client.py): python-can-remote's wire protocol, read and
written in batches; it talks to our relay and to python-can-remote's own server and client alike."""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Iterator

import can
import pytest
from can_remote.client import RemoteBus
from can_remote.server import RemoteServer

from redarm_ros.can.bus import open_bus
from redarm_ros.can.bus_server import LoopbackBusServer
from redarm_ros.can.relay_client import BINARY_MSG, RelayBus
from redarm_ros.errors import BusError, InvalidInputError

pytestmark = pytest.mark.usefixtures("no_open_buses")


def _msgs(n: int) -> list[can.Message]:
    return [can.Message(arbitration_id=0x0E0 + k, data=bytes([k] * (k % 9)), is_extended_id=False, check=True)
            for k in range(n)]


@pytest.fixture
def canremote_server() -> Iterator[str]:
    """python-can-remote's own server on a virtual bus, on an ephemeral loopback port."""
    srv = RemoteServer(host="127.0.0.1", port=0, interface="virtual", channel=f"relay-{time.monotonic_ns()}")
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"ws://127.0.0.1:{srv.server_address[1]}/"
    finally:
        srv.shutdown()
        srv.server_close()
        thread.join(5.0)
        deadline = time.monotonic() + 3.0
        while srv.clients and time.monotonic() < deadline:  # its handlers end when their clients left
            time.sleep(0.02)
        for left in list(srv.clients):  # (python-can-remote's server never closes its buses itself)
            left.bus.shutdown()


def test_a_batch_is_one_write_and_arrives_whole_and_in_order() -> None:
    with LoopbackBusServer() as srv, open_bus(**srv.client_config()) as a, \
            open_bus(**srv.client_config()) as b:
        assert isinstance(a.inner, RelayBus)
        sent = _msgs(9)
        for m in sent:
            m.timestamp = time.time()
        a.send_many(sent)
        got = [b.recv(2.0) for _ in sent]
        assert [(m.arbitration_id, bytes(m.data), m.timestamp) for m in got] == \
            [(m.arbitration_id, bytes(m.data), pytest.approx(m.timestamp, abs=1e-6)) for m in sent]
        assert b.recv(0.0) is None and b.recv(0.05) is None
        # One write, so the relay read the whole batch at once and forwarded it in one go: the
        # receiver's single socket read held all nine (they were buffered before the first was taken).
        a.send_many(sent)
        first = b.recv(2.0)
        assert first is not None and len(b.inner._frames) == len(sent) - 1  # noqa: SLF001
        assert [b.recv(0.0).arbitration_id for _ in range(8)] == [m.arbitration_id for m in sent[1:]]


def test_a_malformed_frame_in_a_batch_sends_nothing() -> None:
    with LoopbackBusServer() as srv, open_bus(**srv.client_config()) as a, \
            open_bus(**srv.client_config()) as b:
        bad = can.Message(arbitration_id=0x900, data=b"\x01", is_extended_id=False)  # 11-bit id out of range
        with pytest.raises(InvalidInputError):
            a.send_many([*_msgs(2), bad])
        assert b.recv(0.3) is None


def test_frames_on_the_wire_are_python_can_remotes_binary_messages() -> None:
    """Masked (the zero key) final binary frames: type 1, then >dIBB and the data."""
    msg = can.Message(arbitration_id=0x1ABCDE, data=b"\x01\x02", is_extended_id=True, timestamp=12.5)
    wire = RelayBus._encode(msg)  # noqa: SLF001
    assert wire[:6] == bytes((0x82, 0x80 | 17)) + b"\0\0\0\0"
    assert wire[6] == 1 and BINARY_MSG.unpack_from(wire, 7) == (12.5, 0x1ABCDE, 2, 0x1)
    assert wire[7 + BINARY_MSG.size:] == b"\x01\x02" and len(wire) == 6 + 17
    assert struct.unpack(">d", wire[7:15]) == (12.5,)


def test_it_talks_to_python_can_remotes_server(canremote_server: str) -> None:
    with open_bus(interface="remote", channel=canremote_server) as a, \
            open_bus(interface="remote", channel=canremote_server) as b:
        assert isinstance(a.inner, RelayBus) and "on ws://127.0.0.1" in a.channel_info
        a.send_many(_msgs(3))
        got = [b.recv(2.0) for _ in range(3)]
        assert [m.arbitration_id for m in got] == [0x0E0, 0x0E1, 0x0E2]
        b.send(can.Message(arbitration_id=0x123, data=b"\x05", is_extended_id=False))
        m = a.recv(2.0)
        assert m is not None and (m.arbitration_id, bytes(m.data)) == (0x123, b"\x05")


def test_python_can_remotes_client_and_ours_share_the_relay() -> None:
    with LoopbackBusServer() as srv, open_bus(**srv.client_config()) as ours:
        theirs = RemoteBus(srv.channel)
        try:
            ours.send_many(_msgs(2))
            got = [theirs.recv(2.0) for _ in range(2)]
            assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(0x0E0, b""), (0x0E1, b"\x01")]
            theirs.send(can.Message(arbitration_id=0x321, data=b"\x07\x08", is_extended_id=False))
            m = ours.recv(2.0)
            assert m is not None and (m.arbitration_id, bytes(m.data)) == (0x321, b"\x07\x08")
        finally:
            theirs.shutdown()


def test_a_stopped_server_is_a_lost_bus() -> None:
    srv = LoopbackBusServer().start()
    bus = open_bus(**srv.client_config())
    try:
        srv.stop()
        with pytest.raises(BusError, match="lost"):
            bus.recv(2.0)
        assert bus.is_lost
    finally:
        bus.shutdown()


def test_recv_waits_its_timeout_and_keeps_software_filters() -> None:
    """recv hands frames on without python-can's per-frame wrapper, but still waits the whole timeout
    for none, and filters set on either layer (ours or the relay bus) are kept."""
    with LoopbackBusServer() as srv, open_bus(**srv.client_config()) as a, \
            open_bus(**srv.client_config()) as b, \
            open_bus(**srv.client_config(), can_filters=[{"can_id": 0x0E1, "can_mask": 0x7FF}]) as f:
        raw = RelayBus(srv.client_config()["channel"], can_filters=[{"can_id": 0x0E2, "can_mask": 0x7FF}])
        try:
            t0 = time.monotonic()
            assert b.recv(0.1) is None
            assert time.monotonic() - t0 >= 0.095
            a.send_many(_msgs(4))
            assert [b.recv(1.0).arbitration_id for _ in range(4)] == [0x0E0, 0x0E1, 0x0E2, 0x0E3]
            assert f.recv(1.0).arbitration_id == 0x0E1 and f.recv(0.1) is None
            assert raw.recv(1.0).arbitration_id == 0x0E2 and raw.recv(0.1) is None
        finally:
            raw.shutdown()
