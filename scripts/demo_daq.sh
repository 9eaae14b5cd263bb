#!/usr/bin/env bash
# Demo of the acquisition part (`make demo`): the virtual rig runs in a second process and emulates
# an slcan CAN adapter on a pseudo-terminal; `cdpr simulate` records it through python-can's slcan
# interface into an MCAP run; `cdpr inspect` and an independent reader (@mcap/core) summarise it;
# then a recorder is killed with kill -9 mid-run and `cdpr recover` salvages the file.
set -euo pipefail
VENV=${VENV:-.venv}
OUT=${OUT:-out}
CDPR="$VENV/bin/cdpr"
RUNS="$OUT/runs"
mkdir -p "$RUNS"

echo "== cdpr simulate: virtual rig -> slcan on a pty (2nd process) -> recorder -> MCAP (~8 s)"
echo "   with a virtual camera rendering the six IR marks at the true pose (5 Hz)"
"$CDPR" simulate --rig data_samples/flat_optimum.toml --schedule data_samples/schedule_demo.toml \
    --out "$RUNS" --transport slcan --label demo-slcan --quiet \
    --camera data_samples/camera_virtual.json --markers data_samples/markers_flat_ir6.toml
RUN=$(ls -t "$RUNS"/*_demo-slcan.mcap | head -n 1)
echo
echo "== cdpr inspect $RUN"
"$CDPR" inspect "$RUN"
if [ -d tools/mcap-check/node_modules ]; then
    echo
    echo "== independent reader (@mcap/core, TypeScript) message counts"
    node --single-threaded tools/mcap-check/mcap_check.js "$RUN" | "$VENV/bin/python" -c \
        'import json,sys; d=json.load(sys.stdin); print("complete:", d["complete"], " counts:", d["topics"])'
fi
echo
echo "== cdpr export $RUN --hdf5 ..."
"$CDPR" export "$RUN" --hdf5 "${RUN%.mcap}.h5"

echo
echo "== crash safety: kill -9 a recording mid-run, then cdpr recover"
CRASH="$OUT/crash"
mkdir -p "$CRASH"
"$CDPR" simulate --rig data_samples/flat_optimum.toml --schedule data_samples/schedule_demo.toml \
    --out "$CRASH" --transport slcan --label demo-kill9 --quiet > /dev/null &
PID=$!
# kill it once it has recorded for a while: wait for the file (a loaded machine starts slowly),
# then for about 4 s of recording
for _ in $(seq 600); do
    ls "$CRASH"/*_demo-kill9.mcap > /dev/null 2>&1 && break
    kill -0 "$PID" 2> /dev/null || { echo "the recorder ended before its file appeared" >&2; exit 1; }
    sleep 0.1
done
sleep 4
CHILDREN=$(pgrep -P "$PID" || true)
kill -9 "$PID"
wait "$PID" 2> /dev/null || true
for c in $CHILDREN; do kill "$c" 2> /dev/null || true; done
KILLED=$(ls -t "$CRASH"/*_demo-kill9.mcap | head -n 1)
"$CDPR" recover "$KILLED"
"$CDPR" inspect "${KILLED%.mcap}.recovered.mcap" | sed -n '1p;/topic/,$p'
