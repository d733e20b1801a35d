"""One exception base for the package, subclasses by kind, each carrying its data.

Every error raised on purpose by redarm_ros derives from :class:`RedarmError`,
so a caller can catch the package's failures without catching bugs.
"""

from __future__ import annotations

from typing import Any


class RedarmError(Exception):
    """Base of every error raised on purpose by redarm_ros."""


class InvalidInputError(RedarmError, ValueError):
    """The caller passed something malformed: NaN, wrong shape, non-unit quaternion, unknown name.

    ``field`` names the offending argument and ``value`` holds what was given.
    """

    def __init__(self, message: str, *, field: str | None = None, value: Any = None) -> None:
        super().__init__(message)
        self.field = field
        self.value = value


class ConfigError(InvalidInputError):
    """A configuration file or parameter set is missing or inconsistent."""


class UnreachableError(RedarmError):
    """A pose lies outside the workspace (``distance`` is how far, in metres, if known)."""

    def __init__(self, message: str, *, distance: float | None = None) -> None:
        super().__init__(message)
        self.distance = distance


class BusError(RedarmError):
    """The CAN bus could not be opened or used; the original error is kept as ``__cause__``."""


class BusConfigError(BusError, ValueError):
    """The CAN bus configuration can never work as given: no interface configured, an unknown interface
    type, no SocketCAN in the kernel (errno 97), no such interface (errno 19). Retrying does not help;
    the message says what to do."""


class BusTimeoutError(BusError, TimeoutError):
    """A module did not answer in time (``module_id`` and ``timeout_s``)."""

    def __init__(self, message: str, *, module_id: int | None = None, timeout_s: float | None = None) -> None:
        super().__init__(message)
        self.module_id = module_id
        self.timeout_s = timeout_s


class ProtocolError(RedarmError, ValueError):
    """A CAN frame does not follow the PowerCube (M5) protocol (``frame`` holds it)."""

    def __init__(self, message: str, *, frame: Any = None) -> None:
        super().__init__(message)
        self.frame = frame


class ModuleFaultError(RedarmError):
    """A bus module reports an error state (``module_id``, ACT_STATE bits in ``state``)."""

    def __init__(self, message: str, *, module_id: int | None = None, state: int | None = None) -> None:
        super().__init__(message)
        self.module_id = module_id
        self.state = state


class ImplausibleMeasurementError(ModuleFaultError):
    """A module reported a position it cannot have reached from the last one measured
    (``module_id``; ``value``: the refused position in rad)."""

    def __init__(self, message: str, *, module_id: int | None = None, value: float | None = None) -> None:
        super().__init__(message, module_id=module_id)
        self.value = value


class RequestHaltedError(RedarmError):
    """A running init or recover was stopped by a halt request (every module has been halted)."""


class RequestRefusedError(RedarmError):
    """A request was refused before anything was sent (e.g. recover on an arm that was never homed)."""
