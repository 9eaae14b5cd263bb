"""The cost of the live server (``--live-server``) and of the on-line reduction.

``recorder_live_server``: CAN frames/s the recorder takes in with the live server on and one
Foxglove client subscribed to every topic, as a ratio to the same recorder with the server off
(goal >= 0.9).  The recorder runs in a child process pinned to one CPU (the SDK's server threads
with it), reading the benchmark bus of ``bench_recorder`` (the shipped DBC's frames, cycled) through
the CAN load-cell driver, decoding every sample into ``/tensions`` (so the server has tensions,
a scene and the on-line feed to serve): a capacity probe at full speed (the bus held back while
20k frames are queued), server off / on / off / on, 6 s each, so both see the same machine load;
the value is the mean of the "on" probes, the peer the mean of the "off" probes.  The client
(``tests/_foxglove_client.py``, the ``websockets`` package, in this process on the other CPU)
subscribes to everything before the recording starts.

``live_server_latency_p99``: the time from a sample's timestamp (its host reception time, the
message's log time) to its arrival at the client, p99 over every ``/tensions/view`` message, with
the bus paced at the design's full rate (8 cells at 1 kHz: 4,000 frames/s, decoded) for 20 s, the
recorder process not pinned (as at the rig); p50, the max, the recorder's share (timestamp to the
SDK) and the same run pinned to one CPU beside it; goal p99 <= 50 ms.

``online_reduction_update``: the on-line reduction's cost per update at the end of the sample
campaign (45 test points: the whole session's points through the core), ms; peer: ``cdpr
analyze``'s reduction of the same run (``reduce_run``).  Also the cost with 10 points ended.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
PROBE_S = 6.0
LATENCY_S = 20.0
FULL_RATE_FRAMES = 4000.0  # 8 cells at 1 kHz: four 8-byte frames per sample


def _child_live(out: str, duration_s: float, rate_hz: float, live: bool, go_file: str) -> dict:
    """The recorder on the benchmark bus (decoding), the live server on or off; waits for
    ``go_file`` (the client subscribed) before it starts recording."""
    sys.path.insert(0, str(HERE))
    from bench_recorder import _cycled_bus_class

    from cdpr.daq.can_source import CanLoadCellSource
    from cdpr.daq.live_server import LiveAddress, LiveServer
    from cdpr.daq.recorder import Recorder, RecorderOptions
    from cdpr.pipelines.config import load_rig
    from cdpr.pipelines.online import OnlineReduction, online_options

    CycledBus = _cycled_bus_class()

    class BenchCanSource(CanLoadCellSource):
        def _make_bus(self):  # noqa: ANN202
            hold = (lambda: rec.backlog(self.name) > 20_000) if rate_hz == 0 else None
            return CycledBus(rate_hz, hold)

    rig = load_rig(ROOT / "data_samples" / "flat_experiment2.toml")
    src = BenchCanSource(
        "can0", interface="bench", channel="bench", bitrate=1_000_000, raw=True, decode=True,
        cables=list(rig.cable_names),
    )  # fmt: skip
    rec = Recorder([src], out, options=RecorderOptions())
    server = None
    if live:
        server = LiveServer(
            LiveAddress("127.0.0.1", 0), rig=rig, online=OnlineReduction(rig, online_options(None))
        )
        server.start()
        server.attach(rec)
        print(f"PORT {server.port}", flush=True)
        end = time.monotonic() + 30
        while not os.path.exists(go_file) and time.monotonic() < end:
            time.sleep(0.01)
    t0 = time.perf_counter()
    c0 = time.process_time()
    rec.start()
    rec.wait(duration_s)
    dt = time.perf_counter() - t0
    rec.stop()
    cpu = time.process_time() - c0
    st = rec.status()
    n = st.counts.get("can_raw", 0)
    res = {
        "written": n,
        "samples": st.counts.get("tensions", 0),
        "elapsed_s": dt,
        "cpu_s": cpu,
        "rate": n / dt,
        "per_cpu_s": n / cpu,
        "dropped": rec.dropped,
    }
    if server is not None:
        deadline = time.monotonic() + 10
        while not server.idle() and time.monotonic() < deadline:
            time.sleep(0.01)
        res.update(
            published=server.published,
            live_dropped_batches=server.dropped_batches,
            batches=server.batches_in,
            server_lag_ms=[(b - a) / 1e6 for a, b in server.view_lag],
            publisher_cpu_s=dict(server.cpu_s),
        )
        time.sleep(0.5)  # the last messages on the wire
        server.stop()
    return res


def _run_child(
    d: str, tag: str, duration_s: float, rate_hz: float, live: bool, pin: bool = True
) -> dict:
    """One recorder child pinned to one CPU; with ``live`` a client in this process subscribes
    to every topic first.  Returns the child's result (+ the client's latencies)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from _foxglove_client import FoxgloveClient

    go = f"{d}/{tag}.go"
    code = (
        "import json, os, sys\n"
        + ("os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})\n" if pin else "")
        + f"sys.path.insert(0, {str(HERE)!r})\n"
        "import bench_live as b\n"
        "r = b._child_live(*json.loads(sys.argv[1]))\n"
        "print('RESULT ' + json.dumps(r), flush=True)\n"
    )
    args = [f"{d}/{tag}.mcap", duration_s, rate_hz, live, go]
    proc = subprocess.Popen(
        [sys.executable, "-c", code, json.dumps(args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    client = None
    if live:
        line = proc.stdout.readline()
        if not line.startswith("PORT "):
            raise RuntimeError(f"live child: {line}{proc.stderr.read() if proc.stderr else ''}")
        client = FoxgloveClient(f"ws://127.0.0.1:{int(line.split()[1])}", keep_bodies=False)
        client.start()
        client.subscribed.wait(30)
        time.sleep(0.3)  # the subscribe message on its way (before the recording starts)
        Path(go).touch()
    out, err = proc.communicate(timeout=300)
    if proc.returncode != 0:
        raise RuntimeError(f"{tag}: {err.strip()[-800:]}")
    res = json.loads(next(x for x in out.splitlines() if x.startswith("RESULT "))[7:])
    if client is not None:
        client.stop()
        lat = [
            (r.arrival_ns - r.log_time_ns) / 1e6 for r in client.received
            if r.topic == "/tensions/view"
        ]  # fmt: skip
        res["latency_ms"] = lat
        res["client_messages"] = len(client.received)
        res["client_topics"] = sorted({r.topic for r in client.received})
    return res


def _pct(x: list[float], q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(x), q)) if x else float("nan")


def _online_cost(d: str) -> dict:
    """The on-line reduction's update at the end of the sample campaign, against analyze."""
    import numpy as np

    sys.path.insert(0, str(ROOT / "pipelines" / "commands"))
    from cdpr.daq.run_reader import open_run
    from cdpr.pipelines.analyze import reduce_run
    from cdpr.pipelines.commands.play import _readings
    from cdpr.pipelines.online import OnlineReduction, online_options
    from cdpr.pipelines.run_arrays import load_run

    matrix = ROOT / "data_samples" / "campaign_alpha_sweep.toml"
    res = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "simulate", "--campaign", str(matrix),
         "--out", f"{d}/campaign", "--quiet", "--speed", "4"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    if res.returncode != 0:
        raise RuntimeError(f"simulate --campaign: {res.stderr[-500:]}")
    (run_file,) = Path(d, "campaign").glob("*.mcap")
    opts = online_options(str(matrix))
    with open_run(run_file) as rec:
        rig_run = load_run(run_file)
        readings = [
            r for t in rec.streams if "view_of" not in rec.streams[t].metadata
            and not t.endswith("can_raw") for r in _readings(rec, t, 0, 2**63 - 1)
        ]  # fmt: skip
    readings.sort(key=lambda r: r.t_ns)
    events = [r for r in readings if r.stream == "events" and r.values.get("phase") == "end"]

    def timed(upto_ns: int, n: int = 5) -> float:
        online = OnlineReduction(rig_run.rig, opts)
        online.feed([r for r in readings if r.t_ns <= upto_ns])
        online.update(final=True)  # the first: the ended points
        last = [r for r in events if r.t_ns <= upto_ns][-1]
        point = (str(last.values["point"]), 0, last.t_ns, 0.0)
        times = []
        for _ in range(n):
            online._ended = [point]  # noqa: SLF001 - one ended point: a full update
            t0 = time.perf_counter()
            online.update(final=True)
            times.append(time.perf_counter() - t0)
        return float(np.median(times))

    at_end = timed(events[-1].t_ns + 10**9)
    at_10 = timed(events[9].t_ns + 10**6)
    t0 = time.perf_counter()
    reduce_run(rig_run, opts)
    t_analyze = time.perf_counter() - t0
    t0 = time.perf_counter()
    reduce_run(rig_run, opts)
    t_analyze = min(t_analyze, time.perf_counter() - t0)
    return {"end_s": at_end, "ten_s": at_10, "analyze_s": t_analyze, "points": len(events)}


def run() -> dict[str, dict]:
    with tempfile.TemporaryDirectory(prefix="bench_live_") as d:
        probes = {"off": [], "on": []}
        for k, live in enumerate((False, True, False, True)):
            r = _run_child(d, f"probe{k}", PROBE_S, 0.0, live)
            probes["on" if live else "off"].append(r)
        lat = _run_child(d, "latency", LATENCY_S, FULL_RATE_FRAMES, True, pin=False)
        lat_pinned = _run_child(d, "latency_pinned", LATENCY_S, FULL_RATE_FRAMES, True)
        cost = _online_cost(d)
    on = sum(r["written"] for r in probes["on"]) / sum(r["elapsed_s"] for r in probes["on"])
    off = sum(r["written"] for r in probes["off"]) / sum(r["elapsed_s"] for r in probes["off"])
    on_cpu = sum(r["written"] for r in probes["on"]) / sum(r["cpu_s"] for r in probes["on"])
    off_cpu = sum(r["written"] for r in probes["off"]) / sum(r["cpu_s"] for r in probes["off"])
    probe_lat = [x for r in probes["on"] for x in r["latency_ms"]]
    ms = lat["latency_ms"]
    return {
        "recorder_live_server": {
            "value": round(on, 1),
            "unit": "frames/s",
            "peer": "the same recorder (CAN driver decoding /tensions) with the live server off",
            "peer_value": round(off, 1),
            "goal_ratio": 0.9,
            "frames_per_cpu_s": round(on_cpu, 1),
            "peer_frames_per_cpu_s": round(off_cpu, 1),
            "ratio_per_cpu_s": round(on_cpu / off_cpu, 3),
            "dropped": sum(r["dropped"] for r in probes["on"] + probes["off"]),
            "live_dropped_batches": sum(r["live_dropped_batches"] for r in probes["on"]),
            "client_messages": sum(r["client_messages"] for r in probes["on"]),
            "client_topics": probes["on"][0]["client_topics"],
            "probes_frames_per_s": {k: [round(r["rate"], 1) for r in v] for k, v in probes.items()},
            "latency_at_capacity_p99_ms": round(_pct(probe_lat, 99), 2),
            "publisher_cpu_share": {
                k: round(
                    sum(r["publisher_cpu_s"][k] for r in probes["on"])
                    / sum(r["cpu_s"] for r in probes["on"]),
                    3,
                )
                for k in ("batches", "scene")
            },  # fmt: skip
            "context": "recorder child pinned to one CPU (the SDK's server threads in it too), "
            "capacity probes at full speed (bus held back at 20k queued frames) off/on/off/on, "
            f"{PROBE_S:g} s each; the client subscribed to every topic in another process; "
            "latency_at_capacity: with a 20k-frame queue in front of the writer by design",
        },
        "live_server_latency_p99": {
            "value": round(_pct(ms, 99), 2),
            "unit": "ms",
            "peer": None,
            "peer_value": None,
            "goal": 50.0,
            "p50_ms": round(_pct(ms, 50), 2),
            "max_ms": round(max(ms), 2) if ms else None,
            "recorder_share_p50_ms": round(_pct(lat["server_lag_ms"], 50), 2),
            "recorder_share_p99_ms": round(_pct(lat["server_lag_ms"], 99), 2),
            "pinned_one_cpu_p50_ms": round(_pct(lat_pinned["latency_ms"], 50), 2),
            "pinned_one_cpu_p99_ms": round(_pct(lat_pinned["latency_ms"], 99), 2),
            "messages": len(ms),
            "frames_per_s": FULL_RATE_FRAMES,
            "dropped": lat["dropped"],
            "live_dropped_batches": lat["live_dropped_batches"],
            "context": "sample timestamp (host reception time = the message's log time) to its "
            "arrival at the client, every /tensions/view message, bus paced at 4,000 frames/s "
            f"(8 cells at 1 kHz, decoded) for {LATENCY_S:g} s, recorder process not pinned (as "
            "it runs at the rig); recorder_share: from the timestamp to the message handed to "
            "the SDK (the CAN driver's 5 ms gathering, the queue, the writer's 10 ms batching, "
            "the publisher); pinned_one_cpu: the same with the recorder and its server threads "
            "on one CPU",
        },
        "online_reduction_update": {
            "value": round(cost["end_s"] * 1e3, 2),
            "unit": "ms",
            "peer": "cdpr analyze's reduction of the same run (reduce_run, the same core)",
            "peer_value": round(cost["analyze_s"] * 1e3, 2),
            "points": cost["points"],
            "ten_points_ms": round(cost["ten_s"] * 1e3, 2),
            "context": "one on-line update (the whole session's test points through the core) at "
            "the end of the sample campaign (data_samples/campaign_alpha_sweep.toml simulated at "
            "4x, camera and corrections), median of 5; the live server runs it once a second",
        },
    }


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
