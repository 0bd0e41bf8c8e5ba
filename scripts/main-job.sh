#!/usr/bin/env bash
# README main-job command: install into ./.venv, then calender a loose NMC622/carbon-black
# bed with the DEM engine and write pressure.csv, pressure.png and summary.json to out/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
python -m calendaring.demo --out "${1:-out/demo}"
