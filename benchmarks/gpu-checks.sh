#!/usr/bin/env bash
# The GPU checks of the DEM-speed work, as one script for a CUDA machine (run from the
# repository root): the CPU/CUDA parity test, our Hertz-Mindlin steps/s on the 5k bed, the
# full model's particle-steps/s at 5k, 100k and 1M particles, then the engine and physics
# tests on the CUDA backend. Every stage has its own time cap and the script goes on after a
# failure; logs and JSON go to $OUT (default benchmarks/results).
#   OUT=DIR BEDS=DIR bash benchmarks/gpu-checks.sh
# BEDS holds the compacted beds of `bench_dem.py scaling --bed-dir` (built on the CPU
# first, so that the GPU time goes to the timed steps).
set -uo pipefail
OUT=${OUT:-benchmarks/results}
BEDS=${BEDS:-benchmarks/results/beds}
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"  # the benchmarks import calendaring
mkdir -p "$OUT"
stage() {  # stage NAME SECONDS COMMAND...
    local name=$1 cap=$2
    shift 2
    local t0=$SECONDS
    echo "=== $name (cap ${cap} s)"
    timeout "$cap" "$@" > "$OUT/gpu-$name.log" 2>&1
    local rc=$?
    grep -E "^\[(versus|scaling)\]|Error|error:|assert|FAILED|^E " "$OUT/gpu-$name.log" | head -n 25
    tail -n 8 "$OUT/gpu-$name.log"
    echo "=== $name: exit $rc after $((SECONDS - t0)) s"
}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
stage versus 120 "$PY" benchmarks/bench_dem.py versus --arch cuda --liggghts off --repeat 1 \
    --bed "$BEDS/full-bed-s0-x1.0000.npz" --out "$OUT/bench_dem_versus_cuda.json"
stage scaling 220 "$PY" benchmarks/bench_dem.py scaling --arch cuda --threads 1 \
    --sizes 5k 100k 1M --particle-steps 2e8 --skip-startup --bed-dir "$BEDS" \
    --out "$OUT/bench_dem_scaling_cuda.json"
stage parity 150 "$PY" -m pytest -q -x -p no:cacheprovider tests/system/test_cuda_parity.py
stage engine 80 env CALENDARING_TEST_ARCH=cuda "$PY" -m pytest -q -p no:cacheprovider --tb=short \
    tests/engine tests/physics
