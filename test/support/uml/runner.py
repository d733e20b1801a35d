"""Boot a User-Mode Linux guest with a genuine SocketCAN ``vcan0`` and run one job in it.

The build and test machines have no SocketCAN (``socket(AF_CAN)`` fails with
errno 97). Debian's ``user-mode-linux`` package brings a Linux kernel that runs
as an ordinary process and has CAN and vcan as modules, so a guest can carry
real python-can ``socketcan`` traffic between processes:

* root file system: the host's ``/``, read-only, over hostfs (the guest runs the
  host's Python, venv and this checkout in place);
* PID 1: :file:`guest_init.sh` (mounts proc/sys/tmpfs, loads ``can``,
  ``can-raw``, ``can-dev``, ``vcan``, creates and raises ``vcan0``, runs the job,
  powers off);
* results: one host directory, mounted read-write in the guest at the same
  path; the job's exit code comes back in ``job.rc`` because ``linux.uml``
  itself exits 0 on power-off whatever happened inside;
* no network device: the guest has loopback only, nothing leaves it;
* one virtual CPU, slow system calls (every guest syscall is a ptrace stop).

Timing measured on a 2-core host: boot to job start ~1.5 s, Python start-up
importing ``can`` ~2 s per process.

Use :func:`run_guest` from code or ``python -m support.uml.runner --out DIR -- CMD ...``
by hand. :func:`uml_unavailable_reason` says why a host cannot do this.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import secrets
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from redarm_ros.errors import InvalidInputError, RedarmError
from support.uml.fpu import GUEST_NO_AVX_ENV

__all__ = [
    "GuestResult",
    "UmlKernel",
    "UmlUnavailableError",
    "find_uml",
    "run_guest",
    "uml_unavailable_reason",
]

_LOG = logging.getLogger(__name__)

GUEST_INIT = Path(__file__).with_name("guest_init.sh")
FPU_SCRIPT = Path(__file__).with_name("fpu.py")
# Load order matters: each module needs the one before it.
CAN_MODULES = (
    "net/can/can.ko",
    "net/can/can-raw.ko",
    "drivers/net/can/dev/can-dev.ko",
    "drivers/net/can/vcan.ko",
)
UML_MODULE_ROOT = Path("/usr/lib/uml/modules")
DEFAULT_TIMEOUT_S = 180.0
DEFAULT_MEM = "512M"
# Host tools the guest runs from the shared root file system.
_GUEST_TOOLS = ("sh", "mount", "umount", "insmod", "ip", "sleep", "sync", "kill")
# Values travel on the kernel command line: no blanks, no quotes.
_CMDLINE_SAFE = re.compile(r"^[A-Za-z0-9_./:,+=@%-]+$")


class UmlUnavailableError(RedarmError):
    """This host cannot boot the guest; ``reason`` says why and how to fix it."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class UmlKernel:
    """A usable UML kernel: ``binary`` (``linux.uml``) and ``modules`` (its ``.../<version>/kernel`` dir)."""

    binary: Path
    modules: Path


@dataclass(frozen=True)
class GuestResult:
    """What came back from one guest run.

    ``job_rc`` is the job's exit code inside the guest, or None when the job
    never finished (boot failure, vcan failure, timeout). ``stage`` is the last
    stage init reported (``boot``, ``vcan_up``, ``vcan_failed``, ``job_done``) or
    ``none``. ``duration_s`` is wall time from starting ``linux.uml`` to its exit.
    """

    job_rc: int | None
    stage: str
    duration_s: float
    timed_out: bool
    uml_returncode: int | None
    out_dir: Path
    console: str
    init_log: str
    job_log: str

    @property
    def ok(self) -> bool:
        """The job ran to completion and exited 0."""
        return self.job_rc == 0

    def explain(self, tail: int = 40) -> str:
        """A multi-line diagnosis for assertion messages: stage, exit codes, log tails."""

        def last(text: str) -> str:
            return "\n".join(text.splitlines()[-tail:])

        return (
            f"stage={self.stage} job_rc={self.job_rc} timed_out={self.timed_out} "
            f"uml_rc={self.uml_returncode} duration={self.duration_s:.1f}s out={self.out_dir}\n"
            f"--- init.log\n{last(self.init_log)}\n--- job.log\n{last(self.job_log)}\n"
            f"--- console (tail)\n{last(self.console)}"
        )


