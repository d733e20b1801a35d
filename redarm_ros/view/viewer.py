"""The browser view's scene and panels on a ``viser`` server (no ROS here).

:class:`ArmViewer` draws, in a ``viser.ViserServer`` (which serves its own bundled web client, so
it works offline):

* the arm from a :class:`~redarm_ros.view.urdf_model.UrdfModel` (primitive visuals; meshes are
  skipped), posed by :meth:`ArmViewer.set_joints`;
* a ground grid at z = 0 and the markers it is given (:meth:`ArmViewer.set_markers`, the
  ``visualization_msgs/Marker`` subset the controller publishes: arrows, spheres, cylinders, cubes,
  line strips/lists, with ADD / DELETE / DELETEALL), in groups so the controller's markers and the
  ``/obstacles`` ones do not overwrite each other;
* a draggable transform gizmo: every drag (or the "Send goal" button) calls ``on_goal`` with the
  gizmo's position (m) and orientation (quaternion x, y, z, w) in the arm's base frame; the
  "Reach (action)" button hands the same pose to ``on_reach``;
* a status panel (:meth:`ArmViewer.set_status`): phase, swivel, clearance, driver state, loop rates;
* optionally a base-placement heat map on the floor under the arm (:meth:`ArmViewer.set_placement`;
  the ground grid then moves down to that floor).

The node :mod:`redarm_ros.nodes.view` feeds it from ROS topics. Units: m, rad.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redarm_ros.view.placement_floor import PlacementFloor, floor_meshes
from redarm_ros.view.urdf_model import UrdfModel, Visual, matrix_to_quat_xyzw

_LOG = logging.getLogger(__name__)

# visualization_msgs/Marker type and action codes (the message's own constants).
ARROW, CUBE, SPHERE, CYLINDER, LINE_STRIP, LINE_LIST = 0, 1, 2, 3, 4, 5
ADD, DELETE, DELETEALL = 0, 2, 3

# Goal callback: position (3,) m and quaternion (x, y, z, w), both in the base frame.
GoalCallback = Callable[[np.ndarray, np.ndarray], None]


@dataclass
class MarkerSpec:
    """The fields of a ``visualization_msgs/Marker`` the view draws (ROS-free copy).

    ``pose`` 4x4 in the base frame, ``scale`` (3,), ``rgba`` 0..1, ``points`` (k, 3) m.
    """

    ns: str
    id: int
    type: int
    action: int = ADD
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    rgba: tuple[float, float, float, float] = (0.5, 0.5, 0.5, 1.0)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


class RateMeter:
    """Arrival rate of a stream over a sliding window (``window_s`` seconds, monotonic clock)."""

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self._t: deque[float] = deque()
        self._lock = threading.Lock()

    def tick(self, now: float | None = None) -> None:
        """Count one arrival at ``now`` (default: ``time.monotonic()``)."""
        t = time.monotonic() if now is None else now
        with self._lock:
            self._t.append(t)
            self._trim(t)

    def _trim(self, now: float) -> None:
        while self._t and now - self._t[0] > self.window_s:
            self._t.popleft()

    def rate(self, now: float | None = None) -> float:
        """Arrivals per second in the window ending at ``now``; 0 with fewer than two."""
        t = time.monotonic() if now is None else now
        with self._lock:
            self._trim(t)
            if len(self._t) < 2:
                return 0.0
            span = self._t[-1] - self._t[0]
            return (len(self._t) - 1) / span if span > 0 else 0.0


@dataclass
class Status:
    """What the status panel shows (NaN / empty = not known yet)."""

    phase: str = ""
    message: str = ""
    swivel: float = math.nan
    swivel_desired: float = math.nan
    clearance: float = math.nan
    distance_to_goal: float = math.nan
    driver_state: str = ""
    driver_message: str = ""
    reach: str = ""  # the last Reach action goal: its feedback, then its result
    rates_hz: dict[str, float] = field(default_factory=dict)

    def markdown(self) -> str:
        """The panel's text (a markdown table)."""

        def num(v: float, fmt: str, unit: str = "") -> str:
            if not math.isfinite(v):
                return "inf" if v == math.inf else "-"
            return f"{v:{fmt}}{unit}"

        rows = [
            ("phase", self.phase or "-"),
            ("swivel", f"{num(math.degrees(self.swivel), '.1f', ' deg')} "
                       f"(desired {num(math.degrees(self.swivel_desired), '.1f', ' deg')})"),
            ("clearance", num(self.clearance, ".3f", " m")),
            ("distance to goal", num(self.distance_to_goal, ".4f", " m")),
            ("driver", _driver_text(self.driver_state, self.driver_message)),
        ]
        if self.reach:
            rows.append(("Reach action", self.reach))
        rows += [(f"rate {k}", f"{v:.1f} Hz") for k, v in self.rates_hz.items()]
        if self.message:
            rows.append(("message", self.message))
        body = "\n".join(f"| {k} | {_md_escape(v)} |" for k, v in rows)
        return "| | |\n|---|---|\n" + body


