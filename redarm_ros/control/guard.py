"""Collision guard: no command may bring the arm into the scene or into itself, nor leave it unable to
brake clear.

A command ``q`` moving at ``qd`` passes when

* its clearance is at least ``margin``, or no lower than the clearance of the previous command (an arm
  started in contact may still move out). The clearance is the smallest of: the capsules against the
  obstacles and the table; the arm's self-collision pairs and its ground plane
  (:mod:`~redarm_ros.geometry.self_collision`, from the arm's ``self_collision`` entry); and
* braking from it at the joints' acceleration limits would keep the same rule: the braking path is
  marched like sphere tracing (a sample with clearance ``c`` proves the next ``c`` of travel safe, each
  joint's travel weighted by its lever arm, :func:`levers`; where ``c`` is below ``step`` the samples
  are ``step`` apart and must clear ``step`` more).

Since every accepted command's braking path is clear, the arm can always brake instead when the next
command is refused. The same sphere tracing checks the straight joint-space segments of the
re-planner (:meth:`CollisionGuard.segment_clearance`). Units: m, rad, s.
"""

from __future__ import annotations

import math
from collections.abc import Generator

import numpy as np

from redarm_ros.control.joint_limits import brake_step
from redarm_ros.geometry.obstacles import TABLE, ArmCapsules, Clearance, Scene, links_clearance
from redarm_ros.geometry.self_collision import collision_model, segment_distance
from redarm_ros.kinematics.protocols import ControlledArm

LINKS = ("base", "upper arm", "forearm", "hand")
#: ``Clearance.obstacle`` of the arm's ground plane (the table is ``TABLE``, -1; -2 is the broad
#: phase's ``LEFT_OUT``).
GROUND_PLANE = -3
#: ``Clearance.obstacle`` of a self-collision: ``SELF - j`` for the other link ``j`` of the pair
#: (``Clearance.link`` is the first one).
SELF = -10


def is_self(obstacle: int) -> bool:
    """Does a ``Clearance.obstacle`` code stand for a link of the arm itself?"""
    return SELF - 3 <= obstacle <= SELF


def levers(key_points: np.ndarray, radius: float) -> np.ndarray:
    """Per joint of a 7-DOF shoulder-elbow-wrist arm, the largest distance (m) from the joint to a
    point of the arm it moves (key points base, shoulder, elbow, wrist, tool, plus the thickest capsule
    ``radius``): joints 1-3 turn about the shoulder, joint 4 about the elbow, joints 5-7 about the
    wrist. A joint turning by ``dq`` moves no point of the arm farther than ``lever * |dq|``."""
    kp = key_points

    def dist(i: int, j: int) -> float:  # np.linalg.norm's own arithmetic (sqrt of the dot), minus its wrapper
        d = kp[i] - kp[j]
        return math.sqrt(d.dot(d))

    sh = max(dist(i, 1) for i in (2, 3, 4)) + radius
    el = max(dist(i, 2) for i in (3, 4)) + radius
    wr = dist(4, 3) + radius
    return np.array([sh, sh, sh, el, wr, wr, wr])


def describe(bad: Clearance, scene: Scene) -> str:
    """'the forearm ... obstacle 2 'can'' style text for a clearance."""
    if is_self(bad.obstacle):
        what = f"the {LINKS[SELF - bad.obstacle]} (self-collision)"
    elif bad.obstacle == GROUND_PLANE:
        what = "the ground plane"
    else:
        what = "the table" if bad.obstacle == TABLE else f"obstacle {bad.obstacle}"
    if 0 <= bad.obstacle < len(scene.obstacles) and scene.obstacles[bad.obstacle].name:
        what += f" {scene.obstacles[bad.obstacle].name!r}"
    link = LINKS[bad.link] if 0 <= bad.link < 4 else "arm"
    return f"the {link} to {bad.distance:.3f} m of {what}"


