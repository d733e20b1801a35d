"""A base-placement problem: task poses in a world frame, a grid of planar base poses, an optional scene.

The arm's base frame stands at ``(x, y, base_height)`` in the world, turned by ``yaw`` about the world z
axis: ``B = Trans(x, y, base_height) Rz(yaw)``; a task pose T (world) is ``B^-1 T`` in the base frame.

Task file (YAML; units m and degrees as named)::

    arm: pa10                    # config/arms/<name>.yaml or a path
    base_height: 0.0             # m, the arm's base frame above the world floor
    grid: {x: [-1.5, 1.5], y: [-1.5, 1.5], step: 0.1, yaw_step_deg: 30}   # or yaw_deg: [0, 90]
    footprint_radius: 0.0        # m, the base's footprint circle, kept clear of the scene
    check_collisions: true       # self-collision model of the arm, and the scene
    scene: table_empty           # a bundled scene name, a path, or an inline {obstacles: [...]}; world frame
    tasks:
      - {name: pick, position: [0.6, 0.1, 0.75], rpy_deg: [180, 0, 0]}
      - {position: [0.6, -0.2, 0.75], quaternion_xyzw: [1, 0, 0, 0]}

No ROS here; numpy and PyYAML only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.errors import ConfigError

__all__ = [
    "BaseGrid", "PlacementProblem", "load_problem", "problem_from_dict", "pose_matrix", "base_transforms"
]

_FIELDS = {"arm", "base_height", "grid", "footprint_radius", "check_collisions", "scene", "tasks"}
QUAT_TOL = 1e-6  # a task quaternion must be unit to this tolerance (not silently renormalised)


@dataclass(frozen=True)
class BaseGrid:
    """Candidate base poses: every combination of ``x``, ``y`` (m) and ``yaw`` (rad), in C order."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nx, ny, nyaw)."""
        return (len(self.x), len(self.y), len(self.yaw))

    @property
    def size(self) -> int:
        """Number of base poses."""
        return int(np.prod(self.shape))

    def poses(self) -> np.ndarray:
        """(N, 3) base poses (x, y, yaw), index ``(ix * ny + iy) * nyaw + iyaw``."""
        X, Y, W = np.meshgrid(self.x, self.y, self.yaw, indexing="ij")
        return np.stack([X.ravel(), Y.ravel(), W.ravel()], axis=1)


@dataclass(frozen=True)
class PlacementProblem:
    """Everything a worker needs to score base poses (plain data: it pickles to another process)."""

    arm: str
    tasks: np.ndarray  # (m, 4, 4) world frame
    grid: BaseGrid
    base_height: float = 0.0
    scene: Mapping[str, Any] | None = None  # Scene.from_dict form, world frame
    footprint_radius: float = 0.0
    check_collisions: bool = True
    task_names: tuple[str, ...] = field(default=())


def _rot_rpy(r: float, p: float, y: float) -> np.ndarray:
    """Rz(y) Ry(p) Rx(r): roll, pitch, yaw about the fixed x, y, z axes (REP-103)."""
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def _rot_quat_xyzw(q: Any, where: str) -> np.ndarray:
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or abs(n - 1.0) > QUAT_TOL:
        raise ConfigError(f"{where}: quaternion_xyzw must be a unit quaternion, its norm is {n:.9g}",
                          field="quaternion_xyzw", value=list(q))
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _floats(v: Any, n: int, where: str, name: str) -> list[float]:
    if not isinstance(v, list | tuple) or len(v) != n:
        raise ConfigError(f"{where}: {name} must be a list of {n} numbers, got {v!r}", field=name, value=v)
    try:
        out = [float(c) for c in v]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {name} must hold numbers, got {v!r}", field=name, value=v) from exc
    if not all(math.isfinite(c) for c in out):
        raise ConfigError(f"{where}: {name} must be finite, got {v!r}", field=name, value=v)
    return out


def pose_matrix(d: Mapping[str, Any], where: str = "task") -> np.ndarray:
    """4x4 pose from ``{position: [x, y, z], rpy_deg: [r, p, y]}`` or ``quaternion_xyzw`` (identity if
    neither). Raises :class:`ConfigError` for a malformed entry or a non-unit quaternion."""
    if not isinstance(d, Mapping):
        raise ConfigError(f"{where} must be a mapping, got {d!r}", value=d)
    unknown = set(d) - {"name", "position", "rpy_deg", "quaternion_xyzw"}
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {sorted(unknown)}", field=sorted(unknown)[0])
    if "rpy_deg" in d and "quaternion_xyzw" in d:
        raise ConfigError(f"{where}: give rpy_deg or quaternion_xyzw, not both", field="rpy_deg")
    T = np.eye(4)
    T[:3, 3] = _floats(d.get("position"), 3, where, "position")
    if "rpy_deg" in d:
        T[:3, :3] = _rot_rpy(*(math.radians(a) for a in _floats(d["rpy_deg"], 3, where, "rpy_deg")))
    elif "quaternion_xyzw" in d:
        T[:3, :3] = _rot_quat_xyzw(_floats(d["quaternion_xyzw"], 4, where, "quaternion_xyzw"), where)
    return T


