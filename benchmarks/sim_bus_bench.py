"""CPU cost of the simulator's bus thread per driver cycle, offline (no ROS, no bus server, no physics).

Runs ``HardwareSim._bus_loop`` (the code of ``redarm-sim``'s ``sim-bus`` thread) in this thread over a
scripted sequence of the frames a 250 Hz can_driver sends (its init: ACT_CONFIG read/write, RESET,
HOME, ACT_STATE polls; then cycles of 7 FSTEP_EXT + startMotionAll + watchdog refresh, first at rest,
then moving), a burst per cycle, and collects every reply. The modules' plants are the physics
process's joints (:class:`~redarm_ros.sim.physics_process.RemoteJoint` over shared memory and a command
pipe), with the process itself replaced by a stand-in that applies each cycle's commands at once.

``--bus relay`` (default) puts the real client stack between: :class:`~redarm_ros.can.bus.ReconnectingBus`
over :class:`~redarm_ros.can.relay_client.RelayBus` on one end of a socket pair, the bench writing the
bus server's frames into the other; ``--bus fake``: a list in, a list out (the simulator's side alone).

Prints the CPU time per cycle (``time.process_time``; the bench's own work between cycles left out)
at rest and moving, and a SHA-256 over every reply (arbitration id + data bytes, in order): the same
hash before and after a change means the same replies, bit for bit. The modules' watchdog timeout is
raised to an hour so that a descheduled bench cannot trip it (it is refreshed all the same).

Run: ``.venv/bin/python benchmarks/sim_bus_bench.py [--cycles 20000] [--bus fake] [--profile]``
(``--drop 0.1 --silence 3``: the fault injection paths, for their hash).
"""

from __future__ import annotations

import argparse
import collections
import cProfile
import gc
import hashlib
import math
import os
import pickle
import pstats
import select
import socket
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from redarm_ros.can import protocol as p  # noqa: E402
from redarm_ros.can.bus import ReconnectingBus  # noqa: E402
from redarm_ros.can.protocol import Command, Param  # noqa: E402
from redarm_ros.can.relay_client import BINARY_MSG, RelayBus, binary_flags  # noqa: E402
from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.sim import physics_process as pp  # noqa: E402
from redarm_ros.sim.hardware import Faults, HardwareSim  # noqa: E402

DT_MS = 4
CFG = int(p.ActConfig.SYNC_MOTION | p.ActConfig.WATCHDOG_ENABLE)


# -- the driver's frames -----------------------------------------------------------------------------
def init_bursts(ids: list[int], max_vel: list[float], max_acc: list[float]) -> list[list[can.Message]]:
    """What PowerCubeArmDriver.init sends, a burst per transaction."""
    wd = p.watchdog_refresh_all()
    return [
        [p.get_param(i, Param.ACT_CONFIG) for i in ids],
        [m for i, v, a in zip(ids, max_vel, max_acc, strict=True)
         for m in (p.set_param(i, Param.ACT_CONFIG, CFG), p.set_param(i, Param.ACT_FMAXVEL, v),
                   p.set_param(i, Param.ACT_FMAXACC, a))],
        [p.get_param(i, Param.ACT_CONFIG) for i in ids],
        [p.command(i, Command.RESET) for i in ids],
        [p.command(i, Command.HOME) for i in ids],
        *([wd, *(p.get_param(i, Param.ACT_STATE) for i in ids)] for _ in range(3)),
        [m for i in ids for m in (p.get_param(i, Param.ACT_STATE), p.get_param(i, Param.ACT_FPOS))],
    ]


def cycle_burst(ids: list[int], q: list[float]) -> list[can.Message]:
    """One 250 Hz cycle: FSTEP_EXT to every joint, startMotionAll, watchdog refresh."""
    return [*(p.fstep(i, x, DT_MS) for i, x in zip(ids, q, strict=True)),
            p.start_motion_all(), p.watchdog_refresh_all()]


def moving_target(k: int, n: int, home: list[float]) -> list[float]:
    """Joint j swings 0.2 rad about home (period 2 s, phase by joint): well within every limit."""
    t = k * DT_MS / 1000.0
    return [home[j] + 0.2 * math.sin(math.pi * t + j) for j in range(n)]