def _driver_text(state: str, message: str) -> str:
    # The driver's loop message usually starts with its state ("halted: module 1 ..."): say it once.
    if message and (not state or message.startswith(state)):
        return message
    return (state or "-") + (f": {message}" if message else "")


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _rgb255(rgba: Sequence[float]) -> tuple[int, int, int]:
    return tuple(int(round(255 * min(1.0, max(0.0, float(c))))) for c in rgba[:3])  # type: ignore[return-value]


def _wxyz(R: np.ndarray) -> tuple[float, float, float, float]:
    x, y, z, w = matrix_to_quat_xyzw(R)
    return (w, x, y, z)


class ArmViewer:
    """The arm, markers, goal gizmo and status panel on ``server`` (a ``viser.ViserServer``).

    ``on_goal`` receives the gizmo pose when it is dragged (if streaming is on) or when "Send goal" is
    pressed. ``on_reach`` receives it when "Reach (action)" is pressed (the node sends a Reach goal); None
    keeps that button disabled. Every method is safe to call from any thread (viser queues its messages).
    """

    def __init__(
        self,
        server: Any,
        model: UrdfModel,
        *,
        on_goal: GoalCallback | None = None,
        on_reach: GoalCallback | None = None,
        goal_stream_hz: float = 20.0,
        base_frame: str = "base_link",
    ) -> None:
        self.server = server
        self.on_goal = on_goal
        self.on_reach = on_reach
        self.base_frame = base_frame
        self.goal_stream_period = 1.0 / goal_stream_hz if goal_stream_hz > 0 else 0.0
        self._lock = threading.RLock()
        self._robot_nodes: list[Any] = []
        self._link_frames: dict[str, Any] = {}
        self._markers: dict[tuple[str, str, int], tuple[Any, tuple[Any, ...]]] = {}
        self._positions: dict[str, float] = {}
        self._last_goal_sent = 0.0
        self._gizmo_placed = False
        self._placement_nodes: list[Any] = []
        self._placement_md: Any = None
        self.model = model
        self.goals_sent = 0

        scene = server.scene
        scene.set_up_direction("+z")
        self._add_ground(0.0)
        cam = server.initial_camera
        cam.position = (1.45, -1.25, 1.0)
        cam.look_at = (0.3, 0.0, 0.4)
        cam.up = (0.0, 0.0, 1.0)
        self._build_robot(model)

        # The goal gizmo: starts at the tool (placed on the first joint state), dragged by the user.
        self.gizmo = scene.add_transform_controls("/goal_gizmo", scale=0.22, line_width=3.0,
                                                  depth_test=False, position=(0.5, 0.0, 0.4),
                                                  wxyz=(0.0, 1.0, 0.0, 0.0))
        self.gizmo.on_update(self._on_gizmo)

        gui = server.gui
        with gui.add_folder("Status"):
            self._status_md = gui.add_markdown(Status().markdown())
        with gui.add_folder("Goal"):
            self.stream_box = gui.add_checkbox("Stream goal while dragging", initial_value=True,
                                               hint="publish the gizmo pose on /goal_pose as it moves")
            send = gui.add_button("Send goal", hint="publish the gizmo pose on /goal_pose once")
            send.on_click(lambda _evt: self.send_goal())
            to_tool = gui.add_button("Gizmo to tool", hint="move the gizmo back onto the arm's tool")
            to_tool.on_click(lambda _evt: self.place_gizmo_at_tool())
            # The Reach action (the controller's ~/reach): the node passes `on_reach`, which sends the
            # gizmo pose as a Reach goal and shows its feedback and result in the status panel
            # (Status.reach). Without it the button stays disabled.
            self.reach_button = gui.add_button(
                "Reach (action)", disabled=on_reach is None,
                hint="send the gizmo pose as a Reach action goal (/controller/reach)" if on_reach is not None
                else "no Reach action client")
            self.reach_button.on_click(lambda _evt: self._reach())

    def _add_ground(self, z: float) -> None:
        # Same name: a second call moves the grid (to the placement map's floor).
        self.server.scene.add_grid("/ground", width=2.0, height=2.0, cell_size=0.1, section_size=0.5,
                                   plane="xy", position=(0.4, 0.0, z))

    # -- robot -----------------------------------------------------------------------------------------
    def _build_robot(self, model: UrdfModel) -> None:
        scene = self.server.scene
        for handle in self._robot_nodes:
            handle.remove()
        self._robot_nodes, self._link_frames = [], {}
        for link in model.links:
            frame = scene.add_frame(f"/robot/{link}", show_axes=False)
            self._robot_nodes.append(frame)
            self._link_frames[link] = frame
            for i, vis in enumerate(model.visuals.get(link, [])):
                node = self._add_visual(f"/robot/{link}/visual_{i}", vis)
                if node is not None:
                    self._robot_nodes.append(node)
        self._apply_joints()

    def _add_visual(self, name: str, vis: Visual) -> Any:
        scene = self.server.scene
        pos = tuple(float(v) for v in vis.origin[:3, 3])
        wxyz = _wxyz(vis.origin[:3, :3])
        color = _rgb255(vis.rgba)
        opacity = float(vis.rgba[3]) if vis.rgba[3] < 1.0 else None
        if vis.kind == "sphere":
            return scene.add_icosphere(name, radius=vis.size[0], color=color, position=pos, wxyz=wxyz,
                                       opacity=opacity)
        if vis.kind == "cylinder":
            return scene.add_cylinder(name, radius=vis.size[0], height=vis.size[1], color=color,
                                      position=pos, wxyz=wxyz, opacity=opacity)
        if vis.kind == "box":
            return scene.add_box(name, color=color, dimensions=vis.size, position=pos, wxyz=wxyz,
                                 opacity=opacity)
        _LOG.debug("visual %s: %s geometry is not drawn", name, vis.kind)
        return None

    def set_model(self, model: UrdfModel) -> None:
        """Replace the drawn arm (e.g. a new ``/robot_description``)."""
        with self._lock:
            self.model = model
            self._build_robot(model)

    def set_joints(self, names: Sequence[str], positions: Sequence[float]) -> None:
        """Pose the arm: joint ``names`` and their ``positions`` (rad or m); unknown names are ignored."""
        with self._lock:
            for n, v in zip(names, positions, strict=False):
                if math.isfinite(float(v)):
                    self._positions[n] = float(v)
            self._apply_joints()
            if not self._gizmo_placed and names:
                self._gizmo_placed = True
                self.place_gizmo_at_tool()

    def _apply_joints(self) -> None:
        poses = self.model.link_transforms(self._positions)
        for link, frame in self._link_frames.items():
            T = poses.get(link)
            if T is None:
                continue
            frame.position = tuple(float(v) for v in T[:3, 3])
            frame.wxyz = _wxyz(T[:3, :3])

    def tool_pose(self) -> np.ndarray:
        """4x4 pose of the last link of the chain (the tool for the generated URDF) at the shown joints."""
        with self._lock:
            poses = self.model.link_transforms(self._positions)
            tip = self.model.joints[-1].child if self.model.joints else self.model.root
            return poses[tip]

    # -- goal gizmo ------------------------------------------------------------------------------------
    def place_gizmo_at_tool(self) -> None:
        """Move the gizmo onto the tool's current pose (publishes nothing)."""
        T = self.tool_pose()
        self.gizmo.position = tuple(float(v) for v in T[:3, 3])
        self.gizmo.wxyz = _wxyz(T[:3, :3])

    def gizmo_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The gizmo's position (3,) m and quaternion (x, y, z, w)."""
        w, x, y, z = (float(v) for v in self.gizmo.wxyz)
        n = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
        return np.asarray(self.gizmo.position, dtype=float), np.array([x, y, z, w]) / n

    def _on_gizmo(self, event: Any) -> None:
        phase = getattr(event, "phase", "update")
        if not self.stream_box.value:
            return
        now = time.monotonic()
        # Stream at most goal_stream_hz while dragging; always send the pose at release.
        if phase == "end" or now - self._last_goal_sent >= self.goal_stream_period:
            self._last_goal_sent = now
            self.send_goal()

    def send_goal(self) -> None:
        """Hand the gizmo pose to ``on_goal`` (the node publishes it on /goal_pose)."""
        if self.on_goal is None:
            return
        p, q = self.gizmo_pose()
        self.goals_sent += 1
        self.on_goal(p, q)

    def _reach(self) -> None:
        if self.on_reach is not None:
            p, q = self.gizmo_pose()
            self.on_reach(p, q)

    # -- markers ---------------------------------------------------------------------------------------
    def set_markers(self, group: str, markers: Iterable[MarkerSpec]) -> None:
        """Apply a marker array to ``group``: ADD/MODIFY replaces (ns, id), DELETE removes it, DELETEALL
        clears the group."""
        with self._lock:
            for m in markers:
                if m.action == DELETEALL:
                    for key in [k for k in self._markers if k[0] == group]:
                        self._markers.pop(key)[0].remove()
                    continue
                key = (group, m.ns, int(m.id))
                if m.action == DELETE:
                    old = self._markers.pop(key, None)
                    if old is not None:
                        old[0].remove()
                    continue
                self._draw_marker(key, m)

    def _draw_marker(self, key: tuple[str, str, int], m: MarkerSpec) -> None:
        scene = self.server.scene
        name = f"/markers/{key[0]}/{key[1] or 'default'}/{key[2]}"
        color = _rgb255(m.rgba)
        opacity = float(m.rgba[3]) if m.rgba[3] < 1.0 else None
        pos = tuple(float(v) for v in m.pose[:3, 3])
        wxyz = _wxyz(m.pose[:3, :3])
        scale = tuple(float(v) for v in m.scale)
        pts = np.asarray(m.points, dtype=float).reshape(-1, 3)
        # Pose-only changes move the existing node; anything else redraws it.
        shape_sig = (m.type, scale, color, opacity, pts.round(5).tobytes())
        old = self._markers.get(key)
        if old is not None and old[1] == shape_sig:
            old[0].position, old[0].wxyz = pos, wxyz
            return
        if old is not None:
            old[0].remove()
        node: Any = None
        if m.type == SPHERE:
            node = scene.add_icosphere(name, radius=0.5, scale=scale, color=color, opacity=opacity,
                                       position=pos, wxyz=wxyz)
        elif m.type == CYLINDER:
            node = scene.add_cylinder(name, radius=0.5, height=1.0, scale=scale, color=color,
                                      opacity=opacity, position=pos, wxyz=wxyz)
        elif m.type == CUBE:
            node = scene.add_box(name, color=color, dimensions=scale, opacity=opacity, position=pos,
                                 wxyz=wxyz)
        elif m.type == ARROW and len(pts) >= 2:
            # Points form: shaft diameter scale.x, head diameter scale.y, head length scale.z.
            node = scene.add_arrows(name, points=pts[None, :2, :], colors=color,
                                    shaft_radius=max(scale[0] / 2, 1e-3), head_radius=max(scale[1] / 2, 2e-3),
                                    head_length=max(scale[2], 4e-3), position=pos, wxyz=wxyz)
        elif m.type == ARROW:
            # Pose form: along the pose's x axis, length scale.x, width scale.y.
            seg = np.array([[[0.0, 0.0, 0.0], [scale[0], 0.0, 0.0]]])
            node = scene.add_arrows(name, points=seg, colors=color, shaft_radius=max(scale[1] / 2, 1e-3),
                                    head_radius=max(scale[2] / 2, 2e-3), head_length=0.2 * scale[0],
                                    position=pos, wxyz=wxyz)
        elif m.type in (LINE_STRIP, LINE_LIST) and len(pts) >= 2:
            segs = np.stack([pts[:-1], pts[1:]], axis=1) if m.type == LINE_STRIP else \
                pts[: len(pts) // 2 * 2].reshape(-1, 2, 3)
            node = scene.add_line_segments(name, points=segs, colors=color, thickness=max(scale[0], 1e-3),
                                           position=pos, wxyz=wxyz)
        if node is None:
            self._markers.pop(key, None)
            return
        self._markers[key] = (node, shape_sig)

    def marker_keys(self, group: str | None = None) -> list[tuple[str, str, int]]:
        """(group, ns, id) of every drawn marker (of ``group`` if given)."""
        with self._lock:
            return sorted(k for k in self._markers if group is None or k[0] == group)

    # -- placement map ---------------------------------------------------------------------------------
    def set_placement(self, floor: PlacementFloor, source: str = "") -> None:
        """Draw a placement heat map on the floor (:mod:`redarm_ros.view.placement_floor`: the arm stands
        at the best placement; the ground grid moves down to that floor) and explain it in a "Placement"
        panel; a second call replaces it."""
        scene = self.server.scene
        with self._lock:
            self._add_ground(-floor.base_height)
            for node in self._placement_nodes:
                node.remove()
            nodes = [scene.add_mesh_simple(f"/placement/share_{k}", verts, faces, color=rgb, side="double",
                                           cast_shadow=False, receive_shadow=False)
                     for k, (rgb, verts, faces) in enumerate(floor_meshes(floor))]
            for name, segs, rgb, width in (("valid", floor.outline, (20, 20, 20), 0.008),
                                           ("extent", floor.extent, (150, 150, 150), 0.004),
                                           ("best", floor.best_mark, (230, 30, 30), 0.012)):
                if len(segs):
                    nodes.append(scene.add_line_segments(f"/placement/{name}", points=segs, colors=rgb,
                                                         thickness=width))
            if len(floor.tasks):
                nodes.append(scene.add_point_cloud("/placement/tasks", points=floor.tasks.astype(np.float32),
                                                   colors=(230, 30, 30), point_size=0.02,
                                                   point_shape="circle"))
            self._placement_nodes = nodes
            if self._placement_md is None:
                with self.server.gui.add_folder("Placement"):
                    self._placement_md = self.server.gui.add_markdown(floor.markdown(source))
            else:
                self._placement_md.content = floor.markdown(source)

    # -- status ----------------------------------------------------------------------------------------
    def set_status(self, status: Status) -> None:
        """Show ``status`` in the panel."""
        text = status.markdown()
        if text != self._status_md.content:
            self._status_md.content = text


def scene_markers(scene: dict[str, Any]) -> list[MarkerSpec]:
    """Markers for a scene dict (``table_height``, ``obstacles`` as in ``config/scenes/*.yaml``): a
    table top and the obstacles, for showing a scene without a controller running."""
    out: list[MarkerSpec] = []
    th = scene.get("table_height")
    if th is not None:
        T = np.eye(4)
        T[:3, 3] = (0.5, 0.0, float(th) - 0.01)
        out.append(MarkerSpec("table", 0, CUBE, pose=T, scale=np.array([1.6, 1.6, 0.02]),
                              rgba=(0.55, 0.45, 0.35, 0.6)))
    for i, o in enumerate(scene.get("obstacles") or []):
        T = np.eye(4)
        kind = o.get("type", "sphere")
        center = o.get("center", o.get("position", (0.0, 0.0, 0.0)))
        T[:3, 3] = [float(v) for v in center]
        rgba = (0.2, 0.45, 0.9, 0.8)
        if kind == "sphere":
            d = 2 * float(o["radius"])
            out.append(MarkerSpec("obstacles", i, SPHERE, pose=T, scale=np.array([d, d, d]), rgba=rgba))
        elif kind == "cylinder":
            d = 2 * float(o["radius"])
            h = float(o.get("height", o.get("length", 0.1)))
            out.append(MarkerSpec("obstacles", i, CYLINDER, pose=T, scale=np.array([d, d, h]), rgba=rgba))
        elif kind in ("box", "cube"):
            yaw = float(o.get("yaw", 0.0))
            T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
            size = o.get("size") or [2 * float(v) for v in o["half_extents"]]
            out.append(MarkerSpec("obstacles", i, CUBE, pose=T, scale=np.asarray(size, float), rgba=rgba))
    return out
