"""Talk PowerCube to the simulated arm with python-can alone (no ROS): find the modules, home one,
move it, and read back its position and state. Frames are built and read by the package's codec
(redarm_ros.can.protocol).

    python powercube_script.py --interface remote --channel ws://127.0.0.1:PORT/
    python powercube_script.py --interface socketcan --channel vcan0
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import can

from redarm_ros.can import protocol as pc
from redarm_ros.can.protocol import ActState, Param

REPLY_S = 0.1  # a module answers within this (the vendor library's limit)


def ask(bus: can.BusABC, request: can.Message, timeout: float = REPLY_S) -> pc.Frame | None:
    """Send ``request``; the module's decoded reply (same id and command byte), or None."""
    module_id = request.arbitration_id & 0x1F
    bus.send(request)
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        msg = bus.recv(left)
        if msg is None:
            break
        if msg.arbitration_id == pc.IdBase.CMD_ACK + module_id and msg.data[:1] == request.data[:1]:
            return pc.decode(msg)
    return None


def param(bus: can.BusABC, module_id: int, which: Param) -> float | int:
    reply = ask(bus, pc.get_param(module_id, which))
    if not isinstance(reply, pc.GetParamReply):
        raise SystemExit(f"module {module_id} did not answer GETPARAM {which.name}")
    return reply.value


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--interface", required=True, help="python-can interface (remote, socketcan, ...)")
    ap.add_argument("--channel", required=True, help="python-can channel")
    ap.add_argument("--module", type=int, default=1, help="the module to home and move")
    ap.add_argument("--target", type=float, default=0.25, help="where to move it (rad)")
    args = ap.parse_args(argv)
    with can.Bus(interface=args.interface, channel=args.channel) as bus:
        # Discovery as the vendor library does it: DEF_VERSION from every id, count who answers.
        found = [m for m in range(1, 32) if ask(bus, pc.get_param(m, Param.DEF_VERSION), 0.05) is not None]
        print(f"modules: {found}")
        m = args.module
        ask(bus, pc.reset(m))
        ask(bus, pc.home(m))
        deadline = time.monotonic() + 10.0
        while not ActState(param(bus, m, Param.ACT_STATE)) & ActState.HOME_OK:
            if time.monotonic() > deadline:
                raise SystemExit(f"module {m} did not home")
            time.sleep(0.05)
        ask(bus, pc.fstep(m, args.target, 1000))  # to the target in 1 s
        while abs(param(bus, m, Param.ACT_FPOS) - args.target) > 1e-3:
            if time.monotonic() > deadline + 10.0:
                raise SystemExit(f"module {m} did not reach {args.target} rad")
            time.sleep(0.05)
        state = ActState(param(bus, m, Param.ACT_STATE))
        print(f"module {m} at {param(bus, m, Param.ACT_FPOS):.4f} rad, state {state!r}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
