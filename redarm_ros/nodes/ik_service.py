"""IK service node: ``~/solve_ik`` (redarm_interfaces/srv/SolveIK) for one or more arm models.

Wiring only: the maths lives in :mod:`redarm_ros.kinematics` (closed-form swivel IK, analytic
PowerCube IK, numeric fallback). This module turns a request into a pose matrix, picks the solver
call and turns the answer into a response. Every request gets an answer with a status code; a bad
request never reaches the solver and never takes the node down.

Run: ``ros2 run redarm_ros ik_service --ros-args -p arms:="[pa10, powercube7]"``
(or ``python -m redarm_ros.nodes.ik_service``). Parameters, service and examples: docs/nodes.md.

Conventions: SI units (m, rad, s); quaternions in messages are (x, y, z, w) as in geometry_msgs and
converted to the kinematics core's (w, x, y, z) here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from rclpy.node import Node
from redarm_interfaces.srv import SolveIK
from trajectory_msgs.msg import JointTrajectoryPoint

from redarm_ros.errors import InvalidInputError, RedarmError, UnreachableError
from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.result import IKInfo, IKStatus
from redarm_ros.nodes._common import (
    ParamSpec,
    check_unique_node_name,
    declare_params,
    non_negative,
    pose_msg_to_matrix,
    positive,
    run_node,
    watch_duplicates,
)

NODE_NAME = "ik_service"

# IKStatus of the kinematics core -> SolveIK response code.
_STATUS_CODE = {
    IKStatus.SUCCESS: SolveIK.Response.SUCCESS,
    IKStatus.NO_SOLUTION_IN_LIMITS: SolveIK.Response.NO_SOLUTION_IN_LIMITS,
    IKStatus.OUT_OF_REACH: SolveIK.Response.OUT_OF_REACH,
    IKStatus.INVALID_INPUT: SolveIK.Response.INVALID_INPUT,
    IKStatus.TIMEOUT: SolveIK.Response.TIMEOUT,
}
STATUS_NAMES = {code: st.name for st, code in _STATUS_CODE.items()}


def _non_empty_string_list(value: Any) -> str | None:
    if not isinstance(value, (list, tuple)) or not value or not all(isinstance(v, str) and v for v in value):
        return "must be a non-empty list of arm names"
    return None


def _non_empty_string(value: Any) -> str | None:
    return None if isinstance(value, str) and value else "must be a non-empty string"


PARAMS = [
    ParamSpec(
        "arms",
        ["pa10", "pa10_7c", "powercube6", "powercube7"],
        "Arm models served (names of config/arms/<name>.yaml, or paths).",
        _non_empty_string_list,
        read_only=True,
    ),
    ParamSpec(
        "default_arm",
        "pa10",
        "Arm used when a request leaves `arm` empty; must be in `arms`.",
        _non_empty_string,
        read_only=True,
    ),
    ParamSpec(
        "base_frame",
        "base_link",
        "Frame the targets must be given in (an empty frame_id means this frame).",
        _non_empty_string,
    ),
    ParamSpec(
        "quaternion_tolerance",
        1e-3,
        "Largest accepted | |q| - 1 | of a target quaternion; within it the quaternion is renormalised.",
        positive,
    ),
    ParamSpec(
        "default_timeout", 0.05, "Solver time budget (s) when a request leaves `timeout` at 0.", positive
    ),
    ParamSpec(
        "duplicate_check_s",
        1.0,
        "At start-up, watch the ROS graph this long (s) for another node of the same name and "
        "refuse to start if there is one (0 = no check).",
        non_negative,
        read_only=True,
    ),
]


# ----------------------------------------------------------------------------------------------
# Plain-Python request handling (no rclpy types beyond the message fields read here)
# ----------------------------------------------------------------------------------------------
@dataclass
class IKAnswer:
    """What the service returns, independent of the message type.

    ``status`` is an :class:`IKStatus`; ``q`` the chosen joint vector (rad) or None; ``solutions`` all
    in-limit solutions (k, n) when asked; ``swivel`` (rad) of ``q`` or NaN; errors in m and rad.
    """

    status: IKStatus
    message: str = ""
    q: np.ndarray | None = None
    solutions: np.ndarray | None = None
    swivel: float = math.nan
    position_error: float = math.nan
    orientation_error: float = math.nan
    joint_names: list[str] = field(default_factory=list)


class IKFrontEnd:
    """Validates SolveIK-style requests and calls the kinematics core; no ROS here.

    ``arms`` maps names to loaded arm models. Units: m, rad, s.
    """

    def __init__(self, arms: dict[str, Any], default_arm: str) -> None:
        if default_arm not in arms:
            raise InvalidInputError(
                f"default_arm {default_arm!r} is not among the served arms {sorted(arms)}",
                field="default_arm",
                value=default_arm,
            )
        self.arms = arms
        self.default_arm = default_arm

    def arm_for(self, name: str) -> Any:
        """The model named ``name`` ('' = the default arm); InvalidInputError if not served."""
        key = name or self.default_arm
        arm = self.arms.get(key)
        if arm is None:
            raise InvalidInputError(
                f"unknown arm {key!r}; this service serves: {', '.join(sorted(self.arms))}",
                field="arm",
                value=key,
            )
        return arm

    @staticmethod
    def seed_for(arm: Any, seed: Sequence[float]) -> np.ndarray:
        """The seed as an (n,) array clipped into the limits; mid-range when ``seed`` is empty."""
        if len(seed) == 0:
            return (arm.lower + arm.upper) / 2.0
        if len(seed) != arm.n:
            raise InvalidInputError(
                f"seed has {len(seed)} values but arm {arm.name!r} has {arm.n} joints",
                field="seed",
                value=list(seed),
            )
        q = np.asarray(seed, dtype=float)
        if not np.all(np.isfinite(q)):
            raise InvalidInputError("seed contains NaN or inf", field="seed", value=list(seed))
        # A seed is only a preference: an out-of-limit one is pulled onto the limits, not refused.
        return np.clip(q, arm.lower, arm.upper)

    def solve(
        self,
        T: np.ndarray,
        arm_name: str,
        *,
        swivel: float | None,
        seed: Sequence[float],
        all_solutions: bool,
        timeout_s: float,
    ) -> IKAnswer:
        """Solve one request. ``swivel`` None: nearest solution to the seed over all swivels.

        Returns an :class:`IKAnswer`; raises only :class:`InvalidInputError` for malformed input.
        """
        arm = self.arm_for(arm_name)
        q_seed = self.seed_for(arm, seed)
        if swivel is not None:
            ans = self._solve_at_swivel(arm, T, swivel, q_seed, all_solutions)
        else:
            ans = self._solve_nearest(arm, T, q_seed, all_solutions, timeout_s)
        ans.joint_names = list(arm.joint_names)
        if ans.q is not None:
            ans.position_error, ans.orientation_error = arm.pose_error(ans.q, T)
        return ans

    def _solve_at_swivel(
        self, arm: Any, T: np.ndarray, swivel: float, q_seed: np.ndarray, all_solutions: bool
    ) -> IKAnswer:
        if not math.isfinite(swivel):
            raise InvalidInputError(f"swivel must be finite, got {swivel}", field="swivel", value=swivel)
        if not _closed_form(arm):
            raise InvalidInputError(
                f"arm {arm.name!r} has no swivel parameterisation (kind {arm.kind}); "
                "leave swivel_given false",
                field="swivel",
                value=swivel,
            )
        # Every in-limit 2*pi copy of every solution: the answer is the one nearest the seed.
        copies = np.asarray(arm.ik(T, swivel, all_copies=True), dtype=float).reshape(-1, arm.n)
        if len(copies) == 0:
            # Tell "unreachable" from "reachable but not at this swivel / not within the limits".
            _, info = arm.ik_nearest(T, q_seed)
            if info.status is IKStatus.OUT_OF_REACH:
                return IKAnswer(IKStatus.OUT_OF_REACH, info.message, swivel=swivel)
            if info.status is IKStatus.SUCCESS:
                hint = f"; solutions exist at other swivels, e.g. {info.swivel:.4f} rad"
            else:
                hint = f"; {info.message}"
            return IKAnswer(
                IKStatus.NO_SOLUTION_IN_LIMITS,
                f"no solution within the joint limits at swivel {swivel:.4f} rad{hint}",
                swivel=swivel,
            )
        q = copies[int(np.argmin(((copies - q_seed) ** 2).sum(axis=1)))]
        # `solutions` lists each solution once, wrapped near 0 (the closed form's default).
        sols = np.asarray(arm.ik(T, swivel), dtype=float).reshape(-1, arm.n) if all_solutions else None
        return IKAnswer(IKStatus.SUCCESS, "", q=q, solutions=sols, swivel=float(arm.swivel(q)))

    @staticmethod
    def _solve_nearest(
        arm: Any, T: np.ndarray, q_seed: np.ndarray, all_solutions: bool, timeout_s: float
    ) -> IKAnswer:
        q, info = arm.ik_nearest(T, q_seed, timeout_s=timeout_s)
        info = info if isinstance(info, IKInfo) else IKInfo(IKStatus.INVALID_INPUT, str(info))
        if q is None or info.status is not IKStatus.SUCCESS:
            if info.status is IKStatus.INVALID_INPUT:
                raise InvalidInputError(info.message or "invalid request")
            return IKAnswer(info.status, info.message, q=None if q is None else np.asarray(q, dtype=float))
        q = np.asarray(q, dtype=float)
        sw = math.nan if info.swivel is None else float(info.swivel)
        sols = None
        if all_solutions:
            if _closed_form(arm) and math.isfinite(sw):
                sols = np.asarray(arm.ik(T, sw), dtype=float).reshape(-1, arm.n)
            if sols is None or len(sols) == 0:
                sols = q.reshape(1, -1)
        return IKAnswer(IKStatus.SUCCESS, "", q=q, solutions=sols, swivel=sw)


def _closed_form(arm: Any) -> bool:
    """True if the model has a closed-form ``ik(T, swivel)`` (a generic chain has none)."""
    return getattr(arm, "kind", "chain") != "chain"


# ----------------------------------------------------------------------------------------------
# The node
# ----------------------------------------------------------------------------------------------
class IKServiceNode(Node):
    """``ik_service``: serves ``~/solve_ik`` (redarm_interfaces/srv/SolveIK) for the configured arms."""

    def __init__(
        self,
        *,
        context: Any = None,
        parameter_overrides: list[Any] | None = None,
        node_name: str = NODE_NAME,
        namespace: str | None = None,
    ) -> None:
        super().__init__(
            node_name, namespace=namespace, context=context, parameter_overrides=parameter_overrides or []
        )
        p = declare_params(self, PARAMS)
        arms: dict[str, Any] = {}
        for name in p["arms"]:
            try:
                arm = load_arm(name)
            except RedarmError as exc:
                raise ValueError(f"parameter arms: cannot load arm {name!r}: {exc}") from exc
            arms[name] = arm
            if arm.name != name:  # a path was given: also answer to the model's own name
                arms.setdefault(arm.name, arm)
        try:
            self.front = IKFrontEnd(arms, p["default_arm"])
        except InvalidInputError as exc:
            raise ValueError(str(exc)) from exc
        check_unique_node_name(self, p["duplicate_check_s"])
        watch_duplicates(self)
        self.requests = 0
        self.failures = 0
        self.srv = self.create_service(SolveIK, "~/solve_ik", self._on_solve)
        self.get_logger().info(
            f"serving {self.get_fully_qualified_name()}/solve_ik for arms {', '.join(sorted(arms))} "
            f"(default {p['default_arm']}, targets in frame '{p['base_frame']}')"
        )

    # Short callback: read parameters, delegate, convert.
    def _on_solve(self, req: SolveIK.Request, resp: SolveIK.Response) -> SolveIK.Response:
        self.requests += 1
        base_frame = self.get_parameter("base_frame").value
        try:
            ans = self._answer(req, base_frame)
        except InvalidInputError as exc:
            ans = IKAnswer(IKStatus.INVALID_INPUT, str(exc))
        except UnreachableError as exc:
            ans = IKAnswer(IKStatus.OUT_OF_REACH, str(exc))
        except RedarmError as exc:
            ans = IKAnswer(IKStatus.INVALID_INPUT, f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001 - a solver bug must not take the service down
            self.get_logger().error(f"internal error on request for arm {req.arm!r}: {exc!r}")
            ans = IKAnswer(IKStatus.INVALID_INPUT, f"internal error: {type(exc).__name__}: {exc}")
        self._fill(resp, ans, base_frame)
        if ans.status is IKStatus.SUCCESS:
            self.get_logger().debug(
                f"solved for {req.arm or self.front.default_arm}: swivel {ans.swivel:.4f}, "
                f"pos err {ans.position_error:.2e} m"
            )
        else:
            self.failures += 1
            self.get_logger().info(
                f"request {self.requests} ({req.arm or self.front.default_arm}): "
                f"{ans.status.name}: {ans.message}"
            )
        return resp

    def _answer(self, req: SolveIK.Request, base_frame: str) -> IKAnswer:
        frame = req.target.header.frame_id
        if frame and frame.lstrip("/") != base_frame:
            raise InvalidInputError(
                f"cannot transform the target from frame {frame!r}: this service has no tf; "
                f"give the pose in {base_frame!r} (or leave frame_id empty)",
                field="target.header.frame_id",
                value=frame,
            )
        T = pose_msg_to_matrix(req.target.pose, self.get_parameter("quaternion_tolerance").value)
        timeout = float(req.timeout)
        if not math.isfinite(timeout) or timeout < 0:
            raise InvalidInputError(f"timeout must be >= 0 s, got {timeout}", field="timeout", value=timeout)
        if timeout == 0:
            timeout = float(self.get_parameter("default_timeout").value)
        return self.front.solve(
            T,
            req.arm,
            swivel=float(req.swivel) if req.swivel_given else None,
            seed=list(req.seed),
            all_solutions=req.all_solutions,
            timeout_s=timeout,
        )

    def _fill(self, resp: SolveIK.Response, ans: IKAnswer, base_frame: str) -> None:
        resp.status = _STATUS_CODE[ans.status]
        resp.message = ans.message
        resp.swivel = float(ans.swivel)
        resp.position_error = float(ans.position_error)
        resp.orientation_error = float(ans.orientation_error)
        if ans.q is not None and ans.status in (IKStatus.SUCCESS, IKStatus.TIMEOUT):
            js = resp.solution
            js.header.stamp = self.get_clock().now().to_msg()
            js.header.frame_id = base_frame
            js.name = ans.joint_names
            js.position = ans.q.tolist()
        if ans.solutions is not None:
            resp.solutions = [
                JointTrajectoryPoint(positions=[float(v) for v in row]) for row in ans.solutions
            ]


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``ros2 run redarm_ros ik_service``)."""
    return run_node(IKServiceNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
