"""``redarm-view`` in a real browser: Debian's headless Chromium loads the page from the view node
(started as its own process) over 127.0.0.1 and takes screenshots.

Checks that the page needs nothing but the view's own server (every request goes to 127.0.0.1 or is
inline), that the arm is drawn (its red motor housings are on screen), that it moves when
``/joint_states`` changes, and that dragging the transform gizmo with the mouse publishes a goal on
``/goal_pose``. Screenshots are kept in the test's temporary directory. Skipped, with the reason,
where Chromium is not installed (``scripts/setup_chromium.sh`` installs it; ``make test`` runs it).
"""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cdp_browser import Chromium, chromium_path

pytest.importorskip("viser")
rclpy = pytest.importorskip("rclpy")
pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.procs import python_module_cmd  # noqa: E402

pytestmark = pytest.mark.slow

ARM = load_arm("pa10")
POSE_A = np.array([-0.5, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])  # tool (and gizmo) mid-screen
POSE_B = np.array([1.2, -0.3, 0.0, 1.9, 0.0, -0.8, 0.0])  # turned the other way, elbow bent further
GIZMO_PLANE_RGB = np.array([171, 231, 193])  # the translucent green plane handle of viser's gizmo
TIMEOUT = 90.0  # software WebGL on a busy two-core machine is slow; deadlines, not speed checks


def _decode(png: bytes) -> np.ndarray:
    import imageio.v3 as iio

    return np.asarray(iio.imread(io.BytesIO(png)))[:, :, :3].astype(int)


def housing_mask(img: np.ndarray) -> np.ndarray:
    """Pixels of the arm's red motor housings, inside the central part of the view (the GUI panel on
    the right, the notification and the axes widget at the left are outside it)."""
    h, w, _ = img.shape
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    red = (r > 110) & (g < 0.6 * r) & (b < 0.65 * r) & (np.abs(g - b) < 50)
    roi = np.zeros_like(red)
    roi[int(0.08 * h): int(0.97 * h), int(0.2 * w): int(0.66 * w)] = True
    return red & roi


class Ros:
    """The test's ROS side: publishes the joint state it is told to, collects /goal_pose."""

    def __init__(self, ctx: Any) -> None:
        self.node = rclpy.create_node("view_browser_test", context=ctx)
        self.js = self.node.create_publisher(JointState, "/joint_states", 10)
        self.goals: list[PoseStamped] = []
        self.node.create_subscription(PoseStamped, "/goal_pose", self.goals.append, 10)
        self.q = POSE_A
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_pub = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_pub:  # 20 Hz, like a slow driver
                next_pub = now + 0.05
                self.js.publish(JointState(name=list(ARM.joint_names), position=[float(v) for v in self.q]))
            self.ex.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.ex.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


@pytest.fixture
def chromium() -> Iterator[Chromium]:
    exe = chromium_path()
    if exe is None:
        pytest.skip("Debian's chromium is not installed (scripts/setup_chromium.sh installs it as root; "
                    "`make test` runs that)")
    browser = Chromium(exe, width=1024, height=768)
    try:
        yield browser
    finally:
        browser.close()


def _poll(shot: Callable[[], np.ndarray], pred: Callable[[np.ndarray], bool], timeout: float
          ) -> tuple[bool, np.ndarray]:
    end = time.monotonic() + timeout
    img = shot()
    while not pred(img) and time.monotonic() < end:
        time.sleep(0.5)
        img = shot()
    return pred(img), img


