"""PNG plots for the benchmarks, written beside their markdown tables in benchmarks/results/.

Small functions over plain arrays: the benchmarks pass in the raw numbers they already measure, these
draw them. matplotlib with the Agg backend (no display), one fixed figure size and 100 dpi, so a plot
is 800 x 450 pixels; saved as a palette PNG (Pillow), 10-35 kB. Every plot carries a caption: the
run it comes from (its size and command) and the load average of the machine, as the tables do.

* :func:`time_distribution`: histogram (log-spaced bins on a log x axis) and cumulative share of
  per-call or per-goal times, one series per solver or method; a sample that is not finite (a goal
  never reached) counts in the share's denominator, so the curve tops out at the success rate;
* :func:`success_bars`: success rates in percent, grouped horizontal bars (a group per pose set or
  scene);
* :func:`tracking_error`: error over time, one line per method;
* :func:`period_histogram`: histogram of loop periods on a log count axis (and a log period axis when
  the tail is long), the nominal period marked.

:func:`run_caption` formats a caption with the load average, :func:`markdown_links` the lines a
results file links its plots with. The benchmarks load this file by path (the tests load the
benchmarks by path too, so a plain sibling import would not resolve there).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

FIGSIZE = (8.0, 4.5)  # inches; at DPI 100: 800 x 450 pixels
DPI = 100
MAX_SERIES = 8  # colours of the default cycle that stay apart; further series are refused


def _pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (imported here: the benchmarks run without plots too)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def load_text(before: Sequence[float] | str | None = None) -> str:
    """``load average (1/5/15 min) B before, N after``: ``before`` as given (three numbers or text),
    ``after`` read when the plot is drawn."""
    try:
        now = "/".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        now = "n/a"
    if before is None:
        return f"load average (1/5/15 min) {now}"
    if isinstance(before, str):  # as the benchmark recorded it
        return f"load average {before} before, (1/5/15 min) {now} after"
    b = "/".join(f"{v:.2f}" for v in before[:3])
    return f"load average (1/5/15 min) {b} before, {now} after"


def run_caption(run: str, load_before: Sequence[float] | str | None = None) -> str:
    """The caption of a plot: ``run`` (its size, e.g. "--quick: 200 poses per arm") and the load."""
    return f"{run}; {load_text(load_before)}"


def _figure(title: str, caption: str, ncols: int = 1) -> tuple[Any, Any]:
    plt = _pyplot()
    fig, axes = plt.subplots(1, ncols, figsize=FIGSIZE, dpi=DPI)
    fig.suptitle(title, fontsize=11)
    fig.text(0.5, 0.01, caption, ha="center", va="bottom", fontsize=7.5, color="0.3", wrap=True)
    return fig, axes


def _save(fig: Any, path: Path) -> Path:
    plt = _pyplot()
    fig.tight_layout(rect=(0.0, 0.05, 1.0, 1.0))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    compact_png(path)
    return path


def compact_png(path: Path, colors: int = 128) -> None:
    """Rewrite the PNG at ``path`` with a palette of ``colors`` colours (a plot has few; noisy
    antialiased lines would otherwise take a full RGBA PNG past 100 kB)."""
    from PIL import Image

    with Image.open(path) as im:
        pal = im.convert("RGB").quantize(colors=colors, method=Image.Quantize.MEDIANCUT)
    pal.save(path, optimize=True)


def _check_series(series: Mapping[str, Any]) -> None:
    if not series:
        raise ValueError("no series to plot")
    if len(series) > MAX_SERIES:
        raise ValueError(f"{len(series)} series; at most {MAX_SERIES} stay readable")


def _fmt(v: float, unit: str) -> str:
    if unit == "us" and v >= 1000.0:
        return f"{v / 1000.0:.3g} ms"
    return f"{v:.3g} {unit}"


def time_distribution(
    path: Path,
    samples: Mapping[str, Sequence[float] | np.ndarray],
    *,
    title: str,
    caption: str,
    unit: str = "us",
    log_x: bool = True,
    bins: int = 40,
    missing: str = "not finite",
) -> Path:
    """Histogram (left) and cumulative share (right) of times, one series per key of ``samples``.

    The histogram is normalised per series (share of its finite samples per bin), so series of
    different sizes (5000 poses of ours, 300 of a slow peer) compare.

    ``unit`` labels the x axis (``us`` values of 1000 and more show as ms in the legend). With
    ``log_x`` the bins are log-spaced and the axis logarithmic (IK times span decades). Samples that
    are not finite are failures: left out of the histogram, but counted in the share's denominator,
    so a curve on the right ends at the share of finite samples. The legend gives n and the median of
    the finite samples and how many were not finite (``missing`` names them, e.g. "not reached").
    Returns ``path``.
    """
    _check_series(samples)
    arrays = {k: np.asarray(v, dtype=float).ravel() for k, v in samples.items()}
    finite = {k: a[np.isfinite(a)] for k, a in arrays.items()}
    if log_x:
        finite = {k: a[a > 0] for k, a in finite.items()}
    allv = np.concatenate([a for a in finite.values()] + [np.empty(0)])
    fig, (ax_h, ax_c) = _figure(title, caption, ncols=2)
    if allv.size:
        lo, hi = float(allv.min()), float(allv.max())
        if hi <= lo:
            hi = lo * 1.1 + 1e-12 if lo > 0 else lo + 1.0
        edges = np.geomspace(lo, hi, bins + 1) if log_x else np.linspace(lo, hi, bins + 1)
    else:
        edges = np.linspace(0.0, 1.0, bins + 1)
    for i, (name, a) in enumerate(finite.items()):
        n_all = arrays[name].size
        med = _fmt(float(np.median(a)), unit) if a.size else "-"
        failed = n_all - a.size
        label = f"{name} (n={n_all}, median {med})"
        if failed:
            label = f"{name} (n={n_all}, {failed} {missing}; median of the rest {med})"
        color = f"C{i}"
        if a.size:
            ax_h.hist(a, bins=edges, weights=np.full(a.size, 1.0 / a.size), histtype="step", lw=1.4,
                      color=color, label=label)
            xs = np.sort(a)
            ys = np.arange(1, xs.size + 1) / max(n_all, 1)
            ax_c.step(np.concatenate([[xs[0]], xs]), np.concatenate([[0.0], ys]), where="post", color=color,
                      lw=1.4, label=label)
        else:
            ax_h.plot([], [], color=color, label=label)
            ax_c.plot([], [], color=color, label=label)
    for ax in (ax_h, ax_c):
        if log_x:
            ax.set_xscale("log")
        ax.set_xlabel(f"time [{unit}]")
        ax.grid(True, which="major", alpha=0.3)
    ax_h.set_ylabel("share of samples per bin")
    ax_c.set_ylabel("share of samples at or below")
    ax_c.set_ylim(0.0, 1.02)
    ax_h.legend(fontsize=7, loc="upper right")
    return _save(fig, path)


def success_bars(
    path: Path,
    groups: Sequence[str],
    rates: Mapping[str, Sequence[float]],
    *,
    title: str,
    caption: str,
    counts: Sequence[int] | None = None,
) -> Path:
    """Horizontal grouped bars of success rates: one group per entry of ``groups`` (top to bottom),
    one bar per key of ``rates`` (horizontal, so long group names stay readable).

    ``rates[name][i]`` is a fraction in [0, 1] for ``groups[i]`` (nan: not measured, no bar). Each bar
    is labelled with its percentage; ``counts`` (samples per group) go beside the group names.
    Returns ``path``.
    """
    _check_series(rates)
    for name, r in rates.items():
        if len(r) != len(groups):
            raise ValueError(f"series {name!r} has {len(r)} rates for {len(groups)} groups")
    if counts is not None and len(counts) != len(groups):
        raise ValueError(f"{len(counts)} counts for {len(groups)} groups")
    fig, ax = _figure(title, caption)
    k = len(rates)
    height = 0.8 / k
    y = np.arange(len(groups))
    for i, (name, r) in enumerate(rates.items()):
        pct = np.asarray(r, dtype=float) * 100.0
        pos = y - 0.4 + height * (i + 0.5)
        bars = ax.barh(pos, np.nan_to_num(pct, nan=0.0), height, color=f"C{i}", label=name)
        for b, v in zip(bars, pct, strict=True):
            if math.isfinite(v):
                ax.annotate(f"{v:.4g}", (b.get_width(), b.get_y() + b.get_height() / 2), ha="left",
                            va="center", fontsize=6.5, xytext=(2, 0), textcoords="offset points")
    labels = list(groups)
    if counts is not None:
        labels = [f"{g} (n={c})" for g, c in zip(groups, counts, strict=True)]
    ax.set_yticks(y, labels, fontsize=7 if len(groups) > 6 else 8)
    ax.invert_yaxis()
    ax.set_xlabel("success [%]")
    ax.set_xlim(0.0, 112.0)
    ax.grid(True, axis="x", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return _save(fig, path)


def tracking_error(
    path: Path,
    series: Mapping[str, tuple[Sequence[float] | np.ndarray, Sequence[float] | np.ndarray]],
    *,
    title: str,
    caption: str,
    ylabel: str = "position error [mm]",
    log_y: bool = True,
) -> Path:
    """Error over time, one line per key of ``series`` (``(t [s], error)`` pairs of equal length).

    A log y axis (default) keeps a sub-millimetre servo and a centimetre baseline on one plot; it spans
    at most four decades below the largest error, smaller values (and zeros) are drawn at its floor.
    The legend gives each line's median and max.
    Returns ``path``.
    """
    _check_series(series)
    fig, ax = _figure(title, caption)
    floor = math.inf
    if log_y:
        pos = [np.asarray(e, float) for _, e in series.values()]
        pos = [e[np.isfinite(e) & (e > 0)] for e in pos]
        top = max((float(e.max()) for e in pos if e.size), default=1.0)
        # four decades below the largest error: the exact start (error ~1e-12) would squash the rest
        floor = max(min((float(e.min()) for e in pos if e.size), default=1e-3), 1e-4 * top)
    for i, (name, (t, e)) in enumerate(series.items()):
        t = np.asarray(t, dtype=float)
        e = np.asarray(e, dtype=float)
        if t.shape != e.shape:
            raise ValueError(f"series {name!r}: {t.shape} times for {e.shape} errors")
        shown = np.maximum(e, floor) if log_y else e
        ok = e[np.isfinite(e)]
        stats = f"median {np.median(ok):.3g}, max {np.max(ok):.3g}" if ok.size else "no data"
        ax.plot(t, shown, color=f"C{i}", lw=1.2, label=f"{name} ({stats})")
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel("time since the stream's first sample [s]")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="best")
    return _save(fig, path)


def period_histogram(
    path: Path,
    periods_ms: Mapping[str, Sequence[float] | np.ndarray],
    nominal_ms: float,
    *,
    title: str,
    caption: str,
    bins: int = 200,
    log_x: bool | None = None,
) -> Path:
    """Histogram of loop periods in ms on a log count axis, one series per key, the nominal marked.

    The log count axis shows the rare long periods (a preempted cycle) beside the thousands at the
    nominal period. ``log_x`` (default: when the longest period exceeds 5 x nominal) puts the periods
    on a log axis with log-spaced bins, so a tail of 100 ms gaps does not squeeze the peak at the
    nominal period into one bin. The legend gives each series' n, median and p99 |period - nominal|.
    Returns ``path``.
    """
    _check_series(periods_ms)
    if not nominal_ms > 0:
        raise ValueError(f"nominal period {nominal_ms!r} ms is not positive")
    arrays = {k: np.asarray(v, dtype=float).ravel() for k, v in periods_ms.items()}
    arrays = {k: a[np.isfinite(a)] for k, a in arrays.items()}
    allv = np.concatenate([a for a in arrays.values()] + [np.array([nominal_ms])])
    if log_x is None:
        log_x = float(allv.max()) > 5.0 * nominal_ms
    if log_x:
        pos = allv[allv > 0]
        lo = max(float(pos.min()), 1e-3 * nominal_ms)
        edges = np.geomspace(lo, max(float(pos.max()), 2.0 * nominal_ms), bins + 1)
    else:
        lo, hi = min(0.0, float(allv.min())), max(float(allv.max()), 2.0 * nominal_ms)
        edges = np.linspace(lo, hi, bins + 1)
    fig, ax = _figure(title, caption)
    for i, (name, a) in enumerate(arrays.items()):
        if a.size:
            err = np.abs(a - nominal_ms)
            label = (f"{name} (n={a.size}, median {np.median(a):.3f} ms, p99 |error| "
                     f"{np.percentile(err, 99):.3f} ms, max {a.max():.1f} ms)")
            shown = np.clip(a, edges[0], edges[-1])  # periods below the first bin land in it
            ax.hist(shown, bins=edges, histtype="step", lw=1.4, color=f"C{i}", label=label)
        else:
            ax.plot([], [], color=f"C{i}", label=f"{name} (no samples)")
    ax.axvline(nominal_ms, color="k", ls="--", lw=1.0, label=f"nominal {nominal_ms:g} ms")
    ax.set_yscale("log")
    if log_x:
        ax.set_xscale("log")
    ax.set_xlabel("period [ms]" + (" (log)" if log_x else ""))
    ax.set_ylabel("count (log)")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    return _save(fig, path)


def markdown_links(paths: Sequence[Path], md_dir: Path, note: str = "") -> list[str]:
    """Lines that link ``paths`` from a markdown file in ``md_dir``: a ``Plots`` line, then one image
    per plot (relative links, so the results directory can move as a whole)."""
    if not paths:
        return []
    head = "Plots" + (f" ({note})" if note else "") + ":"
    out = [head, ""]
    for p in paths:
        rel = os.path.relpath(Path(p).resolve(), Path(md_dir).resolve())
        out.append(f"![{Path(p).stem}]({Path(rel).as_posix()})")
    return out
