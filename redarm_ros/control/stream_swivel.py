"""The elbow while the servo tracks a stream or a twist: the swivel as a function of the hand's pose
(``servo.swivel_law`` pose, the default; ``dynamics`` is eq. 31 with the preferred swivel fed forward).

The swivel is the preferred swivel of the present pose plus an offset, ``s = s_pref(T) + e``:

* ``s_pref(T)`` is the preferred swivel (``preferred_swivel`` from the highest or lowest elbow, or
  absolute), a function of the pose alone, and its change from step to step is fed forward;
* the offset ``e`` is the elbow's only state: the obstacle and joint-limit forces of the swivel
  dynamics (eq. 31) push it, and otherwise it returns to exactly 0 accelerating and braking at
  ``servo.swivel_acc`` (the braking law of :mod:`redarm_ros.motion.limits`: it lands on 0 in finite
  time; 0.1 rad in about 0.9 s at 0.5 rad/s^2), its rate within ``swivel.max_rate`` and its change
  within the joints' acceleration share. While the hand needs the joints' whole acceleration (the
  servo's step was cut to it) the offset holds instead: the hand has priority over the elbow's way
  back.

So once the offset is 0 the joints are a function of the pose (and the branch): a closed path gives the
same joint motion on every lap, and nothing integrates a drift (a differential-IK servo's null space
does). With ``preferred_swivel`` 0 the elbow stays in the vertical plane through the shoulder axis and
the wrist, where the elbow passes over the shoulder regularly: joint 2 changes sign, joint 3 stays at 0
and joint 1 at the wrist's azimuth (the IK step takes the solution on the other shoulder flip there,
continuous with the last). An elbow a little off that plane near the shoulder axis is a true trap
(joint 1 must turn by up to pi as the elbow passes the axis), so the swivel dynamics' singularity force,
which pushes the elbow off the plane, is not used here.

**Look-ahead.** While the offset is not 0, the stream's estimate (position, velocity, acceleration)
predicts the hand ``servo.lookahead`` s ahead; where the elbow, kept at the present offset, would come
within ``servo.axis_margin`` (|sin q2|) of the shoulder axis, the offset is closed before the hand gets
there (braked harder, up to the joints' share, so that it is 0 half-way to that moment), not after.

Units: rad, s, m.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from redarm_ros.control.elbow import ArmGeometry, ElbowCircle, elbow_circle
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.errors import UnreachableError
from redarm_ros.motion import braking_speed_scalar

#: rad: an offset below this counts as 0 (no look-ahead needed)
OFFSET_EPS = 1e-9
#: predicted poses per look-ahead horizon
LOOKAHEAD_SAMPLES = 6


def shoulder_sine(circle: ElbowCircle, s: float) -> float:
    """|sin q2| of the elbow at swivel ``s``: its distance from the vertical axis through the shoulder
    over the upper-arm length (a z-y-z shoulder with a vertical first axis)."""
    e, ps = circle.elbow(s), circle.shoulder
    ux, uy, uz = e[0] - ps[0], e[1] - ps[1], e[2] - ps[2]
    lu = math.sqrt(ux * ux + uy * uy + uz * uz)
    return math.hypot(ux, uy) / lu if lu > 0.0 else 0.0


def time_to_axis(geom: ArmGeometry, poses: Sequence[tuple[float, np.ndarray]], offset: float,
                 preferred: Callable[[ElbowCircle], float], margin: float) -> float | None:
    """The first time ``tau`` (s) of the predicted ``poses`` ((tau, 4x4) each, ascending) at which the
    elbow, ``offset`` rad off the preferred swivel, is within ``margin`` (|sin q2|) of the shoulder axis;
    None if it never is."""
    for tau, T in poses:
        try:
            c = elbow_circle(geom, T)
        except UnreachableError:
            return None  # (the servo slides along the workspace shell there: no elbow to steer)
        if shoulder_sine(c, preferred(c) + offset) < margin:
            return tau
    return None


def offset_rate(offset: float, rate: float, push: float, close_acc: float, max_rate: float, acc: float,
                dt: float) -> float:
    """The offset's rate (rad/s) for the next step of ``dt`` s: back to 0 at the braking speed of
    ``close_acc`` (rad/s^2; it lands on 0 exactly, in finite time; 0: it holds, i.e. no faster towards
    0 than ``rate`` and braking at ``acc`` to land on 0), plus ``push`` (rad/s,
    the obstacle and limit forces); within ``max_rate`` and at most ``acc * dt`` from the last ``rate``
    (speeding up towards 0: ``close_acc * dt``)."""
    d = abs(offset)
    back = 0.0
    if d > 0.0 and close_acc > 0.0:
        back = -math.copysign(min(braking_speed_scalar(d, close_acc, dt), max_rate), offset)
    elif d > 0.0:  # holding: no faster towards 0 than now, braking at ``acc`` so as to land on 0
        closing = abs(rate) if rate * offset < 0.0 else 0.0
        back = -math.copysign(min(braking_speed_scalar(d, acc, dt), max_rate, closing), offset)
    want = max(-max_rate, min(max_rate, back + push))
    # Towards 0 the offset speeds up at close_acc too (not at the joints' whole share: the hand's motion
    # has priority); slowing down, turning and the forces' pushes use ``acc``.
    speeding = push == 0.0 and abs(want) > abs(rate) and want * rate >= 0.0
    step = min(acc, close_acc) * dt if speeding else acc * dt
    new = max(rate - step, min(rate + step, want))
    if push == 0.0 and d > 0.0 and abs(new * dt) >= d and (new * offset) < 0.0:
        return -offset / dt  # (lands on 0, not past it)
    return new


def closing_acc(offset: float, within: float, least: float, most: float) -> float:
    """The braking acceleration (rad/s^2) that closes ``offset`` (rad) from rest within ``within`` s
    (accelerating, then braking: ``4 |offset| / within^2``), at least ``least`` and at most ``most``."""
    if within <= 0.0:
        return most
    return max(least, min(most, 4.0 * abs(offset) / (within * within)))


def wrap_offset(s: float, s_pref: float) -> float:
    """The offset (rad) of swivel ``s`` from the preferred ``s_pref``, in (-pi, pi]."""
    return wrap_angle(s - s_pref)
