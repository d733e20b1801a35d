"""Typed client of the simulator's control channel (:mod:`redarm_ros.sim.control_channel`).

:class:`SimControl` asks a running ``redarm-sim --control-port`` for its state (a
:class:`SimStatus`, read on the simulator's physics thread at the moment of the call) and injects
faults that are in force when the call returns. No ROS, no pybullet, no python-can here.
"""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.can.protocol import ActState
from redarm_ros.errors import RedarmError
from redarm_ros.testing.waits import DEFAULT_PERIOD_S, wait_for

DEFAULT_TIMEOUT_S = 10.0


class SimControlError(RedarmError):
    """The simulator refused a request (``error`` holds its reason) or could not be reached."""


@dataclass(frozen=True)
class ModuleStatus:
    """One emulated module as the simulator sees it: ``id``, ``state`` (ACT_STATE), ``position``
    (rad), ``requests`` (frames it handled), ``halted_at_s``: when HALTED was set, on the
    simulator's ``uptime_s`` clock (the HALT's time on the bus, or when its watchdog ran out), or
    None while not halted."""

    id: int
    state: ActState
    position: float
    requests: int
    halted_at_s: float | None = None

    def has(self, bits: ActState) -> bool:
        """True if every bit of ``bits`` is set."""
        return self.state & bits == bits

    @property
    def homed(self) -> bool:
        """HOME_OK is set."""
        return self.has(ActState.HOME_OK)

    @property
    def halted(self) -> bool:
        """HALTED is set (by a HALT, or by the module's own watchdog)."""
        return self.has(ActState.HALTED)

    @property
    def error(self) -> bool:
        """ERROR is set (motion refused until RESET)."""
        return self.has(ActState.ERROR)

    def __str__(self) -> str:
        flags = "|".join(f.name for f in ActState if f.name and f in self.state) or "0"
        return f"module {self.id}: {flags} at {self.position:.4f} rad"


@dataclass(frozen=True)
class SimStatus:
    """The simulated arm at one moment (units rad, rad/s, m, s).

    ``q``/``dq`` measured joint states, ``q_setpoint`` the modules' setpoints, ``tool`` the tool pose
    (4x4, base frame, pybullet's link state), ``modules`` by id, ``faults`` and ``counters`` as in
    docs/sim.md, ``uptime_s`` on the simulator's monotonic clock, ``raw`` the whole answer.
    """

    q: np.ndarray
    dq: np.ndarray
    q_setpoint: np.ndarray
    tool: np.ndarray
    modules: dict[int, ModuleStatus]
    silenced: frozenset[int]
    faults: dict[str, Any]
    counters: dict[str, Any]
    uptime_s: float
    raw: dict[str, Any]

    @classmethod
    def from_dict(cls, st: dict[str, Any]) -> SimStatus:
        """From the simulator's status object."""
        from redarm_ros.kinematics.quaternion import from_xyzw, quat_to_matrix

        tool = np.eye(4)
        tool[:3, :3] = quat_to_matrix(from_xyzw(st["tool"]["quaternion_xyzw"]))
        tool[:3, 3] = st["tool"]["position"]
        modules = {int(m["id"]): ModuleStatus(int(m["id"]), ActState(int(m["state"])), float(m["position"]),
                                              int(m["requests"]), m.get("halted_at_s"))
                   for m in st["modules"]}
        return cls(q=np.asarray(st["q"], float), dq=np.asarray(st["dq"], float),
                   q_setpoint=np.asarray(st["q_setpoint"], float), tool=tool, modules=modules,
                   silenced=frozenset(st["faults"]["silenced"]), faults=dict(st["faults"]),
                   counters=dict(st["counters"]), uptime_s=float(st["uptime_s"]), raw=st)

    def all_modules(self, bits: ActState, ids: Iterable[int] | None = None) -> bool:
        """Every module (or those of ``ids``) has every bit of ``bits``."""
        chosen = self.modules if ids is None else {i: self.modules[i] for i in ids}
        return all(m.has(bits) for m in chosen.values())

    def __str__(self) -> str:
        q = ", ".join(f"{v:.4f}" for v in self.q)
        mods = "; ".join(str(m) for m in self.modules.values())
        silenced = f"; silenced {sorted(self.silenced)}" if self.silenced else ""
        return f"q=[{q}]{silenced}; {mods}"


