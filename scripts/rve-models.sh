#!/usr/bin/env bash
# The surrogate, calibration and Sobol figures on the representative-volume dataset (issue
# 23, items 1-3): the paper's MLP and a 5-member ensemble; their errors against the
# held-out seed means with the PCA + GP baseline and repeated K-fold CV; the learning
# curve; the same ensemble with a PCA + GP pressure head (`--pressure-head gp`); `inverse
# validate` on every held-out seed with the measured error of whichever ensemble is closer to
# the held-out seed means (the other one too with VALIDATE_OTHER=1); the
# Sobol study against the paper's Fig. 10, the 30 um study (docs/results/sobol-30um.json)
# and the given-data estimate; one calibration of a held-out seed verified by the DEM.
# Each step is skipped when its output exists (rerun to resume; delete an output to redo
# it). Models and reports go to OUT (default models/rve, git-ignored).
#   [JOBS=N] bash scripts/rve-models.sh [DATASET] [OUT] [PRESET]
# JOBS: held-out rows `inverse validate` calibrates at once (default: the number of cores).
# VALIDATE_OTHER=1: also validate the other ensemble (64 more rows; 1.5-2.5 min a row on one
# thread of the loaded 2-core machine with the GP-head ensemble, 7 Dec 2026).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/rve.h5}
OUT=${2:-models/rve}
PRESET=${3:-rve}
JOBS=${JOBS:-$(nproc)}  # inverse validate: rows calibrated at once
VALIDATE_OTHER=${VALIDATE_OTHER:-0}  # 1: validate the other ensemble too (as long again)
. .venv/bin/activate
mkdir -p "$OUT"
t0=$SECONDS
step() { echo "[rve-models] $1 ($((SECONDS - t0)) s)"; }

step "train: the paper's MLP and a 5-member ensemble"
[ -f "$OUT/mlp.pt" ] || surrogate train "$DATA" --out "$OUT/mlp.pt" --seed 0 --quiet \
    | tee "$OUT/train.txt"
[ -f "$OUT/ensemble.pt" ] || surrogate train "$DATA" --out "$OUT/ensemble.pt" --ensemble 5 \
    --seed 0 --quiet | tee "$OUT/train-ensemble.txt"

# the GP pressure head; its network serves the distribution, trained with the weights that
# gave the lowest KL at 30 um (benchmarks/bench_surrogate_tuning.py) and on the partial rve set
[ -f "$OUT/ensemble-gp.pt" ] || surrogate train "$DATA" --out "$OUT/ensemble-gp.pt" \
    --ensemble 5 --seed 0 --pressure-head gp --mse-weight 30 --dropout 0.1 --quiet \
    | tee "$OUT/train-ensemble-gp.txt"

step "evaluate: test split, held-out seed means, replicates, baseline, 5x2 CV"
[ -f "$OUT/mlp_eval/metrics.json" ] || surrogate evaluate "$OUT/mlp.pt" "$DATA" \
    --out-dir "$OUT/mlp_eval" --folds 5 --repeats 2 --quiet | tee "$OUT/evaluate.txt"
[ -f "$OUT/ensemble_eval/metrics.json" ] || surrogate evaluate "$OUT/ensemble.pt" "$DATA" \
    --out-dir "$OUT/ensemble_eval" --folds 0 --no-baseline --quiet \
    | tee "$OUT/evaluate-ensemble.txt"
[ -f "$OUT/ensemble-gp_eval/metrics.json" ] || surrogate evaluate "$OUT/ensemble-gp.pt" "$DATA" \
    --out-dir "$OUT/ensemble-gp_eval" --folds 0 --no-baseline --quiet \
    | tee "$OUT/evaluate-ensemble-gp.txt"

# held-out groups of >= 2 seeds (seed means) exist in the rve set, not in a small test set
HELD_GROUPS=$(python - "$DATA" <<'PY'
import sys
from calendaring import read_dataset, seed_means
print(len(seed_means(read_dataset(sys.argv[1]), "holdout")))
PY
)
if [ "$HELD_GROUPS" -gt 0 ]; then
    step "learning curves on $HELD_GROUPS held-out seed means (network and GP heads)"
    [ -f "$OUT/learning_curve/learning_curve.json" ] || surrogate learning-curve "$DATA" \
        --out-dir "$OUT/learning_curve" --repeats 3 --quiet | tee "$OUT/learning-curve.txt"
    [ -f "$OUT/learning_curve_gp/learning_curve.json" ] || surrogate learning-curve "$DATA" \
        --out-dir "$OUT/learning_curve_gp" --repeats 3 --pressure-head gp --mse-weight 30 \
        --dropout 0.1 --quiet | tee "$OUT/learning-curve-gp.txt"
