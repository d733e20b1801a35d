"""Track benchmark: goal streams followed by the controller, in-process (and one run through the stack).

A goal stream is what a teleoperation device, a planner or a perception loop publishes on
``/goal_pose``: poses along a path, stamped at their sample time, at 10 / 50 / 100 Hz. Paths (PA10 on
a table, tool pointing down unless stated):

  circle-0.08/0.16/0.30   r = 0.1 m horizontal circle at (0.7, 0, 0.2), cruise speed in m/s, one turn
  figure-eight            0.24 x 0.12 m lemniscate at (0.68, 0, 0.22), 0.16 m/s
  line                    0.2 m back and forth along y (cosine, peak 0.16 m/s), two round trips
  min-jerk-vias           5 random via points (seeded), min-jerk segments, the tool turning 45 deg
  elbow-obstacle          circle-0.16 with a ball placed beside the elbow of the path
  ... stopped at t s      the stream stops at full speed (the only paths that do not end at rest)

Every path starts and ends at rest (cruise speed reached by a smooth 0.5 s ramp), so "overshoot at
the stop" is the controller's, not the path's; two paths stop their stream at full speed instead.
Stream variants: ``clean`` (exact stamps, arrival = stamp) and ``jitter`` (5 % of the messages
dropped, stamps off by up to +-5 ms, arrival 0-5 ms late, 2 % of the messages one period late, i.e.
out of order).

Methods (same arm limits, same start posture, same messages):

  servo   ReachController: a stream is told apart from new goals and tracked by the servo with
          the stream's velocity (estimated from the stamps) fed forward (phase TRACKING); the elbow
          at the pose's preferred swivel plus an offset that returns to 0 (servo.swivel_law pose:
          the same joints every lap; over the shoulder in the wrist's plane); where the predicted
          path asks a joint for more than its acceleration limit, the joints' motion planned ahead
          within the limits (servo.plan_horizon)
  servo-step  (lap-by-lap section) the same with servo.plan_horizon 0: each step's joint accelerations
          clipped as they come, no plan ahead within the limits
  servo-dyn  the same with servo.swivel_law dynamics: the elbow by eq. 31, the preferred swivel's
          motion fed forward
  point   the behaviour before goal streams: every message is a new point goal, reached by the
          attractor dynamics (it retargets smoothly)
  dls     a damped-least-squares differential-IK servo (MoveIt Servo's method): pose error times
          a gain plus the same stream-velocity estimate fed forward, through J^T (J J^T + l^2 I)^-1,
          the joint-velocity vector scaled down uniformly to the velocity and acceleration limits;
          no collision model (MoveIt Servo's collision check would stop the arm, not avoid)

Scores, from the commanded joints (FK, capsules): position error |tool(t) - path(t)| in mm while the
stream runs (median / p95 / max), orientation error (deg, median / p95), lag (the time shift of the
path that fits the tool best, ms), overshoot past the last goal along the final direction of motion
(mm, within 2 s after the stream stops), the error 2 s after the stop (mm), smallest clearance (m),
largest joint speed and acceleration over their limits.

    .venv/bin/python benchmarks/track_bench.py     # full in-process run, writes results/track_bench.md
    .venv/bin/python benchmarks/track_bench.py --quick --no-write
    scripts/ros_sandbox.sh .venv/bin/python benchmarks/track_bench.py --stack   # + one run through the stack
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.control.elbow import ArmGeometry, elbow_circle
from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams, StreamParams
from redarm_ros.control.stream import StreamEstimator
from redarm_ros.geometry.obstacles import ArmCapsules, Scene, Sphere, min_distance
from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.quaternion import (
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_to_matrix,
    rotvec_between,
)
from redarm_ros.motion.min_jerk import min_jerk

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_common, also when loaded by path
import bench_common  # noqa: E402

DT = 0.01
RESULTS = Path(__file__).resolve().parent / "results" / "track_bench.md"
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
Q_HINT = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])
SETTLE_S = 3.0  # the arm rests at the path start this long before the stream (the elbow settles)
AFTER_S = 2.0  # how long the run goes on after the last message


# ------------------------------------------------------------------------------------------------
# Paths
# ------------------------------------------------------------------------------------------------
@dataclass
class PathDef:
    """A timed path: ``pose(t)`` (4x4) for t in [0, duration] s, at rest at both ends."""

    name: str
    pose: Callable[[float], np.ndarray]
    duration: float
    scene: Scene = field(default_factory=lambda: Scene((), 0.0))
    q0: np.ndarray | None = None  # start posture (default: where the controller settles at the start)


def _curve_path(
    name: str,
    curve: Callable[[float], np.ndarray],
    v: float,
    rot: Callable[[float], np.ndarray] | None = None,
) -> PathDef:
    """A closed or open curve ``curve(u)``, u in [0, 1], traversed with ``bench_common.ramp_arc``."""
    u = np.linspace(0.0, 1.0, 4001)
    pts = np.array([curve(x) for x in u])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s_of, total = bench_common.ramp_arc(float(arc[-1]), v)

    def pose(t: float) -> np.ndarray:
        s = s_of(t)
        x = float(np.interp(s, arc, u))
        T = np.eye(4)
        T[:3, :3] = R_DOWN if rot is None else rot(t / total)
        T[:3, 3] = curve(x)
        return T

    return PathDef(name, pose, total)


def circle(v: float, center: tuple[float, float, float] = (0.7, 0.0, 0.2), r: float = 0.1) -> PathDef:
    c = np.asarray(center)
    return _curve_path(
        f"circle-{v:.2f}",
        lambda x: c + r * np.array([math.cos(2 * math.pi * x), math.sin(2 * math.pi * x), 0.0]),
        v,
    )


def abrupt(path: PathDef, at: float) -> PathDef:
    """``path`` whose stream stops at ``at`` s, at full speed (no slowing down)."""
    return PathDef(f"{path.name} stopped at {at:g} s", path.pose, at, path.scene)


def figure_eight(v: float = 0.16) -> PathDef:
    c = np.array([0.68, 0.0, 0.22])
    return _curve_path(
        "figure-eight",
        lambda x: c + np.array([0.06 * math.sin(4 * math.pi * x), 0.12 * math.sin(2 * math.pi * x), 0.0]),
        v,
    )


def line(v: float = 0.16, amp: float = 0.1, trips: int = 2) -> PathDef:
    c = np.array([0.65, 0.0, 0.2])
    w = v / amp
    total = trips * 2.0 * math.pi / w

    def pose(t: float) -> np.ndarray:
        t = min(max(t, 0.0), total)
        T = np.eye(4)
        T[:3, :3] = R_DOWN
        T[:3, 3] = c + np.array([0.0, -amp * math.cos(w * t), 0.0])
        return T

    return PathDef("line", pose, total)


def min_jerk_vias(seed: int = 3, n: int = 5, speed: float = 0.12, turn_deg: float = 45.0) -> PathDef:
    rng = np.random.default_rng(seed)
    c = np.array([0.65, 0.0, 0.25])
    vias = [c + np.array([0.0, -0.15, 0.0])]
    while len(vias) < n:
        p = c + rng.uniform([-0.12, -0.2, -0.1], [0.12, 0.2, 0.1])
        if np.linalg.norm(p - vias[-1]) > 0.08:
            vias.append(p)
    durs = [max(0.8, 1.875 * np.linalg.norm(b - a) / speed) for a, b in zip(vias[:-1], vias[1:], strict=True)]
    starts = np.concatenate([[0.0], np.cumsum(durs)])
    total = float(starts[-1])
    axis = np.array([math.cos(rng.uniform(0, 2 * math.pi)), math.sin(rng.uniform(0, 2 * math.pi)), 0.0])
    axis /= np.linalg.norm(axis)
    q0 = quat_from_matrix(R_DOWN)
    rv = axis * math.radians(turn_deg)

    def pose(t: float) -> np.ndarray:
        t = min(max(t, 0.0), total)
        k = min(int(np.searchsorted(starts, t, side="right")) - 1, len(durs) - 1)
        a = min_jerk((t - starts[k]) / durs[k])
        p = vias[k] + a * (vias[k + 1] - vias[k])
        f = min_jerk(t / total)
        qr = quat_mul(quat_from_rotvec(tuple(f * rv)), q0)
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(qr)
        T[:3, 3] = p
        return T

    return PathDef("min-jerk-vias", pose, total)


# ------------------------------------------------------------------------------------------------
# Streams
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Message:
    """A goal message: ``arrive`` (s, receive clock), ``stamp`` (s, header), ``t`` (s, sample time)."""

    arrive: float
    stamp: float
    t: float


def make_stream(duration: float, rate: float, variant: str, seed: int) -> list[Message]:
    """The messages of a stream of ``duration`` s at ``rate`` Hz (``clean`` or ``jitter``)."""
    rng = np.random.default_rng(seed)
    n = int(math.floor(duration * rate + 1e-9))
    times = [min(i / rate, duration) for i in range(n + 1)]
    if times[-1] < duration - 1e-9:
        times.append(duration)  # the last goal is the path's end
    out = []
    for i, ts in enumerate(times):
        if variant == "clean":
            out.append(Message(ts, ts, ts))
            continue
        last = i in (0, len(times) - 1)
        if not last and rng.random() < 0.05:
            continue
        stamp = ts + rng.uniform(-0.005, 0.005)
        arrive = ts + rng.uniform(0.0, 0.005) + (1.0 / rate if (not last and rng.random() < 0.02) else 0.0)
        out.append(Message(arrive, stamp, ts))
    out.sort(key=lambda m: m.arrive)
    return out


# ------------------------------------------------------------------------------------------------
# Methods
# ------------------------------------------------------------------------------------------------
class DLSServo:
    """Damped-least-squares differential IK with the stream's velocity fed forward; joint velocity
    vector scaled uniformly to the velocity and acceleration limits; position limits by braking."""

    def __init__(self, arm, gain: float = 20.0, damping: float = 0.05) -> None:
        self.arm = arm
        self.gain = gain
        self.damping = damping
        self.est = StreamEstimator(StreamParams())
        self.vmax = np.asarray(arm.max_vel, float)
        self.amax = np.asarray(arm.max_acc, float)
        self.lower = np.asarray(arm.lower, float)
        self.upper = np.asarray(arm.upper, float)
        self.q = np.zeros(arm.n)
        self.qd = np.zeros(arm.n)

    def reset(self, q: np.ndarray) -> None:
        self.q = q.copy()
        self.qd = np.zeros(self.arm.n)

    def message(self, T: np.ndarray, stamp: float, now: float) -> None:
        p = (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]))
        self.est.add(p, quat_from_matrix(T[:3, :3]), self.est.stamp_time(stamp, now), now)

    def step(self, now: float) -> np.ndarray:
        # The command is for ``now``: correct towards where the goal was a step ago and feed its
        # velocity forward, so the step lands on the goal of now (no lead, no lag).
        pred = self.est.predict(now - DT, now)
        if pred is None:
            return self.q.copy()
        Tq = self.arm.fk(self.q)
        e_p = np.asarray(pred.pos) - Tq[:3, 3]
        e_r = np.asarray(rotvec_between(quat_from_matrix(Tq[:3, :3]), pred.rot))
        v = np.concatenate([np.asarray(pred.vel) + self.gain * e_p, np.asarray(pred.w) + self.gain * e_r])
        J = self.arm.jacobian(self.q)
        qd = J.T @ np.linalg.solve(J @ J.T + self.damping**2 * np.eye(6), v)
        # Uniform scaling keeps the direction (MoveIt Servo scales the whole command).
        s = 1.0
        s = min(s, float(np.min(self.vmax / np.maximum(np.abs(qd), 1e-12))))
        dv = qd - self.qd
        over = np.abs(dv) / (self.amax * DT)
        if np.max(over) > 1.0:  # the acceleration limit: move the velocity towards qd as far as allowed
            qd = self.qd + dv / float(np.max(over))
        qd = qd * min(s, 1.0)
        # Position limits: brake in time.
        room_hi = np.sqrt(2.0 * self.amax * np.maximum(self.upper - self.q, 0.0))
        room_lo = -np.sqrt(2.0 * self.amax * np.maximum(self.q - self.lower, 0.0))
        qd = np.clip(qd, room_lo, room_hi)
        dq = np.clip(qd - self.qd, -self.amax * DT, self.amax * DT)
        qd = np.clip(self.qd + dq, -self.vmax, self.vmax)
        self.q = np.clip(self.q + qd * DT, self.lower, self.upper)
        self.qd = qd
        return self.q.copy()


@dataclass
class Run:
    """The commanded joints of one run and when the stream ran."""

    q: np.ndarray  # (k, 7), one row per step, the first at the stream's start
    t: np.ndarray  # (k,) s since the stream's first sample
    step_s: list[float]
    phases: set[str]
    messages: set[str]
    step_messages: list[str] = field(default_factory=list)  # the controller's message at each step


def settle_start(arm, path: PathDef, hint: np.ndarray = Q_HINT) -> np.ndarray:
    """The posture our controller settles in at the path start (used by every method)."""
    ctl = make_controller(arm, path.scene)
    q0, _ = arm.ik_nearest(path.pose(0.0), hint)
    ctl.reset(q0, now=0.0)
    ctl.set_goal(path.pose(0.0))
    for k in range(int(SETTLE_S / DT)):
        ctl.step(DT, (k + 1) * DT)
    q = ctl.q
    assert q is not None
    return q


def run_method(method: str, arm, path: PathDef, msgs: list[Message], q0: np.ndarray) -> Run:
    end = path.duration + AFTER_S
    n = int(round(end / DT))
    rows = [q0.copy()]
    times = [0.0]
    steps: list[float] = []
    phases: set[str] = set()
    notes: set[str] = set()
    step_msgs: list[str] = []
    deliver: Callable[[np.ndarray, float, float], None]
    step: Callable[[float], Any]
    record: Callable[[Any], None]
    if method == "dls":
        dls = DLSServo(arm)
        dls.reset(q0)
        deliver, step, record = dls.message, dls.step, rows.append
        phases.add("-")
    else:
        params = ControllerParams()
        if method == "point":  # every message a new point goal (no stream)
            params = params.with_(stream=StreamParams(gap=1e-6))
        elif method == "servo-dyn":  # the elbow by the swivel dynamics (eq. 31)
            params = ControllerParams.from_dict({"servo": {"swivel_law": "dynamics"}})
        elif method == "servo-step":  # no plan ahead: each step's accelerations clipped as they come
            params = ControllerParams.from_dict({"servo": {"plan_horizon": 0.0}})
        ctl = make_controller(arm, path.scene, params)
        ctl.reset(q0, now=0.0)

        def record(r: Any) -> None:
            rows.append(r.q)
            phases.add(r.phase.value)
            step_msgs.append(r.message)
            if r.message:
                notes.add(r.message.split(":")[0])

        deliver, step = ctl.goal_message, partial(ctl.step, DT)
    mi = 0
    for k in range(1, n + 1):
        t = k * DT
        while mi < len(msgs) and msgs[mi].arrive <= t + 1e-9:
            m = msgs[mi]
            deliver(path.pose(m.t), m.stamp, m.arrive)
            mi += 1
        t0 = time.perf_counter()
        r = step(t)
        steps.append(time.perf_counter() - t0)
        record(r)
        times.append(t)
    return Run(np.array(rows), np.array(times), steps, phases, notes, step_msgs)


# ------------------------------------------------------------------------------------------------
# Scores
# ------------------------------------------------------------------------------------------------
@dataclass
class Score:
    pos: np.ndarray  # mm, per step while the stream runs
    ori: np.ndarray  # deg
    lag_ms: float
    overshoot_mm: float
    final_mm: float
    min_clear: float
    vel_ratio: float
    acc_ratio: float
    step_us: np.ndarray


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(Ra.T @ Rb) - 1.0) / 2.0))))


def score(arm, path: PathDef, run: Run) -> Score:
    Ts = arm.fk_batch(run.q)
    tool = Ts[:, :3, 3]
    live = run.t <= path.duration + 1e-9
    ref = np.array([path.pose(t) for t in run.t])
    pos = np.linalg.norm(tool - ref[:, :3, 3], axis=1)[live] * 1e3
    ori = np.array([_angle(Ts[i, :3, :3], ref[i, :3, :3]) for i in range(len(run.t))])[live]
    # Lag: the shift of the path (ms) that fits the tool best during the stream.
    best = (math.inf, 0.0)
    for tau in np.arange(-0.05, 0.301, 0.002):
        shifted = np.array([path.pose(t - tau)[:3, 3] for t in run.t[live]])
        m = float(np.mean(np.linalg.norm(tool[live] - shifted, axis=1)))
        if m < best[0]:
            best = (m, tau)
    end = path.pose(path.duration)[:3, 3]
    before = path.pose(max(path.duration - 0.3, 0.0))[:3, 3]
    u = end - before
    after = tool[~live]
    if np.linalg.norm(u) > 1e-6 and len(after):
        over = max(0.0, float(np.max((after - end) @ (u / np.linalg.norm(u))))) * 1e3
    else:
        over = 0.0
    final = float(np.linalg.norm(tool[-1] - end)) * 1e3
    caps = ArmCapsules()
    clear = min(min_distance(arm, q, path.scene, caps).distance for q in run.q[::2])
    dq = np.diff(run.q, axis=0)
    vel = float(np.max(np.abs(dq) / (np.asarray(arm.max_vel) * DT)))
    acc = float(np.max(np.abs(np.diff(run.q, n=2, axis=0)) / (np.asarray(arm.max_acc) * DT * DT)))
    return Score(pos, ori, best[1] * 1e3, over, final, clear, vel, acc, np.asarray(run.step_s) * 1e6)


def elbow_obstacle_path(arm) -> PathDef:
    """circle-0.16 with a ball beside the elbow: 2 cm into the forearm capsule (next to the elbow) of
    both the servo's
    and the DLS servo's obstacle-free runs at the same moment (mid-path), on the outer side, and far
    from the hand's path, so that an arm that does not use its redundancy hits it."""
    base = circle(0.16)
    q0 = settle_start(arm, base)
    msgs = make_stream(base.duration, 50.0, "clean", 0)
    runs = [run_method(m, arm, base, msgs, q0) for m in ("servo", "dls")]
    r = 0.05
    reach = ArmCapsules().radii[2] + r - 0.02
    best = None
    for i in range(int(0.5 * base.duration / DT), int((base.duration - 0.3) / DT), 5):
        kps = [arm.key_points(run.q[i]) for run in runs]
        for frac in (0.05, 0.15):
            pts = [kp[2] + frac * (kp[3] - kp[2]) for kp in kps]
            mid = 0.5 * (pts[0] + pts[1])
            side = np.cross(kps[0][3] - kps[0][2], [0.0, 0.0, 1.0])
            for sgn in (1.0, -1.0):
                c = mid + sgn * side / np.linalg.norm(side) * reach
                depth = [reach - float(np.linalg.norm(c - p)) for p in pts]
                far = min(np.linalg.norm(c - base.pose(t)[:3, 3]) for t in np.linspace(0, base.duration, 100))
                if far < 0.15 or min(depth) < -0.005:
                    continue
                ball = Scene((Sphere(tuple(c), r, "ball"),), 0.0)
                start = min(
                    min_distance(arm, q, ball).distance for q in runs[0].q[: int(0.4 * base.duration / DT)]
                )
                if start < 0.04:  # the stream starts clear of it
                    continue
                key = min(depth)
                if best is None or key > best[0]:
                    best = (key, c)
    assert best is not None, "no place for the ball beside both elbows"
    return PathDef(
        "elbow-obstacle", base.pose, base.duration, Scene((Sphere(tuple(best[1]), r, "ball"),), 0.0), q0
    )


