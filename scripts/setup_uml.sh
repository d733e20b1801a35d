#!/usr/bin/env bash
# Idempotent install of what the UML SocketCAN test needs: Debian's user-mode-linux
# (kernel binary linux.uml plus CAN/vcan modules) and kmod (insmod for the guest init).
# Never fails the caller: when it cannot install (not root, no apt), it says so and the
# test skips itself with a reason.
set -u
# shellcheck source=scripts/apt_lib.sh
. "$(dirname "${BASH_SOURCE[0]}")/apt_lib.sh"

have_all() {
    command -v linux.uml >/dev/null 2>&1 && command -v insmod >/dev/null 2>&1 \
        && ls /usr/lib/uml/modules/*/kernel/drivers/net/can/vcan.ko >/dev/null 2>&1
}

if have_all; then
    echo "setup_uml: user-mode-linux and kmod already installed"
    exit 0
fi
apt_can_install setup_uml user-mode-linux/kmod "user-mode-linux and kmod" "the UML test will skip" || exit 0
if apt_install setup_uml user-mode-linux kmod; then
    echo "setup_uml: installed user-mode-linux and kmod"
else
    echo "setup_uml: apt-get install user-mode-linux kmod failed (the UML test will skip)" >&2
fi
exit 0
