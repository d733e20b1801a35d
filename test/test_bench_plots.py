"""benchmarks/plots.py: each plot function writes a valid PNG of the fixed size from synthetic data.

No timing, no benchmark run: fixed-seed arrays in, the files read back with Pillow.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

PLOTS = Path(__file__).resolve().parents[1] / "benchmarks" / "plots.py"
SIZE = (800, 450)  # FIGSIZE x DPI
Image = pytest.importorskip("PIL.Image")


@pytest.fixture(scope="module")
def plots() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_plots_under_test", PLOTS)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _read_png(path: Path) -> tuple[int, int]:
    """Decode the whole file (a truncated or corrupt PNG raises) and return its size."""
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(path) as im:
        assert im.format == "PNG"
        im.load()
        size = im.size
        # not a blank canvas: the figure draws something darker than the background
        assert min(im.convert("L").getextrema()) < 128
    assert path.stat().st_size < 150_000
    return size


def test_time_distribution_png(plots: ModuleType, tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    out = plots.time_distribution(
        tmp_path / "t.png",
        {
            "ours": rng.lognormal(np.log(60.0), 0.4, 2000),
            "peer": rng.lognormal(np.log(9000.0), 0.6, 100),
            "with failures": np.r_[rng.lognormal(np.log(900.0), 0.8, 90), [np.nan] * 10],
        },
        title="synthetic IK times",
        caption=plots.run_caption("synthetic: 2000 + 100 + 100 samples", (1.0, 2.0, 3.0)),
    )
    assert out == tmp_path / "t.png" and _read_png(out) == SIZE


def test_time_distribution_linear_and_all_failed(plots: ModuleType, tmp_path: Path) -> None:
    out = plots.time_distribution(
        tmp_path / "lin.png",
        {"reached": [1.2, 2.5, 3.0, np.nan], "never": [np.nan, np.nan]},
        title="synthetic times to goal",
        caption="synthetic",
        unit="s",
        log_x=False,
        missing="not reached",
    )
    assert _read_png(out) == SIZE


def test_success_bars_png(plots: ModuleType, tmp_path: Path) -> None:
    out = plots.success_bars(
        tmp_path / "sub" / "s.png",  # the directory is created
        ["uniform / ik_nearest", "narrow / ik_nearest", "uniform (peer subset) / ikpy"],
        {"pa10": [1.0, 0.999, 0.7], "powercube7": [1.0, np.nan, 0.65]},
        counts=[5000, 1000, 300],
        title="synthetic success",
        caption="synthetic",
    )
    assert _read_png(out) == SIZE


def test_success_bars_rejects_mismatched_lengths(plots: ModuleType, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="2 rates for 3 groups"):
        plots.success_bars(tmp_path / "x.png", ["a", "b", "c"], {"m": [1.0, 0.5]}, title="", caption="")
    assert not (tmp_path / "x.png").exists()


def test_tracking_error_png(plots: ModuleType, tmp_path: Path) -> None:
    t = np.arange(0.0, 4.0, 0.01)
    out = plots.tracking_error(
        tmp_path / "e.png",
        {
            "servo": (t, np.r_[0.0, 0.07 + 0.02 * np.sin(t[1:])]),  # the exact start: a zero on a log axis
            "point": (t, 30.0 + 5.0 * np.sin(t)),
            "dls": (t, 0.2 + 0.1 * np.cos(t)),
        },
        title="synthetic tracking error",
        caption="synthetic",
    )
    assert _read_png(out) == SIZE
    with pytest.raises(ValueError, match="times for"):
        plots.tracking_error(tmp_path / "bad.png", {"x": (t, t[:-1])}, title="", caption="")


def test_period_histogram_png(plots: ModuleType, tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    out = plots.period_histogram(
        tmp_path / "p.png",
        {"core": rng.normal(4.0, 0.05, 2500), "node": np.r_[rng.normal(4.0, 0.5, 1200), [12.0, 20.0]]},
        4.0,
        title="synthetic periods",
        caption="synthetic",
    )
    assert _read_png(out) == SIZE
    # a long tail (a 470 ms gap) switches to a log period axis; a zero period still lands in a bin
    tail = plots.period_histogram(
        tmp_path / "tail.png", {"gaps": np.r_[rng.normal(4.0, 0.1, 3000), [0.0, 35.0, 470.0]]}, 4.0,
        title="synthetic gaps", caption="synthetic",
    )
    assert _read_png(tail) == SIZE
    with pytest.raises(ValueError, match="not positive"):
        plots.period_histogram(tmp_path / "q.png", {"core": [1.0]}, 0.0, title="", caption="")


def test_markdown_links_are_relative_to_the_results_file(plots: ModuleType, tmp_path: Path) -> None:
    pngs = [tmp_path / "res" / "a_time.png", tmp_path / "res" / "a_success.png"]
    lines = plots.markdown_links(pngs, tmp_path / "res", "of the newest run")
    assert lines == ["Plots (of the newest run):", "", "![a_time](a_time.png)", "![a_success](a_success.png)"]
    assert plots.markdown_links([], tmp_path) == []


def test_run_caption_names_the_run_and_the_load(plots: ModuleType) -> None:
    text = plots.run_caption("--quick: 6 scenes", (1.25, 2.5, 3.0))
    assert text.startswith("--quick: 6 scenes; load average (1/5/15 min) 1.25/2.50/3.00 before")
    assert text.endswith(" after")
