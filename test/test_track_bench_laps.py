"""benchmarks/track_bench.py's lap-by-lap scores on synthetic runs: an arm that follows the circle
exactly, and one that stands still for a while in the second lap.

No controller and no timing: the joints are the circle's IK at a fixed swivel, step by step.
"""

from __future__ import annotations

import numpy as np
from support.benches import load_bench

from redarm_ros.kinematics import load_arm

track = load_bench("track_bench")
PA10 = load_arm("pa10")


def _exact_run(lp) -> object:
    """Joints on the circle at the start's swivel, held (so the motion is cyclic)."""
    t = np.arange(0.0, lp.path.duration + 1e-9, track.DT)
    q, _ = PA10.ik_nearest(lp.path.pose(0.0), track.Q_HINT)
    s = PA10.swivel(q)
    rows = []
    for x in t:
        sols = PA10.ik(lp.path.pose(float(x)), s)
        q = sols[int(np.argmin(np.max(np.abs(sols - q), axis=1)))]
        rows.append(q)
    return track.Run(np.array(rows), t, [], set(), set(), [""] * len(t))


def test_lap_scores_of_an_exact_follower_and_of_a_stall() -> None:
    lp = track.lap_circle("test-circle", (0.6, 0.0, 0.3), 0.314, track.R_DOWN, laps=3)
    assert lp.lap_of(0.0) == 0.0 and abs(lp.lap_of(lp.path.duration) - 3.0) < 1e-9
    run = _exact_run(lp)
    sc = track.lap_scores(PA10, lp, run)
    assert len(sc.p95) == len(sc.stall) == len(sc.joint_diff) == 3
    assert max(sc.p95) < 1e-3 and max(sc.stall) == 0.0 and not sc.stalls
    assert np.isnan(sc.joint_diff[0]) and max(sc.joint_diff[1:]) < 1e-3  # the same joints every lap
    # the arm stands for 0.5 s in the middle of lap 2
    i0 = int(np.searchsorted([lp.lap_of(float(x)) for x in run.t], 1.5))
    held = run.q.copy()
    held[i0:i0 + 50] = held[i0]
    msgs = list(run.step_messages)
    msgs[i0] = "stream: joint velocity limits: following as closely as they allow"
    sc2 = track.lap_scores(PA10, lp, track.Run(held, run.t, [], set(), set(), msgs))
    assert sc2.stall[0] == 0.0 and sc2.stall[2] == 0.0
    assert 0.4 <= sc2.stall[1] <= 0.5 + 1e-9
    assert sc2.p95[1] > 50.0 and sc2.p95[0] < 1e-3
    assert sc2.joint_diff[1] > 0.1  # lap 2 differs from lap 1 where the arm stood
    assert len(sc2.stalls) == 1 and sc2.stalls[0].startswith("lap 2,")
    assert "following as closely" in sc2.stalls[0]
