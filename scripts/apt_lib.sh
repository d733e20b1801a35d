# Sourced by the setup_*.sh installers: the checks before an apt-get install, and the install.
# Debian packages only, by name; never a download from anywhere else.

# apt_can_install TAG NAME HAND_NAME SKIP_NOTE: status 0 when this process can run apt-get as root
# (and sets DEBIAN_FRONTEND); otherwise says why on stderr and returns 1 (the caller exits 0).
apt_can_install() {
    local tag=$1 name=$2 hand_name=$3 note=$4
    if [ "$(id -u)" != 0 ]; then
        echo "$tag: not root; cannot install $name ($note)" >&2
        return 1
    fi
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "$tag: no apt-get; install $hand_name by hand ($note)" >&2
        return 1
    fi
    export DEBIAN_FRONTEND=noninteractive
}

# apt_install TAG PACKAGE...: update the package lists only when a package is not known yet (keeps
# re-runs offline), then install the packages quietly without recommends; apt-get's status.
apt_install() {
    local tag=$1 pkg
    shift
    for pkg in "$@"; do
        if ! apt-cache show "$pkg" >/dev/null 2>&1; then
            apt-get update -qq || echo "$tag: apt-get update failed" >&2
            break
        fi
    done
    apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}