def _axis(g: Mapping[str, Any], name: str, step: float) -> np.ndarray:
    lo, hi = _floats(g.get(name), 2, "grid", name)
    if hi < lo:
        raise ConfigError(f"grid: {name} must be [low, high] with low <= high, got {[lo, hi]}", field=name)
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    return lo + step * np.arange(n)


def _grid(g: Any) -> BaseGrid:
    if not isinstance(g, Mapping):
        raise ConfigError(f"grid must be a mapping, got {g!r}", field="grid", value=g)
    unknown = set(g) - {"x", "y", "step", "yaw_step_deg", "yaw_deg"}
    if unknown:
        raise ConfigError(f"grid: unknown field(s) {sorted(unknown)}", field=sorted(unknown)[0])
    step = float(g.get("step", 0.1))
    if not (math.isfinite(step) and step > 0.0):
        raise ConfigError(f"grid: step must be > 0 m, got {step}", field="step", value=step)
    if "yaw_deg" in g:
        if not isinstance(g["yaw_deg"], list | tuple) or not g["yaw_deg"]:
            raise ConfigError("grid: yaw_deg must be a non-empty list", field="yaw_deg", value=g["yaw_deg"])
        yaw = np.radians(_floats(g["yaw_deg"], len(g["yaw_deg"]), "grid", "yaw_deg"))
    else:
        ys = float(g.get("yaw_step_deg", 360.0))
        if not (math.isfinite(ys) and 0.0 < ys <= 360.0):
            raise ConfigError(f"grid: yaw_step_deg must lie in (0, 360], got {ys}", field="yaw_step_deg")
        yaw = np.radians(np.arange(0.0, 360.0 - 1e-9, ys))
    return BaseGrid(_axis(g, "x", step), _axis(g, "y", step), np.asarray(yaw, dtype=float))


def _scene(raw: Any, base: Path | None) -> dict[str, Any] | None:
    from redarm_ros.geometry.obstacles import Scene, load_scene

    if raw is None:
        return None
    if isinstance(raw, str):
        p = Path(raw)
        if base is not None and not p.is_absolute() and (base / p).is_file():
            p = base / p
        return load_scene(p if p.is_file() else raw).to_dict()
    return Scene.from_dict(raw).to_dict()  # validates


def problem_from_dict(d: Mapping[str, Any], base_dir: Path | None = None) -> PlacementProblem:
    """A :class:`PlacementProblem` from the task-file schema (module doc). Raises :class:`ConfigError`."""
    if not isinstance(d, Mapping):
        raise ConfigError(f"a placement task file must be a mapping, got {type(d).__name__}")
    unknown = set(d) - _FIELDS
    if unknown:
        raise ConfigError(f"unknown field(s) {sorted(unknown)}; known: {sorted(_FIELDS)}",
                          field=sorted(unknown)[0])
    tasks = d.get("tasks")
    if not isinstance(tasks, list | tuple) or not tasks:
        raise ConfigError("tasks must be a non-empty list of poses", field="tasks", value=tasks)
    Ts = np.stack([pose_matrix(t, f"tasks[{i}]") for i, t in enumerate(tasks)])
    names = tuple(str(t.get("name", f"task{i}")) for i, t in enumerate(tasks))
    h = float(d.get("base_height", 0.0))
    r = float(d.get("footprint_radius", 0.0))
    if not (math.isfinite(h) and math.isfinite(r) and r >= 0.0):
        raise ConfigError(f"base_height must be finite and footprint_radius >= 0, got {h}, {r}")
    return PlacementProblem(
        arm=str(d.get("arm", "pa10")),
        tasks=Ts,
        grid=_grid(d.get("grid", {"x": [-1.0, 1.0], "y": [-1.0, 1.0]})),
        base_height=h,
        scene=_scene(d.get("scene"), base_dir),
        footprint_radius=r,
        check_collisions=bool(d.get("check_collisions", True)),
        task_names=names,
    )


def load_problem(path: str | Path) -> PlacementProblem:
    """Read a task file (module doc). Raises :class:`ConfigError` naming the file for any problem."""
    import yaml

    from redarm_ros.yaml_safe import safe_load

    p = Path(path)
    try:
        data = safe_load(p.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read task file {p}: {exc}", field="path", value=str(p)) from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"task file {p} is not valid YAML: {exc}", field="path", value=str(p)) from exc
    try:
        return problem_from_dict(data, p.parent)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}", field=exc.field, value=exc.value) from exc


def base_transforms(poses: np.ndarray, base_height: float) -> np.ndarray:
    """(N, 4, 4) base frames ``Trans(x, y, base_height) Rz(yaw)`` of the (N, 3) base poses."""
    P = np.asarray(poses, dtype=float).reshape(-1, 3)
    c, s = np.cos(P[:, 2]), np.sin(P[:, 2])
    B = np.zeros((len(P), 4, 4))
    B[:, 0, 0], B[:, 0, 1], B[:, 1, 0], B[:, 1, 1] = c, -s, s, c
    B[:, 2, 2] = B[:, 3, 3] = 1.0
    B[:, 0, 3], B[:, 1, 3], B[:, 2, 3] = P[:, 0], P[:, 1], base_height
    return B