# -- a physics process without the process -----------------------------------------------------------
class OfflinePhysics:
    """A :class:`PhysicsProcess` handle whose commands a call of :meth:`apply` carries out at once."""

    def __init__(self, arm: Any) -> None:
        proc = pp.PhysicsProcess.__new__(pp.PhysicsProcess)
        proc.arm, proc.n, proc.rate_hz = arm, int(arm.n), 1000.0
        proc._lay = pp._layout(proc.n)
        proc._view = np.zeros(pp._size(proc.n))
        self._rfd, wfd = os.pipe()
        os.set_blocking(self._rfd, False)
        os.set_blocking(wfd, False)
        proc._conn = _Fd(wfd)  # flush() writes to its fileno()
        proc._outbox, proc._outbox_lock = collections.deque(), threading.Lock()
        proc.dropped_commands, proc._seq = 0, 0
        proc._joints = [pp.RemoteJoint(proc, i) for i in range(proc.n)]
        self.proc = proc
        self._buf = b""

    def apply(self) -> None:
        """Read the commands written so far and apply them: a position command puts the joint there
        (moving at the speed that takes one cycle), a halt stops it."""
        while True:
            try:
                chunk = os.read(self._rfd, 1 << 16)
            except BlockingIOError:
                break
            self._buf += chunk
        v, lay = self.proc._view, self.proc._lay
        while len(self._buf) >= 4:
            (size,) = struct.unpack_from("!i", self._buf)
            if len(self._buf) < 4 + size:
                break
            cmds, self._buf = pickle.loads(self._buf[4:4 + size]), self._buf[4 + size:]
            for seq, op, *args in cmds:
                j = args[0] if args else 0
                if op == "position":
                    old = v[lay["q"].start + j]
                    v[lay["q"].start + j] = args[1]
                    v[lay["dq"].start + j] = (args[1] - old) / (DT_MS / 1000.0)
                    v[lay["active"].start + j] = 1.0 if args[1] != old else 0.0
                elif op == "halt":
                    v[lay["dq"].start + j] = v[lay["active"].start + j] = 0.0
                v[pp._APPLIED] = seq


class _Fd:
    def __init__(self, fd: int) -> None:
        self._fd = fd

    def fileno(self) -> int:
        return self._fd


# -- buses -------------------------------------------------------------------------------------------
class FakeBus:
    """Frames in from a list, replies out to a list."""

    def __init__(self) -> None:
        self.inbox: collections.deque[can.Message] = collections.deque()
        self.sent: list[tuple[int, bytes]] = []

    def recv(self, timeout: float | None = None) -> can.Message | None:
        return self.inbox.popleft() if self.inbox else None

    def send_many(self, msgs: list[can.Message]) -> None:
        self.sent.extend((m.arbitration_id, bytes(m.data)) for m in msgs)

    def feed(self, burst: list[can.Message]) -> None:
        now = time.time()
        for m in burst:
            m.timestamp = now
        self.inbox.extend(burst)

    def replies(self) -> list[tuple[int, bytes]]:
        out, self.sent = self.sent, []
        return out


class SocketPairBus:
    """ReconnectingBus over RelayBus on one end of a socket pair; the bench is the bus server."""

    def __init__(self) -> None:
        mine, self._peer = socket.socketpair()
        self._peer.setblocking(False)
        inner = RelayBus.__new__(RelayBus)
        inner.socket, inner._buf, inner._frames = mine, bytearray(), collections.deque()
        inner._send_lock = threading.Lock()
        inner._poll = select.poll()
        inner._poll.register(mine, select.POLLIN)
        inner.channel_info, inner.channel = "socketpair", "bench"
        can.BusABC.__init__(inner, "bench")
        outer = ReconnectingBus.__new__(ReconnectingBus)
        outer.config = {"interface": "remote", "channel": "bench"}
        outer._bus, outer._lost, outer._lock, outer.reopen_count = inner, None, threading.Lock(), 0
        outer.channel_info = "bench"
        can.BusABC.__init__(outer, channel="bench", can_filters=None)
        self.bus = outer
        self._rx = b""

    def feed(self, burst: list[can.Message]) -> None:
        now, parts = time.time(), []
        for m in burst:
            body = b"\x01" + BINARY_MSG.pack(now, m.arbitration_id, m.dlc, binary_flags(m)) + bytes(m.data)
            parts.append(bytes((0x82, len(body))) + body)  # a server's frame: unmasked
        self._peer.sendall(b"".join(parts))

    def replies(self) -> list[tuple[int, bytes]]:
        while True:
            try:
                self._rx += self._peer.recv(1 << 16)
            except BlockingIOError:
                break
        out, buf, pos = [], self._rx, 0
        while len(buf) - pos >= 2 and len(buf) - pos >= 6 + (buf[pos + 1] & 0x7F):
            start, n = pos + 6, buf[pos + 1] & 0x7F  # 2 header bytes, the (zero) mask key
            _, arb, dlc, _ = BINARY_MSG.unpack_from(buf, start + 1)
            out.append((arb, bytes(buf[start + 1 + BINARY_MSG.size:start + n])))
            assert dlc == n - 1 - BINARY_MSG.size
            pos = start + n
        self._rx = buf[pos:]
        return out


