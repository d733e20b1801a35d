"""A simulator plant whose every physics step first holds the interpreter lock without running, as a
physics thread does that the kernel preempts while it holds the lock (pybullet never releases it).

Picklable through :func:`functools.partial`, so a
:class:`~redarm_ros.sim.physics_process.PhysicsProcess` can build it in its own process."""

from __future__ import annotations

import ctypes
import time
from typing import Any

from redarm_ros.sim.physics_process import build_plant
from redarm_ros.sim.plant import PybulletPlant

_CHUNK_S = 0.2  # usleep takes less than a second


def hold_interpreter_lock(seconds: float) -> None:
    """Sleep ``seconds`` in C without releasing the interpreter lock (a ``PyDLL`` call keeps it)."""
    usleep = ctypes.PyDLL(None).usleep
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        usleep(int(min(left, _CHUNK_S) * 1e6))


def stalling_plant(arm: Any, stall_s: float) -> PybulletPlant:
    """The simulator's plant of ``arm`` whose :meth:`~PybulletPlant.step` holds the lock ``stall_s``
    seconds before stepping."""
    plant = build_plant(arm, time_step=1e-3)
    step = plant.step

    def stalled(count: int = 1) -> None:
        hold_interpreter_lock(stall_s)
        step(count)

    plant.step = stalled  # type: ignore[method-assign]
    return plant
