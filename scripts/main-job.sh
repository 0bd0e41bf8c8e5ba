#!/usr/bin/env bash
# README main-job command: install into ./.venv, then build and calender the NMC622/carbon-
# black electrode with the `quick` preset (30 x 30 um cell, bonds, 19.5 um stroke) and write
# the run file, its summary, plots and a ParaView snapshot into out/quick/ (or $1).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
OUT=${1:-out/quick}
mkdir -p "$OUT"
calendaring run --preset quick --out "$OUT/quick.h5" --overwrite
calendaring inspect "$OUT/quick.h5" | tee "$OUT/summary.txt"
calendaring inspect "$OUT/quick.h5" --json > "$OUT/summary.json"
calendaring plot "$OUT/quick.h5"
calendaring export "$OUT/quick.h5" --snapshot 4 --vtk
