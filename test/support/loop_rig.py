"""A 3-module emulated arm served on an in-process virtual CAN channel, with a DriverLoop (real driver
core) on the same channel: the rig of the driver-loop tests."""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

import can

from redarm_ros.can.driver_core import PowerCubeArmDriver
from redarm_ros.can.driver_loop import CycleSample, DriverLoop, LoopConfig
from redarm_ros.can.module_emulator import EmulatedArm, EmulatorRunner

LOWER = [-2.0, -1.5, -2.0]
UPPER = [2.0, 1.5, 2.0]
VMAX = [1.0, 1.0, 2.0]
AMAX = [5.0, 5.0, 10.0]
Q0 = [0.3, -0.2, 0.1]


def virtual_bus(channel: str) -> can.BusABC:
    return can.Bus(interface="virtual", channel=channel)


@contextmanager
def loop_rig(arm: EmulatedArm, cfg: LoopConfig, open_host: Callable[[str], can.BusABC] = virtual_bus,
             **loop_kw: Any) -> Iterator[dict[str, Any]]:
    """``arm`` (built on LOWER..AMAX) served on a fresh virtual channel and a DriverLoop with ``cfg``
    on a host bus from ``open_host(channel)``; yields {"arm", "loop", "host", "samples"}, every
    thread and bus stopped on exit."""
    channel = f"loop-{uuid.uuid4().hex[:8]}"
    samples: list[CycleSample] = []

    def factory(bus: can.BusABC) -> PowerCubeArmDriver:
        # Emulator and driver share this process's GIL (and a busy machine): generous timeouts, so
        # only a module that really is silent counts as silent.
        return PowerCubeArmDriver(bus, [1, 2, 3], LOWER, UPPER, VMAX, AMAX, reply_timeout_s=0.05,
                                  max_missed=10, home_timeout_s=10.0)

    with ExitStack() as down:  # stops and shuts down in reverse order of the starts
        dev_bus = down.enter_context(virtual_bus(channel))
        down.callback(EmulatorRunner(dev_bus, arm, tick_s=0.002).start().stop)
        host = down.enter_context(open_host(channel))
        loop = DriverLoop(factory, lambda: host, 3, cfg, on_sample=samples.append, **loop_kw)
        down.callback(loop.stop)
        yield {"arm": arm, "loop": loop, "host": host, "samples": samples}
