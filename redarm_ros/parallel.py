"""Run independent chunks of work: in this process, in local worker processes, or on a Dask cluster.

Used by the placement study and the capability map; it depends on nothing of the package but
``errors.py``, so any layer may use it.

Both are embarrassingly parallel (over base poses, over voxels). Every engine maps one function over the
same list of chunks and returns the results in chunk order, so the outcome does not depend on the
engine or the number of workers.

* ``local`` (default): ``workers`` processes of this machine (``concurrent.futures``); ``workers=1``
  runs in this process. Workers are forked when the caller runs a single thread (they start in
  milliseconds), and spawned otherwise (a fork of a threaded process can inherit a held lock).
* ``dask``: a ``distributed`` scheduler at ``address`` (``tcp://host:port``), or, without an address,
  a local cluster of ``workers`` processes bound to 127.0.0.1. Dask is an optional extra
  (``pip install redarm_ros[cluster]``, i.e. ``dask[distributed]``); without it only ``local`` exists.

Dask rather than Ray: its wheels with their dependencies weigh 5.2 MB against Ray's 79 MB, it starts a
local cluster in about a second, and its scheduler is plain Python (docs/placement.md has the figures).
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, TextIO

from redarm_ros.errors import ConfigError

__all__ = ["ENGINES", "map_chunks", "Progress"]

ENGINES = ("local", "dask")


class Progress:
    """A one-line progress bar on a terminal (``done/total``, rate, time left); silent when off."""

    def __init__(self, total: int, label: str, stream: TextIO | None = sys.stderr, every_s: float = 0.2):
        self.total, self.label, self.stream, self.every_s = total, label, stream, every_s
        self.done = 0
        self._t0 = time.monotonic()
        self._last = 0.0

    def step(self, k: int = 1) -> None:
        """Count k chunks as done and redraw at most every ``every_s`` seconds (and at the end)."""
        self.done += k
        now = time.monotonic()
        if self.stream is None or (now - self._last < self.every_s and self.done < self.total):
            return
        self._last = now
        el = now - self._t0
        rate = self.done / el if el > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else float("nan")
        bar = "#" * int(30 * self.done / max(self.total, 1))
        self.stream.write(f"\r{self.label} [{bar:<30}] {self.done}/{self.total} chunks, "
                          f"{el:.1f} s, {left:.1f} s left ")
        if self.done >= self.total:
            self.stream.write("\n")
        self.stream.flush()


def _dask_client(address: str | None, workers: int) -> tuple[Any, Any]:
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise ConfigError("engine 'dask' needs the optional extra: pip install 'dask[distributed]' "
                          "(redarm_ros[cluster])", field="engine", value="dask") from exc
    if address:
        return Client(address, timeout=30), None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=None, protocol="tcp")
    return Client(cluster), cluster


def map_chunks(fn: Callable[..., Any], chunks: Sequence[Any], *, args: tuple[Any, ...] = (),
               engine: str = "local", workers: int | None = None, address: str | None = None,
               progress: TextIO | None = None, label: str = "chunks") -> list[Any]:
    """``[fn(*args, chunk) for chunk in chunks]`` on the chosen engine, in chunk order.

    ``fn`` must be importable by name (a module-level function) for the process engines. Raises
    :class:`ConfigError` for an unknown engine, a bad worker count or a missing optional extra.
    """
    if engine not in ENGINES:
        raise ConfigError(f"unknown engine {engine!r}; known: {', '.join(ENGINES)}", field="engine",
                          value=engine)
    n = workers if workers is not None else (os.cpu_count() or 1)
    if n < 1:
        raise ConfigError(f"workers must be >= 1, got {n}", field="workers", value=n)
    bar = Progress(len(chunks), label, progress)
    out: list[Any] = [None] * len(chunks)
    if engine == "local" and (n == 1 or len(chunks) <= 1):
        for i, c in enumerate(chunks):
            out[i] = fn(*args, c)
            bar.step()
        return out
    if engine == "local":
        ctx = multiprocessing.get_context("fork" if threading.active_count() == 1 else "forkserver")
        with cf.ProcessPoolExecutor(max_workers=min(n, len(chunks)), mp_context=ctx) as pool:
            futs = {pool.submit(fn, *args, c): i for i, c in enumerate(chunks)}
            for f in cf.as_completed(futs):
                out[futs[f]] = f.result()
                bar.step()
        return out
    client, cluster = _dask_client(address, n)
    try:
        from distributed import as_completed

        shared = [client.scatter(a, broadcast=True) for a in args]
        futs = [client.submit(fn, *shared, c, pure=False) for c in chunks]
        index = {f.key: i for i, f in enumerate(futs)}
        for f in as_completed(futs):
            out[index[f.key]] = f.result()
            bar.step()
        return out
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
