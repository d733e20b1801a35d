"""The plain python-can script against the simulated arm: the simulator moved the joint it asked for."""

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).with_name("powercube_script.py")


def test_script_homes_and_moves_module_2(redarm_arm):
    bus = redarm_arm.can_kwargs
    out = subprocess.run([sys.executable, str(SCRIPT), "--interface", bus["interface"], "--channel",
                          bus["channel"], "--module", "2", "--target", "0.25"],
                         capture_output=True, text=True, timeout=60, check=True).stdout
    assert "modules: [1, 2, 3, 4, 5, 6, 7]" in out
    st = redarm_arm.wait_at([0, 0.25, 0, 0, 0, 0, 0], tol=1e-3, timeout=5)
    assert st.modules[2].homed and not st.modules[2].error