class SimControl:
    """A connection to one simulator's control channel at ``host:port`` (loopback).

    Thread-safe (one request at a time). Every method raises :class:`SimControlError` when the
    simulator refuses the request or cannot be reached within ``timeout_s``.
    """

    def __init__(self, host: str, port: int, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.host, self.port, self.timeout_s = host, int(port), float(timeout_s)
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._rfile: Any = None

    @classmethod
    def from_ready_line(cls, line: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> SimControl:
        """From the simulator's ready line (``... control=127.0.0.1:PORT``).

        Raises:
            SimControlError: the simulator was started without ``--control-port``.
        """
        for word in line.split():
            if word.startswith("control="):
                host, _, port = word[len("control="):].rpartition(":")
                return cls(host, int(port), timeout_s)
        raise SimControlError(f"no control channel in the simulator's ready line: {line!r}")

    # -- transport ----------------------------------------------------------------------------------
    def _connect(self) -> None:
        sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock, self._rfile = sock, sock.makefile("rb")

    def request(self, op: str, **args: Any) -> Any:
        """Send one request, return its ``result``.

        Raises:
            SimControlError: refused (the simulator's reason) or no answer (closed, timed out).
        """
        line = (json.dumps({"op": op, **args}) + "\n").encode()
        with self._lock:
            try:
                if self._sock is None:
                    self._connect()
                assert self._sock is not None
                self._sock.sendall(line)
                raw = self._rfile.readline()
            except OSError as exc:
                self._close_locked()
                raise SimControlError(f"simulator control channel {self.host}:{self.port}: {exc}") from exc
            if not raw:
                self._close_locked()
                raise SimControlError(f"simulator control channel {self.host}:{self.port} closed")
        answer = json.loads(raw)
        if not answer.get("ok"):
            raise SimControlError(f"simulator refused {op}: {answer.get('error')}")
        return answer["result"]

    def _close_locked(self) -> None:
        if self._sock is not None:
            try:
                self._rfile.close()
                self._sock.close()
            except OSError:
                pass
        self._sock = self._rfile = None

    def close(self) -> None:
        """Close the connection (a later request opens a new one)."""
        with self._lock:
            self._close_locked()

    # -- state ----------------------------------------------------------------------------------------
    def status(self) -> SimStatus:
        """The simulated arm now."""
        return SimStatus.from_dict(self.request("status"))

    def wait_for(self, cond: Callable[[SimStatus], object], timeout: float, *, what: str = "simulator state",
                 period: float = DEFAULT_PERIOD_S) -> SimStatus:
        """Poll :meth:`status` until ``cond(status)`` holds; that status.

        Raises:
            WaitTimeoutError: not within ``timeout`` s; the message shows the last status.
        """
        return wait_for(self.status, cond, timeout, what=what, period=period, describe=str)

    # -- faults ---------------------------------------------------------------------------------------
    def set_faults(self, *, silence: Iterable[int] | None = None, drop_replies: float | None = None,
                   delay_replies_ms: float | None = None) -> dict[str, Any]:
        """Set any of: the silenced modules (replaces the set), the fraction of replies dropped, the
        delay of every reply (ms). In force when this returns; the faults now."""
        args: dict[str, Any] = {}
        if silence is not None:
            args["silence"] = sorted(int(i) for i in silence)
        if drop_replies is not None:
            args["drop_replies"] = float(drop_replies)
        if delay_replies_ms is not None:
            args["delay_replies_ms"] = float(delay_replies_ms)
        return self.request("faults", **args)

    def power_cycle(self, module_ids: Sequence[int]) -> None:
        """Switch these modules off and on now (factory settings, no HOME_OK; they speak again)."""
        self.request("power_cycle", modules=[int(i) for i in module_ids])

    def inject(self, module_id: int, bits: ActState = ActState.ERROR) -> None:
        """Raise ERROR plus ``bits`` on one module, as its hardware would (RESET clears them)."""
        names = [f.name for f in ActState if f.name and f in ActState(bits)]
        self.request("inject", module=int(module_id), bits=names or ["ERROR"])