# ------------------------------------------------------------------------------------------------
# Closed paths followed lap after lap: over the shoulder, and the 6-DOF arm
# ------------------------------------------------------------------------------------------------
LAPS = 3
LAP_R = 0.1  # m, circle radius
STALL_SHARE = 0.1  # the hand "stands" below this share of the cruise speed ...
MOVING_SHARE = 0.5  # ... while the target moves above this share of it
LAP_PHASES = 200  # path points per lap at which consecutive laps' joints are compared
R_UP6 = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # powercube6: approach axis up
Q_HINT6 = np.array([0.0, 0.3, 0.0, 1.0, 0.27, 0.0])
LAP_METHODS = ("servo", "servo-step", "servo-dyn", "dls")
LAP_TARGETS = ("p95 <= 5 mm on every lap at 0.157 m/s (50 Hz); no stall, and p95 <= 10 mm on every lap "
               "after the first, at 0.314 m/s (100 Hz); joints at the same path point within 0.02 rad of the "
               "previous lap's after the first lap")


@dataclass
class LapPath:
    """A horizontal circle followed ``laps`` times: the path, the lap coordinate of a path time (lap
    index + share of the lap) and the cruise speed (m/s)."""

    path: PathDef
    lap_of: Callable[[float], float]
    cruise: float
    laps: int


