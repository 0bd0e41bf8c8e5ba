#!/usr/bin/env bash
# README test command: install into ./.venv, then run the whole test suite on Taichi's CPU
# backend in f64. Exits non-zero on any failure, including "no tests collected" (pytest 5).
set -uo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh || exit 1
. .venv/bin/activate
export CALENDARING_TEST_ARCH=${CALENDARING_TEST_ARCH:-cpu}
python -m pytest tests "$@"
rc=$?
if [ "$rc" -eq 5 ]; then
    echo "pytest collected no tests: failing on purpose" >&2
    exit 1
fi
exit "$rc"
