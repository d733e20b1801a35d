"""One codec for the Schunk/AMTEC PowerCube (M5) CAN protocol, used by the driver and the simulator.

Both directions live here: the host builds requests and parses replies, the module side
(:mod:`redarm_ros.can.module_emulator`) parses requests and builds replies. Every frame is an
11-bit standard frame; values travel little-endian (float32 IEEE, uint32, uint16, uint8).

CAN ids (module id 1..31 is added to the base, see :class:`IdBase`)::

    0x0E0+id  host -> module   commands, SETPARAM, SETMOVE
    0x0C0+id  host -> module   GETPARAM only
    0x0A0+id  module -> host   reply to both of the above
    0x060+id  module -> host   state frame, uint32 ACT_STATE in bytes 0-3
    0x100     host -> all      broadcast (DLC 2), never answered

Frame layouts (DLC in brackets). Every layout has exactly one DLC; a frame whose DLC differs
is malformed (:class:`~redarm_ros.errors.ProtocolError`), except the state frame, see below.

=========================  ======================================  =====================================
request                    frame on 0x0E0/0x0C0+id                 reply on 0x0A0+id
=========================  ======================================  =====================================
simple command             ``[cmd]`` (1)                           ``[cmd]`` (1)
SETPARAM                   ``[08][param][value]`` (2 + size)       ``[08][param]`` (2)
GETPARAM (0x0C0+id)        ``[0A][param]`` (2)                     ``[0A][param][value]`` (2 + size)
SETMOVE FRAMP/FVEL/FCUR    ``[0B][mode][f32]`` (6)                 ``[0B][mode]`` (2)
SETMOVE FSTEP              ``[0B][06][f32][u16 ms]`` (8)           ``[0B][06]`` (2)
SETMOVE any _EXT mode      as the plain mode                       ``[0B][mode][f32 pos][u8 st][u8 dio]`` (8)
=========================  ======================================  =====================================

"Simple commands" are RESET, HOME, HALT, WATCHDOG, RECALCPID, SAVEPOS and SAVEPARAMS: one
byte, echoed in a one-byte acknowledgement. ``size`` is the parameter's type size from
:data:`PARAM_TYPES` (float32/uint32 4, uint16 2, uint8 1), so a GETPARAM reply for DEF_VERSION
is ``[0A][1D][u16]`` (DLC 4) and one for ACT_FPOS is ``[0A][3C][f32]`` (DLC 6).

Details this codec defines because the protocol facts leave them open:

* The position in an extended SETMOVE acknowledgement is the module's actual position
  *before* the move is applied (as the vendor library assumes); it must be finite.
* The state frame on ``0x060+id`` is built with DLC 4; the parser accepts DLC 4..8 and reads
  bytes 0-3 (other bytes unspecified).
* The per-module WATCHDOG command (``0x07``) is a simple command; the bus-wide refresh is the
  broadcast ``0x100 [07 00]``.
* Float values (positions, velocities, currents, float parameters) must be finite: NaN or
  infinity in a frame is malformed, in a builder argument it is an invalid input.
* Only the float motion modes are supported; the integer modes (IRAMP, ISTEP, ...) are
  rejected as unknown.

Error policy: builders reject bad *arguments* with :class:`~redarm_ros.errors.InvalidInputError`
(a programming error on the sending side); parsers reject bad *frames* with
:class:`~redarm_ros.errors.ProtocolError` (something on the bus). A reader loop should use
:class:`FrameDecoder`, which counts and skips malformed frames instead of raising.
"""

from __future__ import annotations

import logging
import math
import struct
from collections import Counter
from dataclasses import dataclass
from enum import Enum, IntEnum, IntFlag
from typing import Final

import can

from redarm_ros.errors import InvalidInputError, ProtocolError

logger = logging.getLogger(__name__)

MIN_MODULE_ID: Final = 1
MAX_MODULE_ID: Final = 31
#: Largest finite float32, used to refuse values that would overflow on packing.
FLOAT32_MAX: Final = 3.4028234663852886e38


class IdBase(IntEnum):
    """11-bit CAN id bases; the module id (1..31) is added to all but BROADCAST."""

    CMD_PUT = 0x0E0  # host -> module: commands, SETPARAM, SETMOVE
    CMD_GET = 0x0C0  # host -> module: GETPARAM
    CMD_ACK = 0x0A0  # module -> host: replies
    STATE = 0x060  # module -> host: ACT_STATE u32
    BROADCAST = 0x100  # host -> all modules, never answered


class Command(IntEnum):
    """Byte 0 of a host -> module frame (and of its reply)."""

    RESET = 0x00
    HOME = 0x01
    HALT = 0x02
    WATCHDOG = 0x07
    SETPARAM = 0x08
    RECALCPID = 0x09
    GETPARAM = 0x0A
    SETMOVE = 0x0B
    SAVEPOS = 0x0E
    STARTMOVE = 0x0F  # broadcast only
    SAVEPARAMS = 0x10


#: Commands that are one byte long and acknowledged by echoing that byte.
SIMPLE_COMMANDS: Final = frozenset(
    {
        Command.RESET,
        Command.HOME,
        Command.HALT,
        Command.WATCHDOG,
        Command.RECALCPID,
        Command.SAVEPOS,
        Command.SAVEPARAMS,
    }
)


class BroadcastCommand(IntEnum):
    """Byte 0 of a broadcast on 0x100 (byte 1 is 0, or the baud-rate index for SET_BAUDRATE)."""

    RESET_ALL = 0x00
    HOME_ALL = 0x01
    HALT_ALL = 0x02
    WATCHDOG_REFRESH = 0x07
    SET_BAUDRATE = 0x09
    SAVEPOS_ALL = 0x0E
    START_MOTION_ALL = 0x0F


