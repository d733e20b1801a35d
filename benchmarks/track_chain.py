"""The command chain of the stack on one simulated clock (no ROS, no bus, no pybullet): what delays a
streamed goal between the controller and the arm, with message latency and timer jitter as parameters.

    goal stream (50 Hz) -> ReachController core (100 Hz timer, late by 0..jitter) -> one /joint_command
    segment per step (delivered after a latency) -> JointCommandSource + ReferenceShaper (250 Hz driver
    cycle) -> FSTEP (1 ms on the bus) -> JointRamp set-point generators (1 kHz, as the simulator's
    modules) -> FK of the set-points

The real classes are used; only the processes, DDS and the bus are replaced by delays. Used by
``track_bench.py --chain`` (section "Command chain model"); the same chain through the real stack is
the "Through the stack" section.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from redarm_ros.can.driver_loop import JointCommandSource, ReferenceShaper
from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams, StreamParams
from redarm_ros.motion import JointLimits
from redarm_ros.sim.ramp import JointRamp

TICK = 1e-3  # s, the simulated clock's step (the modules' rate)
DRIVER_EVERY = 4  # ticks per driver cycle (250 Hz)
FSTEP_DELAY = 1e-3  # s from the driver's cycle to the modules (bus round trip)


@dataclass(frozen=True)
class Timing:
    """Message and timer timing: ``latency`` (s) of every /joint_command message plus an exponential
    extra with mean ``latency_tail`` (s), in order; controller ticks late by up to ``jitter`` (s,
    uniform, on a kept 10 ms grid); goal messages arrive ``goal_latency`` (s) after their stamps."""

    name: str
    latency: float = 0.002
    latency_tail: float = 0.0
    jitter: float = 0.0
    goal_latency: float = 0.001


@dataclass(frozen=True)
class Commands:
    """How commands are timed: ``delay`` (s) after its step that a stamped segment ends (0 = unstamped,
    started on receipt) and the stream ``lead`` (s) of the controller."""

    name: str
    delay: float
    lead: float


def run_chain(arm, path, q0: np.ndarray, timing: Timing, cmds: Commands, seed: int = 1,
              after: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Times (s, since the stream's start) and tool positions (m, FK of the modules' set-points)."""
    rng = np.random.default_rng(seed)
    ctl = make_controller(arm, path.scene, ControllerParams().with_(stream=StreamParams(lead=cmds.lead)))
    ctl.reset(q0, now=-1.0)
    goals = [min(k * 0.02, path.duration) for k in range(int(path.duration / 0.02) + 2)]
    src = JointCommandSource(arm.n)
    src.clear(q0)
    shaper = ReferenceShaper(JointLimits.from_arm(arm), DRIVER_EVERY * TICK)
    shaper.reset(q0)
    ramps = [JointRamp(q0[i], arm.lower[i], arm.upper[i], arm.max_vel[i], arm.max_acc[i])
             for i in range(arm.n)]
    q_ref = q0.copy()
    k_goal = 0
    k_tick = 0
    next_tick = 0.0
    last_tick: float | None = None
    last_cmd: np.ndarray | None = None
    last_delivery = -np.inf
    inbox: list[tuple[float, list[float], np.ndarray, float]] = []  # (deliver at, times, points, start)
    fstep: tuple[float, np.ndarray] | None = None
    ts, ps = [], []
    t0 = -0.05
    for i in range(int(round((path.duration + after - t0) / TICK)) + 1):
        t = t0 + i * TICK
        while k_goal < len(goals) and goals[k_goal] + timing.goal_latency <= t + 1e-12:
            ctl.goal_message(path.pose(goals[k_goal]), goals[k_goal], t)
            k_goal += 1
        if t >= next_tick - 1e-12:
            dt = 0.01 if last_tick is None else min(t - last_tick, 0.02)
            last_tick = t
            q = ctl.step(dt, t).q.copy()
            lat = timing.latency + (rng.exponential(timing.latency_tail) if timing.latency_tail else 0.0)
            last_delivery = max(last_delivery, t + lat)  # one publisher's messages stay in order
            times = [dt] if last_cmd is None else [0.0, dt]
            pts = q[None, :] if last_cmd is None else np.stack([last_cmd, q])
            start = t + cmds.delay - dt if cmds.delay > 0 else None
            inbox.append((last_delivery, times, pts, start))
            last_cmd = q
            k_tick += 1
            next_tick = k_tick * 0.01 + (rng.uniform(0.0, timing.jitter) if timing.jitter else 0.0)
        while inbox and inbox[0][0] <= t + 1e-12:
            deliver, times, pts, start = inbox.pop(0)
            src.set_trajectory(range(arm.n), times, pts, deliver if start is None else start)
        if i % DRIVER_EVERY == 0:
            q_ref = shaper.step(np.clip(src.sample(t, q_ref, q_ref), arm.lower, arm.upper))
            fstep = (t + FSTEP_DELAY, q_ref.copy())
        if fstep is not None and fstep[0] <= t + 1e-12:
            for j, r in enumerate(ramps):
                r.command_position(float(fstep[1][j]), None, None, DRIVER_EVERY * TICK)
            fstep = None
        qs = np.array([r.step(TICK) for r in ramps])
        ts.append(t)
        ps.append(arm.fk(qs)[:3, 3])
    return np.array(ts), np.array(ps)


TIMINGS = [
    Timing("quiet: latency 2 ms, no jitter"),
    Timing("busy: latency 2 ms + exp(8 ms), ticks late 0-10 ms", latency_tail=0.008, jitter=0.01),
    Timing("loaded: latency 2 ms + exp(20 ms), ticks late 0-20 ms", latency_tail=0.02, jitter=0.02),
]
COMMANDS = [
    Commands("unstamped, lead 0 (before)", 0.0, 0.0),
    Commands("unstamped, lead 23 ms", 0.0, 0.023),
    Commands("stamped +30 ms, lead 40 ms", 0.03, 0.04),
    Commands("stamped +50 ms, lead 60 ms (default)", 0.05, 0.06),
]
