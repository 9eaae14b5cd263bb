"""``cdpr analyze`` at campaign scale (issue 9, section 5).

- ``analyze_run_1h``: tension samples per second of ``cdpr analyze`` end to end (a child process:
  reading the run, test points from events, the reduction, the plots, the report) on a generated
  one-hour run (``bench/campaign_run.py``: 8 cells at 1 kHz, 30 Hz camera pose with covariance,
  10 Hz tunnel, a test point every 20 s), one worker.  The entry carries the wall time, the child's
  CPU time (user + system), its peak RSS (``getrusage(RUSAGE_CHILDREN).ru_maxrss``) and the
  issue's bounds (<= 20 s, <= 2 GB).  No peer: nothing else analyses these runs.
- ``analyze_scaling``: a batch of runs on a local Dask cluster of 2 workers against 1 worker (runs
  per second; ratio = speed-up, the issue asks >= 1.7).  The load average is in the entry: on a
  shared 2-core machine the second worker only helps when a core is free.

``CDPR_BENCH_ANALYZE_S`` sets the length of the long run (default 3600 s; shorter for a quick look,
the entry says which length was measured); ``CDPR_BENCH_ANALYZE_RUN=PATH`` analyses a run written
before by ``python bench/campaign_run.py PATH 3600`` instead of writing one (the generator takes
about 20 s of CPU for an hour).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from campaign_run import write_campaign_run  # noqa: E402

GEO = ["--area-m2", str(0.2441 * 0.0815), "--span-m", "0.2441", "--chord-m", "0.0815"]


def _cdpr() -> list[str]:
    return [sys.executable, "-m", "cdpr.pipelines.cli"]


def _child(args: list[str]) -> tuple[float, float, float, int]:
    """Run ``cdpr`` in a child; wall s, CPU s (user + system), peak RSS MB, exit code."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [*_cdpr(), *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=False
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode not in (0, 1):  # 1: flagged points, still a complete analysis
        raise RuntimeError(f"cdpr {' '.join(args)}: exit {proc.returncode}: {proc.stderr[-500:]!r}")
    return wall, cpu, after.ru_maxrss / 1024.0, proc.returncode


def bench_run_1h(tmp: Path) -> dict:
    duration_s = float(os.environ.get("CDPR_BENCH_ANALYZE_S", "3600"))
    reuse = os.environ.get("CDPR_BENCH_ANALYZE_RUN")
    gen_s = float("nan")
    if reuse:  # a run written before by campaign_run.py (its length from the stream's times)
        from cdpr.daq.run_reader import open_run

        run = Path(reuse)
        with open_run(run) as r:
            counts = {k.strip("/"): v.count for k, v in r.streams.items()}
            info = r.streams["/tensions"]
            duration_s = round((info.stop_ns - info.start_ns) * 1e-9)
        gen = {"counts": counts}
    else:
        run = tmp / "hour.mcap"
        t0 = time.perf_counter()
        gen = write_campaign_run(run, duration_s)
        gen_s = time.perf_counter() - t0
    n = gen["counts"]["tensions"]
    wall, cpu, rss_mb, code = _child(
        ["analyze", str(run), "--out", str(tmp / "out1"), "--workers", "1", "--no-progress", *GEO]
    )
    return {
        "value": n / wall,
        "unit": "tension samples/s (cdpr analyze end to end, 1 worker)",
        "context": (
            f"{duration_s:.0f} s run: {n} samples x 8 cells, {gen['counts']['pose']} poses, "
            f"{gen['counts']['tunnel']} tunnel, {gen['counts']['events']} events, "
            f"{run.stat().st_size / 1e6:.0f} MB; wall {wall:.1f} s, child CPU {cpu:.1f} s, "
            f"peak RSS {rss_mb:.0f} MB, exit {code}; "
            + (
                f"run from {run.name}"
                if reuse
                else f"generator {gen_s:.1f} s ({n / gen_s:.0f} samples/s)"
            )
            + f"; load average {os.getloadavg()[0]:.1f}"
        ),
        "duration_s": duration_s,
        "wall_s": wall,
        "cpu_s": cpu,
        "peak_rss_MB": rss_mb,
        "target": "<= 20 s end to end on one core, <= 2048 MB peak RSS (one hour)",
        "within_bounds": bool(duration_s >= 3600 and cpu <= 20.0 and rss_mb <= 2048),
        "generator_samples_per_s": None if reuse else n / gen_s,
    }


def bench_scaling(tmp: Path, n_runs: int = 4, duration_s: float = 3600.0) -> dict:
    runs = tmp / "batch"
    runs.mkdir()
    for k in range(n_runs):
        write_campaign_run(runs / f"run{k}.mcap", duration_s, seed=10 + k)
    times = {}
    for workers in (1, 2):
        wall, _, _, _ = _child(
            ["analyze", str(runs), "--out", str(tmp / f"batch{workers}"), "--workers",
             str(workers), "--no-progress", *GEO]
        )  # fmt: skip
        times[workers] = wall
    return {
        "value": n_runs / times[2],
        "unit": "runs/s on 2 local Dask workers",
        "peer": "the same batch on 1 worker",
        "peer_value": n_runs / times[1],
        "target": "ratio >= 1.7",
        "context": (
            f"{n_runs} runs of {duration_s:.0f} s; 1 worker {times[1]:.1f} s, 2 workers "
            f"{times[2]:.1f} s (1 worker runs in-process; 2 workers include the start of the "
            "local cluster, its workers forked from the command); load average "
            f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
        ),
    }


def run() -> dict[str, dict]:
    with tempfile.TemporaryDirectory(prefix="cdpr-bench-analyze-") as d:
        tmp = Path(d)
        return {"analyze_run_1h": bench_run_1h(tmp), "analyze_scaling": bench_scaling(tmp)}


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
