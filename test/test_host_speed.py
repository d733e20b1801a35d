"""The benchmarks' host-speed probe: it times the same work and ends its child when stopped."""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path
from types import ModuleType

BENCH_DIR = Path(__file__).resolve().parents[1] / "benchmarks"


def _load() -> ModuleType:
    spec = importlib.util.spec_from_file_location("host_speed", BENCH_DIR / "host_speed.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_reference_work_is_the_same_work_every_time() -> None:
    hs = _load()
    assert hs.reference_work(5000) == hs.reference_work(5000)
    assert hs.reference_work(5000) != hs.reference_work(5001)
    assert hs.reference_ms() > 0.0


def test_probe_samples_and_its_child_ends_on_stop() -> None:
    hs = _load()
    probe = hs.HostSpeedProbe(period_s=0.05)
    try:
        deadline = time.monotonic() + 30.0
        while len(probe.samples) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        probe.stop()
    assert probe._proc.poll() is not None  # ended, not left running
    assert len(probe.samples) >= 2 and all(s > 0 for s in probe.samples)
    assert probe.median_ms is not None and f"median of {len(probe.samples)}" in probe.summary()


def test_probe_without_samples_says_so() -> None:
    hs = _load()
    probe = hs.HostSpeedProbe(period_s=60.0)
    probe.stop()
    assert probe._proc.poll() is not None
    probe.samples.clear()  # as when the child ended before its first timing
    assert probe.median_ms is None and probe.summary() == "reference work: no sample"
