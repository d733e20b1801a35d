"""What an arm model can do, as structural protocols: the one way to ask "does this arm have a swivel?".

* :class:`AnalyticIK`: a closed-form ``ik(T, ...)`` returning every in-limit solution, ``ik_batch``
  and ``ik_nearest`` (the swivel arms and the 6-DOF PowerCube arm).
* :class:`SwivelKinematics`: a 7-DOF arm whose self-motion is the elbow swivel: ``ik(T, swivel)``,
  ``ik_u``, ``swivel``, ``elbow_circle``, ``feasible_swivels`` and the batched nearest solve.

* :class:`ControlledArm`: what the reaching controller uses of an arm (:class:`AnalyticIK` plus forward
  kinematics, the Jacobian, the capsule model's key points, the velocity and acceleration limits);
  :class:`ControlledSwivelArm` adds the swivel (the 7-DOF arms), :class:`ControlledArm6` the link lengths
  (the 6-DOF PowerCube arm); :class:`CorridorArm` what the straight and via routes use (the swivel
  corridor of a straight route and the limit check).

Ask with :func:`has_swivel` / :func:`has_analytic_ik` (``isinstance`` against the protocol); a generic
serial chain has neither and is solved numerically. This module imports nothing from the models, so
every kinematics module can depend on it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["AnalyticIK", "ControlledArm", "ControlledArm6", "ControlledSwivelArm", "CorridorArm",
           "SwivelKinematics", "has_swivel", "has_analytic_ik"]


@runtime_checkable
class AnalyticIK(Protocol):
    """A model with a closed-form IK: every in-limit solution of a pose, and a batched form."""

    name: str
    n: int
    lower: np.ndarray
    upper: np.ndarray

    def ik(self, T: np.ndarray, *args: Any, **kwargs: Any) -> np.ndarray: ...

    def ik_batch(self, Ts: np.ndarray, *args: Any, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]: ...

    def ik_nearest(self, T: np.ndarray, q_seed: Sequence[float], **kwargs: Any) -> tuple[Any, Any]: ...


@runtime_checkable
class SwivelKinematics(AnalyticIK, Protocol):
    """A 7-DOF arm parameterised by the elbow swivel angle s (rad): self-motion on the elbow circle."""

    def ik_u(self, T: np.ndarray, u: Sequence[float], **kwargs: Any) -> np.ndarray: ...

    def swivel(self, q: Sequence[float]) -> float: ...

    def elbow_circle(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]: ...

    def feasible_swivels(self, T: np.ndarray) -> list[np.ndarray]: ...

    def ik_nearest_batch(self, Ts: np.ndarray, q_seeds: np.ndarray, **kwargs: Any) -> Any: ...


@runtime_checkable
class ControlledArm(AnalyticIK, Protocol):
    """An arm the reaching controller can run: closed-form IK, and (units m, rad, s) ``max_vel`` and
    ``max_acc`` per joint, ``fk``, ``jacobian``, the five ``key_points`` of the capsule model (base,
    shoulder, elbow, wrist, tool) and the checks of a joint vector and a pose. The swivel arms add
    :class:`SwivelKinematics`."""

    max_vel: np.ndarray
    max_acc: np.ndarray

    def fk(self, q: Sequence[float]) -> np.ndarray: ...

    def jacobian(self, q: Sequence[float]) -> np.ndarray: ...

    def key_points(self, q: Sequence[float]) -> np.ndarray: ...

    def check_q(self, q: Any, field: str = "q") -> np.ndarray: ...

    def check_pose(self, T: Any, field: str = "T") -> list[list[float]]: ...


@runtime_checkable
class ControlledSwivelArm(ControlledArm, SwivelKinematics, Protocol):
    """A 7-DOF swivel arm the reaching controller runs: :class:`ControlledArm` and
    :class:`SwivelKinematics`."""


@runtime_checkable
class CorridorArm(ControlledSwivelArm, Protocol):
    """A swivel arm the corridor and via routes plan on (:mod:`redarm_ros.control.corridor_route`,
    :mod:`redarm_ros.control.via_route`): :class:`ControlledSwivelArm`, the swivel corridor of a
    straight route (:func:`redarm_ros.kinematics.corridor.swivel_corridor`) and the limit check."""

    def swivel_corridor(self, T_start: np.ndarray, T_goal: np.ndarray, q_start: Sequence[float],
                        **options: Any) -> Any: ...

    def within_limits(self, q: np.ndarray, tol: float = ...) -> bool: ...


@runtime_checkable
class ControlledArm6(ControlledArm, Protocol):
    """The 6-DOF PowerCube arm the reaching controller runs (joint 3 locked, no self-motion):
    :class:`ControlledArm` and its ``link_lengths`` (m: L1, L23, L4, L56)."""

    link_lengths: tuple[float, ...]


def has_swivel(arm: object) -> bool:
    """True if ``arm`` has the closed-form swivel IK (:class:`SwivelKinematics`)."""
    return isinstance(arm, SwivelKinematics)


def has_analytic_ik(arm: object) -> bool:
    """True if ``arm`` has a closed-form ``ik`` listing every in-limit solution (:class:`AnalyticIK`)."""
    return isinstance(arm, AnalyticIK)
