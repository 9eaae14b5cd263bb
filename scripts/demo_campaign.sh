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
# the model geometry of the matrix's [model] table (analyze flags it geometry_from_options)
rc=0
"$CDPR" analyze "$C/runs" --out "$C/analysis" --area-m2 0.014646 --span-m 0.2441 --chord-m 0.060 \
    || rc=$?
[ "$rc" -le 1 ] || exit "$rc"
if ! ls "$C"/analysis/*/points.csv >/dev/null 2>&1; then
    # analyze writes the per-point table from the reduction core on (issue 8, section 4)
    echo "cdpr analyze wrote no per-point table (points.csv): campaign report not made" >&2
    exit 1
fi
rc=0
"$CDPR" campaign "$C/analysis" --matrix "$MATRIX" --runs "$C/runs" --out "$C/report" || rc=$?
[ "$rc" -le 1 ] || exit "$rc"
