"""geometry/self_collision: segment distances, key points in batch, known colliding and free postures for
every bundled arm, the ground plane, the configured pair lists against their derivation, and the park
postures."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.obstacles import ArmCapsules
from redarm_ros.geometry.self_collision import (
    GROUND,
    NON_ADJACENT_PAIRS,
    CollisionModel,
    collision_model,
    key_points_batch,
    pair_minima,
    parse_pairs,
    segment_distance,
    segment_distance_batch,
    self_collision,
    self_collision_batch,
)
from redarm_ros.kinematics import load_arm

ARMS = ["pa10", "pa10_7c", "powercube6", "powercube7"]
SEVEN = ["pa10", "pa10_7c", "powercube7"]
CAPS = ArmCapsules()


def _brute(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray, n: int = 2001) -> float:
    """Sample segment a densely; each sample's exact distance to segment b (clamped projection)."""
    P = a0 + np.linspace(0.0, 1.0, n)[:, None] * (a1 - a0)
    d = b1 - b0
    dd = float(d @ d)
    t = np.clip((P - b0) @ d / dd, 0.0, 1.0) if dd > 0.0 else np.zeros(n)
    return float(np.min(np.linalg.norm(P - (b0 + t[:, None] * d), axis=1)))


def test_segment_distance_matches_brute_force_and_batch() -> None:
    rng = np.random.default_rng(0)
    rows = []
    for k in range(600):
        a0, a1, b0, b1 = rng.normal(size=(4, 3))
        if k % 5 == 0:  # parallel
            b1 = b0 + (a1 - a0) * rng.normal()
        if k % 7 == 0:  # crossing
            b0, b1 = a0 + 0.5 * (a1 - a0) - (b1 - b0), a0 + 0.5 * (a1 - a0) + (b1 - b0)
        if k % 11 == 0:  # a point
            b1 = b0.copy()
        rows.append((a0, a1, b0, b1))
        d = segment_distance(a0, a1, b0, b1)
        bf = _brute(a0, a1, b0, b1)
        assert d <= bf + 1e-12  # never more than a sampled pair of points
        assert bf - d < 3e-3 * max(1.0, float(np.linalg.norm(a1 - a0) + np.linalg.norm(b1 - b0)))
    A = np.array(rows)
    db = segment_distance_batch(A[:, 0], A[:, 1], A[:, 2], A[:, 3])
    ds = np.array([segment_distance(*r) for r in rows])
    assert np.max(np.abs(db - ds)) < 1e-12


def test_segment_distance_exact_cases() -> None:
    o = np.zeros(3)
    ex, ey, ez = np.eye(3)
    assert segment_distance(o, ex, ey, ey + ez) == pytest.approx(1.0)  # skew, closest at the ends
    assert segment_distance(o, ex, 0.5 * ex + ey - ez, 0.5 * ex + ey + ez) == pytest.approx(1.0)
    assert segment_distance(o, ex, 2 * ex, 3 * ex) == pytest.approx(1.0)  # collinear, apart
    assert segment_distance(o, ex, 0.5 * ex, 0.5 * ex) == pytest.approx(0.0)  # a point on it
    assert segment_distance(o, o, ez, ez) == pytest.approx(1.0)  # two points


@pytest.mark.parametrize("name", ARMS)
def test_key_points_batch_equals_key_points(name: str) -> None:
    arm = load_arm(name)
    Q = np.random.default_rng(1).uniform(arm.lower, arm.upper, (50, arm.n))
    P = key_points_batch(arm, Q)
    for q, p in zip(Q, P, strict=True):
        assert np.max(np.abs(p - arm.key_points(q))) < 1e-12
    with pytest.raises(InvalidInputError):
        key_points_batch(arm, Q[:, :-1])
    with pytest.raises(InvalidInputError):
        key_points_batch(arm, np.full((1, arm.n), np.nan))


@pytest.mark.parametrize("name", ARMS)
def test_scalar_and_batch_agree(name: str) -> None:
    arm = load_arm(name)
    model = collision_model(arm)
    Q = np.random.default_rng(2).uniform(arm.lower, arm.upper, (300, arm.n))
    res = self_collision_batch(arm, Q, model=model)
    for i, q in enumerate(Q):
        sc = self_collision(arm, q, model=model)
        assert sc.min_distance == pytest.approx(res.min_distance[i], abs=1e-12)
        assert sc.self_distance == pytest.approx(res.self_distance[i], abs=1e-12)
        assert sc.ground_distance == pytest.approx(res.ground_distance[i], abs=1e-12)
        assert sc.colliding == bool(res.colliding[i])
        i_check, j_check = res.checks[res.closest[i]]
        assert sc.pair[0] == ["base", "upper_arm", "forearm", "hand"][i_check]
        assert (sc.pair[1] == GROUND) == (j_check == -1)


