#!/usr/bin/env bash
# The representative-volume dataset (issue 22): with the `rve` preset (100 x 100 um cell),
# 3 LHS points x 5 seeds of replicates (noise floors), 16 held-out LHS points x 4 seeds
# (surrogate test targets as seed means; each seed a calibration truth), 280 LHS training
# runs taking turns over 8 beds (seeds 10-17, none of them a held-out seed's, so every
# held-out bed is unseen and the model learns the mean over beds, not one bed's
# deviation), then the consolidated dataset file. Resumable: rerun the same command after an
# interruption; finished runs are kept, runs in flight resume from their checkpoints and
# failed ones are retried.
#   bash scripts/rve-dataset.sh [RUNS_DIR] [WORKERS] [DATASET]
# Long sweeps run from a git worktree at a fixed commit (data/README.md):
#   git worktree add --detach ../wt-rve COMMIT
#   PYTHONPATH=../wt-rve bash ../wt-rve/scripts/rve-dataset.sh /work/sweep-rve 2
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-runs/rve}
WORKERS=${2:-2}
DATASET=${3:-data/rve.h5}
VENV=${CALENDARING_VENV:-.venv}
. "$VENV/bin/activate"
common=(--preset rve --out "$RUNS" --workers "$WORKERS")
calendaring sweep "${common[@]}" --design lhs --n 3 --design-seed 7 --seed 0 --replicates 5 \
    --role replicate
calendaring sweep "${common[@]}" --design lhs --n 16 --design-seed 1 --seed 0 --replicates 4 \
    --role holdout
calendaring sweep "${common[@]}" --design lhs --n 280 --design-seed 0 --seed 10 --beds 8 \
    --role train
calendaring dataset "$RUNS" --out "$DATASET" --overwrite
