#!/usr/bin/env bash
# Idempotent install of what the UML SocketCAN test needs: Debian's user-mode-linux
# (kernel binary linux.uml plus CAN/vcan modules) and kmod (insmod for the guest init).
# Never fails the caller: when it cannot install (not root, no apt), it says so and the
# test skips itself with a reason.
set -u

have_all() {
    command -v linux.uml >/dev/null 2>&1 && command -v insmod >/dev/null 2>&1 \
        && ls /usr/lib/uml/modules/*/kernel/drivers/net/can/vcan.ko >/dev/null 2>&1
}

if have_all; then
    echo "setup_uml: user-mode-linux and kmod already installed"
    exit 0
fi
if [ "$(id -u)" != 0 ]; then
    echo "setup_uml: not root; cannot install user-mode-linux/kmod (the UML test will skip)" >&2
    exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "setup_uml: no apt-get; install user-mode-linux and kmod by hand (the UML test will skip)" >&2
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
# Update the package lists only when the packages are not known yet (keeps re-runs offline).
if ! apt-cache show user-mode-linux >/dev/null 2>&1 || ! apt-cache show kmod >/dev/null 2>&1; then
    apt-get update -qq || echo "setup_uml: apt-get update failed" >&2
fi
if apt-get install -y -qq --no-install-recommends user-mode-linux kmod >/dev/null; then
    echo "setup_uml: installed user-mode-linux and kmod"
else
    echo "setup_uml: apt-get install user-mode-linux kmod failed (the UML test will skip)" >&2
fi
exit 0