class CollisionGuard:
    """The guard of one arm: ``capsules`` (collision model), ``margin`` (m), ``step`` (m, braking-path
    sampling), joint limits ``lower``/``upper`` (rad) and ``max_acc`` (rad/s^2)."""

    def __init__(self, arm: ControlledArm, capsules: ArmCapsules, margin: float, step: float) -> None:
        self.arm = arm
        self.capsules = capsules
        self.margin = float(margin)
        self.step = float(step)
        self.lower = np.asarray(arm.lower, float)
        self.upper = np.asarray(arm.upper, float)
        self.max_acc = np.asarray(arm.max_acc, float)
        self._rmax = max(capsules.radii)
        self._max_levers: np.ndarray | None = None
        self.evaluations = 0  # clearance evaluations so far (the re-planner budgets them)
        # Self-collision pairs and ground plane of the arm (its YAML ``self_collision`` entry).
        model = collision_model(arm, capsules)
        radii = capsules.radii
        self._self_pairs = [(i, j, radii[i] + radii[j]) for i, j in model.pairs]
        self._ground = [(i, radii[i] + model.ground_z) for i in model.ground_links] \
            if model.ground_z is not None else []

    def key_points(self, q: np.ndarray) -> np.ndarray:
        """(5, 3) key points (m) of the arm at ``q``: base, shoulder, elbow, wrist, tool."""
        return np.asarray(self.arm.key_points(q), float)

    def clearance(self, q: np.ndarray, scene: Scene, kp: np.ndarray | None = None,
                  self_check: bool = True) -> Clearance:
        """Clearance of the arm at ``q`` (rad; or its key points ``kp``) against ``scene`` and, with
        ``self_check``, against itself and its ground plane (see :func:`is_self`, :data:`GROUND_PLANE`)."""
        self.evaluations += 1
        pts = (self.key_points(q) if kp is None else kp).tolist()
        best = links_clearance(pts, scene, self.capsules)
        if self_check:
            for i, j, r in self._self_pairs:
                d = segment_distance(pts[i], pts[i + 1], pts[j], pts[j + 1]) - r
                if d < best.distance:
                    best = Clearance(d, i, SELF - j)
            for i, off in self._ground:
                d = min(pts[i][2], pts[i + 1][2]) - off
                if d < best.distance:
                    best = Clearance(d, i, GROUND_PLANE)
        return best

    def levers(self, q: np.ndarray, kp: np.ndarray | None = None) -> np.ndarray:
        """:func:`levers` at ``q`` (or its key points ``kp``)."""
        return levers(self.key_points(q) if kp is None else kp, self._rmax)

    def allows(self, c: float, c_from: float) -> bool:
        """The rule: clearance ``c`` is at least the margin, or no lower than ``c_from``."""
        return c >= self.margin or c >= c_from - 1e-9

    @staticmethod
    def sync_rate(qd: np.ndarray, max_acc: np.ndarray) -> float:
        """Rate (1/s) at which all joints can scale their velocity down together (the joint that needs
        the longest to stop sets it): braking along the current joint-space direction."""
        with np.errstate(divide="ignore"):
            r = np.where(np.abs(qd) > 0.0, max_acc / np.abs(qd), np.inf)
        return float(r.min())

    def braking_clearance(self, q: np.ndarray, qd: np.ndarray, c: float, dt: float,
                          scene: Scene, sync: bool = False, kp: np.ndarray | None = None) -> Clearance | None:
        """Smallest clearance along the hardest allowed braking from ``q`` moving at ``qd`` (sampled
        every ``step`` m of possible travel and lowered by that much), or None if no point of the arm
        can travel ``c - margin`` before the joints stop. ``sync``: every joint brakes in proportion
        (the arm stays on its joint-space line, e.g. a planned path) instead of each as hard as it can."""
        n = int(float((np.abs(qd) / self.max_acc).max()) / dt) + 2
        if sync:
            v = self._braking_velocities(qd, n, dt, sync)
            turn = np.abs(dt * v.sum(axis=0))
        else:  # (the braking path is needed only past the quick test below: most calls end there)
            turn = qd * qd / (2.0 * self.max_acc)  # rad still to go per joint (the continuous bound)
        turn = turn + np.abs(qd) * dt
        if not (turn > 0.0).any():
            return None
        lever = self.levers(q, kp)
        if c - float(np.dot(lever, turn)) >= self.margin:
            return None
        if not sync:
            v = self._braking_velocities(qd, n, dt, sync)
        worst: Clearance | None = None
        path = np.clip(q + dt * np.cumsum(v, axis=0), self.lower, self.upper)
        moved = np.cumsum(np.abs(np.diff(np.vstack([q, path]), axis=0)) @ lever)
        at, gap = 0.0, max(c - self.margin, self.step)
        while True:
            i = min(int(np.searchsorted(moved, at + gap)), n - 1)
            cb = self.clearance(path[i], scene)
            room = cb.distance - self.margin
            if room < self.step and i < n - 1:  # dense sampling: ask step more
                cb = Clearance(cb.distance - self.step, cb.link, cb.obstacle)
            if worst is None or cb.distance < worst.distance:
                worst = cb
            if i >= n - 1:
                return worst
            at, gap = float(moved[i]), max(room, self.step)

    def _braking_velocities(self, qd: np.ndarray, n: int, dt: float, sync: bool) -> np.ndarray:
        """(n, 7) joint velocities of the n braking steps from ``qd`` (see :meth:`braking_clearance`)."""
        k = np.arange(1, n + 1)[:, None]
        if sync:
            rate = self.sync_rate(qd, self.max_acc)
            return qd * np.maximum(1.0 - k * rate * dt, 0.0)
        return np.sign(qd) * np.maximum(np.abs(qd) - k * self.max_acc * dt, 0.0)  # brake_step, closed form

    def check(self, q: np.ndarray, qd: np.ndarray, prev: float, dt: float, scene: Scene, sync: bool = False,
              on_path: bool = False, kp: np.ndarray | None = None) -> tuple[Clearance, Clearance | None]:
        """Judge command ``q`` (key points ``kp`` if known) moving at ``qd`` after a command of
        clearance ``prev``: returns ``(clearance of q, None)`` if it passes, else ``(clearance of q, the
        offending clearance)``.
        ``sync``: judge the braking that keeps the joint-space direction (see :meth:`braking_clearance`).
        ``on_path``: ``q`` lies on a joint segment checked beforehand (:meth:`segment_clearance`) that
        it can brake along without leaving it: the braking path needs no check."""
        clear = self.clearance(q, scene, kp)
        if not self.allows(clear.distance, prev):
            return clear, clear
        if on_path:
            return clear, None
        stop = self.braking_clearance(q, qd, clear.distance, dt, scene, sync, kp)
        if stop is not None and not self.allows(stop.distance, clear.distance):
            return clear, stop
        return clear, None

    def brake(self, q: np.ndarray, qd: np.ndarray, prev: float, dt: float,
              scene: Scene, sync: bool = False) -> tuple[np.ndarray, np.ndarray, Clearance] | None:
        """One step of the hardest allowed braking from ``q`` moving at ``qd`` (``sync``: keeping the
        joint-space direction), if the rule lets it through: ``(q, qd, clearance)``; None means stop
        where the arm is (an emergency stop)."""
        if sync:
            v = qd * max(1.0 - self.sync_rate(qd, self.max_acc) * dt, 0.0)
            q_b = np.clip(q + v * dt, self.lower, self.upper)
            v_b = (q_b - q) / dt
        else:
            q_b, v_b = brake_step(q, qd, dt, self.max_acc, self.lower, self.upper)
        clear = self.clearance(q_b, scene)
        if self.allows(clear.distance, prev):
            return q_b, v_b, clear
        return None

    def max_levers(self) -> np.ndarray:
        """Levers that hold in every configuration (link lengths instead of the current geometry)."""
        if self._max_levers is None:
            kp = np.asarray(self.arm.key_points(np.clip(np.full(7, 0.3), self.lower, self.upper)), float)
            upper = float(np.linalg.norm(kp[2] - kp[1]))
            fore = float(np.linalg.norm(kp[3] - kp[2]))
            hand = float(np.linalg.norm(kp[4] - kp[3]))
            r = self._rmax
            self._max_levers = np.array([upper + fore + hand + r] * 3 + [fore + hand + r] + [hand + r] * 3)
        return self._max_levers

    def segment_march(self, qa: np.ndarray, qb: np.ndarray, scene: Scene, need: float,
                      budget: int = 10_000, lever: np.ndarray | None = None,
                      fine: float = 5e-4) -> Generator[None, None, float | None]:
        """Check the straight joint-space segment ``qa`` -> ``qb`` (rad) against ``scene``, one
        clearance evaluation per iteration (a generator: the caller may spread the work over control
        steps); its return value is the smallest clearance seen when the segment passes, None when it
        does not or the ``budget`` of evaluations ran out.

        Marches by sphere tracing: a configuration of clearance ``c`` proves that the arm may move
        ``c - need`` (joint travel weighted by ``lever``, default :meth:`max_levers`) keeping ``need``;
        every sample must clear ``need + min(step, need)`` so that the march advances. A segment that
        starts closer than that (an arm the guard stopped at an obstacle) must first get clear along a
        dense march: samples ``fine`` m of travel apart, each with at least ``fine / 2`` of clearance or
        no less than the sample before.
        """
        lev = self.max_levers() if lever is None else lever
        d = qb - qa
        travel = float(np.dot(lev, np.abs(d)))  # m per unit of t
        used = 0
        t = 0.0
        worst = math.inf
        dense = True
        c_prev = -math.inf
        while True:
            c = self.clearance(qa + t * d, scene).distance
            used += 1
            yield None
            if used > budget:
                return None
            if dense and c >= need + min(self.step, max(need, 1e-4)):
                dense = False
            if dense:
                if t > 0.0 and c < 0.5 * fine and c < c_prev - 1e-9:
                    return None
                c_prev = c
            else:
                worst = min(worst, c)
                if c < need + min(self.step, max(need, 1e-4)):
                    return None
            if t >= 1.0:
                return min(worst, c)
            if travel <= 0.0:
                t = 1.0
            else:
                t = min(1.0, t + (fine if dense else c - need) / travel)

    def segment_clearance(self, qa: np.ndarray, qb: np.ndarray, scene: Scene, need: float,
                          budget: int = 10_000, lever: np.ndarray | None = None,
                          fine: float = 5e-4) -> float | None:
        """:meth:`segment_march` run to the end: the smallest clearance (m), or None."""
        march = self.segment_march(qa, qb, scene, need, budget, lever, fine)
        while True:
            try:
                next(march)
            except StopIteration as stop:
                return stop.value
