"""A dense, brute-force oracle: does a straight route between two tool poses exist in joint space?

The straight route is the tool position on the line from the start to the goal and the tool
orientation on the slerp between them, u in [0, 1]. The oracle samples it ``route_samples`` times
(u = k / route_samples) and the elbow swivel ``swivel_samples`` times per route sample, keeps every
in-limit IK solution (and every in-limit 2 pi copy of the wide joints) on the start configuration's
flip pattern (the signs of q2, q4, q6), and links two solutions of neighbouring route samples whose
joints differ by at most ``max_jump`` rad (largest absolute difference). A straight route exists when
a chain of links leads from the start configuration (the only node at u = 0) to any solution at u = 1.

``margin`` (rad) also drops every solution within that angle of the shoulder, elbow or wrist
singularity (|q2|, |q4| or |q6| below it; the start configuration itself is kept: the arm is where it
is). A ``scene`` (the capsule model of redarm_ros.geometry.obstacles) drops colliding solutions too.

The oracle uses only the arm's closed-form ``ik_batch`` (every flip pattern at one swivel) and ``fk``;
it shares nothing with the controller or a corridor planner, so it can score both. It is a sampled
test: a corridor narrower than the swivel step can be missed, and a joint jump of up to ``max_jump``
between samples is taken as continuous. An arm without a swivel (6-DOF) is sampled along the route
only, every branch kept (links decide the continuity).

Loaded by path (benchmarks/ is not a package): ``support.benches.load_bench("route_oracle")`` in the
tests, ``import route_oracle`` in the benches (their folder on ``sys.path``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.kinematics.quaternion import (
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_to_matrix,
    rotvec_between,
)

ROUTE_SAMPLES = 40
SWIVEL_SAMPLES = 180
MAX_JUMP = 0.35  # rad, the largest joint difference taken as continuous between route samples
SINGULAR_MARGIN = math.radians(3.0)
#: joints (0-based) whose sign is the flip pattern and whose zero is a singularity: q2, q4, q6
FLIP_JOINTS = (1, 3, 5)


@dataclass(frozen=True)
class RouteVerdict:
    """``exists``: a continuous in-limit straight route links the start to the goal. ``reached_u``: the
    furthest route parameter any chain from the start reaches (1.0 when it exists). ``path``: one
    such chain, a joint vector per route sample (None when there is none). ``nodes``: solutions kept
    per route sample (how wide the corridor is, in samples)."""

    exists: bool
    reached_u: float
    path: np.ndarray | None
    nodes: tuple[int, ...]


def route_poses(T0: np.ndarray, T1: np.ndarray, n: int = ROUTE_SAMPLES) -> np.ndarray:
    """(n + 1, 4, 4) poses of the straight route: position on the line, orientation on the slerp."""
    r0 = quat_from_matrix(T0[:3, :3])
    w = np.asarray(rotvec_between(r0, quat_from_matrix(T1[:3, :3])))
    out = np.tile(np.eye(4), (n + 1, 1, 1))
    for k in range(n + 1):
        u = k / n
        out[k, :3, :3] = quat_to_matrix(quat_mul(quat_from_rotvec(tuple(u * w)), r0))
        out[k, :3, 3] = T0[:3, 3] + u * (T1[:3, 3] - T0[:3, 3])
    return out


def _copies(arm: Any, Q: np.ndarray) -> np.ndarray:
    """Q (m, n) rows plus every in-limit 2 pi copy of each joint (all combinations)."""
    lo, up = np.asarray(arm.lower, float), np.asarray(arm.upper, float)
    out = Q
    for j in range(Q.shape[1]):
        if up[j] - lo[j] <= 2.0 * math.pi:
            continue
        rows = [out]
        for k in (-2, -1, 1, 2):
            c = out.copy()
            c[:, j] += 2.0 * math.pi * k
            keep = (c[:, j] >= lo[j] - 1e-9) & (c[:, j] <= up[j] + 1e-9)
            rows.append(c[keep])
        out = np.concatenate(rows)
    return out


def _pattern(q: np.ndarray) -> tuple[bool, ...]:
    return tuple(bool(q[j] < 0.0) for j in FLIP_JOINTS)


def _free(arm: Any, Q: np.ndarray, scene: Any) -> np.ndarray:
    """Collision-free rows of Q against ``scene`` (capsules of redarm_ros.geometry.obstacles)."""
    from redarm_ros.geometry.obstacles import ArmCapsules, links_clearance  # noqa: PLC0415
    from redarm_ros.geometry.self_collision import key_points_batch  # noqa: PLC0415

    caps = ArmCapsules()
    kp = key_points_batch(arm, Q)
    return np.array([links_clearance(p.tolist(), scene, caps).distance > 0.0 for p in kp], dtype=bool)


def route_nodes(arm: Any, q_start: np.ndarray, T1: np.ndarray, *, route_samples: int = ROUTE_SAMPLES,
                swivel_samples: int = SWIVEL_SAMPLES, margin: float = 0.0,
                scene: Any = None) -> list[np.ndarray]:
    """The kept solutions per route sample: [start (1, n)] + one (k_i, n) array per u = i / route_samples."""
    q0 = np.asarray(q_start, float)
    T0 = np.asarray(arm.fk(q0), float)
    poses = route_poses(T0, np.asarray(T1, float), route_samples)
    swivel = arm.n == 7
    S = np.linspace(-math.pi, math.pi, swivel_samples, endpoint=False) if swivel else np.zeros(1)
    m = len(S)
    Ts = np.repeat(poses[1:], m, axis=0)
    Q, valid = arm.ik_batch(Ts, np.tile(S, route_samples)) if swivel else arm.ik_batch(Ts)
    pat = _pattern(q0)
    layers: list[np.ndarray] = [q0[None, :]]
    for i in range(route_samples):
        block = Q[i * m:(i + 1) * m][valid[i * m:(i + 1) * m]]
        if swivel and len(block):
            block = block[np.all((block[:, list(FLIP_JOINTS)] < 0.0) == np.array(pat), axis=1)]
        if len(block):
            block = _copies(arm, block)
        if margin > 0.0 and len(block):
            block = block[np.all(np.abs(block[:, list(FLIP_JOINTS)]) >= margin, axis=1)]
        if scene is not None and len(block):
            block = block[_free(arm, block, scene)]
        layers.append(block)
    return layers


def straight_route(arm: Any, q_start: Any, T_goal: Any, *, route_samples: int = ROUTE_SAMPLES,
                   swivel_samples: int = SWIVEL_SAMPLES, max_jump: float = MAX_JUMP, margin: float = 0.0,
                   scene: Any = None) -> RouteVerdict:
    """Is there a continuous in-limit straight route from ``q_start`` (rad) to the tool pose
    ``T_goal`` (4x4)? See the module docstring for the sampling, ``margin`` and ``scene``."""
    layers = route_nodes(arm, np.asarray(q_start, float), np.asarray(T_goal, float),
                         route_samples=route_samples, swivel_samples=swivel_samples, margin=margin,
                         scene=scene)
    nodes = tuple(len(x) for x in layers)
    parents: list[np.ndarray] = []
    reach = np.ones(1, dtype=bool)
    reached = 0
    for i in range(1, len(layers)):
        prev, cur = layers[i - 1][reach], layers[i]
        if len(prev) == 0 or len(cur) == 0:
            break
        idx_prev = np.flatnonzero(reach)
        best = np.full(len(cur), -1)
        link = np.ones((len(prev), len(cur)), dtype=bool)
        for j in range(cur.shape[1]):  # joint by joint: 2-D passes (a max over a short last axis is slow)
            link &= np.abs(prev[:, j, None] - cur[None, :, j]) <= max_jump
        ok = link.any(axis=0)
        best[ok] = idx_prev[np.argmax(link[:, ok], axis=0)]
        if not ok.any():
            break
        parents.append(best)
        reach = ok
        reached = i
    exists = reached == len(layers) - 1
    path = None
    if exists:
        k = int(np.flatnonzero(reach)[0])
        rows = []
        for i in range(len(layers) - 1, 0, -1):
            rows.append(layers[i][k])
            k = int(parents[i - 1][k])
        rows.append(layers[0][0])
        path = np.array(rows[::-1])
    return RouteVerdict(exists, reached / route_samples, path, nodes)
