"""Thin adapter: the PowerCube module emulator (``redarm_ros.can.module_emulator``) over the pybullet plant.

No protocol code lives here: every frame is handled by :class:`~redarm_ros.can.module_emulator.
PowerCubeModule`. This module only

* builds one module per joint with the arm model's limits (soft limits = joint limits, max
  velocity/acceleration = the model's, ramp velocity/acceleration = half of those, home position 0
  clipped into the limits),
* gives each module its joint of the :class:`~redarm_ros.sim.plant.PybulletPlant` as its plant,
  reporting the measured position clamped into the joint limits when it exceeds them by less than
  :data:`LIMIT_SLACK` (pybullet's constraint solver settles a joint parked on its limit a few
  microradians beyond it; a real encoder would not flag that, so neither should the module),
* routes decoded frames to the modules while honouring the process's silenced-module set, and
* reports module states for the status file without side effects.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any

import can

from redarm_ros.can import protocol as pc
from redarm_ros.can.module_emulator import EmulatedArm, ModuleConfig, Plant, PowerCubeModule
from redarm_ros.can.protocol import ActState
from redarm_ros.sim.physics_process import PhysicsProcess
from redarm_ros.sim.plant import PybulletPlant

LIMIT_SLACK = 1e-5  # rad


class _LimitedJoint:
    """A :class:`JointPlant` whose reported position is clamped into the limits within the slack."""

    def __init__(self, joint: Plant, lower: float, upper: float) -> None:
        self._j = joint
        self._lo, self._hi = lower, upper
        self._position = joint.position
        # The rest passes straight through: the joint's own methods, not one more call per use.
        self.command_position = joint.command_position
        self.command_velocity = joint.command_velocity
        self.halt = joint.halt
        self.velocity = joint.velocity
        self.in_motion = joint.in_motion
        self.set_travel_limits = joint.set_travel_limits

    def position(self) -> float:
        q = self._position()
        if self._hi < q <= self._hi + LIMIT_SLACK:
            return self._hi
        if self._lo - LIMIT_SLACK <= q < self._lo:
            return self._lo
        return q


class PlantModules:
    """One emulated PowerCube module per joint of ``plant``, ids ``module_ids`` (joint order).

    Thread-safety: all module access happens under the bank's lock.
    """

    def __init__(self, plant: PybulletPlant | PhysicsProcess, module_ids: Sequence[int], *,
                 homed: bool = False) -> None:
        arm = plant.arm
        if len(module_ids) != plant.n:
            raise ValueError(f"need {plant.n} module ids, got {len(module_ids)}")
        plants = []
        configs = []
        for i in range(plant.n):
            lo, hi = float(arm.lower[i]), float(arm.upper[i])
            plants.append(_LimitedJoint(plant.joint(i), lo, hi))
            configs.append(
                ModuleConfig(
                    lower=lo,
                    upper=hi,
                    max_vel=float(arm.max_vel[i]),
                    max_acc=float(arm.max_acc[i]),
                    home_position=min(max(0.0, lo), hi),
                    homed=homed,
                )
            )
        self.bank = EmulatedArm(plants, configs, module_ids=list(module_ids))
        self.module_ids = list(module_ids)
        self.ids = frozenset(module_ids)

    def module(self, module_id: int) -> PowerCubeModule:
        """The emulated module with this id."""
        return self.bank.modules[module_id]

    def handle(
        self, frame: pc.Frame, silenced: Collection[int] = (), t: float | None = None
    ) -> list[can.Message]:
        """Frames to send for one decoded request or broadcast (silenced modules ignore it).

        ``t`` is when the frame was on the bus (``time.monotonic`` scale; see
        :func:`redarm_ros.can.module_emulator.wire_time`), default now."""
        return self.bank.dispatch(frame, t, silenced)

    def tick(self, silenced: Collection[int] = (), behind_s: float = 0.0) -> list[can.Message]:
        """Advance the modules' time-driven behaviour (as of ``behind_s`` s ago, see
        ``PowerCubeModule.tick``); unsolicited frames of speaking modules."""
        return self.bank.tick(behind_s, silenced)

    def power_cycle(self, module_id: int) -> None:
        """Module ``module_id`` off and on: factory settings, no HOME_OK, its joint held where it is."""
        self.bank.power_cycle(module_id)

    def inject_fault(self, module_id: int, bits: ActState) -> None:
        """ERROR plus ``bits`` on module ``module_id``, as its hardware would raise them."""
        self.bank.inject_fault(module_id, bits)

    def describe(self, epoch: float = 0.0) -> list[dict[str, Any]]:
        """Per module: id, ACT_STATE (int and flag names), position (rad), requests handled, and
        ``halted_at_s``: when HALTED was set, in s since ``epoch`` (``time.monotonic`` scale), or
        None. No side effects."""
        out = []
        with self.bank.lock:
            for mid in self.module_ids:
                m = self.bank.modules[mid]
                st = ActState(m.sticky)
                st |= (ActState.MOTION | ActState.INPROGRESS) if m.plant.in_motion() else ActState.RAMP_END
                out.append(
                    {
                        "id": mid,
                        "state": int(st),
                        "flags": [f.name for f in ActState if f.value and f in st and f.name],
                        "position": m.plant.position(),
                        "requests": m.requests,
                        "halted_at_s": None if m.halted_at is None else m.halted_at - epoch,
                    }
                )
        return out

