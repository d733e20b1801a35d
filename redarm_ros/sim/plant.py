"""The pybullet plant: one simulated arm in one pybullet client, stepped at 1 kHz.

* Fixed base at the world origin, gravity on (``-z``), physics time step 1 ms by default.
* Each joint has a :class:`~redarm_ros.sim.ramp.JointRamp` setpoint generator honouring the joint's max
  velocity and acceleration; every step its setpoint is fed to pybullet's ``POSITION_CONTROL`` with unit
  gains and a large force, so the measured joint tracks the setpoint within about a microradian.
* A held arm that came to rest is not stepped in pybullet (simulated time still advances; a probe step
  every second): see :data:`FIXED_POINT_PROBE_STEPS`.
* :meth:`PybulletPlant.joint` returns per-joint adapters implementing the PowerCube module emulator's
  plant interface (``command_position``, ``command_velocity``, ``halt``, ``position``, ``velocity``,
  ``in_motion``). Those adapters only touch plain Python state under a lock and never call pybullet,
  so a bus thread may use them while the physics thread steps.
* Scene objects (spheres, cylinders, boxes; static by default) can be added for demos and obstacle tests.
* :meth:`PybulletPlant.snapshot_png` renders headless with pybullet's TinyRenderer and writes a PNG with
  Pillow (:func:`redarm_ros.record.animate.write_png`).

Every pybullet call goes to the client id given explicitly; there are no module-level client globals.
All pybullet calls (``step``, ``tool_pose``, ``add_*``, ``snapshot_png``) must come from one thread.
Quaternions at this API are pybullet's order (x, y, z, w); units SI, rad.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError, RedarmError
from redarm_ros.record.animate import write_png
from redarm_ros.sim.ramp import JointRamp
from redarm_ros.sim.urdf import build_urdf, joint_efforts, link_bodies, link_names, urdf_visuals

_LOG = logging.getLogger(__name__)

DEFAULT_TIME_STEP = 1e-3  # s
# POSITION_CONTROL motor gains. Measured on a 7-joint arm: kp = kd = 1 with target velocity 0 makes the
# motor constraint reach the new setpoint within the step (tracking error < 1e-6 rad at 2 rad/s), while
# kp = 0.3 with a velocity feed-forward lags a whole step (2e-3 rad at 2 rad/s).
POSITION_GAIN = 1.0
VELOCITY_GAIN = 1.0
# A held arm settles where a pybullet step with the same setpoints leaves every joint position bit for
# bit unchanged (the velocities are rounding noise, ~1e-14 rad/s): a motion of 1e-13 rad in the step
# would have shown, so the arm is at rest to that bound. From there :meth:`PybulletPlant.step` advances
# simulated time without pybullet until a setpoint changes, and still steps pybullet once every
# FIXED_POINT_PROBE_STEPS steps, which ends this at the first bit a drift would move.
FIXED_POINT_PROBE_STEPS = 1000
FIXED_POINT_SPEED = 1e-9  # rad/s; a measured joint speed above this is never taken for rest
FORCE_SCALE = 10.0  # motor force = FORCE_SCALE * URDF effort (N m); 5 was already enough under gravity
MOTION_EPS = 1e-3  # rad/s; measured speed above this counts as "in motion"


@contextlib.contextmanager
def quiet_stdio() -> Iterator[None]:
    """Silence file descriptors 1 and 2 for the block (pybullet prints from C on import and connect).

    Works on the descriptors themselves, so it also holds under pytest's capture, where
    ``sys.stdout`` has no real descriptor.
    """
    for s in (sys.stdout, sys.stderr):
        if s is not None:
            s.flush()
    saved = []
    try:
        for fd in (1, 2):
            try:
                saved.append((fd, os.dup(fd)))
            except OSError:  # descriptor not open: nothing to silence
                continue
        with open(os.devnull, "wb") as null:
            for fd, _ in saved:
                os.dup2(null.fileno(), fd)
        yield
    finally:
        for fd, keep in saved:
            os.dup2(keep, fd)
            os.close(keep)


def _pybullet() -> Any:
    with quiet_stdio():
        import pybullet

    return pybullet


def connect(gui: bool = False) -> int:
    """Open a pybullet client (DIRECT, or GUI if asked) quietly and return its id."""
    pb = _pybullet()
    with quiet_stdio():
        cid = pb.connect(pb.GUI if gui else pb.DIRECT)
    if cid < 0:
        raise RuntimeError("pybullet could not connect (GUI needs a display)")
    return int(cid)


def _under_plant_lock(method: Callable[..., Any]) -> Callable[..., Any]:
    """A :class:`JointPlant` method that runs the :class:`JointRamp` ``method`` on the joint's ramp
    under :attr:`PybulletPlant.lock`."""

    @functools.wraps(method)
    def call(self: JointPlant, *args: Any, **kwargs: Any) -> Any:
        with self._plant.lock:
            return method(self.ramp, *args, **kwargs)

    return call


class JointPlant:
    """One joint seen as a PowerCube module's plant. Thread-safe; never calls pybullet.

    Positions in rad, velocities rad/s, accelerations rad/s^2, durations s.
    """

    def __init__(self, plant: PybulletPlant, index: int) -> None:
        self._plant = plant
        self.index = index

    @property
    def ramp(self) -> JointRamp:
        """The setpoint generator (read it under :attr:`PybulletPlant.lock`)."""
        return self._plant._ramps[self.index]

    # JointRamp.command_position (same arguments and doc), under the plant lock.
    command_position = _under_plant_lock(JointRamp.command_position)

    def command_velocity(self, velocity: float, acc_limit: float | None = None) -> None:
        """Ramp to ``velocity`` (rad/s); the setpoint brakes to rest before a joint limit."""
        with self._plant.lock:
            self.ramp.command_velocity(velocity, acc_limit)

    def halt(self) -> None:
        """Brake to rest at the joint's max acceleration, then hold."""
        with self._plant.lock:
            self.ramp.halt()

    def set_travel_limits(self, lower: float, upper: float) -> None:
        """Keep the setpoint inside ``[lower, upper]`` (rad, within the joint limits) from now on."""
        lo = max(float(lower), float(self._plant.arm.lower[self.index]))
        hi = min(float(upper), float(self._plant.arm.upper[self.index]))
        with self._plant.lock:
            self.ramp.set_limits(lo, hi)

    def hold(self) -> None:
        """Stop the setpoint where the joint measurably is now (after a reset)."""
        with self._plant.lock:
            self.ramp.hold(self._plant._q[self.index])

    def position(self) -> float:
        """Measured joint position (rad) after the last physics step."""
        return float(self._plant._q[self.index])

    def velocity(self) -> float:
        """Measured joint velocity (rad/s) after the last physics step."""
        return float(self._plant._dq[self.index])

    def setpoint(self) -> float:
        """Current setpoint position (rad)."""
        return float(self._plant._ramps[self.index].pos)

    def in_motion(self) -> bool:
        """True while the setpoint moves or the joint measurably does."""
        with self._plant.lock:
            active = self.ramp.active
        return active or abs(self.velocity()) > MOTION_EPS