class BaudRate(IntEnum):
    """Argument of the setBaudRateAll broadcast."""

    BAUD_125K = 0
    BAUD_250K = 1
    BAUD_500K = 2
    BAUD_1M = 3


class MoveMode(IntEnum):
    """Byte 1 of SETMOVE. The ``*_EXT`` modes are answered with position, short state and dio."""

    FRAMP = 0x04  # ramp to a position (rad), using ACT_FRAMPVEL / ACT_FRAMPACC
    FSTEP = 0x06  # reach a position (rad) in a given time (ms)
    FVEL = 0x07  # velocity (rad/s)
    FCUR = 0x08  # current (A)
    FRAMP_EXT = 0x0E
    FSTEP_EXT = 0x10
    FVEL_EXT = 0x11
    FCUR_EXT = 0x12

    @property
    def extended(self) -> bool:
        """True for the modes whose acknowledgement carries position and state."""
        return self in EXTENDED_MOVE_MODES

    @property
    def has_duration(self) -> bool:
        """True for FSTEP and FSTEP_EXT, which carry a u16 time in milliseconds."""
        return self in _DURATION_MODES

    @property
    def base(self) -> MoveMode:
        """The plain mode of an extended one (itself for a plain mode)."""
        return _EXT_TO_BASE.get(self, self)


#: The modes acknowledged with the position and the short state.
EXTENDED_MOVE_MODES: Final = frozenset(
    {MoveMode.FRAMP_EXT, MoveMode.FSTEP_EXT, MoveMode.FVEL_EXT, MoveMode.FCUR_EXT}
)
_DURATION_MODES: Final = frozenset({MoveMode.FSTEP, MoveMode.FSTEP_EXT})
_EXT_TO_BASE: Final = {
    MoveMode.FRAMP_EXT: MoveMode.FRAMP,
    MoveMode.FSTEP_EXT: MoveMode.FSTEP,
    MoveMode.FVEL_EXT: MoveMode.FVEL,
    MoveMode.FCUR_EXT: MoveMode.FCUR,
}


class Param(IntEnum):
    """Parameter ids for SETPARAM / GETPARAM. Types in :data:`PARAM_TYPES`; units SI (rad, rad/s, A)."""

    DEF_FHOMEOFFSET = 0x00
    DEF_FGEARRATIO = 0x01
    DEF_FLINRATIO = 0x02
    DEF_FMINPOS = 0x03
    DEF_FMAXPOS = 0x04
    DEF_FMAXDELTAPOS = 0x05
    DEF_FMAXVEL = 0x0A
    DEF_FMAXACC = 0x0C
    DEF_CUBESERIAL = 0x1A
    DEF_CONFIG = 0x1B
    DEF_VERSION = 0x1D
    DEF_ADDRESS = 0x20
    DEF_PRIMBAUD = 0x22
    ACT_STATE = 0x27
    ACT_CONFIG = 0x39
    ACT_MOVEMODE = 0x3A
    ACT_FPOS = 0x3C
    ACT_FVEL = 0x41
    ACT_FMINPOS = 0x45
    ACT_FMAXPOS = 0x46
    ACT_FMAXVEL = 0x48
    ACT_FMAXACC = 0x4A
    ACT_FMAXCUR = 0x4C
    ACT_FCUR = 0x4D
    ACT_FRAMPVEL = 0x4F
    ACT_FRAMPACC = 0x50


class ParamType(Enum):
    """Wire type of a parameter value: (struct format, size in bytes)."""

    F32 = ("<f", 4)
    U32 = ("<I", 4)
    U16 = ("<H", 2)
    U8 = ("<B", 1)

    @property
    def size(self) -> int:
        """Size of the value in bytes."""
        return self.value[1]

    @property
    def struct(self) -> struct.Struct:
        """Precompiled little-endian struct for the value."""
        return _TYPE_STRUCTS[self]


_TYPE_STRUCTS: Final = {t: struct.Struct(t.value[0]) for t in ParamType}

#: Per-parameter wire type. Float parameters are in SI units (rad, rad/s, rad/s^2, A).
PARAM_TYPES: Final[dict[Param, ParamType]] = {
    Param.DEF_FHOMEOFFSET: ParamType.F32,
    Param.DEF_FGEARRATIO: ParamType.F32,
    Param.DEF_FLINRATIO: ParamType.F32,
    Param.DEF_FMINPOS: ParamType.F32,
    Param.DEF_FMAXPOS: ParamType.F32,
    Param.DEF_FMAXDELTAPOS: ParamType.F32,
    Param.DEF_FMAXVEL: ParamType.F32,
    Param.DEF_FMAXACC: ParamType.F32,
    Param.DEF_CUBESERIAL: ParamType.U32,
    Param.DEF_CONFIG: ParamType.U32,
    Param.DEF_VERSION: ParamType.U16,  # firmware version
    Param.DEF_ADDRESS: ParamType.U8,  # module id
    Param.DEF_PRIMBAUD: ParamType.U8,  # BaudRate index
    Param.ACT_STATE: ParamType.U32,  # ActState bits
    Param.ACT_CONFIG: ParamType.U32,  # ActConfig bits
    Param.ACT_MOVEMODE: ParamType.U8,  # MoveMode of the last move
    Param.ACT_FPOS: ParamType.F32,
    Param.ACT_FVEL: ParamType.F32,
    Param.ACT_FMINPOS: ParamType.F32,
    Param.ACT_FMAXPOS: ParamType.F32,
    Param.ACT_FMAXVEL: ParamType.F32,
    Param.ACT_FMAXACC: ParamType.F32,
    Param.ACT_FMAXCUR: ParamType.F32,
    Param.ACT_FCUR: ParamType.F32,
    Param.ACT_FRAMPVEL: ParamType.F32,
    Param.ACT_FRAMPACC: ParamType.F32,
}


