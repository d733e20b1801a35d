"""Arm models from configuration: :func:`load_arm` reads ``config/arms/<name>.yaml`` and builds the model.

The YAML ``kind`` picks the class: ``swivel7`` -> :class:`~.swivel.SwivelArm` (closed-form swivel IK),
``powercube6`` -> :class:`~.powercube6.PowerCube6Arm` (analytic IK), ``chain`` -> the generic
:class:`~.model.Arm` (numeric IK only). Keyword overrides replace YAML values. Units: m, rad, rad/s,
rad/s^2 (``limits_deg`` in the YAML is degrees).

This module sits on top of the model classes: ``model`` knows nothing about configuration, so the
kinematics package has no import cycle (model <- swivel, powercube6 <- loader).
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from redarm_ros.errors import ConfigError
from redarm_ros.kinematics.model import Arm, Joint, transform_from_xyz_rpy
from redarm_ros.kinematics.powercube6 import PowerCube6Arm
from redarm_ros.kinematics.swivel import SwivelArm, swivel_chain
from redarm_ros.yaml_safe import safe_load

__all__ = ["load_arm", "load_arm_or_urdf", "build_arm", "arm_config_dirs", "available_arms", "is_urdf_source"]


def arm_config_dirs() -> list[Path]:
    """Directories searched for ``<name>.yaml``, in order.

    ``$REDARM_ARMS_DIR`` (os.pathsep separated), the source tree's ``config/arms``, the installed
    ``share/redarm_ros/config/arms`` under ``sys.prefix``, and the ament index share directory if
    ``ament_index_python`` is importable.
    """
    dirs: list[Path] = []
    env = os.environ.get("REDARM_ARMS_DIR")
    if env:
        dirs.extend(Path(p) for p in env.split(os.pathsep) if p)
    dirs.append(Path(__file__).resolve().parents[2] / "config" / "arms")
    dirs.append(Path(sys.prefix) / "share" / "redarm_ros" / "config" / "arms")
    try:  # ROS install without rclpy: ament_index_python is plain Python
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory("redarm_ros")) / "config" / "arms")
    except Exception:  # noqa: BLE001 - not installed the ament way; the other dirs still apply
        pass
    return dirs


def available_arms() -> list[str]:
    """Names of the arm YAML files found in :func:`arm_config_dirs`."""
    names: set[str] = set()
    for d in arm_config_dirs():
        if d.is_dir():
            names.update(p.stem for p in d.glob("*.yaml"))
    return sorted(names)


def _find_config(name: str | os.PathLike[str]) -> Path:
    p = Path(name)
    if p.suffix in (".yaml", ".yml") or os.sep in str(name):
        if p.is_file():
            return p
        raise ConfigError(f"arm config file {str(p)!r} does not exist", field="name", value=str(name))
    for d in arm_config_dirs():
        cand = d / f"{name}.yaml"
        if cand.is_file():
            return cand
    raise ConfigError(
        f"unknown arm {str(name)!r}; known arms: {', '.join(available_arms()) or '(none)'}",
        field="name",
        value=str(name),
    )


_OVERRIDE_KEYS = {
    "link_lengths",
    "lower",
    "upper",
    "max_vel",
    "max_acc",
    "joint_names",
    "name",
    "roll_fractions",
    "park",
}


def is_urdf_source(name: str | os.PathLike[str]) -> bool:
    """True if ``name`` is URDF text (starts with '<') or a path ending in .urdf."""
    s = str(name)
    return s.lstrip().startswith("<") or s.endswith(".urdf")


def load_arm(
    name: str | os.PathLike[str] = "pa10",
    *,
    base_link: str | None = None,
    tip_link: str | None = None,
    **overrides: Any,
) -> Arm:
    """Load an arm model by name (``config/arms/<name>.yaml``), from a YAML path, or from a URDF.

    Keyword overrides replace YAML values: ``link_lengths`` (m), ``lower``/``upper`` (rad, (n,)),
    ``max_vel`` (rad/s), ``max_acc`` (rad/s^2), ``joint_names``, ``name``, ``roll_fractions``
    (powercube6), ``park`` (rad, (n,): the park posture, ``arm.park``).
    URDF: ``name`` is a ``.urdf`` file or the XML text (as on ``/robot_description``) and ``base_link`` /
    ``tip_link`` name the chain's ends; the model is built by :func:`.urdf_chain.load_urdf_arm` (further
    keywords: ``limits_yaml``, ``tol``, ``closed_form``, ``arm_name`` (the model's name; default the
    URDF robot's), and ``lower``, ``upper``, ``max_vel``,
    ``max_acc``, ``park`` overrides).
    Raises :class:`ConfigError` for an unknown name, a broken file or a bad override.
    """
    if base_link is not None or tip_link is not None or is_urdf_source(name):
        if not base_link or not tip_link:
            raise ConfigError("a URDF arm needs both base_link and tip_link", field="base_link")
        if "arm_name" in overrides:
            overrides["name"] = str(overrides.pop("arm_name"))
        # The URDF front end (and the capsule model it brings) only for a URDF arm: the bundled arms'
        # processes skip its import.
        from redarm_ros.kinematics.urdf_chain import load_urdf_arm  # noqa: PLC0415

        return load_urdf_arm(name, base_link, tip_link, **overrides)
    path = _find_config(name)
    try:
        with open(path, encoding="utf-8") as fh:
            cfg = safe_load(fh)
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(
            f"cannot read arm config {str(path)!r}: {exc}", field="name", value=str(name)
        ) from exc
    if not isinstance(cfg, dict):
        raise ConfigError(f"arm config {str(path)!r} is not a mapping", field="name", value=str(name))
    unknown = set(overrides) - _OVERRIDE_KEYS
    if unknown:
        raise ConfigError(
            f"unknown override(s) {sorted(unknown)}; allowed: {sorted(_OVERRIDE_KEYS)}",
            field=sorted(unknown)[0],
        )
    cfg = dict(cfg)
    cfg["_path"] = str(path)
    return build_arm(cfg, **overrides)


def load_arm_or_urdf(arm: str, urdf: str = "", base_link: str = "", tip_link: str = "") -> Arm:
    """The nodes' and processes' arm: the chain ``base_link`` -> ``tip_link`` of the URDF file ``urdf``
    if one is given, else :func:`load_arm` of ``arm`` (a bundled name or a YAML path)."""
    if urdf:
        return load_arm(urdf, base_link=base_link or None, tip_link=tip_link or None)
    return load_arm(arm)


def _joint_specs(cfg: dict[str, Any], overrides: dict[str, Any]) -> list[dict[str, Any]]:
    name = cfg.get("name", "?")
    joints = cfg.get("joints")
    if not isinstance(joints, list) or not joints:
        raise ConfigError(f"arm {name!r}: 'joints' must be a non-empty list", field="joints")
    n = len(joints)
    specs = []
    for i, jc in enumerate(joints):
        if not isinstance(jc, dict):
            raise ConfigError(f"arm {name!r}: joint {i} must be a mapping", field="joints")
        try:
            if "limits_deg" in jc:
                lo, up = (math.radians(float(v)) for v in jc["limits_deg"])
            else:
                lo, up = (float(v) for v in jc["limits"])
            spec = {
                "name": str(jc.get("name", f"{name}_joint_{i + 1}")),
                "lower": lo,
                "upper": up,
                "max_vel": float(jc["max_vel"]),
                "max_acc": float(jc["max_acc"]),
                "axis": jc.get("axis"),
                "origin": jc.get("origin"),
            }
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(
                f"arm {name!r}: joint {i} is incomplete or malformed ({exc!r})", field="joints"
            ) from exc
        specs.append(spec)
    for key in ("lower", "upper", "max_vel", "max_acc"):
        if key in overrides:
            vals = np.asarray(overrides[key], dtype=float)
            if vals.shape != (n,) or not np.all(np.isfinite(vals)):
                raise ConfigError(
                    f"override {key} must be {n} finite numbers", field=key, value=overrides[key]
                )
            for s, v in zip(specs, vals, strict=True):
                s[key] = float(v)
    if "joint_names" in overrides:
        names = list(overrides["joint_names"])
        if len(names) != n:
            raise ConfigError(f"override joint_names must have {n} entries", field="joint_names")
        for s, v in zip(specs, names, strict=True):
            s["name"] = str(v)
    for i, s in enumerate(specs):
        if not (s["lower"] <= s["upper"]):
            raise ConfigError(
                f"arm {name!r}: joint {i} has lower > upper", field="limits", value=(s["lower"], s["upper"])
            )
        if not (s["max_vel"] > 0 and s["max_acc"] > 0):
            raise ConfigError(f"arm {name!r}: joint {i} needs positive max_vel and max_acc", field="max_vel")
    return specs


def _park(cfg: dict[str, Any], overrides: dict[str, Any], specs: list[dict[str, Any]]) -> list[float] | None:
    """The park posture (rad, one value per joint, inside the limits) from ``park:`` or the override.

    None if the arm has none, and also when ``lower``/``upper`` overrides leave the YAML's park posture
    outside the new limits (a model with other limits has no park posture unless ``park`` is overridden
    too). Raises :class:`ConfigError` for a wrong length, a non-finite value or a joint outside its
    limits (the park service moves there without asking).
    """
    raw = overrides.get("park", cfg.get("park"))
    if raw is None:
        return None
    from_yaml_with_new_limits = "park" not in overrides and ("lower" in overrides or "upper" in overrides)
    name = cfg.get("name", "?")
    try:
        vals = [float(v) for v in raw]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"arm {name!r}: park must be {len(specs)} numbers (rad)", field="park",
                          value=raw) from exc
    if len(vals) != len(specs) or not all(math.isfinite(v) for v in vals):
        raise ConfigError(
            f"arm {name!r}: park must be {len(specs)} finite numbers (rad), got {raw!r}",
            field="park",
            value=raw,
        )
    for i, (v, s) in enumerate(zip(vals, specs, strict=True)):
        if not (s["lower"] - 1e-9 <= v <= s["upper"] + 1e-9):
            if from_yaml_with_new_limits:
                return None
            raise ConfigError(
                f"arm {name!r}: park joint {i + 1} = {v:.4f} rad is outside its limits "
                f"[{s['lower']:.4f}, {s['upper']:.4f}]",
                field="park",
                value=raw,
            )
    return [min(max(v, s["lower"]), s["upper"]) for v, s in zip(vals, specs, strict=True)]


def _axis(spec: Any, where: str) -> np.ndarray:
    table = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
    if isinstance(spec, str) and spec in table:
        return np.array(table[spec])
    try:
        a = np.asarray(spec, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: axis {spec!r} is not x/y/z or a 3-vector", field="axis") from exc
    if a.shape != (3,) or not np.isfinite(a).all() or np.linalg.norm(a) < 1e-9:
        raise ConfigError(f"{where}: axis {spec!r} is not x/y/z or a non-zero 3-vector", field="axis")
    return a / np.linalg.norm(a)


def _origin(spec: Any, where: str) -> np.ndarray:
    if spec is None:
        return np.eye(4)
    try:
        xyz = [float(v) for v in spec.get("xyz", (0, 0, 0))]
        rpy = [float(v) for v in spec.get("rpy", (0, 0, 0))]
        if len(xyz) != 3 or len(rpy) != 3:
            raise ValueError("xyz and rpy need 3 values")
    except (AttributeError, TypeError, ValueError) as exc:
        raise ConfigError(
            f"{where}: origin must be {{xyz: [..], rpy: [..]}} ({exc})", field="origin"
        ) from exc
    return transform_from_xyz_rpy(xyz, rpy)


def _link_lengths(cfg: dict[str, Any], overrides: dict[str, Any], count: int) -> list[float]:
    raw = overrides.get("link_lengths", cfg.get("link_lengths"))
    try:
        L = [float(v) for v in raw]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"link_lengths must be {count} numbers, got {raw!r}", field="link_lengths") from exc
    if len(L) != count or not all(math.isfinite(v) and v > 0 for v in L):
        raise ConfigError(
            f"link_lengths must be {count} positive numbers (m), got {raw!r}", field="link_lengths", value=raw
        )
    return L


def build_arm(cfg: dict[str, Any], **overrides: Any) -> Arm:
    """Build an :class:`Arm` (or subclass) from a config mapping (the parsed YAML) plus overrides."""
    kind = cfg.get("kind", "chain")
    name = str(overrides.get("name", cfg.get("name", "arm")))
    cfg = dict(cfg)
    cfg["name"] = name
    specs = _joint_specs(cfg, overrides)
    cfg["park"] = _park(cfg, overrides, specs)
    T = np.eye(4)

    def mk(s: dict[str, Any], origin: np.ndarray, axis: np.ndarray) -> Joint:
        return Joint(s["name"], origin, axis, s["lower"], s["upper"], s["max_vel"], s["max_acc"])

    if kind == "swivel7":
        if len(specs) != 7:
            raise ConfigError(f"arm {name!r}: kind swivel7 needs exactly 7 joints", field="joints")
        L1, L2, L3, L4 = _link_lengths(cfg, overrides, 4)
        cfg["link_lengths"] = [L1, L2, L3, L4]
        axes = "zyzyzyz"
        for i, s in enumerate(specs):
            if s["axis"] is not None and _axis(s["axis"], name).tolist() != _axis(axes[i], name).tolist():
                raise ConfigError(f"arm {name!r}: swivel7 joint {i + 1} axis must be {axes[i]}", field="axis")
        chain, T = swivel_chain(
            [L1, L2, L3, L4], [(s["name"], s["lower"], s["upper"], s["max_vel"], s["max_acc"]) for s in specs]
        )
        return SwivelArm(name, chain, T, (1, 3, 5), cfg)
    if kind == "powercube6":
        if len(specs) != 6:
            raise ConfigError(f"arm {name!r}: kind powercube6 needs exactly 6 joints", field="joints")
        L1, L23, L4, L56 = _link_lengths(cfg, overrides, 4)
        cfg["link_lengths"] = [L1, L23, L4, L56]
        f3, f6 = (float(v) for v in overrides.get("roll_fractions", cfg.get("roll_fractions", (0.5, 0.5))))
        if not (0.0 <= f3 <= 1.0 and 0.0 <= f6 <= 1.0):
            raise ConfigError("roll_fractions must lie in [0, 1]", field="roll_fractions")
        cfg["roll_fractions"] = [f3, f6]
        # standard DH of the paper's Tab. 1 (a = L1, L23, L4, L56; alpha1 = 90 deg) with the two roll
        # joints inserted on the link axes (x of the DH frames) where they do not change eq. (2)-(4)
        o2 = transform_from_xyz_rpy((L1, 0.0, 0.0), (math.pi / 2, 0.0, 0.0))
        o3 = transform_from_xyz_rpy((f3 * L23, 0.0, 0.0), (0.0, 0.0, 0.0))
        o4 = transform_from_xyz_rpy(((1.0 - f3) * L23, 0.0, 0.0), (0.0, 0.0, 0.0))
        o5 = transform_from_xyz_rpy((L4, 0.0, 0.0), (0.0, 0.0, 0.0))
        o6 = transform_from_xyz_rpy((f6 * L56, 0.0, 0.0), (0.0, 0.0, 0.0))
        origins = [np.eye(4), o2, o3, o4, o5, o6]
        axes6 = "zzxzzx"
        chain = [mk(s, origins[i], _axis(axes6[i], name)) for i, s in enumerate(specs)]
        T[0, 3] = (1.0 - f6) * L56
        return PowerCube6Arm(name, chain, T, (1, 3, 4), cfg)
    if kind == "chain":
        chain = []
        for i, s in enumerate(specs):
            if s["axis"] is None:
                raise ConfigError(f"arm {name!r}: joint {i} needs an axis", field="axis")
            chain.append(
                mk(s, _origin(s["origin"], f"{name} joint {i}"), _axis(s["axis"], f"{name} joint {i}"))
            )
        tool = _origin(cfg.get("tool"), f"{name} tool")
        n = len(chain)
        key = cfg.get("key_joints", [min(1, n - 1), min(n // 2, n - 1), max(n - 2, 0)])
        return Arm(name, chain, tool, key, cfg)
    raise ConfigError(
        f"arm {name!r}: unknown kind {kind!r} (swivel7, powercube6, chain)", field="kind", value=kind
    )