# Known colliding postures (deg), one per configured pair: the named pair overlaps.
COLLIDING = {
    # upper arm horizontal at the shoulder-pitch limit, elbow folded at its limit: the forearm comes back
    # down past the base column; turning the wrist by -90 deg brings the hand into it too
    "pa10": {(0, 2): [0, 91, 0, 137, 0, 0, 0], (0, 3): [0, 91, 0, 137, 0, -90, 0]},
    "pa10_7c": {(0, 2): [0, 91, 0, 137, 0, 0, 0], (0, 3): [0, 91, 0, 137, 0, -90, 0]},
    "powercube7": {(0, 2): [0, 115, 0, 115, 0, 0, 0], (0, 3): [0, 115, 0, 115, 0, -90, 0]},
    # the paper's two pairs: L56 folded back onto L1 (the base link) and onto L23 (the upper arm)
    "powercube6": {(0, 3): [0, 110, 0, 125, 90, 0], (1, 3): [0, 90, 0, -125, -115, 0]},
}

# Known free postures (deg): bent, clear of each other and above the ground.
FREE = {
    "pa10": [[0, 30, 0, 90, 0, 30, 0], [90, -45, 45, 60, -30, 90, 10], [0, 0, 0, 30, 0, 0, 0]],
    "pa10_7c": [[0, 30, 0, 90, 0, 30, 0], [90, -45, 45, 60, -30, 90, 10], [0, 0, 0, 30, 0, 0, 0]],
    "powercube7": [[0, 30, 0, 90, 0, 30, 0], [90, -45, 45, 60, -30, 90, 10], [0, 0, 0, 30, 0, 0, 0]],
    "powercube6": [[0, 30, 0, -30, -30, 0], [45, 60, 0, -90, 0, 90], [0, 0, 0, 0, 0, 0]],
}


@pytest.mark.parametrize("name", ARMS)
def test_known_colliding_postures(name: str) -> None:
    arm = load_arm(name)
    model = collision_model(arm, ground_z=None)  # the link pairs alone
    assert set(COLLIDING[name]) == set(model.pairs)
    for pair, deg in COLLIDING[name].items():
        q = np.radians(deg)
        assert arm.within_limits(q)
        only = CollisionModel((pair,), None, CAPS)
        sc = self_collision(arm, q, model=only)
        assert sc.colliding and sc.self_pair == pair, (pair, sc)
        assert self_collision(arm, q, model=model).colliding
        assert "overlap" in sc.describe()


@pytest.mark.parametrize("name", ARMS)
def test_known_free_postures(name: str) -> None:
    arm = load_arm(name)
    for deg in FREE[name]:
        q = np.radians(deg)
        sc = self_collision(arm, q)
        assert not sc.colliding and sc.min_distance > 0.0, (deg, sc)
        assert "clearance" in sc.describe()


def test_ground_plane() -> None:
    arm = load_arm("pa10")
    q = np.radians([0, 90, 0, 90, 0, 0, 0])  # upper arm horizontal, forearm straight down into the table
    sc = self_collision(arm, q)
    assert sc.colliding and sc.pair[1] == GROUND and sc.ground_distance < 0.0
    assert "below the ground plane" in sc.describe()
    assert self_collision(arm, q, ground_z=-1.0).ground_distance > 0.0  # a lower floor
    off = self_collision(arm, q, ground_z=None)
    assert off.ground_link == -1 and math.isinf(off.ground_distance)
    # the lowest point of the forearm capsule: wrist z - radius - plane
    wrist_z = arm.key_points(q)[3, 2]
    assert sc.ground_distance == pytest.approx(min(wrist_z - CAPS.radii[2], arm.fk(q)[2, 3] - CAPS.radii[3]))
    # the base link stands on the table: never a ground contact
    assert 0 not in collision_model(arm).ground_links


def test_powercube6_deck_plane() -> None:
    arm = load_arm("powercube6")
    model = collision_model(arm)
    assert model.ground_z == pytest.approx(-0.15)
    q = np.radians([0, -60, 0, 0, 0, 0])  # the whole arm pointing down past the deck
    sc = self_collision(arm, q, model=model)
    assert sc.colliding and sc.pair[1] == GROUND


def test_nothing_to_check() -> None:
    arm = load_arm("pa10")
    sc = self_collision(arm, np.zeros(7), model=CollisionModel((), None, CAPS))
    assert not sc.colliding and sc.pair == () and sc.describe() == "nothing to check"
    res = self_collision_batch(arm, np.zeros((3, 7)), model=CollisionModel((), None, CAPS))
    assert np.all(res.free) and np.all(res.closest == -1)


def test_bad_configuration_is_refused() -> None:
    with pytest.raises(ConfigError, match="adjacent"):
        parse_pairs([["base", "upper_arm"]])
    with pytest.raises(ConfigError, match="elbow"):
        parse_pairs([["base", "elbow"]])
    with pytest.raises(ConfigError):
        parse_pairs([["base"]])
    assert parse_pairs([["hand", "base"], [0, 3], ["upper_arm", "hand"]]) == ((0, 3), (1, 3))
    arm = load_arm("pa10")
    arm.config["self_collision"] = {"pairs": [["base", "hand"]], "floor": 0.0}
    with pytest.raises(ConfigError, match="floor"):
        collision_model(arm)
    with pytest.raises(InvalidInputError):
        collision_model(load_arm("pa10"), ground_z=math.nan)
    with pytest.raises(InvalidInputError):
        collision_model(load_arm("pa10"), ground_z="table")  # type: ignore[arg-type]


