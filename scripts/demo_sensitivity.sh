#!/usr/bin/env bash
# Force-sensitivity demo: the paper's study (Figs. 6-15, Table 3) with the reproduction report, then
# a short geometry optimisation of the flat prototype rig with its Pareto plot.
set -euo pipefail
VENV=${VENV:-.venv}
OUT=${OUT:-out}
CDPR="$VENV/bin/cdpr"
echo "== cdpr sensitivity --paper (cubic 960-case study, Z, deflection; flat Table 3, two methods)"
"$CDPR" sensitivity --paper --out "$OUT/sensitivity"
echo
echo "== cdpr design on the flat prototype rig (maximise S, margin >= 0 N, condition <= 1000)"
"$CDPR" design --family flat --objective sensitivity --out "$OUT/design" \
    --maxiter 15 --popsize 12 --samples 2000
echo
echo "Reproduction report: $OUT/sensitivity/report.md (figures and CSV beside it)"
echo "Design: $OUT/design/design.md, Pareto plot $OUT/design/pareto.png, rig $OUT/design/design_rig.toml"