def test_page_draws_the_arm_follows_joint_states_and_gizmo_publishes_goals(
        procs: Any, rclpy_context: Any, chromium: Chromium, tmp_path: Path) -> None:
    view = procs.start("view", python_module_cmd("redarm_ros.nodes.view", "--port", "0"),
                       ready=r"view ready: (http://127\.0\.0\.1:\d+/)", ready_timeout=60)
    url = view.ready_match.group(1)
    ros = Ros(rclpy_context)
    n_shot = [0]

    def shot() -> np.ndarray:
        png = chromium.screenshot()
        n_shot[0] += 1
        (tmp_path / f"shot_{n_shot[0]:03d}.png").write_bytes(png)  # kept for a look after a failure
        return _decode(png)

    try:
        chromium.navigate(url)
        drawn, img_a = _poll(shot, lambda im: housing_mask(im).sum() > 150, TIMEOUT)
        assert drawn, f"no arm on the page (screenshots in {tmp_path}); browser log: {chromium.log_tail()}"
        # Offline: the page and everything it loads come from the view's own server or are inline.
        urls = chromium.requested_urls()
        local = ("http://127.0.0.1:", "ws://127.0.0.1:", "data:", "blob:")
        assert urls and all(u.startswith(local) for u in urls), urls

        # The arm moves with /joint_states: the housings are somewhere else on screen.
        mask_a = housing_mask(img_a)
        ros.q = POSE_B

        def moved(im: np.ndarray) -> bool:
            m = housing_mask(im)
            iou = (m & mask_a).sum() / max(1, (m | mask_a).sum())
            return bool(m.sum() > 150 and iou < 0.5)

        ok, img_b = _poll(shot, moved, TIMEOUT)
        assert ok, f"the drawn arm did not follow /joint_states (screenshots in {tmp_path})"

        # Drag the gizmo's green plane handle upwards: the view publishes the new pose on /goal_pose.
        plane = np.abs(img_b - GIZMO_PLANE_RGB).sum(axis=2) < 40
        ys, xs = np.nonzero(plane)
        assert len(xs) > 20, f"no gizmo handle on screen (screenshots in {tmp_path})"
        x0, y0 = float(np.median(xs)), float(np.median(ys))
        n_before = len(ros.goals)
        tool_a = ARM.fk(POSE_A)[:3, 3]
        for attempt in range(3):  # a busy renderer may miss the press; try again a little beside it
            chromium.drag(x0 + 3 * attempt, y0, x0 + 3 * attempt, y0 - 70)
            end = time.monotonic() + 15
            while time.monotonic() < end and len(ros.goals) == n_before:
                time.sleep(0.1)
            if len(ros.goals) > n_before:
                break
        shot()
        assert len(ros.goals) > n_before, f"dragging the gizmo published no goal (screenshots in {tmp_path})"
        time.sleep(0.5)
        g = ros.goals[-1]
        p = np.array([g.pose.position.x, g.pose.position.y, g.pose.position.z])
        q = g.pose.orientation
        assert g.header.frame_id == "base_link"
        assert abs(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w - 1.0) < 1e-6
        # It started on the tool (the first joint state) and was dragged away from it.
        assert np.linalg.norm(p - tool_a) > 0.01, (p, tool_a)
    finally:
        ros.close()


def yellow_mask(img: np.ndarray) -> np.ndarray:
    """Pixels of the placement map's full-share squares (viridis yellow, about (245, 240, 174) once lit),
    in the 3D part of the page; neither the grey floor nor the pale green of lower shares."""
    h, w, _ = img.shape
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    yellow = (r > 200) & (g > 200) & (b < 0.8 * g) & (r - b > 50)
    roi = np.zeros_like(yellow)
    roi[int(0.08 * h): int(0.97 * h), int(0.2 * w): int(0.66 * w)] = True
    return yellow & roi


def test_page_draws_the_placement_map_on_the_floor(procs: Any, chromium: Chromium, tmp_path: Path) -> None:
    """``redarm-view --placement placements.npz``: the squares where every task is reachable (yellow)
    are on screen, around the arm standing at the best placement."""
    from redarm_ros.demo import DEMOS, demo_placement

    demo_placement(DEMOS["pa10"], tmp_path / "placement", lambda _line: None, plots=False, workers=1,
                   grid={"x": [-0.4, 0.4], "y": [-0.4, 0.4], "step": 0.1, "yaw_deg": [0, 90]})
    npz = tmp_path / "placement" / "placements.npz"
    cmd = python_module_cmd("redarm_ros.nodes.view", "--port", "0", "--placement", str(npz))
    view = procs.start("view", cmd, ready=r"view ready: (http://127\.0\.0\.1:\d+/)", ready_timeout=60)
    chromium.navigate(view.ready_match.group(1))
    n_shot = [0]

    def shot() -> np.ndarray:
        png = chromium.screenshot()
        n_shot[0] += 1
        (tmp_path / f"shot_{n_shot[0]:03d}.png").write_bytes(png)
        return _decode(png)

    # (the tool's small yellow tip alone is under 100 pixels)
    drawn, _ = _poll(shot, lambda im: yellow_mask(im).sum() > 1500, TIMEOUT)
    assert drawn, f"no placement map on the page (screenshots in {tmp_path})"