class ActState(IntFlag):
    """Long module state (parameter ACT_STATE 0x27, state frame on 0x060+id)."""

    ERROR = 0x1
    HOME_OK = 0x2
    HALTED = 0x4
    POWERFAULT = 0x8
    TOW_ERROR = 0x10  # following error
    COMM_ERROR = 0x20
    SWR = 0x40
    SW1 = 0x80
    SW2 = 0x100
    BRAKEACTIVE = 0x200
    CURLIMIT = 0x400
    MOTION = 0x800
    RAMP_ACC = 0x1000
    RAMP_STEADY = 0x2000
    RAMP_DEC = 0x4000
    RAMP_END = 0x8000
    INPROGRESS = 0x10000
    FULLBUFFER = 0x20000
    POW_VOLT_ERR = 0x40000
    POW_FET_TEMP = 0x80000
    POW_WDG_TEMP = 0x100000
    POW_SHORTCUR = 0x200000
    POW_HALLERR = 0x400000
    POW_INTEGRAL_ERR = 0x800000
    CPU_OVERLOAD = 0x1000000
    BEYOND_HARD = 0x2000000
    BEYOND_SOFT = 0x4000000
    POW_SETUP_ERR = 0x8000000


#: The power stage's fault bits of ACT_STATE (voltage, FET and winding temperature, short circuit,
#: Hall sensor, integral error).
POWER_STAGE_FAULTS: Final = (
    ActState.POW_VOLT_ERR | ActState.POW_FET_TEMP | ActState.POW_WDG_TEMP | ActState.POW_SHORTCUR
    | ActState.POW_HALLERR | ActState.POW_INTEGRAL_ERR
)


class ShortState(IntFlag):
    """Short state byte of extended SETMOVE acknowledgements."""

    ERROR = 0x01
    SWR = 0x02
    SW1 = 0x04
    SW2 = 0x08
    MOTION = 0x10
    RAMP_END = 0x20
    INPROGRESS = 0x40
    FULLBUFFER = 0x80


class ActConfig(IntFlag):
    """Module configuration bits (parameter ACT_CONFIG 0x39); only the ones this package uses."""

    DISABLE_ON_HALT = 0x00800000
    WATCHDOG_ENABLE = 0x01000000
    DISABLE_ACK = 0x04000000
    SYNC_MOTION = 0x08000000  # SETMOVE waits for the STARTMOVE broadcast
    SYNC_TRANSMIT = 0x10000000


class DioBits(IntFlag):
    """Digital I/O byte of extended acknowledgements."""

    INBIT0 = 0x01
    INBIT1 = 0x02
    INBIT2 = 0x04
    INBIT3 = 0x08
    OUTBIT0 = 0x10
    OUTBIT1 = 0x20
    OUTBIT2 = 0x40
    OUTBIT3 = 0x80


# Short <-> long state mapping, one table used both ways.
_SHORT_TO_LONG: Final = (
    (ShortState.ERROR, ActState.ERROR),
    (ShortState.SWR, ActState.SWR),
    (ShortState.SW1, ActState.SW1),
    (ShortState.SW2, ActState.SW2),
    (ShortState.MOTION, ActState.MOTION),
    (ShortState.RAMP_END, ActState.RAMP_END),
    (ShortState.INPROGRESS, ActState.INPROGRESS),
    (ShortState.FULLBUFFER, ActState.FULLBUFFER),
)


_SHORT_TO_LONG_INT: Final = tuple((int(s), int(long_bit)) for s, long_bit in _SHORT_TO_LONG)
# Enum construction and flag arithmetic cost microseconds; the hot paths use these int tables.
#: ``LONG_BITS_OF_SHORT[b]``: the ACT_STATE bits (int) a short state byte ``b`` stands for.
LONG_BITS_OF_SHORT: Final = tuple(
    sum(long_bit for s, long_bit in _SHORT_TO_LONG_INT if b & s) for b in range(256)
)
#: The ACT_STATE bits that have a short-state equivalent.
LONG_BITS_WITH_SHORT: Final = LONG_BITS_OF_SHORT[0xFF]
_SHORT_MEMBERS: Final = tuple(ShortState(b) for b in range(256))
#: The inverse of LONG_BITS_OF_SHORT: the short state byte of every combination of those ACT_STATE bits
#: (eight distinct long bits, one per short bit).
_SHORT_OF_LONG: Final = {long_bits: b for b, long_bits in enumerate(LONG_BITS_OF_SHORT)}
assert len(_SHORT_OF_LONG) == 256


def short_bits_from_long(state: int) -> int:
    """:func:`short_state_from_long` as a plain int (hot path)."""
    return _SHORT_OF_LONG[state & LONG_BITS_WITH_SHORT]


def short_state_from_long(state: int) -> ShortState:
    """Map ACT_STATE bits onto the short state byte (bits without a short equivalent are dropped)."""
    return _SHORT_MEMBERS[short_bits_from_long(int(state))]


def long_state_from_short(short: int) -> ActState:
    """Map a short state byte back onto the ACT_STATE bits it stands for (as the vendor library does)."""
    return ActState(LONG_BITS_OF_SHORT[int(short) & 0xFF])


# --------------------------------------------------------------------------------------------------
# Decoded frames. Host -> module requests first, then module -> host replies.
# One record per frame type and one builder per command: alike in shape, as the protocol table is.
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CommandRequest:
    """A simple one-byte command (RESET, HOME, HALT, WATCHDOG, RECALCPID, SAVEPOS, SAVEPARAMS)."""

    module_id: int
    command: Command


@dataclass(frozen=True, slots=True)
class SetParamRequest:
    """SETPARAM: ``value`` is float for F32 parameters, int otherwise."""

    module_id: int
    param: Param
    value: float | int


