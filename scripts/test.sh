#!/usr/bin/env bash
# README test command: install into ./.venv, lint (ruff, the rules in pyproject.toml), then
# run the test suite on Taichi's CPU backend in f64. Exits non-zero on any failure, including
# a lint error and "no tests collected" (pytest 5).
#
#   bash scripts/test.sh            the default tier: every test not marked slow
#   bash scripts/test.sh --slow     the slow tier only (notebook executions, long studies)
#   bash scripts/test.sh --all      both tiers in one go
#
# A tier runs as two pytest sessions: first its tests on one pytest-xdist worker per core
# (each worker pinned to its own core; tests/conftest.py), then the tests marked
# ``multicore`` in one process that has every core. CALENDARING_TEST_WORKERS=1 runs
# everything in one process. Other arguments go to both sessions. CI (.ci/run) runs the
# default tier, then the slow tier.
set -uo pipefail
cd "$(dirname "$0")/.."
tier="default"
args=()
for a in "$@"; do
    case "$a" in
        --slow) tier="slow" ;;
        --all) tier="all" ;;
        *) args+=("$a") ;;
    esac
done
bash scripts/setup.sh || exit 1
. .venv/bin/activate
export CALENDARING_TEST_ARCH=${CALENDARING_TEST_ARCH:-cpu}
if [ "$tier" != "slow" ]; then
    echo "lint: ruff check ." >&2
    ruff check . || { echo "lint failed: fix the findings above (ruff check . --fix)" >&2; exit 1; }
fi
case "$tier" in
    default) select="not slow" ;;
    slow) select="slow" ;;
    all) select="" ;;
esac
workers=${CALENDARING_TEST_WORKERS:-$(python -c "from calendaring.core.config import available_cores; print(available_cores())" | tail -n 1)}
start=$(date +%s)
if [ "$workers" -le 1 ]; then
    python -m pytest tests ${select:+-m "$select"} "${args[@]}"
    rc=$?
    [ "$rc" -eq 5 ] && { echo "pytest collected no tests: failing on purpose" >&2; exit 1; }
else
    # loadfile: a module's tests (and its module fixtures) stay on one worker
    python -m pytest tests -m "${select:+$select and }not multicore" -n "$workers" \
        --dist loadfile "${args[@]}"
    rc_parallel=$?
    python -m pytest tests -m "${select:+$select and }multicore" "${args[@]}"
    rc_multicore=$?
    if [ "$rc_parallel" -eq 5 ] && [ "$rc_multicore" -eq 5 ]; then
        echo "pytest collected no tests: failing on purpose" >&2
        exit 1
    fi
    rc=0
    for r in "$rc_parallel" "$rc_multicore"; do
        [ "$r" -ne 0 ] && [ "$r" -ne 5 ] && rc=$r
    done
fi
echo "pytest ($tier tier) took $(( $(date +%s) - start )) s" >&2
exit "$rc"
