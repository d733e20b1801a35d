"""Run ``linux.uml`` with FXSAVE-only FPU context switching, on hosts whose XSAVE area it cannot handle.

Why: Debian bookworm's UML kernel (6.1) saves and restores a guest process's
FPU state with ``PTRACE_GETREGSET/SETREGSET NT_X86_XSTATE`` and a fixed 832-byte
buffer (x87/SSE + header + AVX). Hosts whose XSAVE area is larger (AVX-512,
PKU, AMX: 2.5-11 kB) refuse the SETREGSET with ``EFAULT`` because the host
kernel wants exactly its full size, and the guest's first process dies
(``userspace - ptrace set fp regs failed, errno = 14``, then "Attempted to
kill init"). Newer UML kernels size the buffer at run time; this one does not.

The way out without patching the kernel: UML probes ``GETREGSET NT_X86_XSTATE``
once at boot and falls back to ``PTRACE_GETFPREGS/SETFPREGS`` (the 512-byte
FXSAVE image) when the probe fails. A seccomp filter installed before exec
makes exactly that ptrace request (and its SET twin) fail with ``EIO``; every
other system call passes untouched.

The price: FXSAVE carries x87 and SSE only, and a host signal (every guest page
fault is one) resets the extended AVX state of the guest process, so AVX code
in the guest sees its upper vector halves zeroed (measured: glibc's AVX2/EVEX
``strchrnul`` made ``printf`` print ``%s`` literally). :data:`GUEST_NO_AVX_ENV`
therefore switches AVX off in the guest's user space: glibc's string and
memory functions (including the ``AVX_Fast_Unaligned_Load`` memcpy choice, which
survives ``-AVX2``), NumPy's dispatch, OpenBLAS kernels and OpenSSL. Without
this, CPython dies during start-up in the guest ("error evaluating path").
The guest kernel itself uses no AVX.

Run as ``python test/support/uml/fpu.py linux.uml <args>``: installs the filter
and execs the rest of the command line. Linux x86-64 only.
"""

from __future__ import annotations

import ctypes
import os
import struct
import sys

__all__ = ["GUEST_NO_AVX_ENV", "install_fxsave_only_filter"]

# Environment for every guest process when FPU state is switched FXSAVE-only (see module doc).
GUEST_NO_AVX_ENV: dict[str, str] = {
    "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX,-AVX2,-AVX512F,-AVX512VL,-AVX512BW,-AVX512DQ,-AVX512CD,"
    "-AVX512ER,-AVX512PF,-FMA,-FMA4,-F16C,-AVX_VNNI,-AVX512_VNNI,-AVX512_BF16,-AVX512_FP16,"
    "-AVX_Fast_Unaligned_Load",
    "NPY_DISABLE_CPU_FEATURES": "X86_V3,X86_V4,AVX512_ICL,AVX512_SPR",
    "OPENBLAS_CORETYPE": "NEHALEM",
    # OpenSSL (hashlib, ssl): clear AVX and FMA in CPUID leaf 1 and every leaf-7 feature.
    "OPENSSL_ia32cap": "~0x1000100000000000:~0xffffffffffffffff",
}

# Constants from <linux/audit.h>, <linux/filter.h>, <linux/seccomp.h>, <linux/ptrace.h>, <linux/elf.h>.
_AUDIT_ARCH_X86_64 = 0xC000003E
_NR_PTRACE_X86_64 = 101
_PTRACE_GETREGSET = 0x4204
_PTRACE_SETREGSET = 0x4205
_NT_X86_XSTATE = 0x202
_EIO = 5
_BPF_LD_W_ABS = 0x20
_BPF_JEQ_K = 0x15
_BPF_RET_K = 0x06
_SECCOMP_RET_ALLOW = 0x7FFF0000
_SECCOMP_RET_ERRNO = 0x00050000
_PR_SET_NO_NEW_PRIVS = 38
_PR_SET_SECCOMP = 22
_SECCOMP_MODE_FILTER = 2
# struct seccomp_data: int nr; u32 arch; u64 ip; u64 args[6]. Low words of args (little-endian).
_OFF_NR, _OFF_ARCH, _OFF_ARG0, _OFF_ARG1 = 0, 4, 16, 24


def _stmt(code: int, k: int) -> bytes:
    return struct.pack("HBBI", code, 0, 0, k)


def _jump(code: int, k: int, jt: int, jf: int) -> bytes:
    return struct.pack("HBBI", code, jt, jf, k)


def _filter_program() -> list[bytes]:
    """BPF: ptrace(GETREGSET|SETREGSET, pid, NT_X86_XSTATE, ...) -> EIO; everything else allowed.

    ptrace's arguments are (request, pid, addr, data): the regset type travels in ``addr`` (arg 2).
    """
    allow = _stmt(_BPF_RET_K, _SECCOMP_RET_ALLOW)
    deny = _stmt(_BPF_RET_K, _SECCOMP_RET_ERRNO | _EIO)
    off_arg2 = _OFF_ARG1 + 8
    return [
        _stmt(_BPF_LD_W_ABS, _OFF_ARCH),
        _jump(_BPF_JEQ_K, _AUDIT_ARCH_X86_64, 0, 7),  # other ABI: allow
        _stmt(_BPF_LD_W_ABS, _OFF_NR),
        _jump(_BPF_JEQ_K, _NR_PTRACE_X86_64, 0, 5),  # not ptrace: allow
        _stmt(_BPF_LD_W_ABS, _OFF_ARG0),
        _jump(_BPF_JEQ_K, _PTRACE_GETREGSET, 1, 0),
        _jump(_BPF_JEQ_K, _PTRACE_SETREGSET, 0, 2),  # other request: allow
        _stmt(_BPF_LD_W_ABS, off_arg2),
        _jump(_BPF_JEQ_K, _NT_X86_XSTATE, 1, 0),
        allow,
        deny,
    ]


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]


def install_fxsave_only_filter() -> None:
    """Install the seccomp filter on the calling process (inherited across fork and exec).

    Raises:
        OSError: the kernel refused ``prctl`` (no seccomp, or not x86-64).
    """
    if os.uname().machine != "x86_64":
        raise OSError(0, "the FXSAVE-only filter is for x86-64 hosts")
    libc = ctypes.CDLL(None, use_errno=True)
    prog = _filter_program()
    buf = ctypes.create_string_buffer(b"".join(prog))
    fprog = _SockFprog(len(prog), ctypes.cast(buf, ctypes.c_void_p))
    # no_new_privs lets an unprivileged user install a filter; linux.uml is not setuid.
    if libc.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"prctl(PR_SET_NO_NEW_PRIVS): {os.strerror(err)}")
    if libc.prctl(_PR_SET_SECCOMP, _SECCOMP_MODE_FILTER, ctypes.byref(fprog), 0, 0) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"prctl(PR_SET_SECCOMP): {os.strerror(err)}")


def main(argv: list[str] | None = None) -> int:
    """``python test/support/uml/fpu.py CMD ARGS...``: install the filter, then exec CMD."""
    args = sys.argv[1:] if argv is None else argv
    if not args:
        sys.stderr.write("usage: python test/support/uml/fpu.py CMD [ARGS...]\n")
        return 2
    try:
        install_fxsave_only_filter()
    except OSError as exc:
        sys.stderr.write(f"uml/fpu.py: cannot install the seccomp filter: {exc}\n")
        return 3
    os.execvp(args[0], args)
    return 127  # not reached


if __name__ == "__main__":
    sys.exit(main())