def lap_circle(name: str, center: Any, v: float, R: np.ndarray, laps: int = LAPS,
               r: float = LAP_R, scene: Scene | None = None) -> LapPath:
    """A circle of radius ``r`` about ``center`` (horizontal), tool orientation ``R`` fixed, ``laps``
    turns at ``v`` m/s with the smooth 0.5 s ramps of every path; ``scene`` default: the table at 0."""
    c = np.asarray(center, float)
    lap_len = 2.0 * math.pi * r
    s_of, total = bench_common.ramp_arc(laps * lap_len, v)

    def pose(t: float) -> np.ndarray:
        a = s_of(t) / r
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c + r * np.array([math.cos(a), math.sin(a), 0.0])
        return T

    path = PathDef(name, pose, total) if scene is None else PathDef(name, pose, total, scene)
    return LapPath(path, lambda t: s_of(t) / lap_len, v, laps)


def shoulder_center(arm, R: np.ndarray = R_DOWN, r: float = LAP_R) -> tuple[np.ndarray, float]:
    """The centre of a horizontal circle (tool orientation ``R``) on which the elbow, at the swivel of
    the circle's start posture held all the way, passes nearest the vertical above the shoulder (|q2|
    smallest), while the start itself is clear of it (|q2| >= 0.25 rad) and the wrist stays clear of
    its singularity (|q6| >= 0.3 rad) and every point is solvable at that swivel; and that least |q2|."""
    def at(c: np.ndarray, k: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = R
        a = 2.0 * math.pi * k / 72
        T[:3, 3] = c + r * np.array([math.cos(a), math.sin(a), 0.0])
        return T

    best: tuple[float, np.ndarray] | None = None
    for x in np.arange(0.15, 0.601, 0.05):
        for z in np.arange(0.15, 0.701, 0.05):
            c = np.array([x, 0.0, z])
            q, _ = arm.ik_nearest(at(c, 0), Q_HINT)
            if q is None or abs(float(q[1])) < 0.25:
                continue
            s = arm.swivel(q)
            worst = math.inf
            for k in range(72):
                sols = arm.ik(at(c, k), s)
                if len(sols) == 0:
                    worst = -1.0
                    break
                q = sols[int(np.argmin(np.max(np.abs(sols - q), axis=1)))]
                if abs(float(q[5])) < 0.3:
                    worst = -1.0
                    break
                worst = min(worst, abs(float(q[1])))
            if worst >= 0.0 and (best is None or worst < best[0]):
                best = (worst, c)
    assert best is not None, "no circle over the shoulder"
    return best[1], best[0]


@dataclass
class LapScore:
    p95: list[float]  # mm per lap
    peak: list[float]  # mm per lap
    stall: list[float]  # s per lap
    min_q2: list[float]  # rad per lap (7-DOF: |q2|; 6-DOF: |q5|, the wrist)
    joint_diff: list[float]  # rad, lap k against lap k - 1 (nan for the first)
    stalls: list[str]  # where and why the hand stood


def lap_scores(arm, lp: LapPath, run: Run) -> LapScore:
    path = lp.path
    live = run.t <= path.duration + 1e-9
    t = run.t[live]
    Q = run.q[live]
    tool = arm.fk_batch(Q)[:, :3, 3]
    ref = np.array([path.pose(x)[:3, 3] for x in t])
    err = np.linalg.norm(tool - ref, axis=1) * 1e3
    lapc = np.array([lp.lap_of(x) for x in t])
    lap = np.minimum(np.floor(lapc).astype(int), lp.laps - 1)
    v_hand = np.r_[0.0, np.linalg.norm(np.diff(tool, axis=0), axis=1) / DT]
    v_ref = np.r_[0.0, np.linalg.norm(np.diff(ref, axis=0), axis=1) / DT]
    stalled = (v_hand < STALL_SHARE * lp.cruise) & (v_ref > MOVING_SHARE * lp.cruise)
    sing = 1 if arm.n == 7 else 4  # q2 (shoulder) for 7-DOF, q5 (wrist) for the 6-DOF arm
    out = LapScore([], [], [], [], [], [])
    for k in range(lp.laps):
        m = lap == k
        out.p95.append(float(np.percentile(err[m], 95)))
        out.peak.append(float(np.max(err[m])))
        out.stall.append(float(np.sum(stalled[m])) * DT)
        out.min_q2.append(float(np.min(np.abs(Q[m, sing]))))
        if k == 0:
            out.joint_diff.append(math.nan)
            continue
        ph = np.arange(LAP_PHASES) / LAP_PHASES
        a = np.stack([np.interp(k - 1 + ph, lapc, Q[:, j]) for j in range(arm.n)], 1)
        b = np.stack([np.interp(k + ph, lapc, Q[:, j]) for j in range(arm.n)], 1)
        out.joint_diff.append(float(np.max(np.abs(b - a))))
    # Each stall (a run of stalled steps of 0.05 s or more): where on the path, the joints, and the
    # controller's message at its start.
    i = 0
    msgs = run.step_messages
    while i < len(stalled):
        if not stalled[i]:
            i += 1
            continue
        j = i
        while j < len(stalled) and stalled[j]:
            j += 1
        if (j - i) * DT >= 0.05:
            q = Q[i]
            lo, up = np.asarray(arm.lower), np.asarray(arm.upper)
            margin = np.minimum(q - lo, up - q)
            near = int(np.argmin(margin))
            why = msgs[i - 1] if 0 < i <= len(msgs) and msgs[i - 1] else "(no message)"
            out.stalls.append(
                f"lap {lap[i] + 1}, {360.0 * (lapc[i] % 1.0):.0f} deg round, {(j - i) * DT:.2f} s, error up "
                f"to {np.max(err[i:j]):.0f} mm; q = {np.array2string(q, precision=2, separator=', ')}, "
                + (f"|q2| {abs(q[1]):.3f}, |q4| {abs(q[3]):.3f}, |q6| {abs(q[5]):.3f}, " if arm.n == 7 else
                   f"|q2| {abs(q[1]):.3f}, |q4| {abs(q[3]):.3f}, |q5| {abs(q[4]):.3f}, ")
                + f"joint {near + 1} "
                f"{margin[near]:.3f} rad from its limit; controller: {why[:140]}"
            )
        i = j
    return out


BOUND_SAMPLES = 200  # points of the cruise lap in the least-error bound
#: unit directions along which the bound measures the position error (axes, face and body diagonals):
#: the largest of these projections is at most the error itself, so the bound stays a lower bound
BOUND_DIRS = np.array([d / np.linalg.norm(d) for d in np.array(
    [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1),
     (1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1)], float)])


