"""A PowerCube host for tests: a python-can bus of the test's own, a request and its reply."""

from __future__ import annotations

import time
from typing import Any

import can

from redarm_ros.can import protocol as pc
from redarm_ros.can.protocol import ActState, Param

REPLY_WAIT = 0.5  # s; the emulator answers in about a millisecond, this only bounds a lost reply


class Host:
    """The test's side of the bus: send a request, wait for the matching reply."""

    def __init__(self, kwargs: dict[str, Any]) -> None:
        self.bus = can.Bus(**kwargs)

    def close(self) -> None:
        self.bus.shutdown()

    def send(self, msg: can.Message) -> None:
        self.bus.send(msg)

    def drain(self, quiet_s: float = 0.05) -> list[can.Message]:
        out = []
        while (m := self.bus.recv(quiet_s)) is not None:
            out.append(m)
        return out

    def ask(self, msg: can.Message, timeout: float = REPLY_WAIT) -> tuple[Any, float] | None:
        """Send ``msg``; the decoded reply of its module and the seconds it took, or None."""
        mid = msg.arbitration_id & 0x1F
        t0 = time.monotonic()
        self.bus.send(msg)
        while (left := t0 + timeout - time.monotonic()) > 0:
            r = self.bus.recv(left)
            if r is None:
                break
            if r.arbitration_id != pc.IdBase.CMD_ACK + mid or bytes(r.data[:1]) != bytes(msg.data[:1]):
                continue
            return pc.decode(r), time.monotonic() - t0
        return None

    def param(self, mid: int, param: Param) -> float | int | None:
        r = self.ask(pc.get_param(mid, param))
        return None if r is None else r[0].value

    def state(self, mid: int) -> ActState:
        v = self.param(mid, Param.ACT_STATE)
        assert v is not None, f"module {mid} did not report ACT_STATE"
        return ActState(v)
