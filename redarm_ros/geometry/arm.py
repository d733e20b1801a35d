"""How an arm enters the geometry: as structural protocols, so nothing here imports the kinematics.

* :class:`KeyPointArm`: the five key points (base, shoulder, elbow, wrist, tool; m, base frame) of a
  joint vector (rad), the ends of the capsule model's four links.
* :class:`ChainArm`: a serial chain, for the self-collision checks: its ``name``, joint count ``n``,
  joint limits ``lower`` and ``upper`` (rad),
  YAML ``config`` (the ``self_collision`` entry), the ``key_joints`` whose frame origins are the
  shoulder, elbow and wrist, the joint ``chain`` (each joint a 4x4 ``origin`` and a unit ``axis``),
  the ``tool`` transform (4x4) and ``fk_axes`` (tool position, joint origins, joint axes).

Every arm model of :mod:`redarm_ros.kinematics` is both.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["ChainArm", "Joint", "KeyPointArm"]


@runtime_checkable
class KeyPointArm(Protocol):
    """An arm as the capsule model sees it."""

    def key_points(self, q: Sequence[float]) -> np.ndarray: ...


class Joint(Protocol):
    """One joint of a chain: ``origin`` (4x4, parent frame to joint frame), ``axis`` (unit 3-vector)."""

    origin: np.ndarray
    axis: np.ndarray


@runtime_checkable
class ChainArm(KeyPointArm, Protocol):
    """A serial chain whose key points the self-collision checks compute themselves."""

    name: str
    n: int
    lower: np.ndarray
    upper: np.ndarray
    config: Mapping[str, Any]
    key_joints: tuple[int, ...]
    chain: Sequence[Joint]
    tool: np.ndarray

    def fk_axes(self, q: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
