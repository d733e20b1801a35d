"""The testing examples (examples/testing/) pass as a user would run them: ``pytest examples/testing``
in a process of its own, with the fixtures of the installed ``redarm`` plugin and no conftest of ours."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from support.requires import require_ros

from redarm_ros.procs import ros_child_env
from redarm_ros.testing.sandbox import DOMAIN_ENV

require_ros(stack=True)

pytestmark = [pytest.mark.hil, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples" / "testing"


def test_examples_pass_under_pytest(ros_env) -> None:
    # The session's sandbox for the inner run too: same domain (nothing else runs on it meanwhile).
    env = ros_child_env(ros_env.domain_id, log_dir=ros_env.log_dir,
                        extra={DOMAIN_ENV: str(ros_env.domain_id)})
    run = subprocess.run([sys.executable, "-m", "pytest", str(EXAMPLES), "-q", "-p", "no:cacheprovider"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-6000:]
    assert "3 passed" in run.stdout, out[-6000:]
