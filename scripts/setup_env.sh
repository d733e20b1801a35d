#!/usr/bin/env bash
# One-stop, idempotent set-up of the development environment (called by every `make` target).
#
#  1. apt: the few system tools the build and the tests need (cmake, g++, make, ip, unshare,
#     Python headers), installed only when missing (`apt-get update` once, first).
#  2. .venv at the repo root with the pinned requirements.txt + requirements-build.txt.
#  3. The ROS wheels' exported CMake files hard-code the wheel builder's interpreter
#     (/opt/python/cp311-cp311/...); rewrite them to this interpreter's include dirs.
#  4. `pip install -e .`: redarm_ros importable from .venv/bin/python, console scripts in .venv/bin.
#  5. colcon build of interfaces/redarm_interfaces, installed (merged) into the .venv prefix:
#     Python modules land in site-packages and the typesupport libraries in .venv/lib, the
#     directory the ros wheels' bootstrapper (ros_wheels_bootstrapper.pth) already puts on
#     LD_LIBRARY_PATH, so any `.venv/bin/python` process can use the interfaces with rclpy.
#
# Each step is keyed on a hash of its inputs (stamp files in .venv/.redarm-stamps), so a second
# run with nothing changed takes well under a second. None of this is needed on an apt ROS 2
# Jazzy install; see docs/setup.md.
#
# Environment: PYTHON (interpreter to build the venv from; default python3.11, else python3 if it
# is 3.11), REDARM_SETUP_VERBOSE=1 (show pip/colcon output), REDARM_SKIP_APT=1.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
VENV="$REPO/.venv"
STAMPS="$VENV/.redarm-stamps"
BUILD="$REPO/.build"
VERBOSE="${REDARM_SETUP_VERBOSE:-0}"

log() { echo "setup_env: $*" >&2; }
die() { log "ERROR: $*"; exit 1; }

# Run a noisy command; keep its output in a log file and show the tail only on failure.
quiet() {
    local logfile="$1"; shift
    mkdir -p "$(dirname "$logfile")"
    if [ "$VERBOSE" = 1 ]; then
        "$@" 2>&1 | tee "$logfile"
        return "${PIPESTATUS[0]}"
    fi
    if ! "$@" >"$logfile" 2>&1; then
        # pip's warnings about the machine's optional local indexes are noise; drop them.
        grep -v "is ignored: it is neither a file nor a directory" "$logfile" | tail -n 60 >&2
        log "command failed: $* (full log: $logfile)"
        return 1
    fi
}

hash_files() { # sha256 over the given files' names and contents (missing files hash as absent)
    local f
    for f in "$@"; do
        echo "== $f"
        if [ -f "$f" ]; then cat "$f"; else echo "(absent)"; fi
    done | sha256sum | cut -d' ' -f1
}

stamp_ok() { [ -f "$STAMPS/$1" ] && [ "$(cat "$STAMPS/$1")" = "$2" ]; }
stamp_set() { mkdir -p "$STAMPS"; echo "$2" >"$STAMPS/$1"; }

