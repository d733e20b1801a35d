"""The attractor dynamics of point goals (heading, speed and orientation: the attractor paper's eq.
17-21; the swivel is the redundancy strategy's, :mod:`~redarm_ros.control.redundancy`), and the hand
along a straight corridor route. :class:`AttractorLaw` is the part of
:class:`~redarm_ros.control.reach_controller.ReachController` that moves the reference towards a point
goal; its methods take the controller's :class:`~redarm_ros.control.state.CoreState` and parameters.
Units: m, rad, s.
"""

from __future__ import annotations

import math

import numpy as np

from redarm_ros.control.attractor import HeadingDynamics, SpeedProfile, direction, heading_angles
from redarm_ros.control.command import SMALL_SCENE, CommandShaper, SceneView
from redarm_ros.control.corridor_route import CorridorRoute
from redarm_ros.control.elbow import ElbowCircle
from redarm_ros.control.ik_step import DeadEnd
from redarm_ros.control.joint_limits import JointBounds, braking_speed, joint_share_acc
from redarm_ros.control.paper_redundancy import MODE as PAPER_MODE
from redarm_ros.control.paper_redundancy import TangentHand
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.redundancy import Redundancy
from redarm_ros.control.slide import obstacle_slide, workspace_slide
from redarm_ros.control.state import CoreState
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.control.types import Quat, Vec3
from redarm_ros.kinematics.quaternion import (
    quat_between_vectors,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_rotate,
    rotvec_between,
    slerp_vectors,
)


