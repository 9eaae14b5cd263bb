#!/usr/bin/env bash
# The demo behind `make demo`: the main job on the built-in virtual rig and the paper's rigs.
set -euo pipefail
VENV=${VENV:-.venv}
OUT=${OUT:-out}
CDPR="$VENV/bin/cdpr"
mkdir -p "$OUT"
echo "== the paper's flat prototype rig (K21 = 51, K22 = 28, H = 0.67 m)"
"$CDPR" rig show data_samples/flat_optimum.toml
echo
echo "== wind-off tensions on the flat prototype rig, exact tension distribution"
"$CDPR" solve --rig data_samples/flat_optimum.toml --method exact --out "$OUT/tensions_wind_off.csv"
column -s, -t < <(grep -v '^#' "$OUT/tensions_wind_off.csv") | cut -c1-200