else
    step "no learning curves: $DATA has no held-out groups of >= 2 seeds"
fi

# the model the calibration steps use: the ensemble closer to the held-out seed means (the
# single held-out runs, or the test split, where the dataset has no seed means)
read -r BEST OTHER BY < <(python - "$OUT" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
m = {k: json.loads((out / f"{k}_eval" / "metrics.json").read_text())
     for k in ("ensemble", "ensemble-gp")}
def mse(k):
    if m[k].get("holdout_means"):
        return "held-out-seed-means", m[k]["holdout_means"]["pressure_mse_normalised"]
    split = "holdout" if "holdout" in m[k]["metrics"] else "test"
    return f"{split}-runs", m[k]["metrics"][split]["pressure"]["pressure_mse_normalised"]
best = min(m, key=lambda k: mse(k)[1])
print(best, "ensemble-gp" if best == "ensemble" else "ensemble", mse(best)[0])
PY
)
step "calibration model: $BEST (closer to the $BY than $OTHER)"

# the surrogate's own error in the likelihood: the model's test RMSE (normalised units;
# single runs, so it holds the run-to-run scatter a measured curve has too)
model_error() {
    python - "$OUT/$1_eval" <<'PY'
import json, math, sys
from pathlib import Path
m = json.loads((Path(sys.argv[1]) / "metrics.json").read_text())
print(f"{math.sqrt(m['metrics']['test']['pressure']['pressure_mse_normalised']):.4f}")
PY
}
ERR=$(model_error "$BEST")
ERR_OTHER=$(model_error "$OTHER")
step "validate every held-out seed: $BEST (model error sigma $ERR, normalised)"
[ -f "$OUT/validate/validation.json" ] || inverse validate --model "$OUT/$BEST.pt" \
    --dataset "$DATA" --out "$OUT/validate" --model-error "$ERR" --jobs "$JOBS" \
    | tee "$OUT/validate.txt"  # a progress line per row (with ETA) on stderr
if [ "$VALIDATE_OTHER" = 1 ]; then
    step "validate every held-out seed: $OTHER (model error sigma $ERR_OTHER), for comparison"
    [ -f "$OUT/validate-$OTHER/validation.json" ] || inverse validate --model "$OUT/$OTHER.pt" \
        --dataset "$DATA" --out "$OUT/validate-$OTHER" --model-error "$ERR_OTHER" \
        --jobs "$JOBS" | tee "$OUT/validate-$OTHER.txt"
fi

step "Sobol indices (N = 2^15) against Fig. 10, the 30 um study and the raw runs"
REF=()
[ -f docs/results/sobol-30um.json ] && REF=(--reference docs/results/sobol-30um.json)
[ -f "$OUT/sobol/sobol.json" ] || analysis sobol "$OUT/$BEST.pt" --n 2**15 \
    --dataset "$DATA" "${REF[@]}" --out-dir "$OUT/sobol" --quiet | tee "$OUT/sobol.txt"

step "one held-out seed calibrated, then the DEM run at the optimum (2 new seeds)"
ROW=$(python - "$DATA" <<'PY'
import sys
import numpy as np
from calendaring import read_dataset
ds = read_dataset(sys.argv[1])
print(int(np.nonzero(ds.role == "holdout")[0][0]))
PY
)
mkdir -p "$OUT/verify"
[ -f "$OUT/verify/result.json" ] || inverse calibrate --model "$OUT/$BEST.pt" \
    --target-row "$ROW" --dataset "$DATA" --posterior --model-error "$ERR" \
    --out "$OUT/verify/result.json" --quiet | tee "$OUT/calibrate.txt"
SEED=$(python - "$DATA" <<'PY'
import sys
from calendaring import read_dataset
print(int(read_dataset(sys.argv[1]).seed.max()) + 1)  # beds no dataset run used
PY
)
[ -f "$OUT/verify/verify.json" ] || inverse verify "$OUT/verify/result.json" \
    --preset "$PRESET" --seeds 2 --first-seed "$SEED" --out-dir "$OUT/verify" \
    | tee "$OUT/verify.txt"
step "done; outputs in $OUT"
