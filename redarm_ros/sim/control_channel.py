"""The simulator's control channel: a test asks the running ``redarm-sim`` for its state and injects
faults, and gets an answer, over one TCP connection on 127.0.0.1.

The status file and the control file (docs/sim.md) are for people and scripts; a test needs an
answer it can wait on: the state as of now, and a fault that is in force when the call returns.
``redarm-sim --control-port 0`` serves this channel on an ephemeral loopback port and names it in
its ready line (``REDARM_SIM_READY ... control=127.0.0.1:PORT``); the client is
:class:`redarm_ros.testing.SimControl`.

Protocol: one JSON object per line each way, one answer per request, in order::

    -> {"op": "status"}
    <- {"ok": true, "result": {...the status object of docs/sim.md...}}
    -> {"op": "inject", "module": 9}
    <- {"ok": false, "error": "no module with id 9 (have [1, ..., 7])"}

Operations:

* ``ping``: ``"pong"``.
* ``status``: the status object (docs/sim.md), taken on the physics thread between two steps.
* ``faults``: any of ``silence`` (ids, replaces the silenced set), ``drop_replies`` (fraction),
  ``delay_replies_ms``; in force for the next frame when the answer comes; the faults now.
* ``power_cycle``: ``modules`` (ids): each is switched off and on (factory settings, no HOME_OK,
  its joint braked and held) and speaks again if it was silenced.
* ``inject``: ``module``, ``bits`` (ACT_STATE flag names, e.g. ``["BEYOND_SOFT"]``): ERROR plus
  those bits, the joint halted, a state frame sent, as a module raises them; RESET clears them.

What the modules do on the bus is unchanged: the channel only sets what the command-line fault
switches and the control file set, plus the two module faults above. The server refuses any
address but loopback.
"""

from __future__ import annotations

import json
import logging
import socket
import socketserver
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from redarm_ros.can.bus_server import check_loopback
from redarm_ros.can.protocol import ActState
from redarm_ros.errors import InvalidInputError

if TYPE_CHECKING:
    from redarm_ros.sim.hardware import HardwareSim

_LOG = logging.getLogger("redarm_ros.sim.control_channel")

STATUS_TIMEOUT_S = 5.0  # the physics thread answers within a step; a snapshot render may take longer
MAX_LINE = 1 << 16


def fault_bits(names: Any) -> ActState:
    """ACT_STATE bits from a list of flag names (``["ERROR", "BEYOND_SOFT"]``).

    Raises:
        InvalidInputError: not a list of known flag names.
    """
    if isinstance(names, str) or not isinstance(names, list):
        raise InvalidInputError(f"bits must be a list of ACT_STATE names, got {names!r}", field="bits")
    bits = ActState(0)
    for name in names:
        if not isinstance(name, str) or name not in ActState.__members__:
            raise InvalidInputError(f"unknown ACT_STATE flag {name!r}", field="bits", value=name)
        bits |= ActState[name]
    return bits


class ControlChannel:
    """Serve the control protocol for ``sim`` on ``host:port`` (loopback only; port 0: ephemeral).

    :meth:`start` binds and serves on daemon threads; :attr:`port` is the bound port; :meth:`close`
    stops serving.
    """

    def __init__(self, sim: HardwareSim, host: str = "127.0.0.1", port: int = 0) -> None:
        self.sim = sim
        self._ops: dict[str, Callable[[dict[str, Any]], Any]] = {
            "ping": lambda _req: "pong",
            "status": self._status,
            "faults": self._faults,
            "power_cycle": self._power_cycle,
            "inject": self._inject,
        }
        channel = self

        class _Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                for raw in self.rfile:
                    if len(raw) > MAX_LINE:
                        return
                    answer = channel.answer(raw)
                    self.wfile.write((json.dumps(answer) + "\n").encode())
                    self.wfile.flush()

        class _Server(socketserver.ThreadingTCPServer):
            daemon_threads = True
            allow_reuse_address = True

        self._server = _Server((check_loopback(host), int(port)), _Handler)
        self.host, self.port = self._server.server_address[:2]
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="sim-control", daemon=True)

    def start(self) -> ControlChannel:
        """Serve on a daemon thread; returns self."""
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving (open connections end with the process)."""
        self._server.shutdown()
        self._server.server_close()

    # -- requests ---------------------------------------------------------------------------------
    def answer(self, raw: bytes | str) -> dict[str, Any]:
        """The answer to one request line: ``{"ok": true, "result": ...}`` or
        ``{"ok": false, "error": ...}``."""
        try:
            req = json.loads(raw)
            if not isinstance(req, dict) or req.get("op") not in self._ops:
                raise InvalidInputError(f"unknown request {req!r}; operations: {sorted(self._ops)}")
            return {"ok": True, "result": self._ops[req["op"]](req)}
        except (ValueError, TypeError, KeyError, TimeoutError) as exc:  # bad requests; the sim goes on
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}

    def _status(self, _req: dict[str, Any]) -> dict[str, Any]:
        return self.sim.call_in_physics(self.sim.status).result(STATUS_TIMEOUT_S)

    def _faults(self, req: dict[str, Any]) -> dict[str, Any]:
        data = {k: req[k] for k in ("silence", "drop_replies", "delay_replies_ms") if k in req}
        self.sim.apply_control(data)
        return self.sim.fault_settings()

    def _power_cycle(self, req: dict[str, Any]) -> list[int]:
        ids = [int(i) for i in req["modules"]]
        for mid in ids:
            self.sim.emulator.power_cycle(mid)
        speaking = set(self.sim.fault_settings()["silenced"]) - set(ids)
        self.sim.apply_control({"silence": sorted(speaking)})
        _LOG.info("power-cycled modules %s", ids)
        return ids

    def _inject(self, req: dict[str, Any]) -> int:
        bits = fault_bits(req.get("bits", ["ERROR"]))
        self.sim.emulator.inject_fault(int(req["module"]), bits)
        _LOG.info("module %s: injected %s", req["module"], bits)
        return int(bits)
