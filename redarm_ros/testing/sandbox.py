"""The DDS sandbox of a test session: SHM-only Fast DDS on a ROS domain of its own.

The children of :mod:`redarm_ros.procs` get these rules in their environment anyway; the sandbox
also puts them in ``os.environ``, so rclpy running inside the test process obeys them too.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from redarm_ros.procs import random_domain_id

#: Set to a number to pin the test session's ROS_DOMAIN_ID (default: random in 1..200).
DOMAIN_ENV = "REDARM_TEST_DOMAIN_ID"
DDS_KEYS = ("FASTDDS_BUILTIN_TRANSPORTS", "ROS_DOMAIN_ID", "ROS_LOG_DIR", "ROS_AUTOMATIC_DISCOVERY_RANGE")


def worker_domain_id(worker: int, workers: int, run_id: str) -> int:
    """The ROS domain of pytest-xdist worker ``worker`` (0-based) of ``workers`` in the run ``run_id``:
    ``$REDARM_TEST_DOMAIN_ID`` plus the worker's index if pinned, else a base drawn from the run's id
    (the same in every worker of the run) plus the index, so the workers of one run never share a
    domain (each starts ROS children of its own)."""
    pinned = os.environ.get(DOMAIN_ENV)
    if pinned:
        return int(pinned) + worker
    span = 200 - workers + 1  # bases 1..span keep every worker's domain in 1..200
    base = 1 + int(hashlib.sha256(run_id.encode()).hexdigest(), 16) % span
    return base + worker


@dataclass(frozen=True)
class RosSandbox:
    """A test session's ROS isolation: ``domain_id`` and ``log_dir`` (also set in ``os.environ``)."""

    domain_id: int
    log_dir: Path


@contextmanager
def dds_sandbox(log_dir: Path, domain_id: int | None = None) -> Iterator[RosSandbox]:
    """SHM-only DDS on ``domain_id`` (default ``$REDARM_TEST_DOMAIN_ID``, else random 1..200) with
    ROS logs in ``log_dir``, in ``os.environ`` until exit (then the old values come back)."""
    domain = int(domain_id if domain_id is not None else (os.environ.get(DOMAIN_ENV) or random_domain_id()))
    saved = {k: os.environ.get(k) for k in DDS_KEYS}
    os.environ.update(
        FASTDDS_BUILTIN_TRANSPORTS="SHM",
        ROS_DOMAIN_ID=str(domain),
        ROS_LOG_DIR=str(log_dir),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
    )
    try:
        yield RosSandbox(domain, Path(log_dir))
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
