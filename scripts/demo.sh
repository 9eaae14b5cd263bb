#!/usr/bin/env bash
# `make demo`: the main job on the built-in virtual rig, then the rest of the tool in short.
#   1. the paper's flat prototype rig;
#   2. calibration of the load cells and check loads on the balance (sample files);
#   2b. acquisition: the virtual rig emulates an slcan CAN adapter in a second process and a camera
#      renders its markers; cdpr records the run to MCAP, inspects it, exports HDF5, and survives a
#      kill -9 (scripts/demo_daq.sh);
#   3. the main job: cdpr analyze on the recorded runs (camera pose error against the truth,
#      wrench, coefficients, uncertainty, the paper's 1 N check, report with plots);
#   4. wrench recovery from CSV files and a CASPR robot (scripts/demo_wrench.sh);
#   5. vision: poses from rendered camera frames against the truth (scripts/demo_vision.sh);
#   6. the force-sensitivity study of the paper and a rig design (scripts/demo_sensitivity.sh);
#   7. a campaign rehearsed on the virtual rig: the aoa sweep of data_samples/campaign_alpha_sweep.toml
#      (zero, tare polar, three speeds, a repeat point; ~41 s in real time), analysed, and the
#      campaign table and report (scripts/demo_campaign.sh); it ends with the report's path and
#      the recovered-vs-true table.
set -euo pipefail
export VENV=${VENV:-.venv}
export OUT=${OUT:-out}
CDPR="$VENV/bin/cdpr"
mkdir -p "$OUT"
banner() { printf '\n#### %s\n\n' "$*"; }

banner "1. The paper's flat prototype rig (K21 = 51, K22 = 28, H = 0.67 m)"
"$CDPR" rig show data_samples/flat_optimum.toml

banner "2. Before the campaign: load cells and check loads (sample files in data_samples/)"
"$CDPR" calibrate loadcells data_samples/loadcell_points.csv --rig data_samples/flat_optimum.toml \
    --out "$OUT/calibration/loadcells.toml"
"$CDPR" calibrate balance data_samples/checkloads_flat.csv --rig data_samples/flat_optimum.toml \
    --out "$OUT/calibration/balance.json"

banner "2b. Acquisition on the virtual rig"
bash scripts/demo_daq.sh

banner "3. The main job: cdpr analyze $OUT/runs"
# the virtual rig's SDM-like model (docs/daq_drivers.md): S = 0.2441 m x 0.060 m; exit 1 means
# "reduced, some points flagged" (each warning is printed above and in the reports)
rc=0
"$CDPR" analyze "$OUT/runs" --out "$OUT/analysis" --area-m2 0.014646 --span-m 0.2441 \
    --chord-m 0.060 || rc=$?
[ "$rc" -le 1 ] || exit "$rc"
for r in "$OUT"/analysis/*/report.md; do
    sed -n '1,/^$/d;1,/^!\[/p' "$r" | grep -v '^!\[' || true
done

banner "4. Wrench recovery from files"
bash scripts/demo_wrench.sh

if [ -f scripts/demo_vision.sh ]; then
    banner "5. Vision"
    bash scripts/demo_vision.sh
fi

banner "6. Force-sensitivity study and rig design"
bash scripts/demo_sensitivity.sh

banner "7. The campaign: an aoa sweep rehearsed on the virtual rig"
bash scripts/demo_campaign.sh

banner "Done. Outputs in $OUT/: runs/ (MCAP, HDF5, truth), analysis/index.md, wrench_demo/, sensitivity/report.md, design/, campaign/report/campaign.html"
