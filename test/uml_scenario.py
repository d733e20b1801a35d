"""Scenario programs for the genuine-SocketCAN test: run inside the UML guest, or natively on a vcan.

Not a test module (pytest collects ``test_*.py`` only); ``test_uml_socketcan.py``
runs it as a separate program, inside the guest or on the host's own vcan.

Sub-commands (each writes a JSON result with ``"ok"`` and the measurements):

* ``echo``: answer every frame on ``--request-id`` with the same data on
  ``--reply-id`` until ``--count`` frames were answered or ``--idle`` seconds
  pass without one; prints ``ECHO_READY`` once the bus is open.
* ``pingpong``: start ``echo`` as a second process, send ``--count`` frames and
  time each round trip; every reply must carry the data that was sent.
* ``hil``: the hardware-in-the-loop scenario (see :func:`run_hil`).

The bus is opened from python-can configuration: ``--interface``/``--channel``
or, when absent, ``CAN_INTERFACE``/``CAN_CHANNEL`` as everywhere in redarm_ros.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can

_LOG = logging.getLogger("uml_scenario")
HERE = Path(__file__).resolve()


def _bus_kwargs(ns: argparse.Namespace) -> dict[str, Any]:
    kwargs: dict[str, Any] = {}
    interface = ns.interface or os.environ.get("CAN_INTERFACE")
    channel = ns.channel or os.environ.get("CAN_CHANNEL")
    if interface:
        kwargs["interface"] = interface
    if channel:
        kwargs["channel"] = channel
    return kwargs


def _write_result(path: str | None, result: dict[str, Any]) -> None:
    text = json.dumps(result, indent=2, sort_keys=True)
    if path:
        tmp = Path(path + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def cmd_echo(ns: argparse.Namespace) -> int:
    """Answer frames on request_id with the same payload on reply_id."""
    answered = 0
    with can.Bus(**_bus_kwargs(ns)) as bus:
        bus.set_filters([{"can_id": ns.request_id, "can_mask": 0x7FF, "extended": False}])
        sys.stdout.write("ECHO_READY\n")
        sys.stdout.flush()
        while answered < ns.count:
            msg = bus.recv(timeout=ns.idle)
            if msg is None:
                break
            if msg.arbitration_id != ns.request_id or msg.is_error_frame:
                continue
            bus.send(can.Message(arbitration_id=ns.reply_id, data=msg.data, is_extended_id=False, check=True))
            answered += 1
    _LOG.info("echo answered %d frames", answered)
    return 0 if answered == ns.count else 1


def _start_child(args: list[str], ready: str, timeout_s: float) -> subprocess.Popen[str]:
    """Start ``python uml_scenario.py ARGS`` and wait for its readiness line."""
    proc = subprocess.Popen(
        [sys.executable, str(HERE), *args],
        stdout=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + timeout_s
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        if line.strip() == ready:
            return proc
    _stop_child(proc)
    raise RuntimeError(f"child {args[0]} did not print {ready} within {timeout_s} s")


def _stop_child(proc: subprocess.Popen[str], timeout_s: float = 10.0, grace_s: float = 0.0) -> int | None:
    """Wait ``grace_s`` for a natural exit, then SIGINT, wait, SIGINT again, SIGKILL (project schedule)."""
    if grace_s > 0:
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
    for sig, wait_s in ((signal.SIGINT, timeout_s), (signal.SIGINT, 3.0), (signal.SIGKILL, 3.0)):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        try:
            proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()


def cmd_pingpong(ns: argparse.Namespace) -> int:
    """Round trips between this process and an echo process."""
    bus_args = []
    if ns.interface:
        bus_args += ["--interface", ns.interface]
    if ns.channel:
        bus_args += ["--channel", ns.channel]
    result: dict[str, Any] = {"ok": False, "count": ns.count, "bus": _bus_kwargs(ns)}
    t_start = time.monotonic()
    echo = _start_child(["echo", *bus_args, "--count", str(ns.count), "--idle", str(max(ns.timeout, 10.0)),
                         "--request-id", hex(ns.request_id), "--reply-id", hex(ns.reply_id)],
                        "ECHO_READY", ns.ready_timeout)
    result["echo_start_s"] = round(time.monotonic() - t_start, 3)
    rtts: list[float] = []
    mismatches = 0
    lost = 0
    try:
        with can.Bus(**_bus_kwargs(ns)) as bus:
            bus.set_filters([{"can_id": ns.reply_id, "can_mask": 0x7FF, "extended": False}])
            for i in range(ns.count):
                payload = i.to_bytes(4, "little") + bytes([0xA5, 0x5A, i & 0xFF, 0x3C])
                t0 = time.perf_counter()
                bus.send(can.Message(arbitration_id=ns.request_id, data=payload, is_extended_id=False,
                                     check=True))
                deadline = t0 + ns.timeout
                while True:
                    msg = bus.recv(timeout=max(0.0, deadline - time.perf_counter()))
                    if msg is None:
                        lost += 1
                        break
                    if msg.arbitration_id != ns.reply_id:
                        continue
                    if bytes(msg.data) != payload:
                        # A late reply to an earlier (lost) request: count it, keep waiting.
                        mismatches += 1
                        continue
                    rtts.append(time.perf_counter() - t0)
                    break
    finally:
        echo_rc = _stop_child(echo, grace_s=10.0)
    result.update(
        received=len(rtts),
        lost=lost,
        mismatches=mismatches,
        echo_rc=echo_rc,
        rtt_median_ms=round(statistics.median(rtts) * 1e3, 3) if rtts else None,
        rtt_p95_ms=round(sorted(rtts)[int(0.95 * (len(rtts) - 1))] * 1e3, 3) if rtts else None,
        rtt_max_ms=round(max(rtts) * 1e3, 3) if rtts else None,
        duration_s=round(time.monotonic() - t_start, 3),
    )
    result["ok"] = len(rtts) == ns.count and lost == 0 and echo_rc == 0
    _write_result(ns.result, result)
    return 0 if result["ok"] else 1


SUITE = ("pingpong",)


def cmd_suite(ns: argparse.Namespace) -> int:
    """Run every scenario in turn; each writes ``result_<name>.json`` into ``--out``."""
    out = Path(ns.out)
    out.mkdir(parents=True, exist_ok=True)
    bus_args = []
    if ns.interface:
        bus_args += ["--interface", ns.interface]
    if ns.channel:
        bus_args += ["--channel", ns.channel]
    failed = 0
    for name in ns.only or SUITE:
        result_path = out / f"result_{name}.json"
        t0 = time.monotonic()
        _LOG.info("scenario %s: start", name)
        try:
            sub_ns = build_parser().parse_args([name, *bus_args, "--result", str(result_path)])
            rc = int(sub_ns.func(sub_ns))
        except Exception as exc:  # one scenario's crash must not hide the others' results
            _LOG.exception("scenario %s crashed", name)
            _write_result(str(result_path), {"ok": False, "error": repr(exc)})
            rc = 1
        _LOG.info("scenario %s: rc=%d in %.1f s", name, rc, time.monotonic() - t0)
        failed += rc != 0
    return 1 if failed else 0


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of the scenario program."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--interface", help="python-can interface (default: $CAN_INTERFACE)")
        p.add_argument("--channel", help="python-can channel (default: $CAN_CHANNEL)")
        p.add_argument("--result", help="write the JSON result here as well")

    p = sub.add_parser("echo", help="answer frames (child of pingpong)")
    common(p)
    p.add_argument("--request-id", type=lambda s: int(s, 0), default=0x123)
    p.add_argument("--reply-id", type=lambda s: int(s, 0), default=0x124)
    p.add_argument("--count", type=int, default=1000)
    p.add_argument("--idle", type=float, default=10.0, help="give up after this long without a frame [s]")
    p.set_defaults(func=cmd_echo)

    p = sub.add_parser("pingpong", help="round trips between two processes")
    common(p)
    p.add_argument("--request-id", type=lambda s: int(s, 0), default=0x123)
    p.add_argument("--reply-id", type=lambda s: int(s, 0), default=0x124)
    p.add_argument("--count", type=int, default=1000)
    p.add_argument("--timeout", type=float, default=1.0, help="per round trip [s]")
    p.add_argument("--ready-timeout", type=float, default=60.0, help="echo start-up [s]")
    p.set_defaults(func=cmd_pingpong)

    p = sub.add_parser("suite", help="every scenario in turn, results into --out")
    common(p)
    p.add_argument("--out", required=True, help="directory for result_<name>.json")
    p.add_argument("--only", nargs="*", choices=SUITE, help="run only these scenarios")
    p.set_defaults(func=cmd_suite)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse, run the sub-command, return its exit code."""
    logging.basicConfig(level=logging.INFO, format="[%(name)s %(process)d] %(message)s", stream=sys.stderr)
    ns = build_parser().parse_args(argv)
    return int(ns.func(ns))


if __name__ == "__main__":
    sys.exit(main())
