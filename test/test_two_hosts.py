"""Two hosts: the stack split across two network namespaces, DDS over UDP between them only.

``robot`` runs the CAN bus server (127.0.0.1 of the robot only), the simulator and can_driver;
``workstation`` runs ik_service, the controller and a client (test/two_hosts_client.py). Each
"host" is a network + mount + UTS namespace of its own (own interfaces, own /dev/shm, own hostname),
and the two are joined by one veth pair, 169.254.77.1/30 <-> 169.254.77.2/30, with no other route.
DDS is Fast DDS over UDPv4 only, discovery unicast to the other host (``ROS_STATIC_PEERS``) and
otherwise local (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``): no multicast at all.

The client on the workstation sees /joint_states arrive from the robot, calls ik_service, moves the
arm to a ready pose and publishes a goal on /goal_pose; it ends when the robot's measured joints put
the tool on the goal, and the simulator (on the robot) must agree within 1 mm / 0.01 rad.

Packet accounting: every packet one end of the veth sent, the other end received (nothing went
anywhere else), each namespace holds exactly ``lo`` and its end of the pair and cannot route to any
other address, the bus server cannot be reached from the workstation, and the host side (the
namespace this test runs in) holds only ``lo`` before and after, so no end of the pair was ever there.
Finally both namespaces are gone: no process is left in them (also when the test fails).

Why not ``ip netns add``: it creates /run/netns/<name> on the host's file system (here /run is on the
root file system, not a tmpfs), even inside the test sandbox's private mount namespace; two runs at
once would collide on the names and a crashed run would leave files behind. A namespace held by a
process of this test (``unshare``), entered with ``nsenter --target PID``, needs no shared state and
disappears with its last process. Skipped, with the reason, where namespaces or veth pairs cannot be
created, or outside a private network namespace (``scripts/ros_sandbox.sh``), where the host-side
count would include the host's own traffic.
"""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")

from redarm_ros.bringup import READY  # noqa: E402
from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.kinematics.quaternion import from_xyzw, quat_to_matrix  # noqa: E402
from redarm_ros.procs import ManagedProcess, python_module_cmd  # noqa: E402

