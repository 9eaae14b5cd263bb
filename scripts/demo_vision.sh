#!/usr/bin/env bash
# Vision demo: poses of the flat prototype's SDM model measured on rendered frames against the truth,
# then `cdpr calibrate camera` on rendered ChArUco views.  Uses $VENV/bin/cdpr and writes to $OUT/vision.
set -euo pipefail
VENV=${VENV:-.venv}
OUT=${OUT:-out}
CDPR="$VENV/bin/cdpr"
D="$OUT/vision"
mkdir -p "$D"
echo "== virtual 1.3 MP camera ~1 m from the SDM model: six ArUco markers, pose error against the truth"
"$CDPR" calibrate verify-pose --camera data_samples/camera_virtual.json \
    --layout data_samples/markers_flat_aruco.toml --rig data_samples/flat_experiment2.toml \
    -n 5 --seed 1 --out "$D/frames_aruco"
echo
echo "== the same with six IR marks (blobs, labelled by scored hypotheses)"
"$CDPR" calibrate verify-pose --camera data_samples/camera_virtual.json \
    --layout data_samples/markers_flat_ir6.toml --rig data_samples/flat_experiment2.toml \
    -n 5 --seed 2 --out "$D/frames_ir6"
echo
echo "== cdpr calibrate camera on 20 rendered ChArUco views (truth: fx = fy = 2000, cx = 642.3, cy = 508.1 px)"
"$CDPR" calibrate render-views --camera data_samples/camera_virtual.json \
    --board data_samples/board_charuco.toml -n 20 --noise-dn 8 --seed 2024 --out "$D/views"
"$CDPR" calibrate camera "$D/views" --board data_samples/board_charuco.toml --out "$D/camera.json"
echo
echo "== a bad image set is refused (exit 2, nothing written)"
mkdir -p "$D/bad_views"
cp "$D/views/view_000.png" "$D/views/view_001.png" "$D/bad_views/"
cp "$D/frames_ir6/frame_000.png" "$D/bad_views/ir_frame_without_board.png"
"$CDPR" calibrate camera "$D/bad_views" --board data_samples/board_charuco.toml \
    --out "$D/bad/camera.json" || echo "(exit $? as expected; $D/bad/camera.json not written)"