def own_visuals(arm: Any) -> dict[int, list[str]]:
    """The visuals (meshes) of the URDF file an arm was loaded from (:func:`.urdf.urdf_visuals`), or {} for
    a bundled arm, an arm from URDF text, or a file that no longer reads."""
    cfg = getattr(arm, "config", None) or {}
    path = cfg.get("urdf")
    if not path or not os.path.isfile(str(path)) or not cfg.get("base_link") or not cfg.get("tip_link"):
        return {}
    try:
        return urdf_visuals(str(path), str(cfg["base_link"]), str(cfg["tip_link"]))
    except (RedarmError, ValueError):  # the arm loaded from it: only a file changed since then lands here
        return {}


class PybulletPlant:
    """A fixed-base arm in pybullet client ``client_id``, position-controlled through setpoint ramps.

    ``arm`` follows the ``redarm_ros.kinematics`` model contract (``n``, ``chain``, ``tool``, ``lower``,
    ``upper``, ``max_vel``, ``max_acc``, ``name``). ``initial_q`` (rad) defaults to zeros clipped into the
    limits. ``gravity`` is m/s^2 along ``-z``. If ``own_client`` the plant disconnects on :meth:`close`.
    """

    def __init__(
        self,
        arm: Any,
        client_id: int,
        *,
        time_step: float = DEFAULT_TIME_STEP,
        initial_q: Sequence[float] | None = None,
        gravity: float = 9.81,
        force_scale: float = FORCE_SCALE,
        own_client: bool = False,
    ) -> None:
        self.pb = _pybullet()
        self.arm = arm
        self.cid = int(client_id)
        self.n = int(arm.n)
        self.dt = float(time_step)
        self.own_client = own_client
        self.lock = threading.Lock()
        self.sim_time = 0.0
        self.steps = 0
        self.link_names = link_names(arm)
        self.tool_link = self.n  # pybullet link index of the tool (fixed joint after the n revolute ones)
        self._objects: list[int] = []
        self._dynamic_objects = False  # a body that can move on its own: the state is never a fixed point
        self.physics_steps = 0  # pybullet steps taken (fewer than :attr:`steps` at a fixed point)
        self._fixed_point = False  # the last pybullet step moved nothing (see FIXED_POINT_PROBE_STEPS)
        self._coasted = 0  # steps since the last pybullet step

        lower = np.asarray(arm.lower, dtype=float)
        upper = np.asarray(arm.upper, dtype=float)
        q0 = np.zeros(self.n) if initial_q is None else np.asarray(initial_q, dtype=float)
        if q0.shape != (self.n,) or not np.all(np.isfinite(q0)):
            raise InvalidInputError(
                f"initial_q must be {self.n} finite values", field="initial_q", value=initial_q
            )
        q0 = np.clip(q0, lower, upper)

        pb = self.pb
        urdf = build_urdf(arm, visuals=own_visuals(arm))
        with tempfile.TemporaryDirectory(prefix="redarm_urdf_") as tmp:
            path = os.path.join(tmp, f"{arm.name}.urdf")
            with open(path, "w", encoding="utf-8") as fh:
                fh.write(urdf)
            self.body = pb.loadURDF(
                path,
                [0, 0, 0],
                [0, 0, 0, 1],
                useFixedBase=True,
                flags=pb.URDF_USE_INERTIA_FROM_FILE,
                physicsClientId=self.cid,
            )
        pb.setTimeStep(self.dt, physicsClientId=self.cid)
        pb.setGravity(0, 0, -float(gravity), physicsClientId=self.cid)
        self.indices = list(range(self.n))
        for i in range(-1, self.n + 1):
            pb.changeDynamics(self.body, i, linearDamping=0.0, angularDamping=0.0, physicsClientId=self.cid)
        for i in self.indices:
            pb.resetJointState(self.body, i, float(q0[i]), 0.0, physicsClientId=self.cid)
        efforts = joint_efforts(arm, link_bodies(arm))
        self._forces = [float(f) * force_scale for f in efforts]
        self._kp = [POSITION_GAIN] * self.n
        self._kd = [VELOCITY_GAIN] * self.n
        self._zeros = [0.0] * self.n
        self._ramps = [
            JointRamp(q0[i], lower[i], upper[i], float(arm.max_vel[i]), float(arm.max_acc[i]))
            for i in range(self.n)
        ]
        self._q = q0.copy()
        self._dq = np.zeros(self.n)
        self._sp = q0.copy()
        self._sp_list = self._sp.tolist()  # the setpoints of the last pybullet step, as fed to it
        self._joints = [JointPlant(self, i) for i in range(self.n)]

    @classmethod
    def create(cls, arm: Any, *, gui: bool = False, **kwargs: Any) -> PybulletPlant:
        """Connect a new client (DIRECT unless ``gui``) and build a plant that owns it."""
        return cls(arm, connect(gui), own_client=True, **kwargs)

    # -- joints ---------------------------------------------------------------------------------------
    def joint(self, index: int) -> JointPlant:
        """Plant adapter of joint ``index`` (0-based; module id = index + 1)."""
        return self._joints[index]

    @property
    def joints(self) -> list[JointPlant]:
        """All per-joint adapters, base to tool."""
        return list(self._joints)

    @property
    def q(self) -> np.ndarray:
        """Measured joint positions (n,) rad after the last step (a copy)."""
        return self._q.copy()

    @property
    def dq(self) -> np.ndarray:
        """Measured joint velocities (n,) rad/s after the last step (a copy)."""
        return self._dq.copy()

    @property
    def q_setpoint(self) -> np.ndarray:
        """Setpoints (n,) rad fed to the motors in the last step (a copy)."""
        return self._sp.copy()

    def busy(self) -> bool:
        """True while any setpoint generator is active."""
        with self.lock:
            return any(r.active for r in self._ramps)

    def reset_joints(self, q: Sequence[float]) -> None:
        """Teleport the joints to ``q`` (rad), zero velocity, setpoints holding there."""
        qa = np.clip(np.asarray(q, dtype=float), np.asarray(self.arm.lower), np.asarray(self.arm.upper))
        with self.lock:
            for i, r in enumerate(self._ramps):
                r.hold(float(qa[i]))
        for i in self.indices:
            self.pb.resetJointState(self.body, i, float(qa[i]), 0.0, physicsClientId=self.cid)
        self._q, self._dq, self._sp = qa.copy(), np.zeros(self.n), qa.copy()
        self._sp_list = self._sp.tolist()
        self._fixed_point = False

    # -- stepping -------------------------------------------------------------------------------------
    def step(self, count: int = 1) -> None:
        """Advance ``count`` physics steps of :attr:`dt` seconds each (at a fixed point of a held arm,
        without pybullet: see :data:`FIXED_POINT_PROBE_STEPS`)."""
        pb, cid, dt = self.pb, self.cid, self.dt
        for _ in range(count):
            with self.lock:
                sp = [r.step(dt) for r in self._ramps]
            held = sp == self._sp_list
            if held and self._fixed_point and self._coasted < FIXED_POINT_PROBE_STEPS - 1:
                self._coasted += 1
                self.steps += 1
                self.sim_time = self.steps * dt
                continue
            pb.setJointMotorControlArray(
                self.body,
                self.indices,
                pb.POSITION_CONTROL,
                targetPositions=sp,
                targetVelocities=self._zeros,
                forces=self._forces,
                positionGains=self._kp,
                velocityGains=self._kd,
                physicsClientId=cid,
            )
            pb.stepSimulation(physicsClientId=cid)
            states = pb.getJointStates(self.body, self.indices, physicsClientId=cid)
            q = np.fromiter((s[0] for s in states), float, self.n)
            dq = np.fromiter((s[1] for s in states), float, self.n)
            self._fixed_point = (held and not self._dynamic_objects and np.array_equal(q, self._q)
                                 and float(np.max(np.abs(dq))) <= FIXED_POINT_SPEED)
            self._coasted = 0
            self.physics_steps += 1
            self._q, self._dq = q, dq
            self._sp_list = sp
            self._sp = np.asarray(sp, dtype=float)
            self.steps += 1
            self.sim_time = self.steps * dt

    def run_until_idle(self, timeout_s: float = 10.0, settle_steps: int = 50) -> bool:
        """Step (simulated time) until every ramp is idle, plus ``settle_steps``; False on timeout."""
        limit = int(round(timeout_s / self.dt))
        for _ in range(limit):
            if not self.busy():
                self.step(settle_steps)
                return True
            self.step()
        return False

    # -- queries --------------------------------------------------------------------------------------
    def link_pose(self, link: int) -> tuple[np.ndarray, np.ndarray]:
        """World pose of pybullet link ``link``'s URDF frame: position (3,) m, quaternion (x, y, z, w)."""
        s = self.pb.getLinkState(self.body, link, computeForwardKinematics=True, physicsClientId=self.cid)
        return np.asarray(s[4], dtype=float), np.asarray(s[5], dtype=float)

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """World pose of the tool frame: position (3,) m, quaternion (x, y, z, w) (pybullet link state)."""
        return self.link_pose(self.tool_link)

    def motion_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``q``, ``dq``, ``q_setpoint``, the tool position and quaternion (x, y, z, w), all after the same
        step (call from the physics thread)."""
        pos, quat = self.tool_pose()
        return self.q, self.dq, self.q_setpoint, pos, quat

    def tool_transform(self) -> np.ndarray:
        """World 4x4 transform of the tool frame (pybullet link state)."""
        p, quat = self.tool_pose()
        T = np.eye(4)
        T[:3, :3] = np.asarray(self.pb.getMatrixFromQuaternion(quat.tolist()), dtype=float).reshape(3, 3)
        T[:3, 3] = p
        return T

    # -- scene ----------------------------------------------------------------------------------------
    def _add(
        self,
        shape: int,
        position: Sequence[float],
        orientation: Sequence[float] | None,
        rgba: Sequence[float],
        mass: float,
        **dims: Any,
    ) -> int:
        pb, cid = self.pb, self.cid
        pos = [float(v) for v in position]
        orn = [0.0, 0.0, 0.0, 1.0] if orientation is None else [float(v) for v in orientation]
        if len(pos) != 3 or len(orn) != 4 or not all(math.isfinite(v) for v in pos + orn):
            raise InvalidInputError(
                "object position must be 3 and orientation 4 (x,y,z,w) finite numbers",
                field="position",
                value=(position, orientation),
            )
        col = pb.createCollisionShape(shape, physicsClientId=cid, **dims)
        vis_dims = dict(dims)
        if "height" in vis_dims:  # createVisualShape calls the cylinder height "length"
            vis_dims["length"] = vis_dims.pop("height")
        vis = pb.createVisualShape(shape, rgbaColor=[float(c) for c in rgba], physicsClientId=cid, **vis_dims)
        body = pb.createMultiBody(float(mass), col, vis, pos, orn, physicsClientId=cid)
        self._objects.append(body)
        self._fixed_point = False  # an object may touch the arm
        self._dynamic_objects = self._dynamic_objects or float(mass) > 0.0
        return int(body)

    def add_sphere(
        self,
        position: Sequence[float],
        radius: float,
        *,
        rgba: Sequence[float] = (0.2, 0.5, 0.9, 1.0),
        mass: float = 0.0,
    ) -> int:
        """Add a sphere (centre m, radius m); static if ``mass`` is 0. Returns the pybullet body id."""
        _positive(radius=radius)
        return self._add(self.pb.GEOM_SPHERE, position, None, rgba, mass, radius=float(radius))

    def add_cylinder(
        self,
        position: Sequence[float],
        radius: float,
        height: float,
        *,
        orientation: Sequence[float] | None = None,
        rgba: Sequence[float] = (0.2, 0.7, 0.3, 1.0),
        mass: float = 0.0,
    ) -> int:
        """Add a cylinder (centre m, radius m, height m along its z, orientation x,y,z,w)."""
        _positive(radius=radius, height=height)
        return self._add(
            self.pb.GEOM_CYLINDER,
            position,
            orientation,
            rgba,
            mass,
            radius=float(radius),
            height=float(height),
        )

    def add_box(
        self,
        position: Sequence[float],
        half_extents: Sequence[float],
        *,
        orientation: Sequence[float] | None = None,
        rgba: Sequence[float] = (0.6, 0.45, 0.3, 1.0),
        mass: float = 0.0,
    ) -> int:
        """Add a box (centre m, half extents (3,) m, orientation x,y,z,w)."""
        he = [float(v) for v in half_extents]
        if len(he) != 3:
            raise InvalidInputError(
                "half_extents must have 3 values", field="half_extents", value=half_extents
            )
        _positive(**{f"half_extents[{i}]": v for i, v in enumerate(he)})
        return self._add(self.pb.GEOM_BOX, position, orientation, rgba, mass, halfExtents=he)

    def add_table(
        self,
        center_xy: Sequence[float] = (0.45, 0.0),
        size_xy: Sequence[float] = (1.3, 1.4),
        height: float = 0.0,
        thickness: float = 0.04,
    ) -> int:
        """Add a static table top (a box whose upper face is at ``height`` m). Returns its body id."""
        return self.add_box(
            [center_xy[0], center_xy[1], height - thickness / 2],
            [size_xy[0] / 2, size_xy[1] / 2, thickness / 2],
            rgba=(0.55, 0.4, 0.25, 1.0),
        )

    def add_object(self, spec: Mapping[str, Any]) -> int:
        """Add one object from a mapping: the scene schema of ``redarm_ros.geometry.obstacles``.

        Keys: ``type`` (sphere | cylinder | box | cube | table), ``center`` (or ``position``) [x, y, z] m;
        sphere ``radius``; cylinder ``radius``, ``height`` (vertical unless ``orientation`` x,y,z,w);
        box ``size`` (full edges) or ``half_extents``, ``yaw`` (rad about z) or ``orientation``;
        optional ``rgba``, ``mass`` (kg, 0 = static); ``name`` is ignored. ``table``: ``center_xy``,
        ``size_xy``, ``height`` (of the top surface), ``thickness``.
        Raises :class:`InvalidInputError` naming what is wrong.
        """
        if not isinstance(spec, Mapping):
            raise InvalidInputError(
                f"scene object must be a mapping, got {spec!r}", field="object", value=spec
            )
        kind = str(spec.get("type", "")).lower()
        common: dict[str, Any] = {k: spec[k] for k in ("rgba", "mass") if k in spec}
        try:
            pos = spec["center"] if "center" in spec else spec.get("position")
            if kind == "sphere":
                return self.add_sphere(pos, spec["radius"], **common)
            if kind == "cylinder":
                height = spec["height"] if "height" in spec else spec["length"]
                return self.add_cylinder(
                    pos, spec["radius"], height, orientation=spec.get("orientation"), **common
                )
            if kind in ("box", "cube"):
                he = spec.get("half_extents")
                if he is None:
                    he = [float(v) / 2 for v in spec["size"]]
                orn = spec.get("orientation")
                if orn is None and "yaw" in spec:
                    yaw = float(spec["yaw"])
                    orn = [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]
                return self.add_box(pos, he, orientation=orn, **common)
            if kind == "table":
                kw = {k: spec[k] for k in ("center_xy", "size_xy", "height", "thickness") if k in spec}
                return self.add_table(**kw)
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InvalidInputError):
                raise
            raise InvalidInputError(
                f"bad scene object {dict(spec)!r}: {exc!r}", field="object", value=spec
            ) from exc
        raise InvalidInputError(
            f"unknown scene object type {kind!r} (sphere, cylinder, box, table)", field="type", value=kind
        )

    def add_scene(self, scene: Mapping[str, Any]) -> list[int]:
        """Add a whole scene: ``{"table_height": z or None, "obstacles": [object, ...]}`` (the schema of
        ``redarm_ros.geometry.obstacles.Scene.to_dict``). A table top is added below ``table_height``
        in front of the arm. Returns the new body ids."""
        ids = []
        th = scene.get("table_height")
        if th is not None:
            ids.append(self.add_table(height=float(th)))
        for obj in scene.get("obstacles") or []:
            ids.append(self.add_object(obj))
        return ids

    @property
    def objects(self) -> list[int]:
        """Body ids of the scene objects added so far."""
        return list(self._objects)

    # -- rendering ------------------------------------------------------------------------------------
    def render(
        self,
        width: int = 640,
        height: int = 480,
        *,
        target: Sequence[float] = (0.2, 0.0, 0.5),
        distance: float = 2.2,
        yaw: float = 45.0,
        pitch: float = -25.0,
        fov: float = 50.0,
    ) -> np.ndarray:
        """RGB image (height, width, 3) uint8 from a camera orbiting ``target`` (yaw/pitch in degrees).

        Headless: always pybullet's TinyRenderer (no OpenGL context needed).
        """
        pb, cid = self.pb, self.cid
        view = pb.computeViewMatrixFromYawPitchRoll(
            list(map(float, target)), float(distance), float(yaw), float(pitch), 0.0, 2, physicsClientId=cid
        )
        proj = pb.computeProjectionMatrixFOV(float(fov), width / height, 0.02, 20.0, physicsClientId=cid)
        _, _, rgba, _, _ = pb.getCameraImage(
            int(width), int(height), view, proj, renderer=pb.ER_TINY_RENDERER, physicsClientId=cid
        )
        img = np.asarray(rgba, dtype=np.uint8).reshape(int(height), int(width), 4)
        return np.ascontiguousarray(img[:, :, :3])

    def snapshot_png(
        self, path: str | os.PathLike[str], width: int = 640, height: int = 480, **camera: Any
    ) -> str:
        """Render (see :meth:`render` for the camera keywords) and write a PNG to ``path``; returns it."""
        return write_png(path, self.render(width, height, **camera))

    def close(self) -> None:
        """Remove the arm and objects; disconnect if this plant owns the client."""
        pb = self.pb
        try:
            if self.own_client:
                pb.disconnect(physicsClientId=self.cid)
            else:
                for b in [*self._objects, self.body]:
                    pb.removeBody(b, physicsClientId=self.cid)
        except pb.error as exc:  # already disconnected
            _LOG.debug("pybullet close: %s", exc)


def _positive(**values: float) -> None:
    for name, v in values.items():
        if v is None or not (math.isfinite(float(v)) and float(v) > 0):
            raise InvalidInputError(f"{name} must be a positive number", field=name, value=v)