# --- the set-up cache outside the clone (docs/setup.md): the pinned wheels and the built interfaces,
# each under a hash of every input of the step; a key that differs builds afresh. REDARM_SETUP_CACHE=0:
# no cache. The newest CACHE_KEEP entries of each kind stay.
CACHE="${REDARM_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/redarm_ros}"
CACHE_KEEP=3
cache_on() { [ "${REDARM_SETUP_CACHE:-1}" != 0 ]; }
cache_prune() { # cache_prune KIND: drop all but the CACHE_KEEP newest entries of $CACHE/KIND
    local old
    mapfile -t old < <(ls -1dt "$CACHE/$1"/* 2>/dev/null | tail -n +$((CACHE_KEEP + 1)))
    [ "${#old[@]}" -eq 0 ] || rm -rf "${old[@]}"
}

# --- serialise concurrent runs (two `make` targets at once must not race pip or colcon) ---------
mkdir -p "$BUILD"
exec 9>"$BUILD/setup.lock"
flock 9

# --- 1. system packages -------------------------------------------------------------------------
pick_python() {
    local cand
    for cand in "${PYTHON:-}" python3.11 python3; do
        [ -n "$cand" ] || continue
        if command -v "$cand" >/dev/null 2>&1 \
            && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
            command -v "$cand"
            return 0
        fi
    done
    return 1
}

APT_UPDATED=0
apt_install() { # apt_install PKG... : install only what is missing, `apt-get update` once first
    [ "${REDARM_SKIP_APT:-0}" = 1 ] && die "missing system packages ($*) and REDARM_SKIP_APT=1"
    command -v apt-get >/dev/null 2>&1 || die "missing system packages ($*) and no apt-get: install them by hand"
    local sudo=()
    if [ "$(id -u)" != 0 ]; then
        command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null \
            || die "missing system packages ($*): run 'sudo apt-get install $*' and retry"
        sudo=(sudo -n)
    fi
    export DEBIAN_FRONTEND=noninteractive
    if [ "$APT_UPDATED" = 0 ]; then
        log "apt-get update"
        quiet "$BUILD/logs/apt-update.log" "${sudo[@]}" apt-get update -q
        APT_UPDATED=1
    fi
    log "apt-get install $*"
    quiet "$BUILD/logs/apt-install.log" "${sudo[@]}" apt-get install -y -q --no-install-recommends "$@"
}

missing=()
command -v cmake >/dev/null 2>&1 || missing+=(cmake)
command -v g++ >/dev/null 2>&1 || missing+=(g++)
command -v gcc >/dev/null 2>&1 || missing+=(gcc)
command -v make >/dev/null 2>&1 || missing+=(make)
command -v ip >/dev/null 2>&1 || missing+=(iproute2)
command -v unshare >/dev/null 2>&1 || missing+=(util-linux)
command -v git >/dev/null 2>&1 || missing+=(git)
PY="$(pick_python || true)"
if [ -z "$PY" ]; then
    missing+=(python3.11 python3.11-venv python3.11-dev)
fi
[ "${#missing[@]}" -eq 0 ] || apt_install "${missing[@]}"
PY="${PY:-$(pick_python)}" || die "no Python 3.11 found (the ROS 2 Jazzy wheels are cp311); set PYTHON=/path/to/python3.11"

# --- 2. the venv ----------------------------------------------------------------------------------
venv_ok() { "$VENV/bin/python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; }
# A venv hard-codes its own path (script shebangs): rebuild it if the repo moved or it is broken.
if [ -e "$VENV" ] && { ! venv_ok || { [ -f "$STAMPS/venv" ] && [ "$(cat "$STAMPS/venv")" != "$REPO" ]; }; }; then
    log "the venv is broken or was made for another path; recreating it"
    rm -rf "$VENV"
fi
if [ ! -x "$VENV/bin/python" ]; then
    log "creating $VENV with $PY"
    if ! "$PY" -m venv "$VENV" 2>"$BUILD/venv.err"; then
        cat "$BUILD/venv.err" >&2
        case "$PY" in
            /usr/bin/*) apt_install python3.11-venv; rm -rf "$VENV"; "$PY" -m venv "$VENV" ;;
            *) die "could not create the venv with $PY" ;;
        esac
    fi
fi
stamp_set venv "$REPO"

# Headers for the rosidl Python extensions: a Debian python needs python3.11-dev, pyenv has them.
PY_INC="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
if [ ! -f "$PY_INC/Python.h" ]; then
    case "$PY_INC" in
        /usr/include/*) apt_install python3.11-dev ;;
        *) die "Python.h not found in $PY_INC (install the development headers of $PY)" ;;
    esac
fi

DEPS_KEY="$(hash_files "$REPO/requirements.txt" "$REPO/requirements-build.txt")"
if ! stamp_ok deps "$DEPS_KEY"; then
    log "installing requirements.txt + requirements-build.txt into .venv (pip)"
    # pip byte-compiles file after file (half of this step); compileall does the venv on every core,
    # in the background while steps 3-5 run (the colcon build leaves a core idle much of the time).
    pip_reqs=(-r "$REPO/requirements.txt" -r "$REPO/requirements-build.txt")
    if cache_on; then
        # Most of a plain install is resolving against the indexes (their pages list thousands of
        # files). The wheels it picks are kept in a wheelhouse keyed on the requirements and on pip's
        # interpreter, version and configuration (constraint files included); with the wheelhouse the
        # install resolves offline, and still fails if it lacks anything rather than taking less.
        WH_KEY="$(
            cd "$REPO" && hash_files requirements.txt requirements-build.txt
            "$VENV/bin/python" -c 'import sys, sysconfig; print(sys.version, sysconfig.get_platform())'
            "$VENV/bin/python" -c 'import pip; print("pip", pip.__version__)'
            pip_config="$("$VENV/bin/python" -m pip config list 2>/dev/null | LC_ALL=C sort)"
            echo "$pip_config"
            env | grep '^PIP_' | LC_ALL=C sort
            for f in $(echo "$pip_config" | sed -n "s/.*constraint='\(.*\)'/\1/p") ${PIP_CONSTRAINT:-}; do
                hash_files "$f"
            done
        )"
        WH="$CACHE/wheels/$(echo "$WH_KEY" | sha256sum | cut -c1-32)"
        if [ ! -f "$WH/.complete" ]; then
            log "collecting the pinned wheels into $WH (pip wheel)"
            mkdir -p "$CACHE/wheels"
            wh_tmp="$(mktemp -d "$CACHE/wheels/.tmp.XXXXXX")"
            trap 'rm -rf "$wh_tmp"' EXIT
            quiet "$BUILD/logs/pip-wheel.log" "$VENV/bin/python" -m pip wheel --progress-bar off \
                -w "$wh_tmp" "${pip_reqs[@]}"
            touch "$wh_tmp/.complete"
            # Another clone may have finished the same key meanwhile: keep the first.
            mv -T "$wh_tmp" "$WH" 2>/dev/null || rm -rf "$wh_tmp"
            trap - EXIT
            cache_prune wheels
        fi
        touch "$WH"
        quiet "$BUILD/logs/pip-install.log" "$VENV/bin/python" -m pip install --progress-bar off --no-compile \
            --no-index --find-links "$WH" "${pip_reqs[@]}"
    else
        quiet "$BUILD/logs/pip-install.log" "$VENV/bin/python" -m pip install --progress-bar off --no-compile \
            "${pip_reqs[@]}"
    fi
    rm -f "$STAMPS/editable" "$STAMPS/interfaces" "$STAMPS/compiled"
    stamp_set deps "$DEPS_KEY"
fi
if ! stamp_ok compiled "$DEPS_KEY"; then
    # Failures are ignored, as pip ignores them (some wheels ship files that are not Python 3.11).
    # Left out: the wheels' own test suites and pybullet's gym examples (a quarter of the source), which
    # nothing imports; anything imported there is compiled on first import.
    ( "$VENV/bin/python" -m compileall -q -j 0 -x '/(tests|pybullet_envs)/' "$VENV/lib" \
        >"$BUILD/logs/compileall.log" 2>&1 || true
      stamp_set compiled "$DEPS_KEY" ) &
    COMPILE_PID=$!
fi

# --- 3. patch the wheels' CMake exports -----------------------------------------------------------
# Cheap enough to check every time (grep over share/*/cmake); also repairs files a later pip
# install of another ros-jazzy-* wheel brings in.
mapfile -t cmake_files < <(grep -rl --include='*.cmake' '/opt/python/cp311-cp311' "$VENV/share" 2>/dev/null || true)
if [ "${#cmake_files[@]}" -gt 0 ]; then
    NP_INC="$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')"
    log "patching ${#cmake_files[@]} exported CMake files to use $PY_INC and $NP_INC"
    sed -i \
        -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$NP_INC#g" \
        -e "s#/opt/python/cp311-cp311/include/python3.11#$PY_INC#g" \
        "${cmake_files[@]}"
    rm -f "$STAMPS/interfaces"
fi

# --- 4. redarm_ros itself (editable) -------------------------------------------------------------
# setup.cfg sends scripts to lib/redarm_ros for ament builds; pip's editable wheel ignores that and
# puts the console scripts in .venv/bin, which is what venv users want.
EDITABLE_KEY="$(hash_files "$REPO/setup.py" "$REPO/setup.cfg")"
if ! stamp_ok editable "$EDITABLE_KEY" || [ ! -x "$VENV/bin/redarm-sim" ]; then
    log "pip install -e . (redarm_ros + console scripts into .venv/bin)"
    quiet "$BUILD/logs/pip-editable.log" "$VENV/bin/python" -m pip install --progress-bar off \
        --no-build-isolation --no-deps -e "$REPO"
    stamp_set editable "$EDITABLE_KEY"
fi

# --- 5. interfaces package, colcon-built into the venv prefix ---------------------------------
# colcon installs into a staging prefix (.build/colcon/install), which is then copied into the venv
# with its path and the building venv's rewritten to this venv's in the few text files that name
# them (setup scripts, one CMake export; no binary does). The staged tree is also what the cache keeps: its key adds to the
# interface files everything the build reads (every installed distribution, the interpreter, the
# compilers, this script), and a hit is deployed exactly as a build is.
IFACE_DIR="$REPO/interfaces/redarm_interfaces"
mapfile -t iface_files < <(cd "$REPO" && find interfaces -type f -not -name '*.pyc' | LC_ALL=C sort)
IFACE_KEY="$(
    cd "$REPO"
    hash_files "${iface_files[@]}" requirements.txt requirements-build.txt scripts/setup_env.sh
    ls "$VENV/lib/python3.11/site-packages" | grep -E '\.(dist|egg)-info$' | grep -v '^redarm_' | LC_ALL=C sort
    "$VENV/bin/python" -c 'import sys, sysconfig; print(sys.version, sysconfig.get_platform())'
    echo "$PY_INC"
    cmake --version | head -n 1; gcc --version | head -n 1; g++ --version | head -n 1
    uname -m
)"
IFACE_KEY="$(echo "$IFACE_KEY" | sha256sum | cut -c1-32)"
if [ -f "$IFACE_DIR/package.xml" ] && { ! stamp_ok interfaces "$IFACE_KEY" \
        || [ ! -d "$VENV/lib/python3.11/site-packages/redarm_interfaces" ]; }; then
    COLCON_DIR="$BUILD/colcon"
    STAGE="$COLCON_DIR/install"
    IFACE_CACHED="$CACHE/interfaces/$IFACE_KEY.tar"
    rm -rf "$STAGE"
    mkdir -p "$COLCON_DIR"
    if cache_on && [ -f "$IFACE_CACHED" ]; then
        log "interfaces/redarm_interfaces from the cache ($IFACE_CACHED)"
        mkdir -p "$STAGE"
        tar -xf "$IFACE_CACHED" -C "$STAGE"
        touch "$IFACE_CACHED"
    else
        log "colcon build interfaces/redarm_interfaces -> .venv (about 15 s)"
        rm -rf "$COLCON_DIR/build/redarm_interfaces"
        (
            cd "$COLCON_DIR"
            export CMAKE_PREFIX_PATH="$VENV" AMENT_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH"
            export PYTHONNOUSERSITE=1 COLCON_HOME="$COLCON_DIR/home"
            # Without -j in MAKEFLAGS colcon runs make with -l<cores> too: no second job while the load
            # average is above the core count, which on a machine with anything else running (or still
            # counting the pip step) makes the whole compile serial.
            export MAKEFLAGS="-j$(nproc)"
            quiet "$BUILD/logs/colcon-interfaces.log" "$VENV/bin/colcon" --log-base "$COLCON_DIR/log" build \
                --merge-install --install-base "$STAGE" --build-base "$COLCON_DIR/build" \
                --base-paths "$REPO/interfaces" --packages-select redarm_interfaces \
                --event-handlers console_direct- \
                --cmake-args -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
                "-DPython3_EXECUTABLE=$VENV/bin/python3"
        )
        # Bytecode names its source's path; the venv's own compile writes it afresh.
        find "$STAGE" -name __pycache__ -type d -prune -exec rm -rf {} +
        # The paths the build wrote into text files: its install base and the venv it built against.
        printf '%s\n' "$STAGE" "$VENV" >"$STAGE/.redarm-prefixes"
        if cache_on; then
            mkdir -p "$CACHE/interfaces"
            if_tmp="$(mktemp "$CACHE/interfaces/.tmp.XXXXXX")"
            trap 'rm -f "$if_tmp"' EXIT
            tar -cf "$if_tmp" -C "$STAGE" .
            mv -f "$if_tmp" "$IFACE_CACHED"
            trap - EXIT
            cache_prune interfaces
        fi
    fi
    # colcon marks its install base with COLCON_IGNORE; in the venv that also keeps any colcon
    # crawl of the repo out of the wheels' share/*/package.xml files.
    mapfile -t built_paths <"$STAGE/.redarm-prefixes"
    rm -f "$STAGE/.redarm-prefixes"
    for built in "${built_paths[@]}"; do
        mapfile -t named < <(grep -rlIF -- "$built" "$STAGE" || true)
        [ "${#named[@]}" -eq 0 ] || sed -i "s#$built#$VENV#g" "${named[@]}"
    done
    cp -a "$STAGE/." "$VENV/"
    # The proof that matters: a plain venv interpreter (new process, bootstrapped LD_LIBRARY_PATH)
    # imports the generated types with their C typesupport.
    quiet "$BUILD/logs/interfaces-import.log" env -u _ROS_WHEELS_BOOTSTRAP_COMPLETE "$VENV/bin/python" -c \
        'from redarm_interfaces.srv import SolveIK; from redarm_interfaces.msg import ControllerState; SolveIK.Request(); ControllerState()'
    stamp_set interfaces "$IFACE_KEY"
fi

if [ -n "${COMPILE_PID:-}" ]; then
    wait "$COMPILE_PID"
fi
log "environment ready ($VENV)"
