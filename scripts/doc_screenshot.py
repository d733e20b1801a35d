"""Take docs/media/view.png: the browser view of the simulated stack, reaching a goal past a can.

Starts the stack with the view (``redarm-bringup --view --scene table_cylinder``), sends one goal,
opens the page in Debian's headless Chromium (``scripts/setup_chromium.sh``; the machinery of the
browser test, test/cdp_browser.py) and saves a screenshot. Run it in the ROS sandbox:

    scripts/ros_sandbox.sh .venv/bin/python scripts/doc_screenshot.py [--out docs/media/view.png]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from redarm_interfaces.msg import ControllerState

from redarm_ros.bringup import Stack, StackConfig
from redarm_ros.nodes._common import spin_until

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "test"))
from cdp_browser import Chromium, chromium_path  # noqa: E402

GOAL_XYZ = (0.55, 0.15, 0.30)  # m, base_link; the tool pointing down, beside the can
# viser's notice that WebGL runs in software (true here: headless SwiftShader) is not part of the view.
HIDE_WEBGL_NOTICE = """
for (const b of document.querySelectorAll('button')) {
  const box = b.closest('[role=alert]') || (b.parentElement && b.parentElement.parentElement);
  if (box && box.textContent.length < 400 && box.textContent.includes('Software WebGL rendering detected')) {
    b.click();
  }
}"""


def red_pixels(png: bytes) -> int:
    """How many pixels look like the arm's red motor housings: the best-rendered screenshot has most."""
    import imageio.v3 as iio
    import numpy as np

    img = np.asarray(iio.imread(png))[:, :, :3].astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((r > 110) & (g < 0.6 * r) & (b < 0.65 * r)).sum())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "media" / "view.png")
    ap.add_argument("--size", default="1024x640", help="browser window WIDTHxHEIGHT")
    args = ap.parse_args()
    exe = chromium_path()
    if exe is None:
        print("no chromium: run scripts/setup_chromium.sh as root", file=sys.stderr)
        return 2
    width, height = (int(v) for v in args.size.split("x"))
    cfg = StackConfig(scene="table_cylinder", view=True, view_port=0, log_level="warn", ready_timeout_s=300.0)
    with Stack(cfg) as stack:
        url = stack.children["view"].ready_match.group(1)  # type: ignore[attr-defined]
        rclpy.init()
        node = rclpy.create_node("doc_screenshot")
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        states: list[ControllerState] = []
        node.create_subscription(ControllerState, "/controller/state", states.append, 10)
        pub = node.create_publisher(PoseStamped, "/goal_pose", 10)
        spin_until(ex, lambda: bool(states), 60.0)
        goal = PoseStamped()
        goal.header.frame_id = "base_link"
        goal.pose.position.x, goal.pose.position.y, goal.pose.position.z = GOAL_XYZ
        goal.pose.orientation.x, goal.pose.orientation.w = 1.0, 0.0
        pub.publish(goal)
        reached = spin_until(ex, lambda: bool(states) and states[-1].phase == "reached", 60.0)
        print(f"goal {'reached' if reached else 'not reached'}: {states[-1].phase if states else '-'}")
        browser = Chromium(exe, width=width, height=height, timeout=300.0)  # a loaded machine renders slowly
        try:
            browser.navigate(url, timeout=300.0)
            for _ in range(3):  # zoom in on the arm a little (mouse wheel over the scene)
                browser.call("Input.dispatchMouseEvent", type="mouseWheel", x=width * 0.42, y=height * 0.5,
                             deltaX=0, deltaY=-120)
            best, best_score = b"", -1
            end = time.monotonic() + 120.0
            while time.monotonic() < end:  # the page loads the arm and fades in slowly in software WebGL
                spin_until(ex, lambda: False, 3.0)
                browser.call("Runtime.evaluate", expression=HIDE_WEBGL_NOTICE)
                png = browser.screenshot()
                score = red_pixels(png)
                if score > best_score:
                    best, best_score = png, score
            print(f"screenshot: {best_score} red housing pixels")
            args.out.write_bytes(best)
        finally:
            browser.close()
            ex.shutdown()
            node.destroy_node()
            rclpy.shutdown()
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
