"""The loopback CAN bus server (``redarm-canbus``) as a child of a test's process group."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from redarm_ros.procs import ManagedProcess, ProcessGroup, python_module_cmd


@dataclass
class CanBusServer:
    """A running loopback bus server: ``port``, python-can ``kwargs`` for ``can.Bus(**kwargs)``,
    ``env`` (``CAN_INTERFACE``/``CAN_CHANNEL`` for a child), the server ``process``."""

    port: int
    kwargs: dict[str, Any]
    process: ManagedProcess
    env: dict[str, str] = field(default_factory=dict)

    @property
    def channel(self) -> str:
        """The python-can channel string (``ws://127.0.0.1:<port>/``)."""
        return str(self.kwargs["channel"])

    def cli_args(self) -> list[str]:
        """``--can-interface remote --can-channel ws://...`` for redarm processes taking CAN flags."""
        return ["--can-interface", str(self.kwargs["interface"]), "--can-channel", self.channel]


def start_canbus_server(group: ProcessGroup, name: str = "canbus", port: int = 0) -> CanBusServer:
    """Start ``redarm-canbus`` on 127.0.0.1 in ``group`` and wait for its port.

    ``port`` 0 picks an ephemeral one; pass a previous server's port to restart "the same bus".
    """
    from redarm_ros.bringup import READY
    from redarm_ros.can.bus_server import client_config, client_env

    proc = group.start(
        name,
        python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1", "--port", str(port)),
        ready=READY["canbus"],
        ready_timeout=20.0,
    )
    port = int(proc.ready_match.group(1))  # type: ignore[attr-defined]
    return CanBusServer(port=port, kwargs=client_config(port), process=proc, env=client_env(port))