@dataclass(frozen=True, slots=True)
class GetParamRequest:
    """GETPARAM on 0x0C0+id."""

    module_id: int
    param: Param


@dataclass(frozen=True, slots=True)
class SetMoveRequest:
    """SETMOVE: ``value`` in rad (FRAMP/FSTEP), rad/s (FVEL) or A (FCUR); ``duration_ms`` for FSTEP only."""

    module_id: int
    mode: MoveMode
    value: float
    duration_ms: int | None = None


@dataclass(frozen=True, slots=True)
class Broadcast:
    """A frame on 0x100: ``arg`` is byte 1 (0, or the BaudRate for SET_BAUDRATE)."""

    command: BroadcastCommand
    arg: int = 0


@dataclass(frozen=True, slots=True)
class CommandAck:
    """One-byte acknowledgement of a simple command."""

    module_id: int
    command: Command


@dataclass(frozen=True, slots=True)
class SetParamAck:
    """Acknowledgement of SETPARAM."""

    module_id: int
    param: Param


@dataclass(frozen=True, slots=True)
class GetParamReply:
    """Reply to GETPARAM: ``value`` is float for F32 parameters, int otherwise."""

    module_id: int
    param: Param
    value: float | int


@dataclass(frozen=True, slots=True)
class SetMoveAck:
    """Acknowledgement of a plain SETMOVE."""

    module_id: int
    mode: MoveMode


@dataclass(frozen=True, slots=True)
class SetMoveExtAck:
    """Acknowledgement of an extended SETMOVE: position (rad) *before* the move, short state, dio."""

    module_id: int
    mode: MoveMode
    position: float
    short_state: ShortState
    dio: int


@dataclass(frozen=True, slots=True)
class StateFrame:
    """Unsolicited state on 0x060+id (ACT_STATE bits)."""

    module_id: int
    state: ActState


Request = CommandRequest | SetParamRequest | GetParamRequest | SetMoveRequest | Broadcast
#: The requests addressed to one module (not the broadcast), for ``isinstance`` checks.
MODULE_REQUEST_TYPES: Final = (CommandRequest, SetParamRequest, GetParamRequest, SetMoveRequest)
Reply = CommandAck | SetParamAck | GetParamReply | SetMoveAck | SetMoveExtAck | StateFrame
Frame = Request | Reply

# --------------------------------------------------------------------------------------------------
# Builders
# --------------------------------------------------------------------------------------------------

# Enum members as plain constants for the per-frame paths (a class attribute look-up of an enum costs
# about 0.1 us).
_SETMOVE: Final = Command.SETMOVE
_SETPARAM: Final = Command.SETPARAM
_GETPARAM: Final = Command.GETPARAM
_CMD_ACK: Final = IdBase.CMD_ACK
_F32: Final = struct.Struct("<f")
_U16: Final = struct.Struct("<H")
_U32: Final = struct.Struct("<I")
_FSTEP: Final = struct.Struct("<BBfH")  # [0B][mode][f32][u16 ms]
_FMOVE: Final = struct.Struct("<BBf")  # [0B][mode][f32]
_EXT_ACK: Final = struct.Struct("<BBfBB")  # [0B][mode][f32 pos][u8 short][u8 dio]
_FSTEP_MODES: Final = frozenset((0x06, 0x10))  # MoveMode.FSTEP, MoveMode.FSTEP_EXT


def _message(arbitration_id: int, data: bytes | bytearray) -> can.Message:
    """A checked 11-bit data frame (check=True guards the remote bus against malformed frames)."""
    return can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False, check=True)


def _check_module_id(module_id: int) -> int:
    if (
        isinstance(module_id, bool)
        or not isinstance(module_id, int)
        or not (MIN_MODULE_ID <= module_id <= MAX_MODULE_ID)
    ):
        raise InvalidInputError(
            f"module id must be an int in {MIN_MODULE_ID}..{MAX_MODULE_ID}, got {module_id!r}",
            field="module_id",
            value=module_id,
        )
    return module_id


