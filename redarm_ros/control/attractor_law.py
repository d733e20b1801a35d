"""The attractor dynamics of point goals (heading, speed, orientation, swivel; the attractor
paper's eq. 17-24 and the swivel paper's eq. 31) and the route check that decides whether a point goal
goes to them or to the joint-space re-planner. Part of
:class:`~redarm_ros.control.reach_controller.ReachController`. Units: m, rad, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from redarm_ros.control.attractor import direction, heading_angles
from redarm_ros.control.base import SMALL_SCENE, ControllerBase
from redarm_ros.control.corridor_route import CorridorRoute, plan_route
from redarm_ros.control.elbow import ElbowCircle
from redarm_ros.control.ik_step import DeadEnd, pose_matrix
from redarm_ros.control.joint_limits import braking_speed
from redarm_ros.control.paper_redundancy import MODE as PAPER_MODE
from redarm_ros.control.replan import check_route, move_time
from redarm_ros.control.slide import obstacle_slide, workspace_slide
from redarm_ros.control.state import REST_SPEED_SHARE, Mode
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.control.types import Phase, Quat, Vec3
from redarm_ros.kinematics.quaternion import (
    quat_between_vectors,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_rotate,
    rotvec_between,
    slerp_vectors,
)


def _brake_for_limit(sd: float, margins: tuple[float, float, float], eps: float, s_acc: float,
                     dt: float) -> float:
    """The swivel rate ``sd`` (rad/s) capped so that the swivel can still stop, decelerating at
    ``s_acc``, before the nearest joint reaches its limit. ``margins``: the joints' least limit margin
    (rad) at s, s + eps, s - eps. Run into a limit at speed, the IK step would stop the swivel at once,
    and the joints, braking each at its own acceleration limit, would take the hand off its pose."""
    m0, m_plus, m_minus = margins
    slope = ((m_plus if sd > 0.0 else m_minus) - m0) / eps  # margin change per rad of swivel, ahead
    if slope >= 0.0:
        return sd
    cap = float(braking_speed(max(m0, 0.0) / -slope, s_acc, dt))
    return max(-cap, min(cap, sd))


#: swivels sampled along the goal's in-limit swivel interval to find where the elbow can rest
REST_SAMPLES = 64


def _swivel_low(circle: ElbowCircle) -> float | None:
    """Swivel (rad) of the lowest elbow position on the circle; None if the circle is horizontal."""
    az, bz = circle.a[2], circle.b[2]
    if math.hypot(az, bz) < 0.05:
        return None
    return math.atan2(-bz, -az)


class AttractorMixin(ControllerBase):
    """The attractor law of point goals (see the module docstring)."""

    def _enter_attractor(self) -> None:
        """Attractor state continuous with the reference's motion (heading = motion direction)."""
        st = self._state()
        v = st.ref.vel
        n = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if n > 1e-4:
            st.att.phi, st.att.theta = heading_angles(v, st.att.phi)
        else:
            st.att.phi, st.att.theta = self._heading_to_goal()
        st.att.v, st.att.a, st.att.turn, st.att.v_cap = n, 0.0, (0.0, 0.0), None

    def _route_dead_end(self, T: np.ndarray) -> str:
        """Why the attractor should not take the straight route to ``T`` ('' if it should): a dead end
        on it, or joint motion along it much slower than a joint-space move to the nearest goal
        configuration (e.g. through the shoulder singularity, or the long way round a wide joint)."""
        st = self._state()
        p = self.params
        T0 = pose_matrix(st.ref.pos, st.ref.rot)
        if p.swivel_mode == "fixed":
            def s_des(_c: ElbowCircle) -> float:
                return st.ref.s_fixed
        else:
            def s_des(c: ElbowCircle) -> float:
                return self._desired_swivel(c)
        route = check_route(self.stepper, T0, st.ref.s, st.ref.q, T, s_des, p.replan.route_steps,
                            p.speed.v_max, p.max_ori_rate, p.swivel.max_rate)
        # The attractor is given a generous multiple of the route's least time before it counts as
        # overdue (it accelerates gently, slows near obstacles and at the goal).
        st.progress.due = st.time + p.replan.overdue_factor * route.time + p.replan.overdue_slack
        if route.dead_end:
            return route.dead_end
        if route.singular:
            return route.singular
        q_near, info = self.arm.ik_nearest(T, st.ref.q)
        if q_near is None:
            return ""
        t_joint = move_time(np.asarray(q_near, float) - st.ref.q, self._max_vel, self._max_acc)
        if route.time > max(p.replan.slow_route * t_joint, t_joint + 2.0):
            return (f"the straight route needs {route.time:.1f} s of joint motion, a joint-space move "
                    f"{t_joint:.1f} s")
        return ""

    def _corridor_asked(self) -> bool:
        """Is a point goal set now planned through the swivel corridor? Only with the hand at rest, in free
        space (the elbow's obstacle avoidance then keeps the attractor dynamics) and with the swivel
        dynamics in charge of the elbow."""
        st = self._state()
        p = self.params
        scene = self._index.reach_scene.scene
        return bool(p.replan.corridor) and p.swivel_mode not in ("fixed", PAPER_MODE) \
            and not len(scene.obstacles) and scene.table_height is None and st.ref.v_tool <= 0.01 \
            and st.att.v <= 0.01 and hasattr(self.arm, "swivel_corridor")

    def _corridor_job(self, T: np.ndarray) -> Callable[[], tuple[CorridorRoute | None, str]]:
        """The planning of the straight route to the point goal ``T`` through the swivel corridor, from
        the reference as it is now: a function of copies (it runs in the worker thread) that returns the
        route, or None and why there is none."""
        st = self._state()
        p = self.params
        rp = p.replan
        arm, q0 = self.arm, st.ref.q.copy()
        T0, T1 = pose_matrix(st.ref.pos, st.ref.rot), np.array(T, float)
        max_vel, max_acc = self._max_vel.copy(), self._max_acc.copy()

        def job() -> tuple[CorridorRoute | None, str]:
            # the longest route taken: a straight route is worth more patience than the attractor's
            # route. A route slower than that in u is paced (it slows where joints 1 and 3 swing near a
            # singularity)
            q_near, _ = arm.ik_nearest(T1, q0)
            t_most, t_joint = math.inf, math.nan
            if q_near is not None:
                t_joint = move_time(np.asarray(q_near, float) - q0, max_vel, max_acc)
                t_most = max(2.0 * rp.slow_route * t_joint, t_joint + 8.0)
            route, why = plan_route(arm, T0, T1, q0, None, rp.corridor_sing_margin, rp.corridor_limit_margin,
                                    p.speed.v_max, p.max_ori_rate, p.swivel.max_rate, max_vel, max_acc,
                                    rp.corridor_share, pace_after=t_most)
            if route is not None and route.duration > t_most:
                return None, (f"its route needs {route.duration:.1f} s of joint motion, a joint-space move "
                              f"{t_joint:.1f} s")
            return route, why

        return job

    def _take_corridor(self, route: CorridorRoute) -> None:
        """Follow ``route`` from now on."""
        st = self._state()
        p = self.params
        st.route = route
        st.progress.due = st.time + p.replan.overdue_factor * route.duration + p.replan.overdue_slack
        st.att.v, st.att.a, st.att.turn, st.att.v_cap = 0.0, 0.0, (0.0, 0.0), None

    def _route_step(self, dt: float) -> None:
        """The hand one step along the corridor route (minimum-jerk pace), the swivel on its schedule at
        the hand's progress. The route ends (the attractor dynamics takes over for the settling) at its
        end, when the goal is dropped, or when the IK step or the guard cannot follow it."""
        st = self._state()
        route = st.route
        assert route is not None
        ref = st.ref
        if st.goal is None:
            st.route = None
            self._enter_attractor()
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

        out = self.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, new_pos, new_rot, dt, swivel)
        if isinstance(out, DeadEnd):
            st.route = None
            self._hold(f"the corridor route cannot be followed here ({out.reason}): attractor dynamics")
            self._track(dt)
            return
        if out.speed_scale < 1.0 - 1e-9 or abs(wrap_angle(out.s - s_goal)) > 1e-6:
            # the step was shortened (a joint limit of speed) or the swivel moved off the schedule: the
            # profile's clock goes back to the progress reached
            u_now = route.progress_of(out.pos, out.rot)
            route.t = route.time_at(u_now)
        if route.t > t_before + 1e-9 or route.t >= route.duration:
            route.t_moved = st.time
        elif st.time - route.t_moved >= self.params.replan.hold_time:
            # the IK step keeps shortening the step or moving the swivel off the schedule: leave the route
            st.route = None
            done = 100.0 * route.progress_of(ref.pos, ref.rot)
            st.message = f"the corridor route stalled at {done:.0f} %: attractor dynamics"
            self._enter_attractor()
            return
        v_before = ref.v_tool
        if not self._commit(out, dt, attractor=False):
            st.route = None  # the guard refused: the attractor dynamics and the re-planner as before
            return
        st.att.v = ref.v_tool
        st.att.a = (ref.v_tool - v_before) / dt
        if route.t >= route.duration:
            st.route = None
            st.att.v, st.att.a = 0.0, 0.0
            st.att.phi, st.att.theta = self._heading_to_goal()
            if st.message == "straight through the swivel corridor":
                st.message = ""

    def _attractor_step(self, dt: float) -> None:
        st = self._state()
        if st.corridor_plan is not None:
            if not st.corridor_plan.done():  # the arm holds while the worker thread plans
                st.ref.qd = np.zeros_like(st.ref.q)
                self._track(dt)
                return
            route, why = st.corridor_plan.result()
            st.corridor_plan = None
            if route is not None and not self._corridor_asked():  # obstacles came while it was planned
                route, why = None, "the scene changed while it was planned"
            assert st.goal is not None
            self._point_goal_route(pose_matrix(st.goal.pos, st.goal.rot), route, why)
            # this step's command: the planner's (it brakes the arm), or braking onto the reference
            if st.mode is Mode.PLAN:
                self._plan_step(dt)
                return
            if st.mode is not Mode.ATTRACTOR:
                st.ref.qd = np.zeros_like(st.ref.q)
                self._track(dt)
                return
        if st.route is not None:
            self._route_step(dt)
            return
        p = self.params
        ref, att = st.ref, st.att
        pos, rot = ref.pos, ref.rot
        goal_p = st.goal.pos if st.goal is not None else None
        dist = math.inf
        # 1-2. heading and speed
        if goal_p is not None:
            dist = math.dist(pos, goal_p)
            reach = self._index.reach_scene
            ahead = reach.scene.obstacles if len(reach.index) <= SMALL_SCENE else \
                self._index.ahead(pos, dist + 0.3 + p.heading.target_gate * 10.0).scene.obstacles
            att.phi, att.theta, rates = self.heading_dyn.step(att.phi, att.theta, dt, pos, goal_p, ahead,
                                                              att.turn)
            att.turn = rates.applied
            cap = att.v_cap
            if rates.speed_factor < 1.0:
                v_obs = rates.speed_factor * self.speed_profile.params.v_max
                cap = v_obs if cap is None else min(cap, v_obs)
            v_stop = self._joint_braking_speed(dist)
            if v_stop is not None:
                cap = v_stop if cap is None else min(cap, v_stop)
            cmd = st.cmd
            if cmd.obs_rate > 1e-4 and att.v > 1e-3:
                # Stopping distance: the clearance the arm would lose while its joints brake at their
                # acceleration limits (~ rate * t_stop / 2) must stay within stop_share of the
                # clearance left; the swivel meanwhile turns the elbow away.
                t_stop = float(np.max(np.abs(cmd.qd) / self._max_acc))
                loss = cmd.obs_rate * (0.5 * t_stop + dt)
                room = p.stop_share * max(cmd.obs_clear - p.collision_margin, 0.0)
                if loss > room:
                    v_stop = att.v * math.sqrt(room / loss)
                    cap = v_stop if cap is None else min(cap, v_stop)
            att.v, att.a = self.speed_profile.step(att.v, att.a, dist, dt, cap, self._hand_acc())
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
        e = workspace_slide(e, pos, rot, self._slide_geom(pos), self._d_inner, self._d_outer,
                            p.workspace_margin)
        if goal_p is None or dist > p.final_distance:  # (the goal itself was checked clear)
            e = obstacle_slide(e, ref.circle, ref.s, self._local.scene, p.capsules, p.slide_band)
        step_len = att.v * dt
        if goal_p is not None:
            step_len = min(step_len, dist)
        new_pos = (pos[0] + step_len * e[0], pos[1] + step_len * e[1], pos[2] + step_len * e[2])
        # 3. orientation
        new_rot = rot
        if st.goal is not None:
            target_rot = self._orientation_target(e, dist if goal_p is not None else 0.0)
            w = rotvec_between(rot, target_rot)
            wn = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
            # Rate of the attractor, clamped, and changed by at most max_ori_acc per second (braking
            # in time): without this the rate jumps when a goal is set.
            ori_acc = self._joint_share_acc(ref.w_ori, p.max_ori_acc)
            rate = min(p.lam_ori * wn, p.max_ori_rate, float(braking_speed(wn, ori_acc, dt)))
            rate = max(0.0, min(rate, ref.w_ori + ori_acc * dt))
            gain = min(rate * dt / wn, 1.0) if wn > 1e-12 else 0.0
            new_rot = quat_normalize(quat_mul(quat_from_rotvec((gain * w[0], gain * w[1], gain * w[2])), rot))
        # 4-5. swivel and IK (with velocity scaling / swivel search / hold)
        out = self.stepper.advance(pos, rot, ref.s, ref.q, new_pos, new_rot, dt, self._swivel_fn(dt))
        if isinstance(out, DeadEnd):
            att.v *= out.speed_scale
            self._hold(out.reason)
            self._track(dt)  # the command brakes onto the (standing) reference
            return
        att.v *= out.speed_scale
        self._commit(out, dt, attractor=True)

    def _swivel_fn(self, dt: float) -> Any:
        """The swivel the dynamics asks for at a proposed pose (see :data:`ik_step.SwivelFn`)."""
        st = self._state()
        p = self.params
        # Tracking a moving goal, the preferred swivel moves with it (e.g. the highest elbow turns as the
        # wrist moves): its change is fed forward, so the elbow does not lag behind its preference
        # (a lagging elbow costs the joints much more motion than the hand needs).
        feed = st.mode is Mode.SERVO and p.swivel_mode != "fixed" and st.ref.circle is not None
        s_des_prev = self._desired_swivel(st.ref.circle) if feed and st.ref.circle is not None else 0.0
        s_acc_feed = self._swivel_acc_share() if feed else p.max_swivel_acc

        def swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            if p.swivel_mode == "fixed":
                st.ref.sdot_want, st.ref.want_over_since = 0.0, math.inf
                return st.ref.s_fixed, st.ref.s_fixed, False
            s_des = self._desired_swivel(circle)
            margins = None
            if p.swivel_mode == PAPER_MODE:  # the attractor paper's eq. 22-24 (paper_redundancy.py)
                paper = self.paper_swivel.step(circle, T, s0, s_des, st.ref.q, dt, self._local.scene,
                                               self.stepper)
                s_new, clearance = paper.s, paper.clearance
            else:
                margins = self.stepper.limit_margins(T, s0, st.ref.q, p.swivel.eps, p.swivel.lim_threshold)
                forces = self.swivel_dyn.forces(circle, s0, self._local.scene, p.capsules, margins)
                s_new, clearance = self.swivel_dyn.step(s0, s_des, dt, forces), forces.clearance
            # The swivel rate changes by at most max_swivel_acc per second.
            sd = wrap_angle(s_new - s0) / dt
            st.ref.sdot_want = sd  # (the dynamics' own: the feed-forward is added below)
            over = abs(sd) > 2.0 * p.settle_swivel_rate
            st.ref.want_over_since = min(st.ref.want_over_since, st.time) if over else math.inf
            if feed:
                # The dynamics' own rate (attraction, obstacles, limits) within its share of the
                # joints' acceleration; the preferred swivel's motion is fed forward on top.
                sd = max(st.ref.sdot_dyn - s_acc_feed * dt, min(st.ref.sdot_dyn + s_acc_feed * dt, sd))
                st.ref.sdot_dyn = sd
                sd += wrap_angle(s_des - s_des_prev) / dt
            else:
                s_acc = self._joint_share_acc(abs(st.ref.sdot), p.max_swivel_acc)
                sd = max(st.ref.sdot - s_acc * dt, min(st.ref.sdot + s_acc * dt, sd))
                if margins is not None and sd != 0.0:
                    sd = _brake_for_limit(sd, margins, p.swivel.eps, s_acc, dt)
                sd = self._settling_rate_cap(sd)
            st.ref.s_des = s_des
            return wrap_angle(s0 + sd * dt), s_des, clearance < p.elbow_priority_clearance

        return swivel

    def _swivel_acc_share(self) -> float:
        """While tracking: the largest change of the swivel rate (rad/s^2) that keeps every joint within
        ``joint_brake_share`` of its acceleration limit, from how much each joint turns per radian of
        swivel at the reference (the rest is the hand's, which has priority); at most max_swivel_acc."""
        st = self._state()
        p = self.params
        s_acc = p.max_swivel_acc
        T_ref = pose_matrix(st.ref.pos, st.ref.rot)
        pick = self.stepper.solve(T_ref, st.ref.s + 0.01, st.ref.q, 1.0)
        if pick is not None:
            dq_ds = np.abs(pick[0] - st.ref.q) / 0.01
            with np.errstate(divide="ignore"):
                lim = np.where(dq_ds > 1e-9, p.joint_brake_share * self._max_acc / dq_ds, np.inf)
            s_acc = min(s_acc, float(np.min(lim)))
        return s_acc

    def _settling_rate_cap(self, sd: float) -> float:
        """With the hand at the goal, the swivel rate ``sd`` (rad/s) capped so that no joint turns
        faster than ``settle_speed_share`` of its velocity limit (the joint rates of the last step
        scaled with the swivel rate: with the hand still, the joints move with the swivel alone). The
        elbow's way to its preferred swivel is a self-motion nobody waits for; at full joint speed the
        joints could not follow its turns within their acceleration limits and took the hand along."""
        st = self._state()
        p = self.params
        goal = st.goal
        if goal is None or not goal.point_at(st.ref.pos, p.pos_tolerance):
            return sd
        # Once REACHED (the user acts on it), what is left of the elbow's way is a creep that keeps the
        # arm at rest as REACHED defines it: the swivel below its settled rate, every joint below its
        # rest share (near the shoulder singularity a slow swivel turns joints 1 and 3 fast).
        reached = st.phase is Phase.REACHED
        cap = p.settle_swivel_rate if reached else math.inf
        rate = abs(st.ref.sdot)
        ratio = float(np.max(np.abs(st.ref.qd) / self._max_vel))
        if rate >= 1e-9 and ratio >= 1e-12:
            cap = min(cap, (REST_SPEED_SHARE if reached else p.settle_speed_share) * rate / ratio)
        return max(-cap, min(cap, sd))

    def _hand_acc(self) -> float | None:
        """Largest hand acceleration (m/s^2) along the path that keeps every joint within
        ``joint_brake_share`` of its acceleration limit, with joint speeds proportional to the hand
        speed; None when the hand is (nearly) at rest."""
        a = self._joint_share_acc(self._state().ref.v_tool, math.inf)
        return None if math.isinf(a) else a

    def _joint_share_acc(self, rate: float, default: float) -> float:
        """Largest rate of change of ``rate`` (a hand speed or an orientation rate) that keeps every
        joint within ``joint_brake_share`` of its acceleration limit, the joint velocities of the last
        reference step taken as proportional to ``rate``; ``default`` caps it and is used at rest."""
        if rate < 1e-4:  # from rest: a gentle first step, the ratio is measured from the next one
            return min(default, 0.1 * float(np.min(self._max_acc)))
        qd = np.abs(self._state().ref.qd)
        mask = qd > 1e-6
        if not np.any(mask):
            return default
        a = float(np.min(self._max_acc[mask] / qd[mask])) * rate * self.params.joint_brake_share
        return max(min(a, default), 1e-3)

    def _joint_braking_speed(self, dist: float) -> float | None:
        """Hand speed (m/s) from which the hand can still stop within the remaining ``dist`` (m) at the
        acceleration of :meth:`_hand_acc`."""
        a_hand = self._hand_acc()
        if a_hand is None:
            return None
        return math.sqrt(2.0 * a_hand * max(dist, 0.0))

    def _orientation_target(self, e: Vec3, dist: float) -> Quat:
        """Goal orientation, turned so that the tool axis leans towards the heading far from the goal."""
        st = self._state()
        assert st.goal is not None
        p = self.params
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

    def _desired_swivel(self, circle: ElbowCircle) -> float:
        """The preferred swivel at ``circle``, moved where the elbow can rest once the hand is at a point
        goal (:meth:`_feasible_at_goal`); where the circle is horizontal, the last desired swivel."""
        if self.params.swivel_reference != "absolute" and _swivel_low(circle) is None:
            return self._state().ref.s_des
        return self._feasible_at_goal(self._preferred_swivel(circle))

    def _preferred_swivel(self, circle: ElbowCircle) -> float:
        """The preferred swivel (rad) at ``circle``: ``preferred_swivel`` from the highest or lowest elbow
        (``swivel_reference``), or absolute; where the circle is horizontal (no highest elbow), the last
        desired swivel."""
        p = self.params
        if p.swivel_reference == "absolute":
            return wrap_angle(p.preferred_swivel)
        low = _swivel_low(circle)
        if low is None:
            return self._state().ref.s_des
        ref = low if p.swivel_reference == "low" else low + math.pi
        return wrap_angle(ref + p.preferred_swivel)

    def _feasible_at_goal(self, s_des: float) -> float:
        """With the hand at the goal (within twice ``pos_tolerance``), ``s_des`` moved to where the elbow
        can rest: the nearest of :data:`REST_SAMPLES` swivels along the in-limit interval of the arm's
        branch that holds the current swivel (closed form) at which every joint keeps the swivel
        dynamics' ``lim_threshold`` from its limits, or, if none does, the one with the widest margin. A
        preferred swivel beyond a joint limit, or within the joint-limit force's reach, pins the elbow
        where that force and the attraction meet, and it chatters there (joints at 10-15 % of their
        speed, ~2 Hz) and never settles."""
        st = self._state()
        goal = st.goal
        interval = getattr(self.arm, "swivel_interval", None)
        # (from twice the tolerance on: when REACHED is first judged, with the hand within it, the elbow's
        # wanted rate is already the one towards its rest swivel, not the one on the way)
        if goal is None or interval is None or not goal.point_at(st.ref.pos, 2.0 * self.params.pos_tolerance):
            return s_des
        if not goal.rest_known:  # once per goal: the hand stays there
            goal.rest_known = True
            T_goal = pose_matrix(goal.pos, goal.rot)
            # the interval at the goal pose itself (not at the hand's pose, up to 2 mm away): where a
            # joint's extreme along the circle just touches its limit, 2 mm split the interval at a limit
            # on the reference's own branch: with a joint at its limit, 2 mm can take that branch a hair
            # beyond it, and the nearest in-limit solution was another branch (a flipped wrist), whose
            # interval and rest swivel the elbow could not reach
            q_goal = self.stepper.follow(T_goal, st.ref.s, st.ref.q)
            if q_goal is not None:
                q_goal = np.clip(q_goal, self.stepper.lower, self.stepper.upper)
            goal.rest = None if q_goal is None else self._rest_swivels(interval(q_goal), T_goal, q_goal)
        if goal.rest is None:
            return s_des
        a, samples, ok = goal.rest
        x = a + ((s_des - a) % (2.0 * math.pi))  # s_des on the interval's unwrapped axis
        # the nearest sample where the margins were checked (between two of them a joint may still dip
        # into the limit force's reach); the one of last step while it is within a sample spacing of
        # that: a preferred swivel midway between the two ends of a stretch near a limit had them take
        # turns as the hand settled, and the elbow turned back and forth after REACHED
        # (around the circle: a preferred swivel just below the interval's start is nearest to that
        # start, not to its far end, where x lands on the unwrapped axis)
        gap = np.abs(samples - x)
        dist = np.minimum(gap, 2.0 * math.pi - gap) + np.where(ok, 0.0, 1e3)
        k = int(np.argmin(dist))
        last = goal.rest_pick
        if last is not None and len(samples) > 1 and dist[last] <= dist[k] + (samples[1] - samples[0]):
            k = last
        goal.rest_pick = k
        return wrap_angle(float(samples[k]))

    def _rest_swivels(self, iv: tuple[float, float] | None, T: np.ndarray, q0: np.ndarray
                      ) -> tuple[float, np.ndarray, np.ndarray] | None:
        """Samples of the in-limit swivel interval ``iv`` of pose T (the interval's start, the swivels
        unwrapped from it, and which of them keep every joint ``lim_threshold`` inside its limits; if
        none does, only the one with the widest margin counts). ``q0``: the joints at T at the current
        swivel, from which the samples are followed along the elbow circle either way; a sample beyond
        one where a joint passes its limit is out of reach. The interval counts a wide joint in limits
        on any 2 pi copy, but the elbow cannot jump to another copy: a joint 5 at its limit made the
        elbow pull towards a swivel on the far side of that limit, held there, and never settle."""
        if iv is None:
            return None
        a, b = iv
        st = self._state()
        samples = np.linspace(a, b, REST_SAMPLES)
        margins = np.full(REST_SAMPLES, -math.inf)
        x0 = a + (st.ref.s - a) % (2.0 * math.pi)  # the current swivel on the interval's axis
        first_up = int(np.searchsorted(samples, x0))
        for walk in (range(first_up, REST_SAMPLES), range(first_up - 1, -1, -1)):
            q = q0
            for i in walk:
                q = self.stepper.follow(T, wrap_angle(float(samples[i])), q)
                if q is None:
                    break
                margins[i] = self.stepper.margin(q)
                if margins[i] < 0.0:
                    margins[i] = -math.inf
                    break
        if not np.isfinite(margins).any():
            return None
        ok = margins >= self.params.swivel.lim_threshold
        if not ok.any():
            ok = margins >= margins.max()
        return a, samples, ok

    def _heading_to_goal(self) -> tuple[float, float]:
        st = self._state()
        if st.goal is None:
            return st.att.phi, st.att.theta
        gp, cp = st.goal.pos, st.ref.pos
        return heading_angles((gp[0] - cp[0], gp[1] - cp[1], gp[2] - cp[2]), st.att.phi)

    def _speed_budget(self, ratio: float, v_now: float, dt: float) -> None:
        """When a joint nears its velocity limit, when the reference asks a joint for much of its
        acceleration, or when the command lags behind the reference, cap the hand speed ahead of
        time (the filter then slows down with bounded jerk)."""
        st = self._state()
        p = self.params
        att = st.att
        sp = self.speed_profile.params
        predicted = ratio + 4.0 * max(ratio - att.ratio, 0.0)  # the ratio can grow fast in turns
        att.ratio = ratio
        cap = math.inf
        if predicted > 0.85 and v_now > 1e-4:
            cap = max(v_now * 0.85 / predicted, 0.02)
        lag = float(np.max(np.abs(st.ref.q - st.cmd.q) * self._inv_vel))  # s at full joint speed
        if lag > p.max_lag and v_now > 1e-3:
            cap = min(cap, max(v_now * p.max_lag / lag, 0.02))
        if math.isfinite(cap):
            att.v_cap = cap if att.v_cap is None else min(cap, att.v_cap + sp.a_max * dt)
        elif att.v_cap is not None:
            att.v_cap += 0.5 * sp.a_max * dt
            if att.v_cap > sp.v_max:
                att.v_cap = None
