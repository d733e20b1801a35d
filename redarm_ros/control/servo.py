"""The tracking law of streamed goals and twists (MoveIt Servo's pose tracking, with feed-forward).

Each step the reference tool pose moves towards where the goal will be at the end of the step:

    e      = p_goal(t + dt) - p - v_goal dt                      (error left after the feed-forward)
    v_des  = v_goal + unit(e) * min(gain |e|, v_brake(|e|))       (v_brake: can still stop on it)
    v      = v + clip(v_des - v, acc dt),  |v| <= v_max,   p += v dt

and the same for the orientation on rotation vectors. With a correct velocity estimate the reference
moves with the goal and the error stays zero; a new sample that moves the estimate is absorbed at
``gain`` (a first-order filter) with bounded acceleration. When the stream stops, the goal is the last
sample at rest: the hand brakes onto it without overshoot (``v_brake`` is the speed from which the
remaining error can be braked at ``acc``). Units: m, rad, s; quaternions (w, x, y, z).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from redarm_ros.control.joint_limits import braking_speed
from redarm_ros.control.types import Quat, Vec3
from redarm_ros.kinematics.quaternion import quat_from_rotvec, quat_mul, quat_normalize, rotvec_between


@dataclass(frozen=True)
class ServoTarget:
    """Where the goal is at the end of the step (``pos`` m, ``rot``) and how it moves (``vel`` m/s,
    ``w`` rad/s). ``hold_position=False``: only the velocity counts (decelerate, or a pure twist)."""

    pos: Vec3
    rot: Quat
    vel: Vec3
    w: Vec3
    hold_position: bool = True


def _norm(v: Sequence[float]) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def track_vector(x_err: Sequence[float], v: Sequence[float], v_goal: Sequence[float], gain: float, acc: float,
                 v_max: float, dt: float, use_error: bool = True) -> Vec3:
    """New velocity (3-vector) for an error ``x_err`` left after the feed-forward ``v_goal``: the
    law of the module docstring. Units follow the arguments (m or rad)."""
    vd = [v_goal[0], v_goal[1], v_goal[2]]
    if use_error:
        d = _norm(x_err)
        if d > 1e-12:
            corr = min(gain * d, float(braking_speed(d, acc, dt)))
            vd = [vd[i] + corr * x_err[i] / d for i in range(3)]
    n = _norm(vd)
    if n > v_max:
        vd = [c * v_max / n for c in vd]
    dv = [vd[i] - v[i] for i in range(3)]
    dn = _norm(dv)
    lim = acc * dt
    if dn > lim:
        dv = [c * lim / dn for c in dv]
    return (v[0] + dv[0], v[1] + dv[1], v[2] + dv[2])


def servo_step(pos: Vec3, rot: Quat, vel: Vec3, w: Vec3, target: ServoTarget, dt: float, gain: float,
               acc: float, v_max: float, ori_gain: float, ori_acc: float, w_max: float
               ) -> tuple[Vec3, Quat, Vec3, Vec3]:
    """One step of the tracking law: returns the new (pos, rot, vel, w)."""
    tv, tw = target.vel, target.w
    e = (target.pos[0] - pos[0] - tv[0] * dt, target.pos[1] - pos[1] - tv[1] * dt,
         target.pos[2] - pos[2] - tv[2] * dt)
    v_new = track_vector(e, vel, tv, gain, acc, v_max, dt, target.hold_position)
    r = rotvec_between(rot, target.rot)
    er = (r[0] - tw[0] * dt, r[1] - tw[1] * dt, r[2] - tw[2] * dt)
    w_new = track_vector(er, w, tw, ori_gain, ori_acc, w_max, dt, target.hold_position)
    p_new = (pos[0] + v_new[0] * dt, pos[1] + v_new[1] * dt, pos[2] + v_new[2] * dt)
    rot_new = quat_normalize(quat_mul(quat_from_rotvec((w_new[0] * dt, w_new[1] * dt, w_new[2] * dt)), rot))
    return p_new, rot_new, v_new, w_new
