"""Run one of ``redarm_ros.can.realtime``'s priority calls in a fresh Python process that has threads
started before the call (as a ROS node's middleware threads are) and one started after it, and report
what every thread ended up with. A subprocess, so the test runner keeps its own scheduling."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Sequence

_PROBE = r"""
import json, os, resource, signal, sys, threading
from redarm_ros.can import realtime

stop = threading.Event()
before = [threading.Thread(target=stop.wait) for _ in range(2)]
for t in before:
    t.start()
prio = getattr(realtime, sys.argv[1])(int(sys.argv[2]), who="probe")
after_tid = []
after = threading.Thread(target=lambda: (after_tid.append(threading.get_native_id()), stop.wait()))
after.start()
while not after_tid:
    pass
tids = [int(t) for t in os.listdir("/proc/self/task")]
print(json.dumps({
    "policy": prio.policy.value, "value": prio.value, "message": prio.message,
    "sched": {str(t): [os.sched_getscheduler(t), os.sched_getparam(t).sched_priority] for t in tids},
    "nice": {str(t): os.getpriority(os.PRIO_PROCESS, t) for t in tids},
    "after": after_tid[0], "before": [t.native_id for t in before],
    "rttime": list(resource.getrlimit(resource.RLIMIT_RTTIME)),
    "sigxcpu_default": signal.getsignal(signal.SIGXCPU) == signal.SIG_DFL,
}))
stop.set()
"""


def probe_threads(call: str, level: int, prefix: Sequence[str] = (), start_nice: int | None = None) -> dict:
    """``realtime.<call>(level)`` in a probe process (run under the command ``prefix``, started at nice
    ``start_nice`` if given). Returns the call's ``policy``, ``value`` and ``message``, per thread id
    its ``sched`` [policy, priority] and ``nice``, the ids of the threads started ``before`` and
    ``after`` the call, the process's RLIMIT_RTTIME and whether SIGXCPU is at its default."""

    def preexec() -> None:  # an absolute start level, whatever this test runner's own is
        if start_nice is not None:
            os.setpriority(os.PRIO_PROCESS, 0, start_nice)

    out = subprocess.run([*prefix, sys.executable, "-c", _PROBE, call, str(level)], capture_output=True,
                         text=True, timeout=60, check=True, preexec_fn=preexec)
    return json.loads(out.stdout)