def test_arm_without_entry_checks_every_non_adjacent_pair() -> None:
    arm = load_arm("pa10")
    arm.config.pop("self_collision")
    m = collision_model(arm)
    assert m.pairs == NON_ADJACENT_PAIRS and m.ground_z is None


# ---------------------------------------------------------------------------------------------
# The configured pair lists, derived from the geometry
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ARMS)
def test_configured_pairs_are_the_ones_that_can_touch(name: str) -> None:
    """Sampling the joint limits: every configured pair overlaps somewhere, every other non-adjacent
    pair keeps a positive clearance (docs/kinematics.md gives the closed-form lower bounds)."""
    arm = load_arm(name)
    mins = pair_minima(arm, CAPS, samples=40_000, refine=30, rng_seed=3)
    configured = set(collision_model(arm).pairs)
    for pair, (d, q) in mins.items():
        assert arm.within_limits(q)
        if pair in configured:
            assert d < -0.02, (pair, d)
        else:
            assert d > 0.02, (pair, d)


@pytest.mark.parametrize(
    "name, bound", [("pa10", 0.146), ("pa10_7c", 0.142), ("powercube7", 0.095)]
)
def test_upper_arm_hand_lower_bound(name: str, bound: float) -> None:
    """The bound of the docs: dist(upper arm, hand) >= L3 sin(theta4_max) - L4 - r_upper - r_hand > 0,
    and sampling never goes below it."""
    arm = load_arm(name)
    L1, L2, L3, L4 = arm.link_lengths
    t4 = float(arm.upper[3])
    assert L3 * abs(math.cos(t4)) <= L2  # the foot of the wrist on the upper-arm line is on the segment
    lb = L3 * math.sin(t4) - L4 - CAPS.radii[1] - CAPS.radii[3]
    assert lb == pytest.approx(bound, abs=5e-4) and lb > 0
    d, _ = pair_minima(arm, CAPS, [(1, 3)], samples=20_000, refine=30, rng_seed=4)[(1, 3)]
    assert d >= lb - 1e-9


def test_powercube6_l1_l4_lower_bound() -> None:
    """The paper's eq. 7 in capsule form: dist(L1, L4) >= |S W|_min - L1 - r_base - r_forearm > 0, with
    the wrist W at least sqrt(L23^2 + L4^2 - 2 L23 L4 cos(pi - phi4_max)) from the shoulder S."""
    arm = load_arm("powercube6")
    L1, L23, L4, L56 = arm.link_lengths
    gamma = math.pi - float(arm.upper[3])  # smallest elbow angle between L23 and L4
    assert L23 * math.cos(gamma) > L4  # the foot from S on the L4 line lies beyond the wrist
    sw = math.sqrt(L23**2 + L4**2 - 2 * L23 * L4 * math.cos(gamma))
    lb = sw - L1 - CAPS.radii[0] - CAPS.radii[2]
    assert lb == pytest.approx(0.026, abs=5e-4) and lb > 0
    assert L1 + L4 + 0.05 == pytest.approx(L23)  # eq. 7: L1 + L4 + dd < L23 holds for dd < 5 cm
    d, _ = pair_minima(arm, CAPS, [(0, 2)], samples=20_000, refine=30, rng_seed=5)[(0, 2)]
    assert d >= lb - 1e-9


# ---------------------------------------------------------------------------------------------
# Park postures
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ARMS)
def test_park_posture_in_limits_collision_free_and_bent(name: str) -> None:
    arm = load_arm(name)
    q = arm.park
    assert q is not None and q.shape == (arm.n,)
    assert np.all(q >= arm.lower) and np.all(q <= arm.upper)
    assert not self_collision(arm, q).colliding
    assert abs(q[3]) > math.radians(30)  # elbow bent: not the stretched zero pose


def test_park_loader_validation() -> None:
    assert load_arm("pa10", park=[0.1] * 7).park == pytest.approx([0.1] * 7)
    with pytest.raises(ConfigError, match="outside its limits"):
        load_arm("pa10", park=[4.0] * 7)
    with pytest.raises(ConfigError, match="7 finite numbers"):
        load_arm("pa10", park=[0.0] * 6)
    with pytest.raises(ConfigError):
        load_arm("pa10", park=[math.nan] * 7)
    # other limits than the YAML's: the YAML posture no longer fits, so the model has none
    assert load_arm("pa10", lower=[-0.1] * 7, upper=[0.1] * 7).park is None
    assert load_arm("pa10", lower=[-0.1] * 7, upper=[0.1] * 7, park=[0.05] * 7).park is not None


@pytest.mark.parametrize("name", ARMS)
def test_every_bundled_arm_enters_the_geometry_through_its_protocols(name: str) -> None:
    from redarm_ros.geometry.arm import ChainArm, KeyPointArm

    arm = load_arm(name)
    assert isinstance(arm, ChainArm) and isinstance(arm, KeyPointArm)
    assert all(hasattr(j, "origin") and hasattr(j, "axis") for j in arm.chain)
