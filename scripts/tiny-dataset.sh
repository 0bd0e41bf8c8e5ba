#!/usr/bin/env bash
# The tiny-preset dataset (data/tiny.h5) that the refinement notebook and the slow tests
# start from: 10 LHS training runs (seed 0) and 2 held-out LHS runs at another bed
# (seed 1, synthetic twins), then the dataset file. The tiny preset is a test
# configuration (25 um cell, 6.5 um stroke, about 30 s a run on one thread), not physics.
# Resumable: rerun the same command.
#   bash scripts/tiny-dataset.sh [RUNS_DIR] [WORKERS] [DATASET]
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-runs/tiny}
WORKERS=${2:-2}
DATASET=${3:-data/tiny.h5}
VENV=${CALENDARING_VENV:-.venv}
. "$VENV/bin/activate"
common=(--preset tiny --out "$RUNS" --workers "$WORKERS")
calendaring sweep "${common[@]}" --design lhs --n 10 --design-seed 0 --seed 0 --role train
calendaring sweep "${common[@]}" --design lhs --n 2 --design-seed 1 --seed 1 --role holdout
calendaring dataset "$RUNS" --out "$DATASET" --overwrite