def _check_float(value: float, field: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InvalidInputError(
            f"{field} must be a number, got {value!r}", field=field, value=value
        ) from None
    if not math.isfinite(x) or abs(x) > FLOAT32_MAX:
        raise InvalidInputError(f"{field} must be a finite float32, got {value!r}", field=field, value=value)
    return x


def _pack_value(param: Param, value: float | int) -> bytes:
    ptype = PARAM_TYPES[param]
    if ptype is ParamType.F32:
        return ptype.struct.pack(_check_float(value, param.name))
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidInputError(f"{param.name} takes an int, got {value!r}", field=param.name, value=value)
    limit = 1 << (8 * ptype.size)
    if not 0 <= value < limit:
        raise InvalidInputError(
            f"{param.name} is {ptype.name}: value must be in 0..{limit - 1}, got {value}",
            field=param.name,
            value=value,
        )
    return ptype.struct.pack(value)


def _as_param(param: int) -> Param:
    try:
        return Param(param)
    except ValueError:
        raise InvalidInputError(f"unknown parameter id {param!r}", field="param", value=param) from None


def _as_mode(mode: int) -> MoveMode:
    try:
        return MoveMode(mode)
    except ValueError:
        raise InvalidInputError(f"unknown SETMOVE mode {mode!r}", field="mode", value=mode) from None


def command(module_id: int, cmd: Command) -> can.Message:
    """A simple one-byte command ``[cmd]`` on 0x0E0+id (RESET, HOME, HALT, WATCHDOG, ...)."""
    _check_module_id(module_id)
    if cmd not in SIMPLE_COMMANDS:
        raise InvalidInputError(f"{cmd!r} is not a simple command", field="cmd", value=cmd)
    return _message(IdBase.CMD_PUT + module_id, bytes((cmd,)))


def reset(module_id: int) -> can.Message:
    """RESET: clears ERROR, HALTED and BEYOND_SOFT."""
    return command(module_id, Command.RESET)


def home(module_id: int) -> can.Message:
    """HOME: start the homing run; HOME_OK is set when it ends."""
    return command(module_id, Command.HOME)


def halt(module_id: int) -> can.Message:
    """HALT: stop immediately and set HALTED."""
    return command(module_id, Command.HALT)


def watchdog(module_id: int) -> can.Message:
    """Per-module WATCHDOG command (refreshes that module's watchdog)."""
    return command(module_id, Command.WATCHDOG)


def set_param(module_id: int, param: Param | int, value: float | int) -> can.Message:
    """SETPARAM ``[08][param][value]``; the value is packed by the parameter's type."""
    _check_module_id(module_id)
    p = _as_param(param)
    return _message(IdBase.CMD_PUT + module_id, bytes((Command.SETPARAM, p)) + _pack_value(p, value))


def get_param(module_id: int, param: Param | int) -> can.Message:
    """GETPARAM ``[0A][param]`` on 0x0C0+id."""
    _check_module_id(module_id)
    p = _as_param(param)
    return _message(IdBase.CMD_GET + module_id, bytes((Command.GETPARAM, p)))


def _check_duration_ms(duration_ms: int) -> int:
    if isinstance(duration_ms, bool) or not isinstance(duration_ms, int) or not 0 <= duration_ms <= 0xFFFF:
        raise InvalidInputError(
            f"FSTEP duration must be an int in 0..65535 ms, got {duration_ms!r}",
            field="duration_ms",
            value=duration_ms,
        )
    return duration_ms


def set_move(
    module_id: int, mode: MoveMode | int, value: float, duration_ms: int | None = None
) -> can.Message:
    """SETMOVE ``[0B][mode][f32]`` (+ ``[u16 ms]`` for FSTEP/FSTEP_EXT, required there, refused elsewhere).

    ``value`` is a position in rad (FRAMP, FSTEP), a velocity in rad/s (FVEL) or a current in A (FCUR).
    """
    _check_module_id(module_id)
    m = _as_mode(mode)
    x = _check_float(value, "value")
    if m.has_duration:
        if duration_ms is None:
            raise InvalidInputError(f"{m.name} needs duration_ms", field="duration_ms", value=None)
        data = _FSTEP.pack(Command.SETMOVE, m, x, _check_duration_ms(duration_ms))
    else:
        if duration_ms is not None:
            raise InvalidInputError(f"{m.name} takes no duration", field="duration_ms", value=duration_ms)
        data = _FMOVE.pack(Command.SETMOVE, m, x)
    return _message(IdBase.CMD_PUT + module_id, data)


def fstep(module_id: int, target_rad: float, duration_ms: int, *, extended: bool = True) -> can.Message:
    """FSTEP(_EXT): reach ``target_rad`` in ``duration_ms`` milliseconds."""
    return set_move(module_id, MoveMode.FSTEP_EXT if extended else MoveMode.FSTEP, target_rad, duration_ms)


def patch_fstep(msg: can.Message, target_rad: float, duration_ms: int) -> None:
    """Rewrite the target and duration of a frame built by :func:`fstep` in place (same id and mode).

    The hot path of a control cycle: the driver builds one FSTEP(_EXT) frame per joint once and
    patches it every cycle instead of building a new message. Same layout and checks as
    :func:`set_move`.

    Raises:
        InvalidInputError: ``msg`` is not an FSTEP/FSTEP_EXT frame, the target is NaN/inf, or the
            duration is outside 0..65535 ms (the frame is left unchanged).
    """
    data = msg.data
    if len(data) != _FSTEP.size or data[0] != Command.SETMOVE or data[1] not in _FSTEP_MODES:
        raise InvalidInputError("not an FSTEP frame built by fstep()", field="msg", value=msg)
    x = _check_float(target_rad, "target_rad")
    _FSTEP.pack_into(data, 0, Command.SETMOVE, data[1], x, _check_duration_ms(duration_ms))


def framp(module_id: int, target_rad: float, *, extended: bool = False) -> can.Message:
    """FRAMP(_EXT): ramp to ``target_rad`` with the module's ramp velocity/acceleration."""
    return set_move(module_id, MoveMode.FRAMP_EXT if extended else MoveMode.FRAMP, target_rad)


def fvel(module_id: int, velocity_rad_s: float, *, extended: bool = False) -> can.Message:
    """FVEL(_EXT): move at ``velocity_rad_s``."""
    return set_move(module_id, MoveMode.FVEL_EXT if extended else MoveMode.FVEL, velocity_rad_s)


def fcur(module_id: int, current_a: float, *, extended: bool = False) -> can.Message:
    """FCUR(_EXT): drive with ``current_a`` amperes."""
    return set_move(module_id, MoveMode.FCUR_EXT if extended else MoveMode.FCUR, current_a)


def broadcast(cmd: BroadcastCommand | int, arg: int = 0) -> can.Message:
    """A broadcast ``[cmd][arg]`` on 0x100; ``arg`` must be 0 except for SET_BAUDRATE (a BaudRate)."""
    try:
        c = BroadcastCommand(cmd)
    except ValueError:
        raise InvalidInputError(f"unknown broadcast command {cmd!r}", field="cmd", value=cmd) from None
    if c is BroadcastCommand.SET_BAUDRATE:
        if arg not in BaudRate.__members__.values():
            raise InvalidInputError(f"baud-rate index must be 0..3, got {arg!r}", field="arg", value=arg)
    elif arg != 0:
        raise InvalidInputError(f"{c.name} takes byte 1 = 0, got {arg!r}", field="arg", value=arg)
    return _message(IdBase.BROADCAST, bytes((c, arg)))


def start_motion_all() -> can.Message:
    """startMotionAll ``0x100 [0F 00]``: starts every move waiting under SYNC_MOTION."""
    return broadcast(BroadcastCommand.START_MOTION_ALL)


def reset_all() -> can.Message:
    """resetAll ``0x100 [00 00]``."""
    return broadcast(BroadcastCommand.RESET_ALL)


def home_all() -> can.Message:
    """homeAll ``0x100 [01 00]``."""
    return broadcast(BroadcastCommand.HOME_ALL)


def halt_all() -> can.Message:
    """haltAll ``0x100 [02 00]``."""
    return broadcast(BroadcastCommand.HALT_ALL)


def watchdog_refresh_all() -> can.Message:
    """Watchdog refresh ``0x100 [07 00]``."""
    return broadcast(BroadcastCommand.WATCHDOG_REFRESH)


def save_pos_all() -> can.Message:
    """savePosAll ``0x100 [0E 00]``."""
    return broadcast(BroadcastCommand.SAVEPOS_ALL)


def set_baudrate_all(rate: BaudRate | int) -> can.Message:
    """setBaudRateAll ``0x100 [09 n]``, n = 0,1,2,3 for 125k, 250k, 500k, 1M."""
    return broadcast(BroadcastCommand.SET_BAUDRATE, int(rate))


# Module side ----------------------------------------------------------------------------------------


def command_ack(module_id: int, cmd: Command) -> can.Message:
    """Acknowledgement ``[cmd]`` of a simple command, on 0x0A0+id."""
    _check_module_id(module_id)
    if cmd not in SIMPLE_COMMANDS:
        raise InvalidInputError(f"{cmd!r} is not a simple command", field="cmd", value=cmd)
    return _message(IdBase.CMD_ACK + module_id, bytes((cmd,)))


def set_param_ack(module_id: int, param: Param | int) -> can.Message:
    """Acknowledgement ``[08][param]`` of SETPARAM."""
    _check_module_id(module_id)
    return _message(IdBase.CMD_ACK + module_id, bytes((Command.SETPARAM, _as_param(param))))


def get_param_reply(module_id: int, param: Param | int, value: float | int) -> can.Message:
    """Reply ``[0A][param][value]`` to GETPARAM, value packed by the parameter's type."""
    _check_module_id(module_id)
    p = _as_param(param)
    return _message(IdBase.CMD_ACK + module_id, bytes((Command.GETPARAM, p)) + _pack_value(p, value))


def set_move_ack(module_id: int, mode: MoveMode | int) -> can.Message:
    """Acknowledgement ``[0B][mode]`` of a plain SETMOVE."""
    _check_module_id(module_id)
    m = _as_mode(mode)
    if m.extended:
        raise InvalidInputError(f"{m.name} is acknowledged by set_move_ext_ack", field="mode", value=mode)
    return _message(IdBase.CMD_ACK + module_id, bytes((Command.SETMOVE, m)))


def set_move_ext_ack(
    module_id: int, mode: MoveMode | int, position_rad: float, short_state: ShortState | int, dio: int = 0
) -> can.Message:
    """Acknowledgement ``[0B][mode][f32 pos][u8 short][u8 dio]`` of an extended SETMOVE.

    ``position_rad`` is the actual position *before* the move.
    """
    _check_module_id(module_id)
    m = mode if type(mode) is MoveMode else _as_mode(mode)
    if m not in EXTENDED_MOVE_MODES:
        raise InvalidInputError(f"{m.name} is acknowledged by set_move_ack", field="mode", value=mode)
    if not 0 <= int(short_state) <= 0xFF:
        raise InvalidInputError(f"short_state must fit a byte, got {short_state!r}", field="short_state",
                                value=short_state)
    if not 0 <= int(dio) <= 0xFF:
        raise InvalidInputError(f"dio must fit a byte, got {dio!r}", field="dio", value=dio)
    data = _EXT_ACK.pack(_SETMOVE, m, _check_float(position_rad, "position_rad"), short_state, dio)
    return _message(_CMD_ACK + module_id, data)


def state_frame(module_id: int, state: ActState | int) -> can.Message:
    """State frame on 0x060+id: ACT_STATE as u32 in bytes 0-3 (DLC 4)."""
    _check_module_id(module_id)
    if not 0 <= int(state) <= 0xFFFFFFFF:
        raise InvalidInputError(f"state must fit u32, got {state!r}", field="state", value=state)
    return _message(IdBase.STATE + module_id, _U32.pack(int(state)))


def encode(frame: Frame) -> can.Message:
    """Build the CAN message of a decoded frame (inverse of :func:`decode`)."""
    match frame:
        case CommandRequest(module_id=i, command=c):
            return command(i, c)
        case SetParamRequest(module_id=i, param=p, value=v):
            return set_param(i, p, v)
        case GetParamRequest(module_id=i, param=p):
            return get_param(i, p)
        case SetMoveRequest(module_id=i, mode=m, value=v, duration_ms=d):
            return set_move(i, m, v, d)
        case Broadcast(command=c, arg=a):
            return broadcast(c, a)
        case CommandAck(module_id=i, command=c):
            return command_ack(i, c)
        case SetParamAck(module_id=i, param=p):
            return set_param_ack(i, p)
        case GetParamReply(module_id=i, param=p, value=v):
            return get_param_reply(i, p, v)
        case SetMoveAck(module_id=i, mode=m):
            return set_move_ack(i, m)
        case SetMoveExtAck(module_id=i, mode=m, position=x, short_state=s, dio=d):
            return set_move_ext_ack(i, m, x, s, d)
        case StateFrame(module_id=i, state=s):
            return state_frame(i, s)
    raise InvalidInputError(f"not a PowerCube frame: {frame!r}", field="frame", value=frame)


# --------------------------------------------------------------------------------------------------
# Parsers
# --------------------------------------------------------------------------------------------------


class FrameKind(Enum):
    """Which id range a frame belongs to."""

    REQUEST = "request"  # 0x0E0+id
    GET_REQUEST = "get_request"  # 0x0C0+id
    REPLY = "reply"  # 0x0A0+id
    STATE = "state"  # 0x060+id
    BROADCAST = "broadcast"  # 0x100


_RANGES: Final = (
    (IdBase.CMD_PUT, FrameKind.REQUEST),
    (IdBase.CMD_GET, FrameKind.GET_REQUEST),
    (IdBase.CMD_ACK, FrameKind.REPLY),
    (IdBase.STATE, FrameKind.STATE),
)


#: (kind, module id) of every id in the PowerCube ranges (classify_id without a loop per frame).
_KIND_OF_ID: Final = {
    int(IdBase.BROADCAST): (FrameKind.BROADCAST, 0),
    **{int(base) + i: (kind, i) for base, kind in _RANGES for i in range(MIN_MODULE_ID, MAX_MODULE_ID + 1)},
}


def classify_id(arbitration_id: int) -> tuple[FrameKind, int]:
    """Split an 11-bit id into (kind, module id); module id is 0 for the broadcast.

    Raises:
        ProtocolError: the id is in none of the PowerCube ranges.
    """
    found = _KIND_OF_ID.get(arbitration_id)
    if found is not None:
        return found
    raise _outside_ranges(arbitration_id)


def _outside_ranges(arbitration_id: int, msg: can.Message | None = None) -> ProtocolError:
    return ProtocolError(f"CAN id 0x{arbitration_id:03X} is outside the PowerCube id ranges", frame=msg)


def _fail(msg: can.Message, why: str) -> ProtocolError:
    raw = bytes(msg.data).hex(" ")
    return ProtocolError(f"malformed frame 0x{msg.arbitration_id:03X} [{raw}]: {why}", frame=msg)


def _need_dlc(msg: can.Message, data: bytes, expected: int, what: str) -> None:
    if len(data) != expected:
        raise _fail(msg, f"{what} needs DLC {expected}, got {len(data)}")


def _finite(msg: can.Message, x: float, what: str) -> float:
    if not math.isfinite(x):
        raise _fail(msg, f"{what} is not finite ({x})")
    return x


_PARAMS_BY_BYTE: Final = {int(x): x for x in Param}
_MODES_BY_BYTE: Final = {int(x): x for x in MoveMode}
_COMMANDS_BY_BYTE: Final = {int(x): x for x in Command}


def _parse_param(msg: can.Message, byte: int) -> Param:
    param = _PARAMS_BY_BYTE.get(byte)
    if param is None:
        raise _fail(msg, f"unknown parameter 0x{byte:02X}")
    return param


def _parse_mode(msg: can.Message, byte: int) -> MoveMode:
    mode = _MODES_BY_BYTE.get(byte)
    if mode is None:
        raise _fail(msg, f"unknown SETMOVE mode 0x{byte:02X}")
    return mode


def _parse_command(msg: can.Message, byte: int) -> Command:
    cmd = _COMMANDS_BY_BYTE.get(byte)
    if cmd is None:
        raise _fail(msg, f"unknown command 0x{byte:02X}")
    return cmd


def _unpack_value(msg: can.Message, param: Param, raw: bytes) -> float | int:
    ptype = PARAM_TYPES[param]
    (value,) = ptype.struct.unpack(raw)
    if ptype is ParamType.F32:
        _finite(msg, value, param.name)
    return value


def _decode_request(msg: can.Message, data: bytes, module_id: int) -> Request:
    cmd = _parse_command(msg, data[0])
    if cmd in SIMPLE_COMMANDS:
        _need_dlc(msg, data, 1, cmd.name)
        return CommandRequest(module_id, cmd)
    if cmd is _SETPARAM:
        if len(data) < 2:
            raise _fail(msg, "SETPARAM needs a parameter byte")
        param = _parse_param(msg, data[1])
        _need_dlc(msg, data, 2 + PARAM_TYPES[param].size, f"SETPARAM {param.name}")
        return SetParamRequest(module_id, param, _unpack_value(msg, param, data[2:]))
    if cmd is _SETMOVE:
        if len(data) < 2:
            raise _fail(msg, "SETMOVE needs a mode byte")
        mode = _parse_mode(msg, data[1])
        if mode in _DURATION_MODES:
            _need_dlc(msg, data, _FSTEP.size, f"SETMOVE {mode.name}")
            _, _, x, ms = _FSTEP.unpack(data)
            return SetMoveRequest(module_id, mode, _finite(msg, x, "target"), ms)
        _need_dlc(msg, data, _FMOVE.size, f"SETMOVE {mode.name}")
        _, _, x = _FMOVE.unpack(data)
        return SetMoveRequest(module_id, mode, _finite(msg, x, "value"))
    if cmd is _GETPARAM:
        raise _fail(msg, "GETPARAM must be sent on 0x0C0+id")
    raise _fail(msg, f"{cmd.name} is not a module command (broadcast only)")


def _decode_get_request(msg: can.Message, data: bytes, module_id: int) -> GetParamRequest:
    if data[0] != Command.GETPARAM:
        raise _fail(msg, f"only GETPARAM (0x0A) is allowed on 0x0C0+id, got 0x{data[0]:02X}")
    _need_dlc(msg, data, 2, "GETPARAM")
    return GetParamRequest(module_id, _parse_param(msg, data[1]))


def _decode_reply(msg: can.Message, data: bytes, module_id: int) -> Reply:
    cmd = _parse_command(msg, data[0])
    if cmd in SIMPLE_COMMANDS:
        _need_dlc(msg, data, 1, f"{cmd.name} ack")
        return CommandAck(module_id, cmd)
    if len(data) < 2:
        raise _fail(msg, f"{cmd.name} reply needs at least 2 bytes")
    if cmd is Command.SETPARAM:
        param = _parse_param(msg, data[1])
        _need_dlc(msg, data, 2, "SETPARAM ack")
        return SetParamAck(module_id, param)
    if cmd is Command.GETPARAM:
        param = _parse_param(msg, data[1])
        _need_dlc(msg, data, 2 + PARAM_TYPES[param].size, f"GETPARAM {param.name} reply")
        return GetParamReply(module_id, param, _unpack_value(msg, param, data[2:]))
    if cmd is Command.SETMOVE:
        mode = _parse_mode(msg, data[1])
        if mode.extended:
            _need_dlc(msg, data, _EXT_ACK.size, f"SETMOVE {mode.name} ack")
            _, _, x, short, dio = _EXT_ACK.unpack(data)
            return SetMoveExtAck(module_id, mode, _finite(msg, x, "position"), _SHORT_MEMBERS[short], dio)
        _need_dlc(msg, data, 2, f"SETMOVE {mode.name} ack")
        return SetMoveAck(module_id, mode)
    raise _fail(msg, f"{cmd.name} is never acknowledged")


def _decode_state(msg: can.Message, data: bytes, module_id: int) -> StateFrame:
    if not 4 <= len(data) <= 8:
        raise _fail(msg, f"state frame needs DLC 4..8, got {len(data)}")
    (state,) = _U32.unpack_from(data)
    return StateFrame(module_id, ActState(state))


def _decode_broadcast(msg: can.Message, data: bytes, _module_id: int) -> Broadcast:
    known = _BROADCASTS.get(data)  # a driver sends the same two or three every cycle
    if known is not None:
        return known
    _need_dlc(msg, data, 2, "broadcast")
    try:
        cmd = BroadcastCommand(data[0])
    except ValueError:
        raise _fail(msg, f"unknown broadcast command 0x{data[0]:02X}") from None
    arg = data[1]
    if cmd is BroadcastCommand.SET_BAUDRATE:
        if arg > max(BaudRate):
            raise _fail(msg, f"baud-rate index {arg} is not 0..3")
    elif arg != 0:
        raise _fail(msg, f"{cmd.name} needs byte 1 = 0, got 0x{arg:02X}")
    frame = _BROADCASTS[data] = Broadcast(cmd, arg)  # immutable; one per valid byte pair (a dozen at most)
    return frame


_BROADCASTS: dict[bytes, Broadcast] = {}


_DECODERS: Final = {
    FrameKind.REQUEST: _decode_request,
    FrameKind.GET_REQUEST: _decode_get_request,
    FrameKind.REPLY: _decode_reply,
    FrameKind.STATE: _decode_state,
    FrameKind.BROADCAST: _decode_broadcast,
}


def decode(msg: can.Message) -> Frame:
    """Classify any frame by id range and byte 0 and return its typed dataclass.

    Raises:
        ProtocolError: extended/remote/error/FD frame, id out of range, DLC and data length
            disagree, wrong DLC for the layout, unknown command/mode/parameter, or a
            non-finite float. ``exc.frame`` is the message.
    """
    if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
        raise ProtocolError(
            f"not a PowerCube frame (extended/remote/error/FD) id 0x{msg.arbitration_id:X}", frame=msg
        )
    found = _KIND_OF_ID.get(msg.arbitration_id)  # classify_id, without one more call per frame
    if found is None:
        raise _outside_ranges(msg.arbitration_id, msg)
    kind, module_id = found
    data = bytes(msg.data)
    if msg.dlc != len(data):
        raise _fail(msg, f"DLC {msg.dlc} does not match {len(data)} data bytes")
    if not data:
        raise _fail(msg, "empty frame")
    return _DECODERS[kind](msg, data, module_id)


def fstep_ext_ack_fields(msg: can.Message) -> tuple[float, int] | None:
    """Fast path for the one reply a control cycle waits for: (position rad, short state bits)
    if ``msg`` is a well-formed FSTEP_EXT acknowledgement (any module id; the caller routes by
    id), else None, in which case the caller decodes it with :func:`decode` (which also rejects
    a non-finite position as malformed)."""
    data = msg.data
    if len(data) != 8 or data[0] != 0x0B or data[1] != 0x10 or msg.dlc != 8 or msg.is_extended_id:
        return None
    _, _, x, short, _dio = _EXT_ACK.unpack(data)
    if x - x != 0.0:  # NaN or inf
        return None
    return x, short


class FrameDecoder:
    """Decode frames for a reader loop: malformed ones are counted, logged and skipped, never raised.

    ``malformed`` is the total count, ``malformed_by_id`` per CAN id, ``last_error`` the latest
    :class:`ProtocolError`. Not thread-safe: one decoder per reader loop.
    """

    __slots__ = ("decoded", "malformed", "malformed_by_id", "last_error", "_log_every")

    def __init__(self, log_every: int = 100) -> None:
        self.decoded = 0
        self.malformed = 0
        self.malformed_by_id: Counter[int] = Counter()
        self.last_error: ProtocolError | None = None
        self._log_every = max(1, log_every)

    def decode(self, msg: can.Message) -> Frame | None:
        """The decoded frame, or None (counted) if ``msg`` is malformed."""
        try:
            frame = decode(msg)
        except ProtocolError as exc:
            self.malformed += 1
            self.malformed_by_id[msg.arbitration_id] += 1
            self.last_error = exc
            # Rate-limited: a babbling node must not flood the log.
            if self.malformed % self._log_every == 1 or self._log_every == 1:
                logger.warning("skipping malformed CAN frame (%d so far): %s", self.malformed, exc)
            return None
        self.decoded += 1
        return frame
