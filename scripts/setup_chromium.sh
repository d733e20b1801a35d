#!/usr/bin/env bash
# Idempotent install of what the browser test of `redarm-view` needs: Debian's headless-capable
# Chromium (/usr/bin/chromium) and the fonts its pages use. Never a browser download: the Debian
# package only. Never fails the caller: when it cannot install (not root, no apt), it says so and
# test/test_view_browser.py skips itself with that reason.
set -u
# shellcheck source=scripts/apt_lib.sh
. "$(dirname "${BASH_SOURCE[0]}")/apt_lib.sh"

have_all() {
    command -v chromium >/dev/null 2>&1 && chromium --version >/dev/null 2>&1
}

if have_all; then
    echo "setup_chromium: $(chromium --version 2>/dev/null) already installed"
    exit 0
fi
if [ "${REDARM_SKIP_APT:-0}" = 1 ]; then
    echo "setup_chromium: REDARM_SKIP_APT=1; not installing chromium (the browser test will skip)" >&2
    exit 0
fi
apt_can_install setup_chromium chromium "Debian's chromium" "the browser test will skip" || exit 0
# fonts-liberation: the page's status panel text renders in a real font in the screenshots.
if apt_install setup_chromium chromium fonts-liberation; then
    echo "setup_chromium: installed $(chromium --version 2>/dev/null)"
else
    echo "setup_chromium: apt-get install chromium failed (the browser test will skip)" >&2
fi
exit 0
