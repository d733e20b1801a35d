"""The HIL failure recordings (test/hil_recording.py): a failing ROS test leaves its recording in the
failure output directory and says so in its report; a passing one leaves nothing there.

Runs an inner pytest session in a subprocess, on the same ROS domain, with the plugin loaded the way
test/conftest.py loads it."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy")

from sensor_msgs.msg import JointState  # noqa: E402

from redarm_ros.record.mcap_io import summarize  # noqa: E402

HERE = Path(__file__).resolve().parent

INNER_CONFTEST = f"""
import sys
sys.path.insert(0, {str(HERE)!r})
import pytest
import rclpy
from hil_recording import _hil_recording, pytest_runtest_makereport  # noqa: F401


@pytest.fixture
def ros_env(tmp_path_factory):
    import os
    from types import SimpleNamespace
    domain = int(os.environ["ROS_DOMAIN_ID"])
    return SimpleNamespace(domain_id=domain, log_dir=tmp_path_factory.mktemp("logs"))


@pytest.fixture
def rclpy_context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)
"""

INNER_TEST = """
import time
import pytest
import rclpy
from sensor_msgs.msg import JointState


def _publish(ctx, n):
    node = rclpy.create_node("inner_pub", context=ctx)
    pub = node.create_publisher(JointState, "/joint_states", 50)
    # Wait for the recorder's own subscription, matched: with only a count, another subscriber of the
    # domain (a node left in the outer session's worker) would let the messages go before it.
    def recorder_matched():
        subs = node.get_subscriptions_info_by_topic("/joint_states")
        return (any(s.node_name == "redarm_record" for s in subs)
                and pub.get_subscription_count() >= len(subs))

    end = time.monotonic() + 60
    while not recorder_matched():
        assert time.monotonic() < end, "the recorder never subscribed to /joint_states"
        time.sleep(0.05)
    for i in range(n):
        pub.publish(JointState(name=[f"pa10_joint_{k}" for k in range(1, 8)], position=[0.01 * i] * 7))
        time.sleep(0.01)
    time.sleep(0.5)
    node.destroy_node()


@pytest.mark.hil
def test_fails(rclpy_context):
    _publish(rclpy_context, 25)
    assert False, "on purpose"


@pytest.mark.hil
def test_passes(rclpy_context):
    _publish(rclpy_context, 5)
"""


def test_failing_hil_run_keeps_its_recording(tmp_path: Path, rclpy_context: Any) -> None:
    # Another subscriber of /joint_states on the domain, as a worker of a full run may hold: the
    # recording must still have every message.
    bystander = rclpy.create_node("bystander", context=rclpy_context)
    bystander.create_subscription(JointState, "/joint_states", lambda _msg: None, 50)
    inner = tmp_path / "inner"
    inner.mkdir()
    (inner / "conftest.py").write_text(INNER_CONFTEST, encoding="utf-8")
    (inner / "test_inner.py").write_text(textwrap.dedent(INNER_TEST), encoding="utf-8")
    (inner / "pytest.ini").write_text("[pytest]\nmarkers =\n    hil: test\n", encoding="utf-8")
    failures = tmp_path / "failures"
    env = dict(os.environ, REDARM_TEST_FAILURE_DIR=str(failures))  # the session's ROS domain and SHM rule
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", str(inner)],
                       cwd=inner, env=env, capture_output=True, text=True, timeout=180)
    out = r.stdout + r.stderr
    assert r.returncode == 1, out
    assert "1 failed, 1 passed" in out, out
    kept = sorted(failures.rglob("*.mcap"))
    names = [p.relative_to(failures).as_posix() for p in kept]
    assert names == ["test_inner.py_test_fails/recording.mcap"], out
    assert "HIL recording" in out and str(kept[0]) in out, out
    _, topics = summarize(kept[0])
    assert topics["/joint_states"].count == 25, {t: s.count for t, s in topics.items()}
    assert topics["/tf"].count >= 1
    assert topics["*"].monotonic
