#!/usr/bin/env bash
# Create ./.venv (if missing) and install the project with what the tests and the main job
# need. Safe to re-run. A fresh machine needs only Python >= 3.11, pip and a C compiler.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
. .venv/bin/activate
python -m pip install --quiet --upgrade pip
python -m pip install --quiet -e ".[dev,all]"
