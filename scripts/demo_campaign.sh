#!/usr/bin/env bash
# The campaign on the virtual rig (part 7 of `make demo`; runs alone too):
#   simulate the test matrix (the run carries /events test points, /pose from the camera, /tunnel),
#   analyze it (per-point table points.csv), then the campaign table and HTML/Markdown report.
# Exit code 1 of analyze or campaign means "points with flags": they are listed in the reports.
set -euo pipefail
VENV=${VENV:-.venv}
OUT=${OUT:-out}
CDPR="$VENV/bin/cdpr"
MATRIX=data_samples/campaign_alpha_sweep.toml
C="$OUT/campaign"
rm -rf "$C"   # the demo's own folder: a fresh rehearsal each time

"$CDPR" simulate --campaign "$MATRIX" --out "$C/runs" --quiet
# the matrix gives the model geometry ([model]), the test section ([tunnel]) and turns the
# corrections on: zero drift, windage (the model-off points), wall corrections, q/Re/Mach
rc=0
"$CDPR" analyze "$C/runs" --out "$C/analysis" --matrix "$MATRIX" || rc=$?
[ "$rc" -le 1 ] || exit "$rc"
if ! ls "$C"/analysis/*/points.csv >/dev/null 2>&1; then
    # analyze writes the per-point table from the reduction core on (issue 8, section 4)
    echo "cdpr analyze wrote no per-point table (points.csv): campaign report not made" >&2
    exit 1
fi

# The same run as another tool would have left it (a candump log that starts in the middle of a
# sample, the camera's poses, the tunnel's log, the test-point list): imported, analysed again,
# and compared with the analysis of the recorded run
RUN=$(ls "$C"/runs/*.mcap | head -n 1)
O="$C/other_tool"
"$VENV/bin/python" scripts/other_tool_logs.py "$RUN" "$O"
mkdir -p "$C/imported"
"$CDPR" import --can-log "$O/can.log" --dbc data_samples/loadcell.dbc \
    --rig data_samples/flat_experiment2.toml --calibration "${RUN%.mcap}.loadcells.toml" \
    --poses "$O/poses.csv" --tunnel "$O/tunnel.csv" --events "$O/events.csv" \
    --label imported --out "$C/imported/imported.mcap"
rc=0
"$CDPR" analyze "$C/imported" --out "$C/imported_analysis" --matrix "$MATRIX" || rc=$?
[ "$rc" -le 1 ] || exit "$rc"
"$VENV/bin/python" - "$C" <<'PY'
import sys
from pathlib import Path

import numpy as np
import pandas as pd

c = Path(sys.argv[1])
a = pd.read_csv(next((c / "imported_analysis").glob("*/points.csv")))
b = pd.read_csv(next((c / "analysis").glob("*/points.csv")))
cols = ["fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm"]
on = (b.kind == "wind_on").to_numpy()
d = np.abs(a.loc[on, cols].to_numpy() - b.loc[on, cols].to_numpy()).max(axis=0)
print("imported (other tools' files) - recorded run, wind-on wrench, max |difference|: "
      + ", ".join(f"{k} {v:.2g}" for k, v in zip(cols, d, strict=True)))
PY
rc=0
"$CDPR" campaign "$C/analysis" --matrix "$MATRIX" --runs "$C/runs" --out "$C/report" || rc=$?
[ "$rc" -le 1 ] || exit "$rc"