def _find_modules(explicit: str | None) -> Path | None:
    if explicit:
        p = Path(explicit)
        return p if (p / CAN_MODULES[-1]).is_file() else None
    if not UML_MODULE_ROOT.is_dir():
        return None
    for version_dir in sorted(UML_MODULE_ROOT.iterdir(), reverse=True):
        if (version_dir / "kernel" / CAN_MODULES[-1]).is_file():
            return version_dir / "kernel"
    return None


def find_uml() -> UmlKernel:
    """Locate ``linux.uml`` and its CAN modules (``REDARM_UML_KERNEL`` / ``REDARM_UML_MODULES`` override).

    Raises:
        UmlUnavailableError: with the reason and the command that would fix it.
    """
    if sys.platform != "linux" or os.uname().machine != "x86_64":
        raise UmlUnavailableError("UML guest needs a Linux x86-64 host")
    binary = os.environ.get("REDARM_UML_KERNEL") or shutil.which("linux.uml")
    if not binary or not os.access(binary, os.X_OK):
        raise UmlUnavailableError(
            "linux.uml not found: install Debian's user-mode-linux (scripts/setup_uml.sh, needs root)"
        )
    modules = _find_modules(os.environ.get("REDARM_UML_MODULES"))
    if modules is None:
        raise UmlUnavailableError(
            f"no UML kernel modules with {CAN_MODULES[-1]} under {UML_MODULE_ROOT} "
            "(package user-mode-linux; or set REDARM_UML_MODULES)"
        )
    if not GUEST_INIT.is_file():
        raise UmlUnavailableError(f"{GUEST_INIT} is missing from this installation of redarm_ros")
    tool_path = "/usr/sbin:/usr/bin:/sbin:/bin"
    missing = [t for t in _GUEST_TOOLS if shutil.which(t, path=tool_path) is None]
    if missing:
        raise UmlUnavailableError(
            f"guest tools missing on the shared root: {', '.join(missing)} "
            "(insmod is in package kmod, ip in iproute2: scripts/setup_uml.sh)"
        )
    try:
        if Path("/proc/sys/kernel/yama/ptrace_scope").read_text().strip() == "3":
            raise UmlUnavailableError("ptrace is disabled (kernel.yama.ptrace_scope=3); UML needs it")
    except OSError:
        pass  # no Yama: ptrace is governed by permissions only
    probe = subprocess.run(
        [sys.executable, str(FPU_SCRIPT), "true"],
        capture_output=True,
        text=True,
        timeout=30,
        env={"PATH": "/usr/bin:/bin"},
        check=False,
    )
    if probe.returncode != 0:
        why = probe.stderr.strip() or f"exit {probe.returncode}"
        raise UmlUnavailableError(f"cannot run linux.uml under the FXSAVE-only seccomp filter: {why}")
    return UmlKernel(Path(binary), modules)


def uml_unavailable_reason() -> str | None:
    """None when :func:`run_guest` can work here, else a one-line reason."""
    try:
        find_uml()
    except UmlUnavailableError as exc:
        return exc.reason
    return None


def _check_cmdline_value(name: str, value: str) -> str:
    if not _CMDLINE_SAFE.match(value):
        raise InvalidInputError(
            f"{name} must be a plain path/word (it travels on the kernel command line): {value!r}",
            field=name,
            value=value,
        )
    return value


