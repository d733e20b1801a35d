"""Run a controller in-process and score the motion (used by reproductions, benchmark and tests).

The scores are computed from the joint trajectory alone (forward kinematics of the commanded q and
the capsule model), independently of what the controller believes, so that different controllers
are judged by the same yardstick. Units: m, rad, s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redarm_ros.control.reach_controller import Phase, ReachController
from redarm_ros.geometry.obstacles import ArmCapsules, Scene, min_distance
from redarm_ros.kinematics.protocols import ControlledArm


@dataclass
class Trajectory:
    """Samples of one run, one row per control step (the first row is the start state).

    t [s], q [rad] (k, n), tool [m] (k, 3), elbow [m] (k, 3), swivel / swivel_desired [rad],
    clearance [m] (from the controller), phase (list of str), step_s: wall time of each step [s].
    """

    t: np.ndarray
    q: np.ndarray
    tool: np.ndarray
    elbow: np.ndarray
    swivel: np.ndarray
    swivel_desired: np.ndarray
    clearance: np.ndarray
    phase: list[str]
    step_s: np.ndarray
    reached_at: float | None = None
    info: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ReachMetrics:
    """Scores of one reach.

    reached: final pose within tolerance before the time limit; time_to_goal [s] (nan if not);
    pos_err [m], ori_err [rad]: final errors; min_clearance [m] (> 0: collision-free, computed from q);
    limit_margin [rad]: smallest distance of any joint to its limit; path_length [m] of the tool;
    straight [m]: start-goal distance; path_ratio = path_length / straight; peak_jerk [m/s^3] of the
    tool; max_vel_ratio: largest joint speed over its limit; max_acc_ratio: largest joint acceleration
    (second difference of q over dt^2) over its limit; step_median_us / step_p99_us [us].
    """

    reached: bool
    time_to_goal: float
    pos_err: float
    ori_err: float
    min_clearance: float
    limit_margin: float
    path_length: float
    straight: float
    path_ratio: float
    peak_jerk: float
    max_vel_ratio: float
    step_median_us: float
    step_p99_us: float
    max_acc_ratio: float = 0.0

    @property
    def collision_free(self) -> bool:
        """No capsule ever touched an obstacle or the table."""
        return self.min_clearance > 0.0

    @property
    def success(self) -> bool:
        """Reached and collision-free."""
        return self.reached and self.collision_free


Event = tuple[float, Callable[[Any], None]]


def run_controller(ctl: ReachController, T_goal: np.ndarray, duration: float = 8.0, dt: float = 0.01,
                   events: Sequence[Event] = (), stop_when_reached: bool = True,
                   settle: float = 0.0) -> Trajectory:
    """Step ``ctl`` (already reset) towards ``T_goal`` for up to ``duration`` s at ``dt`` s.

    ``events``: ``(time_s, fn)`` pairs; ``fn(ctl)`` is called once when the clock passes ``time_s``
    (move the goal, change the scene, ...). With ``stop_when_reached`` the run ends ``settle`` s after
    the first REACHED phase (and after the last event).
    """
    check = ctl.set_goal(T_goal)
    arm = ctl.arm
    pending = sorted(events, key=lambda e: e[0])
    q0 = ctl.q
    assert q0 is not None
    kp = arm.key_points(q0)
    rows_t = [0.0]
    rows_q = [q0]
    rows_tool = [kp[4]]
    rows_elbow = [kp[2]]
    rows_s = [ctl.swivel]
    rows_sd = [ctl.swivel]
    rows_c = [math.nan]
    phases = [ctl.phase.value]
    steps: list[float] = []
    reached_at: float | None = None
    n = int(round(duration / dt))
    for k in range(1, n + 1):
        t = k * dt
        while pending and pending[0][0] <= t:
            pending.pop(0)[1](ctl)
        t0 = time.perf_counter()
        r = ctl.step(dt)
        steps.append(time.perf_counter() - t0)
        kp = arm.key_points(r.q)
        rows_t.append(t)
        rows_q.append(r.q)
        rows_tool.append(kp[4])
        rows_elbow.append(kp[2])
        rows_s.append(r.swivel)
        rows_sd.append(r.swivel_desired)
        rows_c.append(r.clearance)
        phases.append(r.phase.value)
        if r.phase is Phase.REACHED:
            if reached_at is None:
                reached_at = t
        elif r.phase is Phase.REACHING:
            reached_at = None  # a moved goal restarts the clock
        if (stop_when_reached and reached_at is not None and not pending and t >= reached_at + settle):
            break
    return Trajectory(np.array(rows_t), np.array(rows_q), np.array(rows_tool), np.array(rows_elbow),
                      np.array(rows_s), np.array(rows_sd), np.array(rows_c), phases, np.array(steps),
                      reached_at, {"goal_check": check})


def peak_jerk(positions: np.ndarray, dt: float) -> float:
    """Largest norm of the third finite difference of a (k, 3) position series over dt^3 (m/s^3)."""
    if len(positions) < 4:
        return 0.0
    j = np.diff(positions, n=3, axis=0) / dt ** 3
    return float(np.max(np.linalg.norm(j, axis=1)))


def path_length(positions: np.ndarray) -> float:
    """Length (m) of the polyline through the (k, 3) positions."""
    if len(positions) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(positions, axis=0), axis=1)))


def evaluate(arm: ControlledArm, scene: Scene, q: np.ndarray, T_goal: np.ndarray, dt: float,
             step_s: np.ndarray | None = None, reached_at: float | None = None,
             capsules: ArmCapsules | None = None, pos_tol: float = 1e-3,
             ori_tol: float = 0.01) -> ReachMetrics:
    """Score a joint trajectory ``q`` (k, n) sampled every ``dt`` s against goal ``T_goal``.

    Collision and path are recomputed from ``q`` (forward kinematics + capsules), not trusted from the
    controller. ``reached_at`` (s) is the controller's report; without it the first sample within
    tolerance is used.
    """
    caps = capsules or ArmCapsules()
    tool = np.array([arm.fk(qi)[:3, 3] for qi in q])
    min_c = min(min_distance(arm, qi, scene, caps).distance for qi in q)
    Tf = arm.fk(q[-1])
    pos_err = float(np.linalg.norm(Tf[:3, 3] - T_goal[:3, 3]))
    Rerr = Tf[:3, :3].T @ T_goal[:3, :3]
    ori_err = float(math.acos(max(-1.0, min(1.0, (np.trace(Rerr) - 1.0) / 2.0))))
    reached = pos_err <= pos_tol and ori_err <= ori_tol
    if reached and reached_at is None:
        ok = np.linalg.norm(tool - T_goal[:3, 3], axis=1) <= pos_tol
        reached_at = float(np.argmax(ok) * dt)
    lower = np.asarray(arm.lower)
    upper = np.asarray(arm.upper)
    margin = float(np.min(np.minimum(q - lower, upper - q)))
    vel = np.max(np.abs(np.diff(q, axis=0)) / (np.asarray(arm.max_vel) * dt), initial=0.0)
    acc = np.max(np.abs(np.diff(q, n=2, axis=0)) / (np.asarray(arm.max_acc) * dt * dt), initial=0.0)
    plen = path_length(tool)
    straight = float(np.linalg.norm(tool[0] - T_goal[:3, 3]))
    steps = np.asarray(step_s if step_s is not None else [math.nan]) * 1e6
    return ReachMetrics(
        reached=reached,
        time_to_goal=float(reached_at) if reached and reached_at is not None else math.nan,
        pos_err=pos_err,
        ori_err=ori_err,
        min_clearance=float(min_c),
        limit_margin=margin,
        path_length=plen,
        straight=straight,
        path_ratio=plen / straight if straight > 1e-9 else math.nan,
        peak_jerk=peak_jerk(tool, dt),
        max_vel_ratio=float(vel),
        step_median_us=float(np.median(steps)),
        step_p99_us=float(np.percentile(steps, 99)),
        max_acc_ratio=float(acc),
    )
