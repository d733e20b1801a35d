"""pybullet plant: step tracking within the velocity limit, gravity hold, tool pose, scene, snapshots."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from redarm_ros.errors import InvalidInputError
from redarm_ros.geometry.obstacles import load_scene
from redarm_ros.kinematics import load_arm
from redarm_ros.sim import plant as plant_module
from redarm_ros.sim.plant import FIXED_POINT_PROBE_STEPS, PybulletPlant


@pytest.fixture
def pa10():
    plant = PybulletPlant.create(load_arm("pa10"), initial_q=[0, 0.3, 0, 0.6, 0, 0.4, 0])
    yield plant
    plant.close()


def test_step_is_tracked_within_velocity_limit(pa10):
    arm = pa10.arm
    q0 = pa10.q
    target = q0 + np.array([0.8, 0.5, -0.7, 0.9, 1.5, -1.2, 2.0])
    for i, j in enumerate(pa10.joints):
        j.command_position(float(target[i]))
    assert all(j.in_motion() for j in pa10.joints)
    track, peak, steps = 0.0, np.zeros(arm.n), 0
    while pa10.busy() and steps < 10000:
        pa10.step()
        steps += 1
        track = max(track, float(np.abs(pa10.q - pa10.q_setpoint).max()))
        peak = np.maximum(peak, np.abs(pa10.dq))
    pa10.step(20)
    assert not any(j.in_motion() for j in pa10.joints)
    assert np.abs(pa10.q - target).max() < 1e-5
    assert track < 1e-4  # rad, measured joint vs setpoint during the whole move
    assert np.all(peak <= arm.max_vel * 1.01)  # measured speed, the 1 % is the physics' jitter
    # trapezoid or triangle: the peak speed is the limit or sqrt(acc * distance), whichever is lower
    expected = np.minimum(arm.max_vel, np.sqrt(arm.max_acc * np.abs(target - q0)))
    assert np.all(np.abs(peak / expected - 1) < 0.01)
    # the slowest joint needs at least distance / max_vel (simulated time, not wall clock)
    assert steps * pa10.dt >= float(np.max(np.abs(target - q0) / arm.max_vel))
    T = pa10.tool_transform()
    Tf = arm.fk(pa10.q)
    assert np.abs(T - Tf).max() < 1e-6


def test_gravity_is_on_and_the_arm_holds_an_outstretched_pose(pa10):
    q = np.array([0.0, 1.5, 0.0, 0.0, 0.0, 0.0, 0.0])  # horizontal arm: largest shoulder torque
    pa10.reset_joints(q)
    pa10.step(1000)
    assert np.abs(pa10.q - q).max() < 1e-5
    pa10.reset_joints([0, 0.5, 0, 0, 0, 0, 0])
    pa10._forces = [1e-3] * pa10.n  # a limp arm must fall: gravity really acts
    pa10.step(1000)
    assert pa10.q[1] > 1.0


def _settle(plant: PybulletPlant, limit: int = 5000) -> None:
    """Step until pybullet is no longer stepped every step (the held arm reached its rest)."""
    for _ in range(limit // 10):
        before = plant.physics_steps
        plant.step(10)
        if plant.physics_steps - before < 10:
            return
    raise AssertionError("a held arm never came to rest")


def test_a_held_arm_advances_simulated_time_without_stepping_pybullet(pa10):
    _settle(pa10)
    q, steps, physics = pa10.q, pa10.steps, pa10.physics_steps
    pa10.step(3 * FIXED_POINT_PROBE_STEPS)
    assert pa10.steps == steps + 3 * FIXED_POINT_PROBE_STEPS
    assert pa10.sim_time == pytest.approx(pa10.steps * pa10.dt)
    assert 1 <= pa10.physics_steps - physics <= 4  # only the periodic probes
    assert np.array_equal(pa10.q, q)


def test_a_command_after_rest_moves_the_arm_as_if_pybullet_had_stepped_all_along(monkeypatch):
    arm, q0 = load_arm("pa10"), [0.3, 0.8, 0.2, -1.2, 0.4, 0.9, 0.1]

    def trajectory(probe_steps: int) -> tuple[np.ndarray, int]:
        monkeypatch.setattr(plant_module, "FIXED_POINT_PROBE_STEPS", probe_steps)
        plant = PybulletPlant.create(arm, initial_q=q0)
        try:
            plant.step(2500)  # settled, and resting a while
            plant.joint(1).command_position(1.2)
            plant.joint(5).command_position(0.5, 0.5, None, None)
            rows = []
            for _ in range(1500):
                plant.step()
                rows.append(np.concatenate([plant.q, plant.dq, plant.q_setpoint]))
            return np.array(rows), plant.physics_steps
        finally:
            plant.close()

    stepped_always, n_always = trajectory(1)  # a probe every step: pybullet steps every step
    coasting, n_coasting = trajectory(FIXED_POINT_PROBE_STEPS)
    assert n_always == 4000 and n_coasting < n_always
    n = coasting.shape[1] // 3
    # positions and setpoints bit for bit (the first moving step is the same step); the velocities of a
    # resting arm are rounding noise either way
    assert np.array_equal(coasting[:, :n], stepped_always[:, :n])
    assert np.array_equal(coasting[:, 2 * n:], stepped_always[:, 2 * n:])
    assert np.abs(coasting[:, n:2 * n] - stepped_always[:, n:2 * n]).max() < 1e-12


def test_a_resting_arm_that_starts_to_drift_is_stepped_again(pa10):
    pa10.reset_joints([0, 0.5, 0, 0, 0, 0, 0])
    _settle(pa10)
    pa10._forces = [1e-3] * pa10.n  # the motors give way while nothing is stepped
    pa10.step(FIXED_POINT_PROBE_STEPS)  # the probe sees the first bit move
    physics = pa10.physics_steps
    pa10.step(1000)
    assert pa10.physics_steps == physics + 1000
    assert pa10.q[1] > 1.0  # the arm falls: no rest hides it


def test_a_scene_with_a_loose_object_is_stepped_every_step(pa10):
    pa10.add_sphere([1.0, 1.0, 0.05], 0.05, mass=0.5)
    pa10.step(3000)
    physics = pa10.physics_steps
    pa10.step(500)
    assert pa10.physics_steps == physics + 500


def test_velocity_halt_and_hold(pa10):
    j = pa10.joint(0)
    j.command_velocity(0.5)
    pa10.step(1500)
    assert j.velocity() == pytest.approx(0.5, abs=1e-3) and j.in_motion()
    j.halt()
    pa10.step(400)
    assert abs(j.velocity()) < 1e-3 and not j.in_motion()
    before = j.position()
    pa10.step(200)
    assert j.position() == pytest.approx(before, abs=1e-6)
    assert j.setpoint() == pytest.approx(before, abs=1e-5)


def test_two_plants_in_two_clients_are_independent():
    a = PybulletPlant.create(load_arm("powercube6"))
    b = PybulletPlant.create(load_arm("powercube7"))
    try:
        assert a.cid != b.cid
        a.joint(0).command_position(0.5)
        a.run_until_idle(timeout_s=5.0)
        b.step(100)
        assert a.q[0] == pytest.approx(0.5, abs=1e-5)
        assert np.abs(b.q).max() < 1e-5
    finally:
        a.close()
        b.close()


def test_scene_objects_and_snapshot(pa10, tmp_path):
    empty = pa10.render(160, 120)
    ids = pa10.add_scene(load_scene("table_cylinder").to_dict())  # table top + one can
    ids += [
        pa10.add_object({"type": "sphere", "center": [0.5, 0.2, 0.5], "radius": 0.06}),
        pa10.add_object(
            {
                "type": "box",
                "center": [0.7, 0.0, 0.45],
                "size": [0.1, 0.1, 0.1],
                "yaw": 0.3,
                "rgba": [1, 0, 0, 1],
            }
        ),
    ]
    assert len(set(ids)) == 4 and pa10.objects == ids
    path = pa10.snapshot_png(tmp_path / "snap.png", 160, 120)
    img = np.asarray(Image.open(path))
    assert img.shape == (120, 160, 3)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10  # not a blank image
    assert np.abs(img.astype(int) - empty.astype(int)).sum() > 0  # the objects are in view
    with pytest.raises(InvalidInputError):
        pa10.add_object({"type": "torus", "position": [0, 0, 0]})
    with pytest.raises(InvalidInputError):
        pa10.add_object({"type": "sphere", "position": [0, 0, 0]})  # no radius
    with pytest.raises(InvalidInputError):
        pa10.add_sphere([0, 0, float("nan")], 0.1)
    with pytest.raises(InvalidInputError):
        PybulletPlant.create(pa10.arm, initial_q=[0.0] * 3)