def _scratch_root() -> str | None:
    # UML's guest memory is a file under TMPDIR: on tmpfs, boots were steadier (8.5 s vs up to 21 s).
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def _umid_pids(umid: str) -> list[int]:
    """Live host processes carrying ``umid=<umid>`` on their command line (UML and its helpers)."""
    needle = f"umid={umid}".encode()
    pids = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/cmdline", "rb") as f:
                if needle in f.read().split(b"\0"):
                    with open(f"/proc/{entry.name}/stat", "rb") as st:
                        if st.read().rsplit(b")", 1)[-1].split()[0] not in (b"Z", b"X"):
                            pids.append(int(entry.name))
        except (OSError, ValueError, IndexError):
            continue
    return pids


def _kill_leftovers(umid: str, timeout_s: float = 5.0) -> int:
    """SIGKILL every process of guest ``umid`` still alive and wait until they are gone."""
    killed = 0
    deadline = time.monotonic() + timeout_s
    while (pids := _umid_pids(umid)) and time.monotonic() < deadline:
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
                killed += 1
            except OSError:
                pass
        time.sleep(0.05)
    return killed


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def _job_script(command: str | Sequence[str], env: Mapping[str, str], cwd: str | None) -> str:
    lines = ["#!/bin/sh", "# Written by test/support/uml/runner.py; runs inside the UML guest."]
    lines += [f"export {k}={shlex.quote(v)}" for k, v in env.items()]
    if cwd:
        lines.append(f"cd {shlex.quote(cwd)} || exit 125")
    body = command if isinstance(command, str) else shlex.join(command)
    lines.append(body)
    return "\n".join(lines) + "\n"


