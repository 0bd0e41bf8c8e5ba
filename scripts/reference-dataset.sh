#!/usr/bin/env bash
# The reference training dataset (issue "parameter sweeps"): 3 LHS points x 5 seeds of
# replicates (noise floors), 10 held-out LHS runs (calibration truth), 280 LHS training runs,
# all with the `sweep` preset, then the consolidated dataset file. Resumable: rerun the same
# command after an interruption; finished runs are kept and failed ones retried.
#   bash scripts/reference-dataset.sh [RUNS_DIR] [WORKERS]
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-runs/reference}
WORKERS=${2:-2}
. .venv/bin/activate
common=(--preset sweep --out "$RUNS" --workers "$WORKERS")
calendaring sweep "${common[@]}" --design lhs --n 3 --design-seed 7 --seed 0 --replicates 5 \
    --role replicate
calendaring sweep "${common[@]}" --design lhs --n 10 --design-seed 1 --seed 0 --role holdout
calendaring sweep "${common[@]}" --design lhs --n 280 --design-seed 0 --seed 0 --role train
calendaring dataset "$RUNS" --out data/reference.h5 --overwrite
