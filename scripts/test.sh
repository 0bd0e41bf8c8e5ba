#!/usr/bin/env bash
# README test command: install into ./.venv, lint (ruff, the rules in pyproject.toml), then
# run the test suite on Taichi's CPU backend in f64. Exits non-zero on any failure, including
# a lint error and "no tests collected" (pytest 5).
#
#   bash scripts/test.sh            the default tier: every test not marked slow
#   bash scripts/test.sh --slow     the slow tier only (notebook executions, long studies)
#   bash scripts/test.sh --all      both tiers in one pytest run
#
# Other arguments go to pytest. CI (.ci/run) runs the default tier, then the slow tier.
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
    default) marks=(-m "not slow") ;;
    slow) marks=(-m "slow") ;;
    all) marks=() ;;
esac
start=$(date +%s)
python -m pytest tests "${marks[@]}" "${args[@]}"
rc=$?
echo "pytest ($tier tier) took $(( $(date +%s) - start )) s" >&2
if [ "$rc" -eq 5 ]; then
    echo "pytest collected no tests: failing on purpose" >&2
    exit 1
fi
exit "$rc"
