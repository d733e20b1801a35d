"""Base-move suggestion: the smallest planar move of the arm's base that makes a pose solvable.

For a pose the arm cannot solve where it stands (out of reach, no in-limit or no collision-free
solution), :func:`suggest_base_move` returns the smallest planar displacement ``(x, y)`` of the base
(m, in the current base frame; optionally a yaw, rad) after which the pose is solvable with the elbow in
the *optimal region*:

* **powercube6** (Duguleana, mobile-base paper): the paper's "optimal end-effector region", the space
  where a solution with ``phi4 = 0`` exists (L23 and L4 folded into one 0.54 m link). When no solution
  passes the IK and collision tests, the paper's program moves the robot "in a desired position where
  the goal is reachable", and the motion is base first, then the arm from its base joint to the
  end effector.
* **7-DOF swivel arms**: the elbow at mid-range, ``|theta4| = max(|lower4|, |upper4|) / 2`` (the elbow
  triangle half bent: far from the stretched singularity and from the folded limit).

The elbow value fixes the shoulder-wrist distance ``d``; a planar move keeps every height, so the base
must put the shoulder at the horizontal distance ``sqrt(d^2 - dz^2)`` from the wrist point (``dz``: the
wrist's height above the shoulder). For a 7-DOF arm the shoulder is on the base axis: the base lies on
a circle around the wrist; the nearest point to the current base comes first, then the circle in steps
of ``step_deg``. For powercube6 the shoulder sits L1 off the base axis in the arm's vertical plane, and
with joint 3 locked that plane must contain the tool's approach axis: the base lies on the vertical
plane through the approach (4 points), or on a circle when the approach is vertical. Each candidate is
verified with the real IK (in the limits, and collision-free with the self-collision model unless
``check_collisions`` is False); the first (smallest displacement) that passes is the answer. If no
candidate at the optimal elbow passes, the elbow is relaxed in 5 deg steps away from it (``optimal``
is then False). A yaw is only suggested when no position works without it: the base then turns so that
the target is straight ahead (joint 1 near 0).

The displacement moves the arm's base frame: the new base frame, seen from the current one, is
``B = Trans(x, y, 0) Rz(yaw)`` and the target in it is ``B^-1 T`` (:meth:`BasePlacement.apply`). A
mobile base whose reference point is elsewhere converts it with its mounting transform.

``python -m redarm_ros.kinematics.base_placement --arm powercube6 1.2 0.0 0.1`` prints the suggestion.
No ROS here; numpy only. Units: m, rad.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError
from redarm_ros.geometry.obstacles import ArmCapsules
from redarm_ros.geometry.self_collision import CollisionModel, collision_model, self_collision_batch
from redarm_ros.kinematics.collision_ik import nearest_collision_free
from redarm_ros.kinematics.protocols import has_swivel

__all__ = [
    "BasePlacement",
    "suggest_base_move",
    "base_move_hint",
    "planar_transform",
    "wrist_point",
    "pose_ground_clearance",
    "main",
]

PI = math.pi
TWO_PI = 2.0 * math.pi
RELAX_STEP = math.radians(5.0)  # elbow relaxation step when the optimal region cannot be reached
MIN_ELBOW = math.radians(2.0)  # 7-DOF: never relax into the stretched elbow (no swivel there)
ELBOW_TOL = 1e-6  # rad: powercube6 solution rows counted as "at" the elbow value
CHUNK = 16  # 7-DOF candidates verified per batched nearest solve


def planar_transform(x: float, y: float, yaw: float) -> np.ndarray:
    """4x4 ``Trans(x, y, 0) Rz(yaw)`` (m, rad): the moved base frame seen from the current one."""
    c, s = math.cos(yaw), math.sin(yaw)
    B = np.eye(4)
    B[:2, :2] = [[c, -s], [s, c]]
    B[0, 3], B[1, 3] = x, y
    return B


def _moved(T: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """The target T expressed in the base frame moved by (x, y, yaw): ``B^-1 T`` (exact inverse)."""
    c, s = math.cos(yaw), math.sin(yaw)
    Binv = np.eye(4)
    Binv[:2, :2] = [[c, s], [-s, c]]
    Binv[0, 3] = -(c * x + s * y)
    Binv[1, 3] = -(-s * x + c * y)
    return Binv @ T


def wrist_point(arm: Any, T: np.ndarray) -> np.ndarray | None:
    """The wrist key point (m, base frame) that pose T fixes, or None for an arm without one.

    Swivel arms: ``p - L4 z_tool`` (the swivel paper's eq. 10); powercube6: the wrist pitch joint,
    ``p - L56 x_tool``. The hand capsule (wrist to tool) is then fixed by the pose alone.
    """
    T = np.asarray(T, dtype=float)
    own = getattr(arm, "wrist_point", None)
    if callable(own):  # a URDF arm mapped onto the swivel model: its own frames
        return own(T)
    if has_swivel(arm):
        return T[:3, 3] - arm.link_lengths[3] * T[:3, 2]
    if getattr(arm, "kind", "") == "powercube6":
        return T[:3, 3] - arm.link_lengths[3] * T[:3, 0]
    return None


def pose_ground_clearance(arm: Any, T: np.ndarray, model: CollisionModel) -> float:
    """Ground clearance (m) of the part of the arm that pose T alone fixes (the hand capsule, and the
    forearm's wrist end): no solution and no planar base move can do better. inf without a ground
    plane or for an arm without a wrist point."""
    W = wrist_point(arm, T)
    if W is None or model.ground_z is None:
        return math.inf
    r = model.capsules.radii
    links = model.ground_links
    d = math.inf
    if 3 in links:
        d = min(d, min(float(W[2]), float(T[2][3])) - r[3] - model.ground_z)
    if 2 in links:
        d = min(d, float(W[2]) - r[2] - model.ground_z)
    return d


@dataclass(frozen=True)
class BasePlacement:
    """A base-move suggestion.

    ``valid``: a move was found; ``x``, ``y`` (m) and ``yaw`` (rad): the displacement of the base in the
    current base frame; ``elbow`` (rad): the elbow value of the placement (powercube6: phi4; 7-DOF arms:
    |theta4|); ``optimal``: that value is the optimal region's; ``q`` (rad): a collision-free in-limit
    solution of the pose at the moved base (the one nearest the seed among those at ``elbow``);
    ``candidates``: base placements verified; ``message``: why none was found, or empty.
    """

    valid: bool
    arm: str
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    elbow: float = math.nan
    optimal: bool = False
    q: np.ndarray | None = None
    candidates: int = 0
    message: str = ""
    elbow_name: str = "elbow"

    @property
    def distance(self) -> float:
        """Length of the planar displacement (m)."""
        return math.hypot(self.x, self.y)

    def transform(self) -> np.ndarray:
        """4x4 pose of the moved base frame in the current base frame."""
        return planar_transform(self.x, self.y, self.yaw)

    def apply(self, T: np.ndarray) -> np.ndarray:
        """The target T (current base frame) expressed in the moved base frame, ``B^-1 T``."""
        return _moved(np.asarray(T, dtype=float), self.x, self.y, self.yaw)

    def describe(self) -> str:
        """One sentence for messages (the ik_service's and, later, the controller's rejections)."""
        if not self.valid:
            return f"no base move found: {self.message}"
        where = (
            f"with {self.elbow_name} = {math.degrees(self.elbow):.1f} deg (the optimal region)"
            if self.optimal
            else f"with {self.elbow_name} = {math.degrees(self.elbow):.1f} deg (the optimal region is not "
            "reachable by a planar move)"
        )
        yaw = f", yaw {math.degrees(self.yaw):.1f} deg" if self.yaw != 0.0 else ""
        return (
            f"moving the base by x = {self.x:.3f} m, y = {self.y:.3f} m ({self.distance:.3f} m{yaw}), "
            f"base first, makes it solvable {where}"
        )


# ----------------------------------------------------------------------------------------------
# Geometry per arm kind
# ----------------------------------------------------------------------------------------------
def _elbow_values(optimal: float, lo: float, hi: float) -> Iterator[tuple[float, bool]]:
    """The optimal elbow value, then values 5 deg, 10 deg, ... away from it inside [lo, hi]."""
    yield optimal, True
    k = 1
    while True:
        vals = [v for v in (optimal - k * RELAX_STEP, optimal + k * RELAX_STEP) if lo <= v <= hi]
        if not vals:  # both sides left [lo, hi] (they only move further out)
            return
        for v in vals:
            yield v, False
        k += 1


def _circle_points(cx: float, cy: float, r: float, step: float) -> list[tuple[float, float]]:
    """Points of the circle (centre (cx, cy), radius r) by distance from the origin: nearest first."""
    if r <= 1e-12:
        return [(cx, cy)]
    dc = math.hypot(cx, cy)
    alpha = math.atan2(-cy, -cx) if dc > 1e-12 else 0.0  # direction from the centre to the origin
    pts = [(cx + r * math.cos(alpha), cy + r * math.sin(alpha))]
    n = int(math.ceil(PI / step))
    for k in range(1, n + 1):
        phi = min(k * step, PI)
        for sg in ((1.0,) if phi >= PI else (1.0, -1.0)):
            pts.append((cx + r * math.cos(alpha + sg * phi), cy + r * math.sin(alpha + sg * phi)))
    return pts


def _with_yaw(pts: list[tuple[float, float, float]], yaw_of: Any, allow_yaw: bool) -> list[tuple[float, ...]]:
    out: list[tuple[float, ...]] = []
    for x, y, extra in pts:
        out.append((x, y, 0.0))
        if allow_yaw:
            yaw = yaw_of(x, y, extra)
            if abs(yaw) > 1e-9:
                out.append((x, y, yaw))
    return out


# ----------------------------------------------------------------------------------------------
# The suggestion
# ----------------------------------------------------------------------------------------------
def suggest_base_move(
    arm: Any,
    T: np.ndarray,
    *,
    q_seed: Sequence[float] | None = None,
    check_collisions: bool = True,
    model: CollisionModel | None = None,
    capsules: ArmCapsules | None = None,
    allow_yaw: bool = True,
    timeout_s: float = 1.0,
    step_deg: float = 1.0,
) -> BasePlacement:
    """The smallest planar base move after which pose T (4x4, current base frame, m) is solvable.

    ``q_seed`` (rad; default mid-range) picks the returned ``q`` among the solutions at the new base;
    ``check_collisions``: require a collision-free solution (``model``, or the arm's collision model
    with ``capsules``); ``allow_yaw``: a yaw may be suggested when no position works without it;
    ``timeout_s`` (s) bounds the search (the answer is then invalid, saying so); ``step_deg``: spacing
    of the candidates along a circle of base positions. Works for the swivel arms and powercube6; any
    other arm gets an invalid answer. Raises :class:`InvalidInputError` for a malformed T or seed.
    """
    Tl = np.asarray(arm.check_pose(T), dtype=float)
    seed = (arm.lower + arm.upper) / 2.0 if q_seed is None else arm.check_q(q_seed, "q_seed")
    t_end = time.perf_counter() + float(timeout_s)
    step = math.radians(float(step_deg))
    if not step > 0.0:
        raise InvalidInputError(f"step_deg must be > 0, got {step_deg}", field="step_deg", value=step_deg)
    md = (model or collision_model(arm, capsules)) if check_collisions else None
    if md is not None:
        g = pose_ground_clearance(arm, Tl, md)
        if g < 0.0:
            return BasePlacement(
                False, arm.name,
                message=f"the hand would be {-g:.3f} m below the ground plane at this pose (a planar base "
                "move keeps every height)",
            )
    if has_swivel(arm) and not callable(getattr(arm, "wrist_point", None)):  # (not a URDF arm's frames)
        return _suggest_swivel(arm, Tl, seed, md, allow_yaw, t_end, step)
    if getattr(arm, "kind", "") == "powercube6":
        return _suggest_powercube6(arm, Tl, seed, md, allow_yaw, t_end, step)
    return BasePlacement(False, arm.name, message=f"no base placement model for arm kind {arm.kind!r}")


def _suggest_swivel(
    arm: Any, T: np.ndarray, seed: np.ndarray, md: CollisionModel | None, allow_yaw: bool, t_end: float,
    step: float,
) -> BasePlacement:
    L1, L2, L3, L4 = arm.link_lengths
    W = T[:3, 3] - L4 * T[:3, 2]  # wrist point (eq. 10 of the swivel paper)
    dz = W[2] - L1  # wrist above the shoulder
    top = max(abs(arm.lower[3]), abs(arm.upper[3]))
    optimal = 0.5 * top
    name = "|theta4|"
    checked = 0
    for e, is_opt in _elbow_values(optimal, MIN_ELBOW, top):
        d = math.sqrt(L2 * L2 + L3 * L3 + 2.0 * L2 * L3 * math.cos(e))
        if abs(dz) > d:
            continue
        h = math.sqrt(max(d * d - dz * dz, 0.0))
        pts = [(x, y, 0.0) for x, y in _circle_points(float(W[0]), float(W[1]), h, step)]
        cands = _with_yaw(pts, lambda x, y, _: math.atan2(W[1] - y, W[0] - x), allow_yaw)
        for k in range(0, len(cands), CHUNK):
            if time.perf_counter() > t_end:
                return BasePlacement(False, arm.name, candidates=checked, elbow_name=name,
                                     message="the time budget ran out before a base placement was found")
            chunk = cands[k:k + CHUNK]
            Ts = np.stack([_moved(T, *c) for c in chunk])
            res = arm.ik_nearest_batch(Ts, seed)
            checked += len(chunk)
            for j, c in enumerate(chunk):
                if not res.ok[j]:
                    continue
                q = res.q[j]
                if md is not None and self_collision_batch(arm, q[None], model=md).colliding[0]:
                    if time.perf_counter() > t_end:
                        break
                    found = nearest_collision_free(arm, Ts[j], seed, md)
                    if found is None:
                        continue
                    q = found.q
                return BasePlacement(True, arm.name, float(c[0]), float(c[1]), float(c[2]), e, is_opt,
                                     np.asarray(q, dtype=float).copy(), checked, elbow_name=name)
    why = (
        f"the wrist point is {abs(dz):.3f} m {'above' if dz > 0 else 'below'} the shoulder, beyond the "
        f"reach {L2 + L3:.3f} m"
        if abs(dz) > L2 + L3
        else "no base position on the candidate circles has an in-limit"
        + (", collision-free" if md is not None else "")
        + " solution"
    )
    return BasePlacement(False, arm.name, candidates=checked, elbow_name=name, message=why)


def _suggest_powercube6(
    arm: Any, T: np.ndarray, seed: np.ndarray, md: CollisionModel | None, allow_yaw: bool, t_end: float,
    step: float,
) -> BasePlacement:
    L1, L23, L4, L56 = arm.link_lengths
    a = T[:3, 0]  # approach (tool x)
    W = T[:3, 3] - L56 * a  # wrist pitch point
    ah = math.hypot(a[0], a[1])
    name = "phi4"
    lo, hi = float(arm.lower[3]), float(arm.upper[3])
    top = max(abs(lo), abs(hi))
    checked = 0
    for e, is_opt in _elbow_values(0.0, 0.0, top):
        la = math.sqrt(L23 * L23 + L4 * L4 + 2.0 * L23 * L4 * math.cos(e))
        if abs(W[2]) > la:
            continue
        h = math.sqrt(max(la * la - W[2] * W[2], 0.0))
        pts: list[tuple[float, float, float]] = []
        if ah > 1e-9:
            ux, uy = a[0] / ah, a[1] / ah
            # base = W_h - rho e_r with e_r = +-u along the approach and rho = L1 +- h: 4 points on a line
            for rho in (L1 + h, L1 - h, -(L1 + h), -(L1 - h)):
                pts.append((float(W[0] - rho * ux), float(W[1] - rho * uy), rho))
        else:
            for rho in (L1 + h, abs(L1 - h)):
                pts += [(x, y, rho) for x, y in _circle_points(float(W[0]), float(W[1]), rho, step)]
        pts.sort(key=lambda p: math.hypot(p[0], p[1]))

        def yaw_of(x: float, y: float, rho: float) -> float:
            # turn so that the arm plane (e_r of the solution) points straight ahead: phi1 = 0
            az = math.atan2(W[1] - y, W[0] - x)
            return math.remainder(az + (PI if rho < 0 else 0.0), TWO_PI)

        for x, y, yaw in _with_yaw(pts, yaw_of, allow_yaw):
            if time.perf_counter() > t_end:
                return BasePlacement(False, arm.name, candidates=checked, elbow_name=name,
                                     message="the time budget ran out before a base placement was found")
            checked += 1
            sols = np.asarray(arm.ik(_moved(T, x, y, yaw)), dtype=float).reshape(-1, arm.n)
            sols = sols[np.abs(np.abs(sols[:, 3]) - e) <= ELBOW_TOL] if len(sols) else sols
            if len(sols) and md is not None:
                sols = sols[self_collision_batch(arm, sols, model=md).free]
            if len(sols) == 0:
                continue
            q = sols[int(np.argmin(((sols - seed) ** 2).sum(axis=1)))]
            return BasePlacement(True, arm.name, x, y, yaw, e, is_opt, q.copy(), checked, elbow_name=name)
    why = (
        f"the wrist point is {abs(W[2]):.3f} m {'above' if W[2] > 0 else 'below'} the shoulder, beyond the "
        f"reach {L23 + L4:.3f} m of L23 + L4"
        if abs(W[2]) > L23 + L4
        else "no base position puts the pose in reach with an in-limit"
        + (", collision-free" if md is not None else "")
        + " solution"
    )
    return BasePlacement(False, arm.name, candidates=checked, elbow_name=name, message=why)


def base_move_hint(arm: Any, T: np.ndarray, **kwargs: Any) -> str:
    """One sentence with the base-move suggestion for pose T (keyword arguments of
    :func:`suggest_base_move`), for a rejection message (e.g. the controller's when a goal is out of
    reach). Never raises: a malformed pose gives a sentence saying so."""
    try:
        return suggest_base_move(arm, T, **kwargs).describe()
    except InvalidInputError as exc:
        return f"no base move computed: {exc}"


# ----------------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------------
def _pose(
    position: Sequence[float], quat_xyzw: Sequence[float] | None, rpy: Sequence[float] | None
) -> np.ndarray:
    from redarm_ros.kinematics.model import transform_from_xyz_rpy
    from redarm_ros.kinematics.quaternion import from_xyzw, quat_to_matrix

    if quat_xyzw is not None:
        T = np.eye(4)
        q = np.asarray(quat_xyzw, dtype=float)
        n = float(np.linalg.norm(q))
        if not (math.isfinite(n) and n > 1e-9):
            raise InvalidInputError(
                "the quaternion must be finite and non-zero", field="quat", value=quat_xyzw
            )
        T[:3, :3] = quat_to_matrix(from_xyzw(q / n))
        T[:3, 3] = position
        return T
    return transform_from_xyz_rpy(position, rpy or (0.0, 0.0, 0.0))


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: print the base-move suggestion for one pose."""
    from redarm_ros.kinematics import load_arm

    ap = argparse.ArgumentParser(
        prog="python -m redarm_ros.kinematics.base_placement",
        description="Smallest planar base move that makes a tool pose solvable with the elbow in the "
        "optimal region (phi4 = 0 for powercube6, elbow mid-range for the 7-DOF arms).",
    )
    ap.add_argument("--arm", default="powercube6", help="arm name (config/arms/<name>.yaml) or YAML path")
    ap.add_argument("position", nargs=3, type=float, metavar=("X", "Y", "Z"), help="tool position (m)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--quat", nargs=4, type=float, metavar=("QX", "QY", "QZ", "QW"),
                   help="tool orientation as a quaternion in ROS order x, y, z, w")
    g.add_argument("--rpy", nargs=3, type=float, metavar=("R", "P", "Y"),
                   help="tool orientation as fixed-axis roll, pitch, yaw (rad); default 0 0 0")
    ap.add_argument("--no-yaw", action="store_true", help="suggest a translation only")
    ap.add_argument("--ignore-collisions", action="store_true", help="skip the self-collision check")
    ap.add_argument("--timeout", type=float, default=2.0, help="search budget in s (default 2)")
    args = ap.parse_args(argv)
    out = sys.stdout
    try:
        arm = load_arm(args.arm)
        T = _pose(args.position, args.quat, args.rpy)
        t0 = time.perf_counter()
        bp = suggest_base_move(arm, T, check_collisions=not args.ignore_collisions,
                               allow_yaw=not args.no_yaw, timeout_s=args.timeout)
    except InvalidInputError as exc:
        sys.stderr.write(f"base_placement: {exc}\n")
        return 2
    dt = time.perf_counter() - t0
    out.write(f"arm {arm.name}, target position {np.round(T[:3, 3], 4).tolist()} m\n")
    if not bp.valid:
        out.write(
            f"no base move found ({bp.candidates} placements checked, {dt * 1e3:.1f} ms): {bp.message}\n"
        )
        return 1
    out.write(
        f"base move: x = {bp.x:.4f} m, y = {bp.y:.4f} m, yaw = {bp.yaw:.4f} rad "
        f"({bp.distance:.4f} m, {math.degrees(bp.yaw):.1f} deg)\n"
        f"{bp.elbow_name} = {math.degrees(bp.elbow):.2f} deg "
        f"({'optimal region' if bp.optimal else 'relaxed'}); "
        f"{bp.candidates} placements checked in {dt * 1e3:.1f} ms\n"
        f"solution at the moved base (rad): {np.round(bp.q, 4).tolist()}\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
