"""``redarm-bringup --view`` starts the browser view with the stack and says where it is."""

from __future__ import annotations

import urllib.request
from typing import Any

import pytest

pytest.importorskip("viser")
pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")

from redarm_ros.bringup import Stack, build_parser, config_from_args  # noqa: E402
from redarm_ros.procs import python_module_cmd  # noqa: E402


def test_view_flags() -> None:
    cfg = config_from_args(build_parser().parse_args([]))
    assert cfg.view is False and cfg.view_port == 8080
    cfg = config_from_args(build_parser().parse_args(["--view", "--view-port", "0"]))
    assert cfg.view is True and cfg.view_port == 0 and cfg.view_placement == ""


def test_view_placement_reaches_the_view_node(monkeypatch: Any) -> None:
    started: dict[str, dict[str, str]] = {}
    monkeypatch.setattr(Stack, "_start_node", lambda self, node, params: started.setdefault(node, params))
    for argv, expected in ((["--view"], None), (["--view", "--view-placement", "out/placements.npz"],
                                                "out/placements.npz")):
        started.clear()
        cfg = config_from_args(build_parser().parse_args(
            ["--hardware", "none", "--no-ik-service", "--no-controller", "--no-description", *argv]))
        stack = Stack(cfg, domain_id=1)  # nothing starts: _start_node only records
        try:
            stack.start()
        finally:
            stack.close()
        assert started["view"].get("placement") == expected


def test_bringup_view_serves_the_page_on_loopback(procs: Any) -> None:
    cmd = python_module_cmd("redarm_ros.bringup", "--hardware", "none", "--no-ik-service", "--no-controller",
                            "--view", "--view-port", "0")
    bringup = procs.start("bringup", cmd, ready=r"browser view: (http://127\.0\.0\.1:\d+/)", ready_timeout=90)
    url = bringup.ready_match.group(1)
    with urllib.request.urlopen(url, timeout=10) as r:
        page = r.read().decode("utf-8", errors="replace")
    assert r.status == 200 and page.lstrip().lower().startswith("<!doctype html")
    bringup.expect_exit()
    bringup.send_signal(2)
    bringup.wait_for_line(r"all children stopped", 60)
    assert bringup.popen.wait(timeout=30) == 0
