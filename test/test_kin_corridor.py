"""The swivel corridor of a straight route (kinematics/corridor.py) against a dense sampling oracle.

The oracle samples the route 40 times and the swivel 180 times, keeps every solution on the start's flip
pattern (every 2 pi copy of the wide joints) that keeps the bounds, and links solutions of neighbouring
samples (and of the same sample) whose joints differ by at most 0.35 rad. Random routes on the PA10 and
the PowerCube 7 arm, and routes built from the kinematics: a corridor that narrows below 0.1 deg, a
schedule that runs past pi, the elbow passing over the shoulder, a route whose corridor closes. Every
schedule is checked by FK (each sample's joints give the route's pose to 1e-9) and by the bounds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics import SwivelCorridor, load_arm, route_pose, swivel_corridor

TWO_PI = 2.0 * math.pi
ARMS = {name: load_arm(name) for name in ("pa10", "powercube7")}


def oracle(arm, T0, T1, q0, pattern, *, shoulder=0.0, wrist=0.0, elbow=0.0, n_u=40, n_s=180, link=0.35):
    """(found, first progress without a linked solution) of the dense sampling oracle."""
    lo, up = np.asarray(arm.lower, float), np.asarray(arm.upper, float)
    wide = [j for j in range(7) if up[j] - lo[j] > TWO_PI]
    offsets = np.zeros((1, 7))
    for j in wide:
        offsets = np.concatenate([offsets + k * TWO_PI * np.eye(7)[j] for k in (-2, -1, 0, 1, 2)])
    ss = np.linspace(-math.pi, math.pi, n_s, endpoint=False)
    prev = reach = None
    for k in range(n_u + 1):
        u = k / n_u
        T = route_pose(T0, T1, u)
        rows = [arm.ik(T, float(s), limits=False) for s in ss]
        base = np.array([r[pattern] for r in rows if len(r) == 8]).reshape(-1, 7)
        Q = (base[:, None, :] + offsets[None, :, :]).reshape(-1, 7)
        keep = np.all((Q >= lo) & (Q <= up), axis=1) & (np.abs(np.sin(Q[:, 1])) >= shoulder) \
            & (np.abs(np.sin(Q[:, 5])) >= wrist) & (np.abs(Q[:, 3]) >= elbow)
        Q = Q[keep]
        if k == 0:
            Q = np.vstack([q0[None], Q])
            r = np.zeros(len(Q), bool)
            r[0] = True
        else:
            if len(Q) == 0:
                return False, u
            r = (np.abs(prev[reach][:, None, :] - Q[None, :, :]).max(axis=2) <= link).any(axis=0)
        while True:  # along the sample too
            r2 = r | (np.abs(Q[r][:, None, :] - Q[None, :, :]).max(axis=2) <= link).any(axis=0)
            if r2.sum() == r.sum():
                break
            r = r2
        if not r.any():
            return False, u
        prev, reach = Q, r
    return True, 1.0


def check_schedule(arm, T0, T1, cor: SwivelCorridor, *, shoulder, wrist, elbow=0.0, limit=0.0) -> None:
    """FK, bounds, continuity, flip pattern and the start of a found schedule."""
    assert cor.found, cor.reason
    assert cor.u[0] == 0.0 and cor.u[-1] == 1.0 and np.all(np.diff(cor.u) > 0)
    lo, up = np.asarray(arm.lower) + limit, np.asarray(arm.upper) - limit
    for u, s, q in zip(cor.u, cor.swivel, cor.q, strict=True):
        assert np.abs(arm.fk(q) - route_pose(T0, T1, u)).max() <= 1e-9
        assert np.all(q >= lo - 1e-9) and np.all(q <= up + 1e-9)
        assert abs(math.sin(q[1])) >= shoulder - 1e-9 and abs(math.sin(q[5])) >= wrist - 1e-9
        assert abs(q[3]) >= elbow - 1e-9
        assert abs(math.remainder(arm.swivel(q) - s, TWO_PI)) <= 1e-6
        rows = arm.ik(route_pose(T0, T1, u), float(s), limits=False)
        assert np.abs(np.remainder(rows[cor.pattern] - q + math.pi, TWO_PI) - math.pi).max() <= 1e-9
    steps = np.abs(np.diff(cor.q, axis=0)).max(axis=1)
    assert steps.max() <= cor.max_joint_step + 1e-12
    assert cor.max_joint_step <= 0.1 + 1e-12


def random_route(arm, rng, spread=0.5):
    lo, up = np.asarray(arm.lower), np.asarray(arm.upper)
    while True:
        q0 = rng.uniform(0.8 * lo, 0.8 * up)
        q1 = np.clip(q0 + rng.normal(0.0, spread, 7), lo, up)
        if min(abs(math.sin(q0[1])), abs(math.sin(q0[5]))) > 0.1 and abs(q0[3]) > 0.1:
            return q0, arm.fk(q0), arm.fk(q1)


@pytest.mark.parametrize("name", ["pa10", "powercube7"])
def test_random_routes_agree_with_the_oracle(name):
    """Found schedules pass every check; the corridor (margin 0.02) is found wherever the oracle links
    a route with wider margins (0.04), and the oracle (margin 0.01) finds every route the corridor finds."""
    arm = ARMS[name]
    rng = np.random.default_rng(7)
    found = 0
    for _ in range(5):
        q0, T0, T1 = random_route(arm, rng, spread=0.4)
        cor = arm.swivel_corridor(T0, T1, q0, shoulder_margin=0.02, wrist_margin=0.02, elbow_margin=0.0,
                                  max_rate=TWO_PI)
        wide_ok, _ = oracle(arm, T0, T1, q0, cor.pattern, shoulder=0.04, wrist=0.04)
        narrow_ok, _ = oracle(arm, T0, T1, q0, cor.pattern, shoulder=0.01, wrist=0.01)
        if cor.found:
            check_schedule(arm, T0, T1, cor, shoulder=0.02, wrist=0.02)
            assert narrow_ok
            found += 1
        else:
            assert not wide_ok, cor.reason
            assert cor.closed_at is not None and cor.reason
    assert found >= 3


def _q2_max(arm, T):
    """The largest q2 over the swivel circle of pose T (base pattern), in closed form: q2 = acos(Z2(s))
    with Z2 = k0 + k1 cos s + k2 sin s, and where it is."""
    k0, k1, k2 = arm.swivel_functions(T).K[8]
    return math.acos(k0 - math.hypot(k1, k2)), math.atan2(-k2, -k1)


def test_narrow_corridor_below_a_tenth_of_a_degree():
    """The shoulder margin set so that at the goal only the swivels within 5e-8 rad of the lowest elbow
    keep it (a window about 0.07 deg wide), the corridor wider before: found, ending in the window, its
    narrowest width below 0.1 deg at the goal."""
    arm = ARMS["powercube7"]
    rng = np.random.default_rng(5)
    T0 = arm.fk(np.array([0.2, 0.3, 0.1, 1.0, 0.2, 0.8, 0.1]))
    g0, s0 = _q2_max(arm, T0)
    q0 = next(q for q in arm.ik(T0, s0) if q[1] > 0.0)
    for _ in range(50):
        T1 = arm.fk(np.array([0.2, 0.3, 0.1, 1.0, 0.2, 0.8, 0.1]) + rng.normal(0.0, 0.3, 7))
        g1, s1 = _q2_max(arm, T1)
        inner = min(_q2_max(arm, route_pose(T0, T1, u))[0] for u in np.linspace(0.0, 0.97, 40))
        if 0.3 < g1 < inner - 1e-3 and g1 < g0:
            break
    else:
        pytest.fail("no seeded route whose lowest elbow rises towards the goal")
    margin = math.sin(g1 - 5e-8)
    cor = arm.swivel_corridor(T0, T1, q0, shoulder_margin=margin, max_rate=TWO_PI)
    check_schedule(arm, T0, T1, cor, shoulder=margin, wrist=0.05, elbow=0.05)
    assert cor.narrowest < math.radians(0.1) and cor.narrowest_u == 1.0
    assert abs(math.remainder(cor.swivel[-1] - s1, TWO_PI)) < math.radians(0.05)
    off = arm.ik(T1, s1 + math.radians(0.05), limits=False)[cor.pattern]
    assert math.sin(off[1]) < margin  # just beside the window the margin is broken


def test_schedule_runs_past_pi():
    """A start swivel just below pi and a preferred swivel beyond it: the schedule crosses pi on the
    unwrapped axis, continuous, and the oracle links the route too."""
    arm = ARMS["powercube7"]
    rng = np.random.default_rng(3)
    for _ in range(200):
        q0, T0, T1 = random_route(arm, rng, spread=0.2)
        s0 = arm.swivel(q0)
        if 2.7 < s0 < 3.05:
            cor = arm.swivel_corridor(T0, T1, q0, preferred=s0 + 0.8 - TWO_PI, max_rate=TWO_PI)
            if cor.found and cor.swivel[-1] > math.pi + 0.2:
                break
    else:
        pytest.fail("no route with a corridor across pi among the seeded ones")
    check_schedule(arm, T0, T1, cor, shoulder=0.05, wrist=0.05, elbow=0.05)
    assert np.any(cor.swivel > math.pi) and cor.swivel[0] < math.pi
    assert oracle(arm, T0, T1, q0, cor.pattern, shoulder=0.05, wrist=0.05, elbow=0.05)[0]


def test_elbow_passing_over_the_shoulder():
    """A route through a pose whose start swivel puts the elbow straight above the shoulder (q2 = 0):
    held at that swivel the arm would pass the shoulder singularity; the schedule turns the elbow round
    it, keeping |sin q2| >= the margin, and the oracle agrees."""
    arm = ARMS["pa10"]
    q_mid = np.array([0.4, 0.0, 0.3, 1.3, 0.5, 1.0, 0.2])
    T_mid = arm.fk(q_mid)
    s_mid = arm.swivel(q_mid)
    v = np.array([0.12, -0.08, 0.0])
    T0, T1 = T_mid.copy(), T_mid.copy()
    T0[:3, 3] -= v
    T1[:3, 3] += v
    rows = arm.ik(T0, s_mid)
    q0 = rows[np.argmax(np.abs(np.sin(rows[:, 1])))]
    held = arm.ik(route_pose(T0, T1, 0.5), s_mid, limits=False)
    assert np.min(np.abs(np.sin(held[:, 1]))) < 1e-9  # the held swivel meets the singularity
    cor = arm.swivel_corridor(T0, T1, q0, shoulder_margin=0.05, preferred=s_mid, max_rate=TWO_PI)
    check_schedule(arm, T0, T1, cor, shoulder=0.05, wrist=0.05, elbow=0.05)
    k = int(np.argmin(np.abs(cor.u - 0.5)))
    assert abs(math.remainder(cor.swivel[k] - s_mid, TWO_PI)) > 0.01  # it went round
    assert oracle(arm, T0, T1, q0, cor.pattern, shoulder=0.05, wrist=0.05, elbow=0.05)[0]


def test_route_whose_corridor_closes():
    """The wrist passing close to the shoulder: the elbow would have to fold beyond joint 4's limit at
    every swivel. Not found, closed in the middle, joint 4 named; the oracle finds nothing either."""
    arm = ARMS["powercube7"]
    T0 = np.eye(4)
    T0[:3, 3] = [0.45, -0.25, 0.3]
    T1 = T0.copy()
    T1[:3, 3] = [-0.1, 0.3, 0.3]
    q0, info = arm.ik_nearest(T0, np.array(arm.park))
    assert q0 is not None, info
    cor = arm.swivel_corridor(T0, T1, q0)
    assert not cor.found
    assert cor.closed_at is not None and 0.1 < cor.closed_at < 0.9
    assert "joint 4" in cor.reason
    assert len(cor.u) and cor.u[-1] < cor.closed_at  # the schedule up to where it closed
    assert not oracle(arm, T0, T1, q0, cor.pattern, shoulder=0.05, wrist=0.05, elbow=0.05)[0]


def test_a_schedule_riding_a_curved_bound_is_not_halved_to_min_du():
    """PA10 from its ready posture to the first goal of reach_quality_bench's free45 case, with the
    margins of the controller's first attempt: the schedule rides the shoulder margin along a stretch,
    where the chord between two samples sags past it by about 1e-4 rad, a sag that halving shrinks only
    4 times per step (halved down to min_du / 16 that made 825 samples). Each step's midpoint passes a
    bound by at most MID_SHARE of its margin, and far fewer samples do."""
    from redarm_ros.kinematics.corridor import MID_SHARE

    arm = ARMS["pa10"]
    q0 = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])
    T0, T1 = arm.fk(q0), np.eye(4)
    T1[:3] = [[-0.8569785693731684, 0.3889759611626206, 0.33806128626734644, 0.3929507043394475],
              [0.4114140926630704, 0.911430263123888, -0.005772332296615619, 0.7600314115756154],
              [-0.31036458559787383, 0.13413641228069073, -0.9411063951047854, 0.4594049181314856]]
    m = {"limit": 0.05, "shoulder": 0.4314829847437827, "wrist": 0.45, "elbow": 0.45}
    cor = arm.swivel_corridor(T0, T1, q0, limit_margin=m["limit"], shoulder_margin=m["shoulder"],
                              wrist_margin=m["wrist"], elbow_margin=m["elbow"], max_rate=1.0, samples=12)
    check_schedule(arm, T0, T1, cor, shoulder=m["shoulder"], wrist=m["wrist"], elbow=m["elbow"],
                   limit=m["limit"])
    assert len(cor.u) < 200
    sh, wr = math.asin(m["shoulder"]), math.asin(m["wrist"])
    lo, up = np.asarray(arm.lower) + m["limit"], np.asarray(arm.upper) - m["limit"]
    riding = 0
    for i in range(1, len(cor.u)):
        um = 0.5 * (cor.u[i - 1] + cor.u[i])
        sm = 0.5 * (cor.swivel[i - 1] + cor.swivel[i])
        qm = arm.ik(route_pose(T0, T1, um), sm, limits=False)[cor.pattern]
        qm = qm + TWO_PI * np.round((cor.q[i - 1] - qm) / TWO_PI)
        assert np.all(qm >= lo - MID_SHARE * m["limit"]) and np.all(qm <= up + MID_SHARE * m["limit"])
        assert sh * (1.0 - MID_SHARE) <= abs(qm[1]) <= math.pi - sh * (1.0 - MID_SHARE)
        assert wr * (1.0 - MID_SHARE) <= abs(qm[5]) <= math.pi - wr * (1.0 - MID_SHARE)
        assert abs(qm[3]) >= m["elbow"] * (1.0 - MID_SHARE)
        riding += abs(qm[1]) < sh - 1e-9
    assert riding  # (the case in point: some midpoints do pass the shoulder margin)


def test_bad_input_is_refused():
    arm = ARMS["pa10"]
    q0 = np.array([0.3, 0.35, 0.2, 1.4, 0.3, 0.9, 0.1])
    T0 = arm.fk(q0)
    with pytest.raises(InvalidInputError, match="q_start"):
        swivel_corridor(arm, T0, T0, q0 + 0.1)
    with pytest.raises(InvalidInputError, match="shoulder_margin"):
        arm.swivel_corridor(T0, T0, q0, shoulder_margin=0.0)
    with pytest.raises(InvalidInputError, match="max_rate"):
        arm.swivel_corridor(T0, T0, q0, max_rate=-1.0)
    cor = arm.swivel_corridor(T0, T0, q0)  # no motion: the start swivel throughout
    assert cor.found and np.allclose(cor.swivel, arm.swivel(q0))


def test_the_speed_guide_lowers_the_joints_path_speed_demand():
    """A PA10 line passing near the shoulder axis: the schedule nearest the start swivel turns joint 1
    at 15 times its speed per unit progress; on the speed guide (the least largest |dq/du| over the
    joints' speeds, weighted by the minimum-jerk profile) at 12, the schedule keeping the bounds and the
    route's poses."""
    arm = ARMS["pa10"]
    q0 = np.array([1.2999125794864783, -0.6065520243287214, -0.019005298270521, -1.0164191446634179,
                   2.6314811019964726, 1.4905848010482132, -1.7073761691289138])
    T1 = np.eye(4)
    T1[:3, 3] = [-0.5149858994923524, 0.40000454424521975, 0.8102976233400754]
    T1[:3, :3] = [[-0.9403096969527954, 0.2999003693222375, 0.16086467075441946],
                  [0.3290791526687879, 0.9217433450550282, 0.20517338308260152],
                  [-0.08674436636078929, 0.24586373121538874, -0.9654151648785678]]
    T0 = arm.fk(q0)
    speeds = np.array([0.7, 0.7, 1.4, 1.4, 4.4, 4.4, 4.4, 1.0])  # joints' speeds (rad/s), then the swivel
    opts = {"limit_margin": 0.05, "shoulder_margin": 0.15, "wrist_margin": 0.15, "elbow_margin": 0.15,
            "max_rate": 4.0, "samples": 12}

    def demand(c: SwivelCorridor) -> float:
        u = np.linspace(0.0, 1.0, 401)
        Q = np.stack([np.interp(u, c.u, c.q[:, j]) for j in range(7)], axis=1)
        return float(np.max(np.abs(np.gradient(Q, u, axis=0)) / speeds[:7]))

    plain = swivel_corridor(arm, T0, T1, q0, **opts)
    guided = swivel_corridor(arm, T0, T1, q0, speed_rates=speeds, **opts)
    assert plain.found and guided.found
    assert demand(guided) < 0.85 * demand(plain), (demand(guided), demand(plain))
    lo, up = np.asarray(arm.lower) + 0.05 - 1e-9, np.asarray(arm.upper) - 0.05 + 1e-9
    assert np.all(guided.q >= lo) and np.all(guided.q <= up)
    assert np.min(np.abs(np.sin(guided.q[:, 1]))) >= 0.15 - 1e-9
    for u, q in zip(guided.u, guided.q, strict=True):
        assert np.allclose(arm.fk(q), route_pose(T0, T1, float(u)), atol=1e-9)
    with pytest.raises(InvalidInputError):
        swivel_corridor(arm, T0, T1, q0, speed_rates=speeds[:7], **opts)


def test_the_schedule_between_samples_has_no_rate_corners_and_no_overshoot():
    """swivel_at: the rate is continuous at a sample where the schedule bends (linear interpolation
    jumps from 2 to 1 rad per unit progress there), and between samples the swivel stays within its
    neighbours' (a schedule turning back at a sample does not pass it)."""
    u = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    cor = SwivelCorridor(True, u, np.array([0.0, 0.5, 0.75, 1.0, 0.5]), np.zeros((5, 7)), 0, 1.0, 0.5,
                         None, "", 0.1)
    e = 1e-6
    left = (cor.swivel_at(0.25) - cor.swivel_at(0.25 - e)) / e
    right = (cor.swivel_at(0.25 + e) - cor.swivel_at(0.25)) / e
    assert abs(left - right) < 1e-3 and 1.0 < left < 2.0
    assert cor.swivel_at(0.0) == 0.0 and cor.swivel_at(1.0) == 0.5 and cor.swivel_at(0.5) == 0.75
    xs = np.linspace(0.5, 1.0, 201)
    assert max(cor.swivel_at(float(x)) for x in xs) <= 1.0 + 1e-12  # the turn at u = 0.75
    assert cor.swivel_at(-1.0) == 0.0 and cor.swivel_at(2.0) == 0.5
