"""`make demo` end to end: redarm-demo as its own process must exit 0 and leave a report and PNGs whose
numbers agree with the acceptance rule (reachable goals within 1 mm / 0.01 rad on the simulated tool,
the out-of-reach goal rejected). The iiwa14 demo is also the end-to-end test of an arm of its own from
a URDF file (docs/urdf.md): the whole stack from that file, its IK service asked by the test too."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")
pytest.importorskip("redarm_ros.nodes.can_driver", reason="can_driver node not written yet")
pytest.importorskip("redarm_ros.sim.hardware", reason="simulator not written yet")

from redarm_ros.demo import GOALS  # noqa: E402
from redarm_ros.procs import python_module_cmd  # noqa: E402

pytestmark = [pytest.mark.hil, pytest.mark.slow]


def test_demo_passes_and_reports(procs: Any, tmp_path: Path) -> None:
    out = tmp_path / "demo_output"
    # The GIF at 2 frames per second of recording time instead of the default 10: the same rendering
    # and writing, some 80 frames instead of 400 (each a TinyRenderer picture, 40 ms of CPU).
    cmd = python_module_cmd("redarm_ros.demo", "--output", str(out), "--log-level", "warn", "--gif-fps", "2")
    demo = procs.start("demo", cmd)
    demo.expect_exit()
    # About 70 s on a quiet machine (45 s of motion, then the GIF); far longer when it is starved.
    demo.wait_for_line(r"demo (PASSED|FAILED)", timeout=420.0)
    rc = demo.popen.wait(timeout=60.0)
    text = "\n".join(demo.output())
    assert rc == 0, text[-4000:]

    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["success"] is True
    goals = report["goals"]
    assert [g["name"] for g in goals] == [g.name for g in GOALS]
    for g, spec in zip(goals, GOALS, strict=True):
        for key in ("reached", "pos_err_m", "rot_err_rad", "time_s"):
            assert key in g, key
        if spec.reachable:
            assert g["reached"] and g["pos_err_m"] < 1e-3 and g["rot_err_rad"] < 0.01, g
            assert g["min_clearance_m"] > 0.0, g  # collision-free by the controller's own measure
        else:
            assert g["rejected"] and not g["reached"] and g["ik_status"] == "OUT_OF_REACH", g
    rates = report["loop_rates"]
    assert rates["controller_state"]["samples"] > 100
    assert rates["simulator_physics"]["samples"] > 1000
    # PNGs: one per goal plus start/ready/final, each a real image, not all identical.
    pngs = sorted((out / "snapshots").glob("*.png"))
    assert len(pngs) >= len(GOALS) + 2
    blobs = [p.read_bytes() for p in pngs]
    assert all(b.startswith(b"\x89PNG\r\n\x1a\n") and len(b) > 500 for b in blobs)
    assert len(set(blobs)) > 1
    # The table was printed.
    assert "pos err mm" in text and "out_of_reach" in text
    # Snapshots and the GIF are 640x480; the GIF shows the run (frames of the arm moving).
    import imageio.v3 as iio

    from redarm_ros.record.mcap_io import summarize

    assert {iio.imread(p).shape[:2] for p in pngs} == {(480, 640)}
    gif = iio.imread(out / "demo.gif", index=None)
    assert gif.shape[0] >= 50 and gif.shape[1:3] == (480, 640), gif.shape
    assert report["animation"]["ok"] and report["recording"]["ok"], (report["animation"], report["recording"])
    animation = report["animation"]
    assert animation["fps"] == 2 and animation["frames"] >= gif.shape[0], animation
    # The recording: ROS 2 profile, every demo topic with its schema, /tf for 3-D viewers, in time order.
    profile, topics = summarize(out / "demo.mcap")
    assert profile == "ros2"
    assert topics["/joint_states"].count >= 1000
    assert topics["/goal_pose"].count == len(GOALS)
    for topic in ("/tf", "/robot_description", "/joint_command", "/controller/state", "/controller/markers",
                  "/diagnostics"):
        assert topics[topic].count > 0, topic
    assert topics["/tf"].schema_name == "tf2_msgs/msg/TFMessage"
    encodings = {(s.schema_encoding, s.message_encoding) for t, s in topics.items() if t != "*"}
    assert encodings == {("ros2msg", "cdr")}
    assert topics["*"].monotonic


def _wait(pred: Callable[[], Any], timeout: float) -> bool:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            return False
        time.sleep(0.02)
    return True


def test_iiwa_demo_from_its_urdf_passes(procs: Any, ros_env: Any, tmp_path: Path) -> None:
    # The iiwa14-like arm through the stack's URDF path (simulator, driver, IK service, controller and
    # description all from the URDF file), its own goal set; no GIF (the recording and the GIF are
    # tested above). A lighter stack than the default rates above: the driver at 125 Hz, the controller
    # at 50 Hz (a quarter less CPU), which also runs the demo's two rate options end to end.
    from redarm_interfaces.srv import SolveIK

    from redarm_ros.demo import DEMOS
    from redarm_ros.kinematics import load_arm
    from redarm_ros.nodes._common import call_resending
    from redarm_ros.nodes.controller import pose_to_msg
    from redarm_ros.sim.urdf_arms import iiwa14_urdf
    from redarm_ros.testing.ros import RosTestContext

    out = tmp_path / "demo_iiwa"
    cmd = python_module_cmd("redarm_ros.demo", "--arm", "iiwa14", "--output", str(out), "--log-level", "warn",
                            "--gif-fps", "0", "--driver-rate", "125", "--control-rate", "50")
    demo = procs.start("demo_iiwa", cmd)
    demo.expect_exit()
    # While the demo's stack is up (on this test's ROS domain), the test asks its ik_service itself:
    # an arm of its own from a URDF file gets the closed form, in the URDF's joint names, exact.
    demo.wait_for_line(r"stack up", timeout=300.0)
    arm = load_arm(iiwa14_urdf(), base_link="base_link", tip_link="tool0")
    T = arm.fk(np.array([0.4, 0.7, -0.3, -1.0, 0.2, 0.9, 0.3]))
    req = SolveIK.Request()
    req.target = pose_to_msg(T)
    req.target.header.frame_id = "base_link"
    req.seed = [float(v) for v in DEMOS["iiwa14"].ready_q]
    with RosTestContext(ros_env.domain_id) as ros:  # (only for the call: its executor thread spins)
        ik = call_resending(ros.node.create_client(SolveIK, "/ik_service/solve_ik"), req, _wait, 30.0)
    assert ik is not None and ik.status == SolveIK.Response.SUCCESS, ik
    assert ik.solver == "closed-form swivel IK"
    assert list(ik.solution.name) == arm.joint_names
    assert np.abs(arm.fk(np.array(ik.solution.position)) - T).max() < 1e-9
    demo.wait_for_line(r"demo (PASSED|FAILED)", timeout=420.0)
    rc = demo.popen.wait(timeout=60.0)
    assert rc == 0, "\n".join(demo.output())[-4000:]
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["success"] is True and report["arm"] == "iiwa14"
    assert report["loop_rates"]["controller_state"]["target_hz"] == 50, report["loop_rates"]
    goals = DEMOS["iiwa14"].goals
    assert [g["name"] for g in report["goals"]] == [g.name for g in goals]
    for g, spec in zip(report["goals"], goals, strict=True):
        if spec.reachable:
            assert g["reached"] and g["pos_err_m"] < 1e-3 and g["rot_err_rad"] < 0.01, g
        else:
            assert g["rejected"] and g["ik_status"] == "OUT_OF_REACH", g
    assert "iiwa_joint_1" in (out / "iiwa14.urdf").read_text(encoding="utf-8")