def cruise_lap_joints(arm, lp: LapPath, hint: np.ndarray, n: int = BOUND_SAMPLES
                      ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The exact joint motion over one lap at cruise speed: (n, dof) joints at equal steps of the lap,
    the 2 pi shift of each joint from the lap's end to its start, and the time step (s). 7-DOF: the IK
    at the preferred swivel of the controller's defaults (the highest elbow), each sample on the
    solution nearest the one before (the shoulder flip where joint 2 passes 0); 6-DOF: the IK solution
    nearest the one before. None where the IK has no solution or the motion does not close."""
    t1 = 0.0
    hi_t = lp.path.duration
    for _ in range(60):  # the start of lap 2 (all of it at cruise speed)
        mid = 0.5 * (t1 + hi_t)
        t1, hi_t = (mid, hi_t) if lp.lap_of(mid) < 1.0 else (t1, mid)
    period = 2.0 * math.pi * LAP_R / lp.cruise
    geom = ArmGeometry.from_arm(arm) if arm.n == 7 else None
    q, _ = arm.ik_nearest(lp.path.pose(t1), hint)
    if q is None:
        return None
    rows = []
    for k in range(n + 1):
        T = lp.path.pose(t1 + period * k / n)
        if geom is not None:
            c = elbow_circle(geom, T)
            sols = arm.ik(T, math.atan2(-c.b[2], -c.a[2]) + math.pi, limits=False)  # the highest elbow
        else:
            sols = arm.ik(T)
        if len(sols) == 0:
            return None
        sols = sols + 2.0 * math.pi * np.round((q - sols) / (2.0 * math.pi))
        q = sols[int(np.argmin(np.max(np.abs(sols - q), axis=1)))]
        rows.append(q)
    Q = np.array(rows)
    shift = Q[n] - Q[0]
    if np.max(np.abs(shift - 2.0 * math.pi * np.round(shift / (2.0 * math.pi)))) > 1e-6:
        return None
    return Q[:n], shift, period / n


def least_lap_error(arm, Q: np.ndarray, shift: np.ndarray, h: float) -> tuple[float, float] | None:
    """The least position error (m) with which the joints can follow the lap ``Q`` (n, dof; step ``h``
    s; ``shift`` from the lap's end to its start) within their velocity, acceleration and position
    limits, the tool orientation held: a linear program over periodic joint deviations ``dq`` of the
    motion linearised about it (tool error ``J dq``), minimising the largest projection of the
    position error on :data:`BOUND_DIRS`. Returns (that least value: a lower bound of the error of the
    linearised problem; the largest true error of its solution: an upper bound of the least error, up
    to the linearisation), or None if the program has no solution."""
    import scipy.sparse as sparse
    from scipy.optimize import linprog

    n, dof = Q.shape
    lifted = np.vstack([Q[-1] - shift, Q, Q[0] + shift])
    vel = (lifted[2:] - lifted[:-2]) / (2.0 * h)
    acc = (lifted[2:] - 2.0 * lifted[1:-1] + lifted[:-2]) / (h * h)
    eye = sparse.identity(n, format="csr")
    fwd = sparse.csr_matrix((np.ones(n), (np.arange(n), (np.arange(n) + 1) % n)), shape=(n, n))
    d1 = (fwd - fwd.T) / (2.0 * h)
    d2 = (fwd - 2.0 * eye + fwd.T) / (h * h)
    nv = n * dof + 1  # dq[i, j] at i * dof + j, then the error bound
    blocks, rhs = [], []
    for j in range(dof):
        pick = sparse.csr_matrix((np.ones(n), (np.arange(n), np.arange(n) * dof + j)), shape=(n, nv))
        for D, base, lim in ((d1, vel[:, j], arm.max_vel[j]), (d2, acc[:, j], arm.max_acc[j])):
            blocks += [D @ pick, -(D @ pick)]
            rhs += [lim - base, lim + base]
    J = np.array([arm.jacobian(q) for q in Q])
    rows, cols, vals = [], [], []
    r = 0
    for i in range(n):
        for g in BOUND_DIRS @ J[i, :3]:
            for sign in (1.0, -1.0):
                rows += [r] * (dof + 1)
                cols += [*range(i * dof, (i + 1) * dof), nv - 1]
                vals += [*(sign * g), -1.0]
                r += 1
    blocks.append(sparse.csr_matrix((vals, (rows, cols)), shape=(r, nv)))
    rhs.append(np.zeros(r))
    eq = sparse.block_diag([J[i, 3:] for i in range(n)], format="csr")
    eq = sparse.hstack([eq, sparse.csr_matrix((3 * n, 1))], format="csr")
    lower, upper = np.asarray(arm.lower, float), np.asarray(arm.upper, float)
    bounds = [(lower[i % dof] - Q[i // dof, i % dof], upper[i % dof] - Q[i // dof, i % dof])
              for i in range(n * dof)] + [(0.0, None)]
    cost = np.zeros(nv)
    cost[-1] = 1.0
    A_ub, b_ub = sparse.vstack(blocks, format="csr"), np.concatenate(rhs)
    res = linprog(cost, A_ub=A_ub, b_ub=b_ub, A_eq=eq, b_eq=np.zeros(3 * n), bounds=bounds, method="highs")
    if res.status != 0:
        return None
    least = float(res.x[-1])
    # Among the deviations with that least error, the smallest (sum of |dq|, through dq <= t, -dq <= t):
    # the joints' self-motion is free in the program, and a large one makes the linearisation wrong.
    m = n * dof
    A2 = sparse.vstack([
        sparse.hstack([A_ub, sparse.csr_matrix((A_ub.shape[0], m))]),
        sparse.hstack([sparse.identity(m), sparse.csr_matrix((m, 1)), -sparse.identity(m)]),
        sparse.hstack([-sparse.identity(m), sparse.csr_matrix((m, 1)), -sparse.identity(m)]),
    ], format="csr")
    b2 = np.concatenate([b_ub, np.zeros(2 * m)])
    eq2 = sparse.hstack([eq, sparse.csr_matrix((3 * n, m))], format="csr")
    cost2 = np.concatenate([np.zeros(nv), np.ones(m)])
    bounds2 = [*bounds[:-1], (0.0, least * (1.0 + 1e-6) + 1e-9)] + [(0.0, None)] * m
    res2 = linprog(cost2, A_ub=A2, b_ub=b2, A_eq=eq2, b_eq=np.zeros(3 * n), bounds=bounds2, method="highs")
    x = res2.x if res2.status == 0 else res.x
    dq = x[:m].reshape(n, dof)
    tool = arm.fk_batch(Q)[:, :3, 3]
    moved = arm.fk_batch(Q + dq)[:, :3, 3]
    return least, float(np.max(np.linalg.norm(moved - tool, axis=1)))


def lap_cases(quick: bool, notes: list[str], arms: tuple[str, ...] = ("pa10", "powercube6")
              ) -> list[tuple[str, LapPath, list[float], np.ndarray]]:
    """(arm, lap path, rates Hz, start hint) of the lap-by-lap section for ``arms``; where the circles are
    goes to ``notes``."""
    pa10 = load_arm("pa10")
    c, q2 = shoulder_center(pa10)
    notes.append(f"PA10 circle centre ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}) m, tool pointing down; |q2| down "
                 f"to {q2:.4f} rad at the start's swivel held.")
    cases = [("pa10", lap_circle("shoulder-circle-0.157", c, 0.157, R_DOWN), [50.0], Q_HINT)]
    if not quick:
        cases.append(("pa10", lap_circle("shoulder-circle-0.314", c, 0.314, R_DOWN), [100.0], Q_HINT))
    cases = [case for case in cases if case[0] in arms]
    if not quick and "powercube6" in arms:
        pc6 = load_arm("powercube6")
        c6, q5 = wrist_center6(pc6)
        notes.append(f"powercube6 circles: centre (0.50, 0.00, 0.45) m, and ({c6[0]:.2f}, {c6[1]:.2f}, "
                     f"{c6[2]:.2f}) m where |q5| comes down to {q5:.4f} rad.")
        for v, rate in ((0.157, 50.0), (0.314, 100.0)):
            # (on a pedestal: no table, its shoulder turns the upper arm below the base plane)
            cases.append(("powercube6", lap_circle(f"pc6-circle-{v:.3f}", (0.5, 0.0, 0.45), v, R_UP6,
                                                   scene=Scene()), [rate], Q_HINT6))
            cases.append(("powercube6", lap_circle(f"pc6-wrist-circle-{v:.3f}", c6, v, R_UP6, scene=Scene()),
                          [rate], Q_HINT6))
    return cases


def wrist_center6(arm, r: float = LAP_R) -> tuple[np.ndarray, float]:
    """powercube6: the centre of a horizontal circle (approach axis vertical) on which |q5| (the
    wrist pitch) comes nearest 0, every point solvable; and that least |q5|."""
    best: tuple[float, np.ndarray] | None = None
    for x in np.arange(0.2, 0.651, 0.05):
        for z in np.arange(0.2, 0.751, 0.05):
            c = np.array([x, 0.0, z])
            q = Q_HINT6
            worst = math.inf
            for k in range(72):
                T = np.eye(4)
                T[:3, :3] = R_UP6
                a = 2.0 * math.pi * k / 72
                T[:3, 3] = c + r * np.array([math.cos(a), math.sin(a), 0.0])
                qn, _ = arm.ik_nearest(T, q)
                if qn is None:
                    worst = -1.0
                    break
                q = qn
                worst = min(worst, abs(float(q[4])))
            if worst >= 0.0 and (best is None or worst < best[0]):
                best = (worst, c)
    assert best is not None, "no powercube6 circle"
    return best[1], best[0]


def lap_section(args: argparse.Namespace) -> list[str]:
    """Circles followed lap after lap: over the PA10's shoulder (slow and fast) and the powercube6's."""
    lines = [
        "",
        f"A horizontal circle (r {LAP_R} m, tool orientation fixed) streamed as `/goal_pose` feeds it "
        f"(clean stream), {LAPS} laps with the smooth start and stop ramps. PA10: the circle is placed where "
        "the elbow, at the swivel the controller settles in at the start, passes nearest the vertical above "
        "the shoulder (q2 near 0). powercube6 (no swivel, no table; the approach axis vertical): a circle in "
        "front and one placed, by a search, where |q5| comes nearest 0 on the circle. Per lap: p95 and "
        f"largest position error, stall time (hand below {STALL_SHARE:.0%} of the cruise speed while the "
        f"target moves above {MOVING_SHARE:.0%} of it), the least |q2| (powercube6: |q5|), and the largest "
        f"joint difference to the previous lap at the same path point ({LAP_PHASES} points per lap). "
        "*Least error*: how closely any motion within the joints' velocity, acceleration and position "
        "limits, the tool orientation held, can follow a lap at cruise speed (collisions and the guard "
        f"left out): a linear program over periodic deviations ({BOUND_SAMPLES} points per lap) from the "
        "exact motion (PA10: at the highest elbow), linearised about it; its optimum is a lower bound "
        "(the first figure), the true largest error of its solution an upper one (the second).",
        "",
        "| arm | path | Hz | method | lap | p95 mm | max mm | stall s | least abs(q2) (pc6: q5) rad | "
        "joint difference to the previous lap rad | least error mm |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    stall_notes: list[str] = []
    where: list[str] = []
    step_s: dict[str, list[float]] = {}
    for arm_name, lp, rates, hint in lap_cases(args.quick, where, tuple(args.lap_arms.split(","))):
        arm = load_arm(arm_name)
        q0 = settle_start(arm, lp.path, hint)
        exact = cruise_lap_joints(arm, lp, hint)
        least = None if exact is None else least_lap_error(arm, *exact)
        least_txt = "-" if least is None else f"{1e3 * least[0]:.1f} - {1e3 * least[1]:.1f}"
        for rate in rates:
            msgs = make_stream(lp.path.duration, rate, "clean", seed=int(rate))
            for method in LAP_METHODS:
                if arm.n != 7 and method in ("servo-dyn", "servo-step"):
                    continue  # (no swivel, no plan ahead: the same as servo)
                run = run_method(method, arm, lp.path, msgs, q0)
                if method.startswith("servo"):
                    step_s.setdefault(method, []).extend(run.step_s)
                sc = lap_scores(arm, lp, run)
                for k in range(lp.laps):
                    jd = "-" if k == 0 else f"{sc.joint_diff[k]:.3f}"
                    lines.append(
                        f"| {arm_name} | {lp.path.name} | {rate:g} | {method} | {k + 1} | {sc.p95[k]:.1f} | "
                        f"{sc.peak[k]:.1f} | {sc.stall[k]:.2f} | {sc.min_q2[k]:.3f} | {jd} | {least_txt} |"
                    )
                if method.startswith("servo") and sc.stalls:
                    stall_notes.append(f"- {arm_name} {lp.path.name} {rate:g} Hz {method}, "
                                       f"{len(sc.stalls)} stall(s): " + " / ".join(sc.stalls[:3]))
                if args.verbose:
                    print(*lines[-lp.laps:], sep="\n", flush=True)
    lines += ["", " ".join(where), "", f"Targets (PA10 over the shoulder): {LAP_TARGETS}.", "",
              "Controller step time (wall clock, these runs): " + ", ".join(
                  f"{m} median {1e6 * np.median(v):.0f} us / p99 {1e6 * np.percentile(v, 99):.0f} us"
                  for m, v in step_s.items()) + ".", ""]
    if stall_notes:
        lines += ["Where the controller's hand stood while the target moved (first three per run):", "",
                  *stall_notes, ""]
    return lines


# ------------------------------------------------------------------------------------------------
# Report
# ------------------------------------------------------------------------------------------------
def _row(name: str, rate: float, variant: str, method: str, s: Score) -> str:
    return (
        f"| {name} | {rate:g} | {variant} | {method} | {np.median(s.pos):.2f} | "
        f"{np.percentile(s.pos, 95):.2f} | "
        f"{np.max(s.pos):.2f} | {np.median(s.ori):.2f} / {np.percentile(s.ori, 95):.2f} | {s.lag_ms:.0f} | "
        f"{s.overshoot_mm:.2f} | {s.final_mm:.2f} | {s.min_clear:.3f} | "
        f"{s.vel_ratio:.2f} / {s.acc_ratio:.2f} |"
    )


HEADER = (
    "| path | Hz | stream | method | pos err median mm | p95 mm | max mm | ori err median / p95 deg | "
    "lag ms | overshoot at stop mm | error 2 s after stop mm | min clearance m | max joint vel / acc "
    "ratio |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


PLOT_PATH, PLOT_RATE = "circle-0.16", 50.0  # the runs whose error over time is plotted


def in_process(
    args: argparse.Namespace, traces: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] | None = None
) -> tuple[list[str], dict[str, list[float]]]:
    """The in-process table rows and step times; ``traces`` gets (t s, position error mm) of the
    PLOT_PATH runs at PLOT_RATE, keyed by (stream variant, method)."""
    arm = load_arm("pa10")
    if args.quick:
        cases = [(circle(0.16), [50.0], ["clean", "jitter"]), (circle(0.30), [50.0], ["clean"])]
        methods = ["servo", "servo-dyn", "point", "dls"]
    else:
        cases = [
            (circle(0.08), [10.0, 50.0, 100.0], ["clean", "jitter"]),
            (circle(0.16), [10.0, 50.0, 100.0], ["clean", "jitter"]),
            (circle(0.30), [10.0, 50.0, 100.0], ["clean", "jitter"]),
            (figure_eight(), [50.0], ["clean", "jitter"]),
            (line(), [50.0], ["clean", "jitter"]),
            (min_jerk_vias(), [10.0, 50.0, 100.0], ["clean", "jitter"]),
            (abrupt(circle(0.16), 2.0), [50.0, 100.0], ["clean"]),
            (abrupt(circle(0.30), 1.5), [50.0, 100.0], ["clean"]),
        ]
        methods = ["servo", "servo-dyn", "point", "dls"]
    cases.append((elbow_obstacle_path(arm), [50.0], ["clean"]))
    lines = [HEADER]
    steps: dict[str, list[float]] = {m: [] for m in methods}
    for path, rates, variants in cases:
        q0 = settle_start(arm, path) if path.q0 is None else path.q0
        for rate in rates:
            for variant in variants:
                msgs = make_stream(path.duration, rate, variant, seed=int(rate) * 7 + len(variant))
                for method in methods:
                    r = run_method(method, arm, path, msgs, q0)
                    s = score(arm, path, r)
                    steps[method] += list(s.step_us)
                    if traces is not None and path.name == PLOT_PATH and rate == PLOT_RATE:
                        traces[(variant, method)] = (r.t[r.t <= path.duration + 1e-9], s.pos)
                    lines.append(_row(path.name, rate, variant, method, s))
                    if args.verbose:
                        print(lines[-1], sorted(r.phases), sorted(r.messages), flush=True)
    return lines, steps


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run: circle 0.16 and 0.30 m/s at 50 Hz")
    ap.add_argument("--no-write", action="store_true", help="do not write benchmarks/results/track_bench.md")
    ap.add_argument(
        "--stack", action="store_true", help="also one run through the whole stack (ROS, CAN, sim)"
    )
    ap.add_argument("--stack-only", action="store_true", help="only the run through the stack")
    ap.add_argument("--chain", action="store_true",
                    help="only the command-chain model (controller -> driver -> modules on one clock)")
    ap.add_argument(
        "--stack-compare",
        action="store_true",
        help="stack runs with the commands of before (unstamped, no lead) and the defaults, alternating",
    )
    ap.add_argument("--stack-repeats", type=int, default=1, help="stack runs per command timing (default 1)")
    ap.add_argument("--laps-only", action="store_true",
                    help="only the closed paths followed lap after lap (over the shoulder, powercube6)")
    ap.add_argument("--lap-arms", default="pa10,powercube6",
                    help="arms of the lap-by-lap section (default pa10,powercube6)")
    ap.add_argument("--verbose", action="store_true")
    bench_common.add_plot_dir(ap)
    args = ap.parse_args(argv)
    header = bench_common.doc_header("# Track benchmark (`benchmarks/track_bench.py`)", __doc__)
    sections: dict[str, list[str]] = {}
    if args.chain:
        load0, t0 = os.getloadavg(), time.time()
        title, body = chain_section()
        sections[title] = [*body, bench_common.load_line(load0, t0), ""]
    if not args.stack_only and not args.chain:
        load0, t0 = os.getloadavg(), time.time()
        title = "## In-process, lap by lap: circles over the shoulder and on the 6-DOF arm"
        if args.quick:
            title += " -- quick"
        sections[title] = [*lap_section(args), bench_common.load_line(load0, t0), ""]
    if not args.stack_only and not args.chain and not args.laps_only:
        load0, t0 = os.getloadavg(), time.time()
        traces: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}
        lines, steps = in_process(args, traces)
        title = "## In-process (the controller core at 100 Hz, commanded joints scored)"
        if args.quick:
            title += " -- quick"
        body = ["", *lines, ""]
        body.append(
            "Controller step time (wall clock, all runs): "
            + ", ".join(
                f"{m} median {np.median(v):.0f} us / p99 {np.percentile(v, 99):.0f} us"
                for m, v in steps.items()
                if v
            )
        )
        body += ["", bench_common.load_line(load0, t0), ""]
        plot_dir = args.plot_dir or (None if args.no_write else RESULTS.parent)
        if plot_dir is not None and traces:
            pngs = write_plots(traces, plot_dir, "track_bench.py" + (" --quick" if args.quick else ""), load0)
            body += [*bench_common.plots().markdown_links(pngs, RESULTS.parent), ""]
        sections[title] = body
    if args.stack or args.stack_only:
        load0, t0 = os.getloadavg(), time.time()
        title, body = stack_run(args)
        sections[title] = [*body, bench_common.load_line(load0, t0), ""]
    bench_common.finish_sections(RESULTS, header, sections, NOT_COVERED, args.no_write)
    return 0


def write_plots(
    traces: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]], out_dir: Path, run: str,
    load0: tuple[float, ...],
) -> list[Path]:
    """track_bench_error_<variant>.png: position error over time of PLOT_PATH at PLOT_RATE, one line
    per method, one plot per stream variant (clean, jitter)."""
    plots = bench_common.plots()
    out = []
    for variant in dict.fromkeys(v for v, _ in traces):
        series = {m: tr for (v, m), tr in traces.items() if v == variant}
        out.append(plots.tracking_error(
            out_dir / f"track_bench_error_{variant}.png", series,
            title=f"Track benchmark: tool position error, {PLOT_PATH} (m/s), {PLOT_RATE:g} Hz {variant} "
            "stream",
            caption=plots.run_caption(f"{run}: one turn per method, commanded joints scored", load0)))
    return out


# ------------------------------------------------------------------------------------------------
# Through the stack (ROS 2 nodes, CAN bus, simulator as separate processes)
# ------------------------------------------------------------------------------------------------
class StackClient:
    """An ordinary ROS client of the stack started by :class:`redarm_ros.bringup.Stack`: goals out,
    joint states and controller state in (rclpy imported only here). Also used by sequence_bench."""

    def __init__(self, stack_cfg: dict | None = None) -> None:
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from redarm_interfaces.msg import ControllerState
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Trigger

        from redarm_ros.bringup import Stack, StackConfig

        self.arm = load_arm("pa10")
        kw = {
            "arm": "pa10",
            "log_level": "warn",
            "ready_timeout_s": 90.0,
            "extra_args": {"sim": ["--status-rate", "100"]},
        }
        kw.update(stack_cfg or {})
        cfg = StackConfig(**kw)
        self._lines: list[str] = []
        self.stack = Stack(cfg, sink=self._lines.append)
        self.stack.start()
        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=self.stack.domain_id)
        self.node = rclpy.create_node("bench_client", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.PoseStamped = PoseStamped
        self.CS = ControllerState
        self.Trigger = Trigger
        self.goal_pub = self.node.create_publisher(PoseStamped, "goal_pose", 50)
        self.recover_cli = self.node.create_client(Trigger, "/can_driver/recover")
        self.states: list = []
        self.joints: list[tuple[float, np.ndarray]] = []  # (header stamp s, positions)
        self.node.create_subscription(ControllerState, "/controller/state", self.states.append, 200)
        self.node.create_subscription(JointState, "joint_states", self._on_js, 500)
        from trajectory_msgs.msg import JointTrajectory

        self.commands: list[tuple[float, np.ndarray]] = []  # (ROS time of receipt, commanded joints)
        self.node.create_subscription(JointTrajectory, "joint_command", self._on_cmd, 500)
        self._names = list(self.arm.joint_names)
        self._seen_halts = 0

    def _on_js(self, msg) -> None:
        pos = dict(zip(msg.name, msg.position, strict=False))
        if all(n in pos for n in self._names):
            t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            self.joints.append((t, np.array([pos[n] for n in self._names])))

    def _on_cmd(self, msg) -> None:
        if not msg.points:
            return
        pos = dict(zip(msg.joint_names, msg.points[-1].positions, strict=False))
        if all(n in pos for n in self._names):
            self.commands.append((self.now(), np.array([pos[n] for n in self._names])))

    def now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        from redarm_ros.nodes._common import spin_until  # needs rclpy, as this client does

        return spin_until(self.ex, cond, timeout, 0.002)

    def halts(self) -> int:
        return sum("HALTED:" in line for line in self._lines)

    def halt_lines(self) -> list[str]:
        """The driver's log lines that say it halted, and why."""
        return [line for line in self._lines if "HALTED:" in line]

    def ensure_running(self) -> None:
        """Recover the driver if it halted since the last look (a starved machine at bring-up)."""
        if self.halts() > self._seen_halts:
            for _ in range(3):
                if self.recover():
                    break
                self.spin_until(lambda: False, 1.0)
            self.spin_until(lambda: False, 1.0)  # the controller restarts from the still arm
        self._seen_halts = self.halts()

    def recover(self) -> bool:
        if not self.spin_until(self.recover_cli.service_is_ready, 5.0):
            return False
        from redarm_ros.nodes._common import call_resending

        resp = call_resending(self.recover_cli, self.Trigger.Request(), self.spin_until, 20.0)
        return resp is not None and bool(resp.success)

    def send(self, T: np.ndarray, stamp: float | None = None) -> None:
        msg = self.PoseStamped()
        msg.header.frame_id = "base_link"
        st = self.now() if stamp is None else stamp
        msg.header.stamp.sec = int(st)
        msg.header.stamp.nanosec = int((st - int(st)) * 1e9)
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in T[:3, 3])
        w, x, y, z = quat_from_matrix(T[:3, :3])
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = x, y, z, w
        # Until the controller's subscription has matched ours (discovery is slow on a busy machine),
        # a goal would go nowhere.
        if self.goal_pub.get_subscription_count() == 0:
            self.spin_until(lambda: self.goal_pub.get_subscription_count() > 0, 10.0)
        self.goal_pub.publish(msg)

    def reach(self, T: np.ndarray, timeout: float) -> tuple[bool, float]:
        """Send a point goal and wait for REACHED of it; returns (reached, seconds). If the driver
        halted the arm meanwhile (a starved machine), recover and send the goal again (twice at most;
        the halts are counted in :meth:`halts`)."""
        t0 = time.monotonic()
        ok = False
        for _ in range(3):
            self.ensure_running()
            n = len(self.states)
            h0 = self.halts()
            self.send(T)

            def done(n: int = n) -> bool:
                return any(
                    s.phase == self.CS.REACHED
                    and abs(s.goal.position.x - T[0, 3]) < 1e-6
                    and abs(s.goal.position.y - T[1, 3]) < 1e-6
                    for s in self.states[n:]
                )

            ok = self.spin_until(done, timeout)
            self.spin_until(lambda: False, 0.2)
            if self.halts() == h0:
                break
            ok = False
        return ok, time.monotonic() - t0

    def sim_tool(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        st = self.stack.sim_status()
        if not st:
            return None
        return float(st["wall_time"]), np.asarray(st["tool"]["position"], float), np.asarray(st["q"], float)

    def close(self) -> None:
        try:
            self.ex.shutdown()
            self.node.destroy_node()
            self.rclpy.shutdown(context=self.ctx)
        finally:
            self.stack.close()


#: Command timings of the stack runs: name -> controller parameters.
STACK_COMMANDS = {
    "unstamped, lead 0 (before)": ["-p", "command_delay_s:=0.0", "-p", "stream_lead_s:=0.0"],
    "stamped +50 ms, lead 60 ms (default)": [],
}


def stack_run(args: argparse.Namespace) -> tuple[str, list[str]]:
    """circle-0.16 at 50 Hz through the stack; the simulated tool (pybullet, from the simulator's
    status at 100 Hz), FK of /joint_states (the modules' measured positions) and FK of /joint_command
    as it arrives (the controller's commands, at receipt) are scored."""
    title = "## Through the stack (bring-up: bus server, simulator, can_driver, ik_service, controller)"
    out = [""]
    rows = [
        "| path | Hz | commands | measured on | samples | pos err median mm | p95 mm | max mm | "
        "lag ms | "
        "overshoot at stop mm | error 2 s after stop mm | driver halts | load (1 min) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    path = circle(0.16)
    names = list(STACK_COMMANDS) if args.stack_compare else list(STACK_COMMANDS)[-1:]
    for name in [n for _ in range(args.stack_repeats) for n in names]:
        c = StackClient(
            {
                "extra_args": {
                    "sim": ["--status-rate", "100"],
                    "controller": STACK_COMMANDS[name],
                }
            }
        )
        try:
            if not c.spin_until(lambda c=c: len(c.joints) > 5 and len(c.states) > 0, 60.0):
                raise RuntimeError("no joint_states / controller state from the stack")
            # From the homed (stretched) pose the controller moves in joint space by itself.
            ok, _ = c.reach(path.pose(0.0), 40.0)
            if not ok:
                if c.halts():
                    c.recover()
                ok, _ = c.reach(path.pose(0.0), 40.0)  # a starved machine: once more
            if not ok:
                rows.append(f"| {path.name} | 50 | {name} | - | 0 | the start of the path was not reached "
                            f"(load {os.getloadavg()[0]:.1f}): {c.states[-1].message} |||||||")
                continue
            c.spin_until(lambda: False, 2.0)  # the elbow settles
            c.joints.clear()
            c.commands.clear()
            load = os.getloadavg()[0]
            sim: list[tuple[float, np.ndarray]] = []
            t0 = c.now() + 0.05
            k = 0
            period = 1.0 / 50.0
            last_poll = 0.0
            while True:
                now = c.now()
                t = now - t0
                if t >= k * period and k * period <= path.duration + 1e-9:
                    ts = min(k * period, path.duration)
                    c.send(path.pose(ts), t0 + ts)
                    k += 1
                if now - last_poll >= 0.01:
                    last_poll = now
                    st = c.sim_tool()
                    if st is not None and (not sim or st[0] != sim[-1][0]):
                        sim.append((st[0], st[1]))
                if t > path.duration + AFTER_S:
                    break
                c.ex.spin_once(timeout_sec=0.001)
            for where, series in (
                ("simulated tool (pybullet)", [(w - t0, p) for w, p in sim]),
                ("FK of /joint_states", [(t - t0, c.arm.fk(q)[:3, 3]) for t, q in c.joints]),
                ("FK of /joint_command at receipt", [(t - t0, c.arm.fk(q)[:3, 3]) for t, q in c.commands]),
            ):
                rows.append(_stack_row(path, name, where, series, c.halts(), load))
        finally:
            c.close()
    out += rows
    out.append("")
    out.append(
        "Errors against the path at the sample's own time (simulator wall clock, joint-state header "
        "stamps, receipt of /joint_command by this client); the stream is stamped with the ROS clock of "
        "the same machine. Commands: before = /joint_command segments started on receipt and no lead "
        "(command_delay_s 0, stream_lead_s 0); default = segments stamped to end 50 ms after their step "
        "(command_delay_s) and the stream tracked 50 + 10 ms ahead (stream_lead_s: the driver cycle "
        "and the modules' set-point generators). A negative lag of /joint_command is that lead."
    )
    out.append("")
    return title, out


def _stack_row(
    path: PathDef, commands: str, name: str, series: list[tuple[float, np.ndarray]], halts: int, load: float
) -> str:
    ts = np.array([t for t, _ in series])
    ps = np.array([p for _, p in series])
    e, lag, over, final = _series_scores(path, ts, ps, lag_samples=None)
    return (
        f"| {path.name} | 50 | {commands} | {name} | {len(e)} | {np.median(e):.2f} | "
        f"{np.percentile(e, 95):.2f} | {np.max(e):.2f} | {lag:.0f} | {over:.2f} | {final:.2f} | "
        f"{halts} | {load:.1f} |"
    )


def chain_section() -> tuple[str, list[str]]:
    """circle-0.16 at 50 Hz through the model of the command chain (benchmarks/track_chain.py): each
    command timing under each message timing; the modules' set-points (FK) are scored."""
    from track_chain import COMMANDS, TIMINGS, run_chain

    arm = load_arm("pa10")
    path = circle(0.16)
    q0 = settle_start(arm, path)
    title = "## Command chain model (controller core -> driver -> modules on one clock, no ROS)"
    out = [
        "",
        "| message timing | commands | pos err median mm | p95 mm | max mm | lag ms | overshoot at stop mm | "
        "error 2 s after stop mm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for timing in TIMINGS:
        for cmds in COMMANDS:
            ts, ps = run_chain(arm, path, q0, timing, cmds)
            e, lag, over, final = _series_scores(path, ts, ps)
            out.append(
                f"| {timing.name} | {cmds.name} | {np.median(e):.2f} | {np.percentile(e, 95):.2f} | "
                f"{np.max(e):.2f} | {lag:.0f} | {over:.2f} | {final:.2f} |"
            )
    out += [
        "",
        "The real JointCommandSource, ReferenceShaper and JointRamp classes and the controller core, with "
        "the processes, DDS and the bus replaced by the delays named (the controller's 100 Hz timer on a "
        "kept grid, its ticks late by up to the jitter; /joint_command messages delivered in order after "
        "the latency). Scored: FK of the modules' set-points against the path at the same time.",
        "",
    ]
    return title, out


def _series_scores(
    path: PathDef, ts: np.ndarray, ps: np.ndarray, lag_samples: int | None = 400
) -> tuple[np.ndarray, float, float, float]:
    """Errors (mm) while the stream runs, lag (ms), overshoot at the stop (mm), final error (mm) of a
    timed series of tool positions; the lag is fitted on about ``lag_samples`` of the running samples
    (None: all of them)."""
    live = (ts >= 0.0) & (ts <= path.duration)
    ref = np.array([path.pose(min(max(t, 0.0), path.duration))[:3, 3] for t in ts])
    e = np.linalg.norm(ps - ref, axis=1)[live] * 1e3
    best = (math.inf, 0.0)
    sub = np.flatnonzero(live)
    if lag_samples is not None:
        sub = sub[:: max(1, int(live.sum() // lag_samples))]
    for tau in np.arange(-0.05, 0.301, 0.002):
        sh = np.array([path.pose(min(max(ts[i] - tau, 0.0), path.duration))[:3, 3] for i in sub])
        m = float(np.mean(np.linalg.norm(ps[sub] - sh, axis=1)))
        if m < best[0]:
            best = (m, tau)
    end = path.pose(path.duration)[:3, 3]
    u = end - path.pose(path.duration - 0.3)[:3, 3]
    after = ps[ts > path.duration]
    over = max(0.0, float(np.max((after - end) @ (u / np.linalg.norm(u))))) * 1e3 if len(after) else math.nan
    return e, best[1] * 1e3, over, float(np.linalg.norm(ps[-1] - end)) * 1e3


NOT_COVERED = """What this does not cover: one arm (PA10) and one region of its workspace per path; streams
whose message rate changes while they run; clocks of another machine (the stamp-offset estimate is
tested, not benchmarked); obstacles that move; the DLS baseline is our own implementation of MoveIt
Servo's method (its singularity and collision velocity scaling are not reproduced). In-process, the
commanded joints are scored: the arm is taken to follow its commands exactly; the run through the
stack measures the simulated arm."""


if __name__ == "__main__":
    sys.exit(main())