class AttractorLaw:
    """The attractor law of point goals (see the module docstring): its dynamics built from ``params``
    (heading, speed, the paper's hand orientation), the ``redundancy`` strategy (IK stepper and swivel),
    the ``command`` part, the joint ``bounds``, the ``view`` of the scene and the wrist ``shell`` (inner
    and outer radius, m) the workspace slide keeps to."""

    def __init__(self, params: ControllerParams, redundancy: Redundancy, command: CommandShaper,
                 bounds: JointBounds, view: SceneView, shell: tuple[float, float]) -> None:
        self.heading_dyn = HeadingDynamics(params.heading)
        self.speed_profile = SpeedProfile(params.speed)
        self.tangent_hand = TangentHand(params.paper_swivel)
        self.redundancy = redundancy
        self.command = command
        self.bounds = bounds
        self.view = view
        self.shell = shell

    def enter(self, st: CoreState) -> None:
        """Attractor state continuous with the reference's motion (heading = motion direction)."""
        v = st.ref.vel
        n = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if n > 1e-4:
            st.att.phi, st.att.theta = heading_angles(v, st.att.phi)
        else:
            st.att.phi, st.att.theta = self.heading_to_goal(st)
        st.att.v, st.att.a, st.att.turn, st.att.v_cap = n, 0.0, (0.0, 0.0), None

    def take_corridor(self, st: CoreState, p: ControllerParams, route: CorridorRoute) -> None:
        """Follow ``route`` from now on."""
        st.route = route
        st.progress.due = st.time + p.replan.overdue_factor * route.duration + p.replan.overdue_slack
        st.att.v, st.att.a, st.att.turn, st.att.v_cap = 0.0, 0.0, (0.0, 0.0), None

    def _route_step(self, st: CoreState, p: ControllerParams, dt: float) -> None:
        """The hand one step along the corridor route (minimum-jerk pace), the swivel on its schedule at
        the hand's progress. The route ends (the attractor dynamics takes over for the settling) at its
        end, when the goal is dropped, or when the IK step or the guard cannot follow it."""
        route = st.route
        assert route is not None
        ref = st.ref
        if st.goal is None:
            st.route = None
            self.enter(st)
            return
        if route.t == 0.0:
            route.t_moved = st.time
        t_before = route.t
        route.t = min(route.t + dt, route.duration)
        u = route.progress_at(route.t)
        new_pos, new_rot = route.pose(u)
        s_goal = wrap_angle(route.corridor.swivel_at(u))

        def swivel(_circle: ElbowCircle, _T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            ref.sdot_want = wrap_angle(s_goal - s0) / dt
            ref.want_over_since = math.inf
            ref.s_des = s_goal
            return s_goal, s_goal, False

        out = self.redundancy.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, new_pos, new_rot, dt, swivel)
        if isinstance(out, DeadEnd):
            st.route = None
            self.command.hold(st, f"the corridor route cannot be followed here ({out.reason}): attractor "
                                  "dynamics")
            self.command.track(st, dt)
            return
        if out.speed_scale < 1.0 - 1e-9 or abs(wrap_angle(out.s - s_goal)) > 1e-6:
            # the step was shortened (a joint limit of speed) or the swivel moved off the schedule: the
            # profile's clock goes back to the progress reached
            u_now = route.progress_of(out.pos, out.rot)
            route.t = route.time_at(u_now)
        if route.t > t_before + 1e-9 or route.t >= route.duration:
            route.t_moved = st.time
        elif st.time - route.t_moved >= p.replan.hold_time:
            # the IK step keeps shortening the step or moving the swivel off the schedule: leave the route
            st.route = None
            done = 100.0 * route.progress_of(ref.pos, ref.rot)
            st.message = f"the corridor route stalled at {done:.0f} %: attractor dynamics"
            self.enter(st)
            return
        v_before = ref.v_tool
        if not self.command.commit(st, p, out, dt):
            st.route = None  # the guard refused: the attractor dynamics and the re-planner as before
            return
        st.att.v = ref.v_tool
        st.att.a = (ref.v_tool - v_before) / dt
        if route.t >= route.duration:
            st.route = None
            st.att.v, st.att.a = 0.0, 0.0
            st.att.phi, st.att.theta = self.heading_to_goal(st)
            if st.message == route.message():
                st.message = ""

    def step(self, st: CoreState, p: ControllerParams, dt: float) -> None:
        """One step of the reference towards the point goal (or, without one, braking along the
        heading): along the corridor route while there is one, else the attractor dynamics."""
        if st.route is not None:
            self._route_step(st, p, dt)
            return
        ref, att = st.ref, st.att
        pos, rot = ref.pos, ref.rot
        goal_p = st.goal.pos if st.goal is not None else None
        dist = math.inf
        # 1-2. heading and speed
        if goal_p is not None:
            dist = math.dist(pos, goal_p)
            reach = self.view.index.reach_scene
            ahead = reach.scene.obstacles if len(reach.index) <= SMALL_SCENE else \
                self.view.index.ahead(pos, dist + 0.3 + p.heading.target_gate * 10.0).scene.obstacles
            att.phi, att.theta, rates = self.heading_dyn.step(att.phi, att.theta, dt, pos, goal_p, ahead,
                                                              att.turn)
            att.turn = rates.applied
            cap = att.v_cap
            if rates.speed_factor < 1.0:
                v_obs = rates.speed_factor * self.speed_profile.params.v_max
                cap = v_obs if cap is None else min(cap, v_obs)
            v_stop = self._joint_braking_speed(st, p, dist)
            if v_stop is not None:
                cap = v_stop if cap is None else min(cap, v_stop)
            cmd = st.cmd
            if cmd.obs_rate > 1e-4 and att.v > 1e-3:
                # Stopping distance: the clearance the arm would lose while its joints brake at their
                # acceleration limits (~ rate * t_stop / 2) must stay within stop_share of the
                # clearance left; the swivel meanwhile turns the elbow away.
                t_stop = float((np.abs(cmd.qd) / self.bounds.max_acc).max())
                loss = cmd.obs_rate * (0.5 * t_stop + dt)
                room = p.stop_share * max(cmd.obs_clear - p.collision_margin, 0.0)
                if loss > room:
                    v_stop = att.v * math.sqrt(room / loss)
                    cap = v_stop if cap is None else min(cap, v_stop)
            att.v, att.a = self.speed_profile.step(att.v, att.a, dist, dt, cap, self._hand_acc(st, p))
        else:  # no goal: decelerate along the current heading (jerk-limited, like any speed change)
            att.v, att.a = self.speed_profile.step(att.v, att.a, math.inf, dt, 0.0)
            if att.v < 1e-4:
                att.v, att.a = 0.0, 0.0
        e = direction(att.phi, att.theta)
        if goal_p is not None and dist < p.final_distance:
            # Final approach: blend towards the straight line so that a heading which ended up
            # opposite to the target (an unstable but balanced state) cannot carry the hand away.
            w = 1.0 - dist / p.final_distance
            g = ((goal_p[0] - pos[0]) / dist, (goal_p[1] - pos[1]) / dist, (goal_p[2] - pos[2]) / dist) \
                if dist > 1e-12 else e
            m = ((1.0 - w) * e[0] + w * g[0], (1.0 - w) * e[1] + w * g[1], (1.0 - w) * e[2] + w * g[2])
            mn = math.sqrt(m[0] ** 2 + m[1] ** 2 + m[2] ** 2)
            e = (m[0] / mn, m[1] / mn, m[2] / mn) if mn > 1e-9 else g
        e = workspace_slide(e, pos, rot, self.redundancy.slide_geom(st), *self.shell,
                            p.workspace_margin)
        if goal_p is None or dist > p.final_distance:  # (the goal itself was checked clear)
            e = obstacle_slide(e, ref.circle, ref.s, self.view.local.scene, p.capsules, p.slide_band)
        step_len = att.v * dt
        if goal_p is not None:
            step_len = min(step_len, dist)
        new_pos = (pos[0] + step_len * e[0], pos[1] + step_len * e[1], pos[2] + step_len * e[2])
        # 3. orientation
        new_rot = rot
        if st.goal is not None:
            target_rot = self._orientation_target(st, p, e, dist if goal_p is not None else 0.0)
            w = rotvec_between(rot, target_rot)
            wn = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
            # Rate of the attractor, clamped, and changed by at most max_ori_acc per second (braking
            # in time): without this the rate jumps when a goal is set.
            ori_acc = joint_share_acc(ref.w_ori, p.max_ori_acc, ref.qd, self.bounds.max_acc,
                                      p.joint_brake_share)
            rate = min(p.lam_ori * wn, p.max_ori_rate, float(braking_speed(wn, ori_acc, dt)))
            rate = max(0.0, min(rate, ref.w_ori + ori_acc * dt))
            gain = min(rate * dt / wn, 1.0) if wn > 1e-12 else 0.0
            new_rot = quat_normalize(quat_mul(quat_from_rotvec((gain * w[0], gain * w[1], gain * w[2])), rot))
        # 4-5. swivel and IK (with velocity scaling / swivel search / hold)
        out = self.redundancy.stepper.advance(pos, rot, ref.s, ref.q, new_pos, new_rot, dt,
                                              self.redundancy.swivel_fn(st, p, dt, self.view.local.scene))
        if isinstance(out, DeadEnd):
            att.v *= out.speed_scale
            self.command.hold(st, out.reason)
            self.command.track(st, dt)  # the command brakes onto the (standing) reference
            return
        att.v *= out.speed_scale
        ratio = self.command.speed_ratio(st, out.q, dt)
        if self.command.commit(st, p, out, dt):
            self._speed_budget(st, p, ratio, st.ref.v_tool, dt)

    def _hand_acc(self, st: CoreState, p: ControllerParams) -> float | None:
        """Largest hand acceleration (m/s^2) along the path that keeps every joint within
        ``joint_brake_share`` of its acceleration limit, with joint speeds proportional to the hand
        speed; None when the hand is (nearly) at rest."""
        a = joint_share_acc(st.ref.v_tool, math.inf, st.ref.qd, self.bounds.max_acc, p.joint_brake_share)
        return None if math.isinf(a) else a

    def _joint_braking_speed(self, st: CoreState, p: ControllerParams, dist: float) -> float | None:
        """Hand speed (m/s) from which the hand can still stop within the remaining ``dist`` (m) at the
        acceleration of :meth:`_hand_acc`."""
        a_hand = self._hand_acc(st, p)
        if a_hand is None:
            return None
        return math.sqrt(2.0 * a_hand * max(dist, 0.0))

    def _orientation_target(self, st: CoreState, p: ControllerParams, e: Vec3, dist: float) -> Quat:
        """Goal orientation, turned so that the tool axis leans towards the heading far from the goal."""
        assert st.goal is not None
        goal_q = st.goal.rot
        if p.swivel_mode == PAPER_MODE:  # eq. 20-21: the hand trails the path tangent e
            tangent = e if st.att.v >= 1e-3 else None
            return self.tangent_hand.target(st.goal, goal_q, st.ref.rot, tangent, dist, p.dt)
        if p.tangent_weight <= 0.0 or st.att.v < 1e-3:
            return goal_q
        w = p.tangent_weight * max(0.0, min(1.0, (dist - p.tangent_distance) / p.tangent_distance))
        if w <= 0.0:
            return goal_q
        g = quat_rotate(goal_q, (0.0, 0.0, 1.0))  # tool approach axis at the goal
        a = slerp_vectors(g, e, w)
        return quat_normalize(quat_mul(quat_between_vectors(g, a), goal_q))

    @staticmethod
    def heading_to_goal(st: CoreState) -> tuple[float, float]:
        """The heading (azimuth, elevation) straight at the goal; the current one without a goal."""
        if st.goal is None:
            return st.att.phi, st.att.theta
        gp, cp = st.goal.pos, st.ref.pos
        return heading_angles((gp[0] - cp[0], gp[1] - cp[1], gp[2] - cp[2]), st.att.phi)

    def _speed_budget(self, st: CoreState, p: ControllerParams, ratio: float, v_now: float,
                      dt: float) -> None:
        """When a joint nears its velocity limit, when the reference asks a joint for much of its
        acceleration, or when the command lags behind the reference, cap the hand speed ahead of
        time (the filter then slows down with bounded jerk)."""
        att = st.att
        sp = self.speed_profile.params
        predicted = ratio + 4.0 * max(ratio - att.ratio, 0.0)  # the ratio can grow fast in turns
        att.ratio = ratio
        cap = math.inf
        if predicted > 0.85 and v_now > 1e-4:
            cap = max(v_now * 0.85 / predicted, 0.02)
        lag = float((np.abs(st.ref.q - st.cmd.q) * self.bounds.inv_vel).max())  # s at full joint speed
        if lag > p.max_lag and v_now > 1e-3:
            cap = min(cap, max(v_now * p.max_lag / lag, 0.02))
        if math.isfinite(cap):
            att.v_cap = cap if att.v_cap is None else min(cap, att.v_cap + sp.a_max * dt)
        elif att.v_cap is not None:
            att.v_cap += 0.5 * sp.a_max * dt
            if att.v_cap > sp.v_max:
                att.v_cap = None