def run_guest(
    command: str | Sequence[str],
    out_dir: str | os.PathLike[str],
    *,
    env: Mapping[str, str] | None = None,
    cwd: str | None = None,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    mem: str = DEFAULT_MEM,
    can_name: str = "vcan0",
    fxsave_only: bool = True,
) -> GuestResult:
    """Boot a guest, create ``can_name`` (vcan), run ``command`` there, power off, collect results.

    Args:
        command: a shell command line (str) or an argv list, run by ``/bin/sh`` in the guest.
        out_dir: host directory for the job script and results; mounted read-write in the guest
            at the same path, so the job can write files there. Created if missing.
        env: extra environment for the job (the guest already sets HOME, TMPDIR, ROS_LOG_DIR
            on a tmpfs, and the no-AVX variables when ``fxsave_only``).
        cwd: working directory of the job inside the guest (default: ``out_dir``).
        timeout_s: outer wall-clock limit for the whole guest [s]; on expiry every process of
            the guest is killed and ``timed_out`` is set.
        mem: guest memory (kernel ``mem=`` syntax).
        can_name: vcan interface to create.
        fxsave_only: run UML under the seccomp filter of :mod:`support.uml.fpu` (needed on
            hosts with AVX-512/PKU/AMX, harmless elsewhere) and switch AVX off in the guest.

    Returns:
        A :class:`GuestResult`; check ``ok`` or ``job_rc``.

    Raises:
        UmlUnavailableError: no usable UML kernel on this host.
        InvalidInputError: ``out_dir`` or ``can_name`` unusable on a kernel command line.
    """
    kernel = find_uml()
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    _check_cmdline_value("out_dir", str(out))
    _check_cmdline_value("can_name", can_name)
    _check_cmdline_value("modules", str(kernel.modules))
    _check_cmdline_value("mem", mem)
    for stale in ("job.rc", "job.log", "init.log", "console.log"):
        (out / stale).unlink(missing_ok=True)
    (out / "job.sh").write_text(_job_script(command, env or {}, cwd))
    init = out / "init.sh"
    shutil.copyfile(GUEST_INIT, init)
    init.chmod(0o755)

    umid = f"redarm-{os.getpid()}-{secrets.token_hex(4)}"
    guest_env = {
        "REDARM_UML_OUT": str(out),
        "REDARM_UML_MODULES": str(kernel.modules),
        "REDARM_UML_CAN": can_name,
    }
    if fxsave_only:
        guest_env.update(GUEST_NO_AVX_ENV)
    scratch = tempfile.mkdtemp(prefix="redarm-uml-", dir=_scratch_root())
    args = [
        str(kernel.binary),
        f"mem={mem}",
        f"umid={umid}",
        f"uml_dir={scratch}",
        "root=/dev/root",
        "rootfstype=hostfs",
        "rootflags=/",
        "ro",
        "con=null",
        "con0=null,fd:1",
        f"init={init}",
        *(f"{k}={v}" for k, v in guest_env.items()),
    ]
    proc_env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "TMPDIR": scratch, "HOME": scratch}
    if fxsave_only:
        args = [sys.executable, str(FPU_SCRIPT), *args]  # stdlib only: runs as a plain script
    _LOG.info("booting UML guest %s (timeout %.0f s)", umid, timeout_s)
    console_path = out / "console.log"
    timed_out = False
    t0 = time.monotonic()
    try:
        with open(console_path, "wb") as console:
            # Own session: on timeout the whole group (UML and its helper processes) is killed.
            proc = subprocess.Popen(
                args,
                stdin=subprocess.DEVNULL,
                stdout=console,
                stderr=subprocess.STDOUT,
                env=proc_env,
                start_new_session=True,
            )
            try:
                rc: int | None = proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                timed_out = True
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                rc = proc.wait()
    finally:
        duration = time.monotonic() - t0
        # UML's helpers normally die with it; make sure, by the unique umid on their command line.
        if _kill_leftovers(umid):
            _LOG.warning("killed leftover UML processes of %s", umid)
        shutil.rmtree(scratch, ignore_errors=True)

    init_log = _read(out / "init.log")
    stages = re.findall(r"^stage=(\w+)", init_log, flags=re.M)
    rc_text = _read(out / "job.rc").strip()
    return GuestResult(
        job_rc=int(rc_text) if rc_text.lstrip("-").isdigit() else None,
        stage=stages[-1] if stages else "none",
        duration_s=duration,
        timed_out=timed_out,
        uml_returncode=rc,
        out_dir=out,
        console=_read(console_path),
        init_log=init_log,
        job_log=_read(out / "job.log"),
    )


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``python -m support.uml.runner --out DIR [--timeout S] -- CMD [ARGS...]``.

    Runs CMD in a fresh guest with ``vcan0`` up, prints its output, exits with its exit code
    (or 124 on timeout, 125 when the guest never reached the job).
    """
    parser = argparse.ArgumentParser(prog="python -m support.uml.runner", description=main.__doc__)
    parser.add_argument("--out", required=True, help="host directory for job script and results")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, help="outer limit [s]")
    parser.add_argument("--mem", default=DEFAULT_MEM)
    parser.add_argument("--can", default="vcan0", help="vcan interface name to create")
    parser.add_argument("--env", action="append", default=[], metavar="K=V", help="job environment")
    parser.add_argument("command", nargs=argparse.REMAINDER)
    ns = parser.parse_args(argv)
    command = ns.command[1:] if ns.command[:1] == ["--"] else ns.command
    if not command:
        parser.error("no command given")
    env = dict(item.split("=", 1) for item in ns.env)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        result = run_guest(command, ns.out, env=env, timeout_s=ns.timeout, mem=ns.mem, can_name=ns.can,
                           cwd=os.getcwd())
    except UmlUnavailableError as exc:
        sys.stderr.write(f"UML unavailable: {exc.reason}\n")
        return 125
    sys.stdout.write(result.job_log)
    _LOG.info("guest finished: stage=%s job_rc=%s in %.1f s", result.stage, result.job_rc, result.duration_s)
    if result.timed_out:
        return 124
    return result.job_rc if result.job_rc is not None else 125


if __name__ == "__main__":
    sys.exit(main())
