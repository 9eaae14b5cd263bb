"""``cdpr analyze`` on an hour of forced-oscillation points (issue 22, "Speed").

- ``analyze_dynamic_1h``: tension samples per second of ``cdpr analyze`` end to end (a child
  process: reading the run, the test points from events, the dynamic reduction: the motion fitted
  from the camera, the clock offset, the structure matrix and the cable wrench at every load-cell
  sample, the harmonic fits, the derivatives; the plots, the hysteresis loops and the report) on
  a generated one-hour run (``bench/dynamic_run.py``: 8 cells at 1 kHz, the camera's pose at
  50 Hz with its covariance and a 3 ms clock offset, 10 Hz tunnel, 5 deg pitch oscillations at 2
  and 1 Hz, wind off and at two speeds, 60 cycles each), one worker.  The entry carries the wall
  time, the child's CPU time (user + system), its peak RSS and the issue's bounds (the static
  hour's: >= 180 k samples/s, i.e. <= 20 s of CPU for the hour, <= 2 GB).  No peer.
- ``analyze_dynamic_1h_camera200``: the same with the camera at 200 Hz (the issue's test
  camera): 720 k pose messages, whose JSON decoding in the reader (``foxglove.PoseInFrame``, one
  message a frame) costs more than the whole reduction.

``CDPR_BENCH_DYNAMIC_S`` sets the length (default 3600 s); ``CDPR_BENCH_DYNAMIC_RUN=PATH``
analyses a run written before by ``python bench/dynamic_run.py PATH 3600`` (the first entry
only).
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

import dynamic_run  # noqa: E402

GEO = ["--area-m2", "0.014646", "--span-m", "0.2441", "--chord-m", "0.060"]


def _child(args: list[str]) -> tuple[float, float, float, int]:
    """Run ``cdpr`` in a child; wall s, CPU s (user + system), peak RSS MB, exit code."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        check=False,
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"cdpr {' '.join(args)}: exit {proc.returncode}: {proc.stderr[-500:]!r}")
    return wall, cpu, after.ru_maxrss / 1024.0, proc.returncode


def bench_dynamic_1h(tmp: Path, cam: float, reuse: str | None = None) -> dict:
    duration_s = float(os.environ.get("CDPR_BENCH_DYNAMIC_S", "3600"))
    gen_s = float("nan")
    if reuse:
        from cdpr.daq.run_reader import open_run

        run = Path(reuse)
        with open_run(run) as r:
            counts = {k.strip("/"): v.count for k, v in r.streams.items()}
            info = r.streams["/tensions"]
            duration_s = round((info.stop_ns - info.start_ns) * 1e-9)
        gen = {"counts": counts, "points": []}
    else:
        tmp.mkdir(parents=True, exist_ok=True)
        run = tmp / "dynamic_hour.mcap"
        t0 = time.perf_counter()
        gen = dynamic_run.write_dynamic_run(run, duration_s, camera_hz=cam)
        gen_s = time.perf_counter() - t0
    n = gen["counts"]["tensions"]
    wall, cpu, rss_mb, code = _child(
        ["analyze", str(run), "--out", str(tmp / "out"), "--workers", "1", "--no-progress", *GEO]
    )
    n_osc = sum(1 for p in gen["points"] if p[1] != "zero")
    return {
        "value": n / wall,
        "unit": "tension samples/s (cdpr analyze end to end on oscillation points, 1 worker)",
        "context": (
            f"{duration_s:.0f} s run: {n} samples x 8 cells, {gen['counts']['pose']} poses "
            f"({'?' if reuse else f'{cam:g}'} Hz camera), {n_osc or '?'} oscillation points, "
            f"{run.stat().st_size / 1e6:.0f} MB; wall {wall:.1f} s, child CPU {cpu:.1f} s "
            f"({n / cpu:.0f} samples per CPU second), peak RSS {rss_mb:.0f} MB, exit {code}; "
            + (f"run from {run.name}" if reuse else f"generator {gen_s:.1f} s")
            + f"; load average {os.getloadavg()[0]:.1f}"
        ),
        "duration_s": duration_s,
        "wall_s": wall,
        "cpu_s": cpu,
        "samples_per_cpu_s": n / cpu,
        "peak_rss_MB": rss_mb,
        "target": ">= 180k samples/s (<= 20 s for the hour on one core), <= 2048 MB peak RSS",
        "within_bounds": bool(duration_s >= 3600 and n / cpu >= 180_000 and rss_mb <= 2048),
    }


def run() -> dict[str, dict]:
    reuse = os.environ.get("CDPR_BENCH_DYNAMIC_RUN")
    out = {}
    with tempfile.TemporaryDirectory(prefix="cdpr-bench-dynamic-") as d:
        out["analyze_dynamic_1h"] = bench_dynamic_1h(Path(d) / "50", 50.0, reuse)
        if not reuse:
            out["analyze_dynamic_1h_camera200"] = bench_dynamic_1h(Path(d) / "200", 200.0)
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