pytestmark = [pytest.mark.hil, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config"
ROBOT_IP, WORKSTATION_IP, PREFIX_LEN = "169.254.77.1", "169.254.77.2", 30
ARM = "pa10"
READY_Q = [0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0]  # elbow bent: the homed all-zero pose is singular
GOAL_Q = [0.4, 0.7, -0.3, 1.0, 0.2, 0.9, 0.3]
POS_TOL, ROT_TOL = 1e-3, 0.01
START_TIMEOUT_S = 60.0  # per readiness line; generous for a starved 2-core machine


def _stderr(line: str) -> None:
    try:
        sys.stderr.write(line + "\n")
    except (ValueError, OSError):
        pass


def _die_with_parent() -> None:
    # A namespace holder must not outlive a killed pytest: SIGKILL it when its parent dies.
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def _run(cmd: Sequence[str], timeout: float = 20.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(cmd), stdin=subprocess.DEVNULL, capture_output=True, text=True,
                          timeout=timeout)


def _link_counters(prefix: Sequence[str] = ()) -> dict[str, tuple[int, int]]:
    """Interface name -> (rx_packets, tx_packets) in the namespace ``prefix`` enters (netlink)."""
    out = _run([*prefix, "ip", "-s", "-j", "link", "show"])
    assert out.returncode == 0, out.stderr
    return {link["ifname"]: (int(link["stats64"]["rx"]["packets"]), int(link["stats64"]["tx"]["packets"]))
            for link in json.loads(out.stdout)}


def _netns_inode(pid: int) -> int:
    return os.stat(f"/proc/{pid}/ns/net").st_ino


def _pids_in_netns(inode: int) -> list[int]:
    pids = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                if os.stat(f"/proc/{entry.name}/ns/net").st_ino == inode:
                    pids.append(int(entry.name))
            except OSError:
                pass
    return pids


@dataclass
class Host:
    """A network + mount + UTS namespace held by ``holder`` (``sleep``), named ``name``, with the veth
    end ``ifname`` at ``ip``."""

    name: str
    ip: str
    ifname: str
    holder: subprocess.Popen[str]
    netns: int = 0

    @classmethod
    def create(cls, name: str, ip: str, ifname: str) -> Host:
        # Private /dev/shm (two machines share no memory), lo up, own hostname; then just stay alive.
        script = (f"mount -t tmpfs -o mode=1777 tmpfs /dev/shm && ip link set lo up && hostname {name} "
                  "&& echo NETNS_READY && exec sleep 3600")
        holder = subprocess.Popen(
            ["unshare", "--net", "--mount", "--uts", "--propagation", "private", "sh", "-c", script],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            preexec_fn=_die_with_parent,
        )
        line = holder.stdout.readline() if holder.stdout else ""
        if "NETNS_READY" not in line:
            holder.kill()
            rest = holder.communicate(timeout=10)[0]
            pytest.skip(f"cannot create a network namespace here: {(line + rest).strip()}")
        host = cls(name, ip, ifname, holder)
        host.netns = _netns_inode(holder.pid)
        return host

    def enter(self) -> list[str]:
        """Command prefix that runs a program inside this host."""
        return ["nsenter", f"--target={self.holder.pid}", "--net", "--mount", "--uts", "--"]

    def sh(self, script: str) -> None:
        out = _run([*self.enter(), "sh", "-c", script])
        assert out.returncode == 0, f"{self.name}: {script}: {out.stderr}"

    def remove(self) -> None:
        if self.holder.poll() is None:
            self.holder.kill()
        self.holder.wait(timeout=10)
        if self.holder.stdout:
            self.holder.stdout.close()


@pytest.fixture
def hosts() -> Iterator[tuple[Host, Host]]:
    """``robot`` and ``workstation`` joined by a veth pair; removed afterwards, also on failure."""
    for tool in ("unshare", "nsenter", "ip"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} not installed")
    host_side = _link_counters()
    if set(host_side) != {"lo"}:
        pytest.skip(f"not inside a private network namespace (interfaces {sorted(host_side)}): run through "
                    "scripts/ros_sandbox.sh, or the host-side packet count would include the host's traffic")
    made: list[Host] = []
    try:
        made.append(Host.create("robot", ROBOT_IP, "veth-robot"))
        made.append(Host.create("workstation", WORKSTATION_IP, "veth-ws"))
        robot, ws = made
        out = _run(["ip", "link", "add", robot.ifname, "type", "veth", "peer", "name", ws.ifname])
        if out.returncode != 0:
            pytest.skip(f"cannot create a veth pair here: {out.stderr.strip()}")
        for h in made:
            moved = _run(["ip", "link", "set", h.ifname, "netns", str(h.holder.pid)])
            assert moved.returncode == 0, moved.stderr
            h.sh(f"ip addr add {h.ip}/{PREFIX_LEN} dev {h.ifname} && ip link set {h.ifname} up")
        yield robot, ws
    finally:
        for h in made:
            h.remove()
    gone = {h.name: _pids_in_netns(h.netns) for h in made}
    assert all(not p for p in gone.values()), f"processes left in the namespaces: {gone}"
    # The host side holds only lo, before and after: the pair lived entirely inside the two namespaces,
    # so nothing of theirs could reach a host-side interface. (lo's own counters are not compared:
    # other tests of the same session leave loopback traffic of their own, e.g. closing web sockets.)
    assert set(_link_counters()) == set(host_side) == {"lo"}, "an interface appeared on the host side"


def _dds_env(host: Host, peer: Host, log_dir: Path) -> dict[str, str]:
    """What docs/setup.md "Two machines" tells users to set, plus the test's domain, logs and PYTHONPATH."""
    env = dict(os.environ)
    env.update(
        FASTDDS_BUILTIN_TRANSPORTS="UDPv4",  # SHM is host-local; UDP is the only way between hosts
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",  # no multicast: automatic discovery on this host only
        ROS_STATIC_PEERS=peer.ip,  # ... and unicast discovery of the other host
        ROS_LOG_DIR=str(log_dir / host.name),
        PYTHONUNBUFFERED="1",
        RCUTILS_COLORIZED_OUTPUT="0",
        PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
    )
    env["ROS_DOMAIN_ID"] = os.environ["ROS_DOMAIN_ID"]  # the session's (conftest), same on both hosts
    return env


def _ros_args(node: str, **params: str) -> list[str]:
    args = ["--ros-args", "--log-level", "warn", "--log-level", f"{node}:=info",
            "--params-file", str(CONFIG / f"{node}.yaml")]
    for k, v in params.items():
        args += ["-p", f"{k.replace('__', '.')}:={v}"]
    return args


def _sim_tool(status_file: Path) -> np.ndarray:
    st = json.loads(status_file.read_text(encoding="utf-8"))
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(from_xyzw(st["tool"]["quaternion_xyzw"]))
    T[:3, 3] = st["tool"]["position"]
    return T


def _pose_err(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(np.arccos(np.clip(c, -1.0, 1.0)))


def test_goal_reached_across_two_hosts(hosts: tuple[Host, Host], tmp_path: Path) -> None:
    robot, ws = hosts
    # Each host: only lo and its end of the link, and no route beyond the link.
    for h in hosts:
        assert set(_link_counters(h.enter())) == {"lo", h.ifname}, h.name
        outside = _run([*h.enter(), "ip", "route", "get", "192.0.2.1"])
        assert outside.returncode != 0, f"{h.name} has a route out: {outside.stdout}"
    for h, peer in ((robot, ws), (ws, robot)):
        route = _run([*h.enter(), "ip", "route", "get", peer.ip])
        assert route.returncode == 0 and f"dev {h.ifname}" in route.stdout, route.stdout + route.stderr

    status_file = tmp_path / "sim_status.json"
    children: list[ManagedProcess] = []

    def start(host: Host, name: str, cmd: list[str]) -> ManagedProcess:
        peer = ws if host is robot else robot
        child = ManagedProcess.start(f"{host.name}/{name}", [*host.enter(), *cmd],
                                     env=_dds_env(host, peer, tmp_path), cwd=tmp_path, sink=_stderr)
        children.append(child)
        return child

    try:
        # Workstation nodes start at once; the robot's chain bus -> simulator -> driver in order.
        ik = start(ws, "ik_service", python_module_cmd(
            "redarm_ros.nodes.ik_service", *_ros_args("ik_service")))
        controller = start(ws, "controller", python_module_cmd(
            "redarm_ros.nodes.controller", *_ros_args("controller", arm=ARM)))
        bus = start(robot, "canbus", python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1",
                                                        "--port", "0"))
        port = int(bus.wait_for_line(READY["canbus"], START_TIMEOUT_S).group(1))
        channel = f"ws://127.0.0.1:{port}/"
        sim = start(robot, "sim", python_module_cmd(
            "redarm_ros.sim.hardware", "--arm", ARM, "--can-interface", "remote", "--can-channel", channel,
            "--status-file", str(status_file)))
        sim.wait_for_line(READY["sim"], START_TIMEOUT_S)
        driver = start(robot, "can_driver", python_module_cmd("redarm_ros.nodes.can_driver", *_ros_args(
            "can_driver", arm=ARM, auto_init="true", can__interface="remote", can__channel=channel)))
        driver.wait_for_line(READY["can_driver"], START_TIMEOUT_S)
        ik.wait_for_line(READY["ik_service"], START_TIMEOUT_S)
        controller.wait_for_line(READY["controller"], START_TIMEOUT_S)
        # A starved machine can make the driver's own init fail (a reply later than 20 ms); the client
        # then calls ~/init, as a user would.
        init = driver.wait_for_line(r"init (done|failed)", START_TIMEOUT_S)

        # The bus is the robot's own: its server is not reachable from the workstation.
        probe = _run([*ws.enter(), sys.executable, "-c",
                      f"import socket; socket.create_connection(('{robot.ip}', {port}), timeout=2)"])
        assert probe.returncode != 0 and "Connection refused" in probe.stderr, probe.stderr

        client = start(ws, "client", [
            sys.executable, str(Path(__file__).with_name("two_hosts_client.py")), "--arm", ARM,
            "--ready", *map(str, READY_Q), "--goal", *map(str, GOAL_Q), "--timeout", "20",
            *(["--init"] if init.group(1) == "failed" else [])])
        reached = client.wait_for_line(r"CLIENT (REACHED|FAILED)(.*)", 240.0)
        halts = [line for line in driver.output() if "HALTED:" in line]
        assert reached.group(1) == "REACHED", f"{reached.group(0)}; driver halts: {halts}"
        result = json.loads(reached.group(2))
        client.expect_exit()
        assert any(f"arriving on {ws.name}" in line for line in client.output()), "client not on workstation"
        for c in children:
            assert c is client or c.returncode is None, f"{c.name} died: {c.tail(20)}"

        # The simulator on the robot agrees (it follows the last commands within a few cycles).
        T_goal = load_arm(ARM).fk(np.array(GOAL_Q))
        deadline = time.monotonic() + 10.0
        while True:
            pe, re_ = _pose_err(_sim_tool(status_file), T_goal)
            if (pe < POS_TOL and re_ < ROT_TOL) or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        assert pe < POS_TOL and re_ < ROT_TOL, f"simulated tool {pe * 1e3:.3f} mm / {re_:.4f} rad off"
        _stderr(f"two hosts: goal reached in {result['reach_s']} s ({result['total_s']} s client run); "
                f"simulated tool {pe * 1e3:.3f} mm / {re_:.4f} rad from it; driver halts {len(halts)}, "
                f"recoveries {result['recoveries']}")

    finally:
        for c in reversed(children):
            c.stop()

    # With every ROS process stopped the link is quiet: every packet one end sent, the other end
    # received (the link carried the DDS traffic and nothing was lost to anywhere else). Read again if
    # the kernel sent something (IPv6 neighbour discovery) while the four counters were being read.
    for _ in range(5):
        before = _link_counters(robot.enter())[robot.ifname]
        w_rx, w_tx = _link_counters(ws.enter())[ws.ifname]
        r_rx, r_tx = _link_counters(robot.enter())[robot.ifname]
        if (r_rx, r_tx) == before:
            break
    assert r_tx > 100 and w_tx > 100, "hardly any traffic over the link: DDS did not use it?"
    assert (r_tx, w_tx) == (w_rx, r_rx), f"robot tx/rx {r_tx}/{r_rx}, workstation tx/rx {w_tx}/{w_rx}"
    _stderr(f"two hosts: veth robot->workstation {r_tx} packets, workstation->robot {w_tx} packets")
