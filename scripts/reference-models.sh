#!/usr/bin/env bash
# The surrogate and calibration figures on the reference dataset (issues "surrogate" and
# "inverse calibration"): one paper model and a 5-member deep ensemble trained on the
# 'train' rows, evaluated on the test split with repeated K-fold CV and the PCA + GP
# baseline, the benchmarks, then the calibration of the 10 held-out runs with posteriors.
# Models and reports go to OUT (default models/reference, git-ignored).
#   bash scripts/reference-models.sh [DATASET] [OUT]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/reference.h5}
OUT=${2:-models/reference}
. .venv/bin/activate
mkdir -p "$OUT"
t0=$SECONDS
surrogate train "$DATA" --out "$OUT/mlp.pt" --seed 0 --quiet --overwrite | tee "$OUT/train.txt"
surrogate train "$DATA" --out "$OUT/ensemble.pt" --ensemble 5 --seed 0 --quiet --overwrite \
    | tee "$OUT/train-ensemble.txt"
surrogate evaluate "$OUT/mlp.pt" "$DATA" --out-dir "$OUT/mlp_eval" --folds 5 --repeats 2 \
    --quiet | tee "$OUT/evaluate.txt"
surrogate evaluate "$OUT/ensemble.pt" "$DATA" --out-dir "$OUT/ensemble_eval" --folds 0 \
    --no-baseline --quiet | tee "$OUT/evaluate-ensemble.txt"
python benchmarks/bench_surrogate.py "$DATA" --threads 1 2
python benchmarks/bench_inverse.py --model "$OUT/ensemble.pt"
# the surrogate's own error enters the likelihood: the ensemble's held-out pressure RMSE
# in normalised units, read from its evaluation
ERR=$(python - "$OUT/ensemble_eval" <<'PY'
import json, math, sys
from pathlib import Path
m = json.loads((Path(sys.argv[1]) / "metrics.json").read_text())
print(f"{math.sqrt(m['metrics']['test']['pressure']['pressure_mse_normalised']):.4f}")
PY
)
echo "model error sigma (normalised): $ERR"
inverse validate --model "$OUT/ensemble.pt" --dataset "$DATA" --out "$OUT/validate" \
    --model-error "$ERR" --quiet | tee "$OUT/validate.txt"
echo "reference models done in $((SECONDS - t0)) s; outputs in $OUT"
