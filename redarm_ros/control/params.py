"""Parameters of the reaching controller (all with units; validated on construction).

:class:`ControllerParams` holds the top-level parameters and the nested groups ``heading``, ``swivel``,
``paper_swivel``, ``speed`` (the attractor dynamics), ``capsules`` (the collision model), ``stream`` (how
goal messages are told apart and how a stream's velocity is estimated), ``servo`` (the tracking law) and
``replan`` (stall detection and the joint-space re-planner). ``ControllerParams.from_dict`` reads the YAML
form.

Every parameter is declared once, with its default, unit, bound and meaning, in the table
``redarm_ros/parameters.yaml``; :mod:`redarm_ros.param_table` builds the classes from it.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from redarm_ros.control.attractor import HeadingParams, SpeedParams
from redarm_ros.control.paper_redundancy import PaperSwivelParams
from redarm_ros.control.swivel_dynamics import SwivelParams
from redarm_ros.errors import ConfigError
from redarm_ros.geometry.obstacles import ArmCapsules
from redarm_ros.param_table import declared, from_mapping, table

__all__ = ["ArmCapsules", "ControllerParams", "HeadingParams", "PaperSwivelParams", "ReplanParams",
           "SWIVEL_MODES", "ServoParams", "SpeedParams", "StreamParams", "SwivelParams"]


@declared("stream")
class StreamParams:
    """How goal messages are told apart and how a stream's velocity is estimated (see
    :mod:`redarm_ros.control.stream`)."""


@declared("servo")
class ServoParams:
    """The tracking law of streams and twists (the reference pose follows the predicted goal; see
    :mod:`redarm_ros.control.servo`)."""


@declared("replan")
class ReplanParams:
    """Stall detection and the joint-space re-planner (see :mod:`redarm_ros.control.replan`)."""


#: The values of ``ControllerParams.swivel_mode``.
SWIVEL_MODES: tuple[str, ...] = table()["controller"].param("swivel_mode").bound.arg

#: Least |elbow pitch| (rad) of ``ControllerParams.unfold_pitch``: the fold posture must be bent.
MIN_FOLD_ELBOW = 0.2


@declared("controller")
class ControllerParams:
    """Controller parameters (units in brackets).

    The nested groups hold the parameters of the dynamics (``heading``, ``swivel``, ``paper_swivel``,
    ``speed``), of the collision model (``capsules``), of goal streams (``stream``), of the tracking law
    (``servo``) and of the re-planner (``replan``); the rest are the top level. Why the default elbow is
    "high": the PA10's shoulder pitch is limited to +/-91 deg, which keeps the elbow above the shoulder
    for every pose; the human-like "low elbow" of the attractor paper (an arm mounted above the table)
    is ``swivel_reference="low"``.
    """

    def __post_init__(self) -> None:
        # Not a bound of its own: the bound (3 finite angles) is checked first, then the elbow.
        if abs(self.unfold_pitch[1]) < MIN_FOLD_ELBOW:
            raise ConfigError(f"ControllerParams.unfold_pitch must be 3 finite angles (rad) with an elbow "
                              f"pitch of at least {MIN_FOLD_ELBOW} rad, got {self.unfold_pitch!r}",
                              field="unfold_pitch", value=self.unfold_pitch)

    def with_(self, **changes: Any) -> ControllerParams:
        """A copy with some fields changed."""
        return replace(self, **changes)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> ControllerParams:
        """Parameters from a (YAML-like) dict; nested dicts for the groups (``heading``, ``swivel``,
        ``paper_swivel``, ``speed``, ``capsules``, ``stream``, ``servo``, ``replan``), e.g.
        ``{"preferred_swivel": 0.3, "speed": {"v_max": 0.25}}``. Missing keys keep their defaults.

        Raises:
            ConfigError: unknown key or bad value (the message names it; ``field`` is its dotted path).
        """
        return from_mapping(cls, d, "controller")
