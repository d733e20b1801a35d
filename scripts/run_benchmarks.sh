#!/usr/bin/env bash
# Run every benchmarks/*.py (used by `make bench`). By default a smoke run: each benchmark gets
# --quick and --no-write when its --help lists them (so the committed results tables stay those of
# full runs); one without --quick is skipped with a note, as its full run can take many minutes.
# BENCH_FULL=1 runs them all in full and lets them write benchmarks/results/*.md.
# Extra arguments are passed to every benchmark. Exit code: 1 if any benchmark failed.
set -uo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
PY="$REPO/.venv/bin/python"
cd "$REPO"
rc=0
for bench in benchmarks/*.py; do
    [ -e "$bench" ] || continue
    flags=()
    if [ "${BENCH_FULL:-0}" != 1 ]; then
        help="$("$PY" "$bench" --help 2>/dev/null || true)"
        for flag in --quick --no-write; do
            grep -q -- "$flag" <<<"$help" && flags+=("$flag")
        done
        if [ "${flags[0]:-}" != --quick ]; then
            echo "+ $bench: skipped (no --quick option; run it with BENCH_FULL=1)"
            continue
        fi
    fi
    echo "+ $bench ${flags[*]} $*"
    if ! "$PY" "$bench" "${flags[@]}" "$@"; then
        echo "run_benchmarks: $bench failed" >&2
        rc=1
    fi
done
exit "$rc"