# -- the run -----------------------------------------------------------------------------------------
def run(cycles: int, bus_kind: str, faults: Faults, profile: bool) -> dict[str, Any]:
    arm = load_arm("pa10")
    physics = OfflinePhysics(arm)
    fake = FakeBus() if bus_kind == "fake" else None
    pair = SocketPairBus() if fake is None else None
    bus = fake if fake is not None else pair.bus  # type: ignore[union-attr]
    sim = HardwareSim(physics.proc, bus, faults=faults)  # type: ignore[arg-type]
    ids = sim.module_ids
    for mid in ids:
        sim.emulator.module(mid).cfg.watchdog_timeout_s = 3600.0
    home = [min(max(0.0, float(lo)), float(hi)) for lo, hi in zip(arm.lower, arm.upper, strict=True)]
    bursts = init_bursts(ids, [float(v) for v in arm.max_vel], [float(a) for a in arm.max_acc])
    n_init = len(bursts)
    bursts += [cycle_burst(ids, home) for _ in range(cycles)]
    bursts += [cycle_burst(ids, moving_target(k, sim.n, home)) for k in range(cycles)]
    io = fake if fake is not None else pair
    digest, n_replies = hashlib.sha256(), 0
    cpu = {"rest": 0.0, "moving": 0.0}
    state = {"k": 0, "left": 0.0}
    prof = cProfile.Profile() if profile else None

    def between_cycles() -> None:  # the bench's work: collect, apply the physics, feed the next burst
        nonlocal n_replies
        entered = time.process_time()
        k = state["k"]
        if prof is not None:
            prof.disable()
        if k > n_init:
            cpu["rest" if k <= n_init + cycles else "moving"] += entered - state["left"]
        for arb, data in io.replies():  # type: ignore[union-attr]
            digest.update(struct.pack("<HB", arb, len(data)) + data)
            n_replies += 1
        physics.apply()
        if k < len(bursts):
            io.feed(bursts[k])  # type: ignore[union-attr]
        else:
            sim._stop.set()
        state["k"] = k + 1
        if prof is not None and k >= n_init:
            prof.enable()
        state["left"] = time.process_time()

    real_recv = bus.recv

    def recv(timeout: float | None = None) -> can.Message | None:
        if timeout:  # the receive after a burst's replies went out: the next burst comes
            between_cycles()
        return real_recv(timeout)

    bus.recv = recv  # type: ignore[method-assign]
    gc.collect()
    gc.freeze()
    sim._bus_loop()
    if prof is not None:
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(30)
    return {"rest_us": cpu["rest"] / cycles * 1e6, "moving_us": cpu["moving"] / cycles * 1e6,
            "replies": n_replies, "hash": digest.hexdigest(), "counters": sim.counters}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=20000, help="cycles at rest, then as many moving")
    ap.add_argument("--bus", choices=("relay", "fake"), default="relay")
    ap.add_argument("--drop", type=float, default=0.0, help="drop this fraction of replies (seed 0)")
    ap.add_argument("--silence", type=int, action="append", default=[], help="a silenced module id")
    ap.add_argument("--profile", action="store_true", help="cProfile the cycles (slower; no timing)")
    args = ap.parse_args()
    faults = Faults(drop_replies=args.drop, silenced=set(args.silence))
    r = run(args.cycles, args.bus, faults, args.profile)
    c = r["counters"]
    print(f"bus={args.bus} cycles={args.cycles}+{args.cycles} rest_us_per_cycle={r['rest_us']:.1f} "
          f"moving_us_per_cycle={r['moving_us']:.1f} replies={r['replies']} frames={c.frames_rx} "
          f"handler_errors={c.handler_errors} hash={r['hash'][:16]}")


if __name__ == "__main__":
    main()
