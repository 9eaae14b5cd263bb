"""Many runs at once (``cdpr analyze runs/``): in parallel on a Dask cluster (a local one of
single-threaded worker processes by default, or a scheduler's address), skipping the runs whose
results are current (the fingerprint of their inputs, :mod:`cdpr.pipelines.freshness`), with a
progress bar, and ``index.md`` listing every run.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import CdprError, ConfigError

from .analyze import (
    AnalyzeOptions,
    analyze_run,
    check_recalibration,
    result_folder,
    run_fingerprint,
)
from .freshness import is_current


def _safe(path: str, out_dir: str, opts: AnalyzeOptions, fp: dict[str, Any]) -> dict[str, Any]:
    try:
        return analyze_run(path, out_dir, opts, fp)
    except CdprError as exc:
        return {"run": path, "error": str(exc)}


def _current_summary(path: str, out_dir: str, fp: dict[str, Any]) -> dict[str, Any] | None:
    """The recorded summary of run ``path`` when its result folder is current, else None."""
    folder = result_folder(path, out_dir)
    if not is_current(folder, fp):
        return None
    try:
        summary: dict[str, Any] = json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    summary["folder"] = str(folder)
    summary["skipped"] = "current"
    return summary


class _RunsProgress:
    """A progress bar across runs on stderr (rich), silent when ``enabled`` is False."""

    def __init__(self, total: int, enabled: bool) -> None:
        self._bar = None
        if enabled and total:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

            self._bar = Progress(
                "[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                TimeElapsedColumn(), console=Console(file=sys.stderr),
            )  # fmt: skip
            self._bar.start()
            self._task = self._bar.add_task("analyze: runs", total=total)

    def advance(self) -> None:
        if self._bar is not None:
            self._bar.advance(self._task)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()


#: settings of the local cluster: no sampling profiler (a stack sample of the task every 10 ms)
#: and no GIL monitor (every 1 ms) in the workers, resource polls once a second (on a machine
#: with as many cores as workers they take CPU from the runs); workers forked from this process
#: once it has imported what a run needs (spawned workers each imported it anew: ~1 s each)
_LOCAL_DASK: dict[str, Any] = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.gil.enabled": False,
    "distributed.admin.system-monitor.interval": "1s",
    "distributed.admin.system-monitor.disk": False,
    "distributed.worker.memory.monitor-interval": "1s",
}
if sys.platform.startswith("linux"):  # fork is not safe on macOS; spawn (Dask's default) there
    _LOCAL_DASK["distributed.worker.multiprocessing-method"] = "fork"


class _ClusterStart:
    """A local Dask cluster of ``n`` single-threaded worker processes, started in a thread (so
    that this process can go on meanwhile); :meth:`cluster` waits for it, :meth:`close` stops it
    (started or not)."""

    def __init__(self, n: int) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(1, thread_name_prefix="cdpr-cluster")
        self._future = self._pool.submit(self._start, n)

    @staticmethod
    def _start(n: int) -> Any:
        import dask
        import matplotlib
        from dask.distributed import LocalCluster

        import cdpr.pipelines.plotting
        import cdpr.pipelines.report
        import cdpr.pipelines.run_report  # noqa: F401  (imported here, the forked workers have them)
        from cdpr.daq import run_reader  # noqa: F401

        matplotlib.use("Agg")
        import matplotlib.pyplot  # noqa: F401

        # Dask starts its workers with MALLOC_TRIM_THRESHOLD_ set, which also fixes glibc's mmap
        # threshold: every array over 128 KiB is then mapped and unmapped anew (page faults: a
        # worker spent 4x the system time of one process on the same runs); the workers get
        # glibc's own adaptive thresholds instead
        environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
        environ.pop("MALLOC_TRIM_THRESHOLD_", None)
        with dask.config.set({"distributed.nanny.pre-spawn-environ": environ, **_LOCAL_DASK}):
            return LocalCluster(
                n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None
            )

    def cluster(self) -> Any:
        return self._future.result()

    def close(self) -> None:
        try:
            if self._future.exception() is None:
                self._future.result().close()
        finally:
            self._pool.shutdown()


def analyze_runs(
    paths: Sequence[str],
    out_dir: str,
    opts: AnalyzeOptions,
    scheduler: str | None = None,
    workers: int = 2,
    progress: bool = True,
    force: bool = False,
) -> list[dict[str, Any]]:
    """Analyse runs in parallel on Dask (a local cluster of ``workers`` single-threaded processes,
    unless ``scheduler`` is the address of a running scheduler; with one worker, or one run, and
    no scheduler: one after the other in this process); a bad run is reported in its
    summary (``error``) without stopping the others.  A run whose result folder records the
    fingerprint of its inputs now is not recomputed (its recorded summary comes back with
    ``skipped = "current"``) unless ``force``.  ``progress``: a bar across runs on stderr (when
    more than one run is to be analysed)."""
    if not paths:
        raise ConfigError("runs", "", "no run files given")
    # the local cluster starts (processes, imports) while the inputs are checked and hashed here
    local = (
        _ClusterStart(min(workers, len(paths)))
        if scheduler is None and workers > 1 and len(paths) > 1
        else None
    )
    try:
        if opts.loadcell_calibration_file is not None:  # every run can be re-calibrated: first
            from cdpr.daq.loadcell import read_calibration_file

            lc_file = read_calibration_file(opts.loadcell_calibration_file)
            for p in paths:
                check_recalibration(p, lc_file)
        fps = [run_fingerprint(p, opts) for p in paths]
        results: list[dict[str, Any] | None] = [
            None if force else _current_summary(p, out_dir, fp)
            for p, fp in zip(paths, fps, strict=True)
        ]
        todo = [i for i, r in enumerate(results) if r is None]
        bar = _RunsProgress(len(todo), progress and len(todo) > 1)
        try:
            if scheduler is None and (len(todo) <= 1 or workers == 1):
                if local is not None:  # at most one run to analyse: no use for the cluster
                    local.close()
                    local = None
                for i in todo:  # one worker: in this process, no cluster to start
                    results[i] = _safe(paths[i], out_dir, opts, fps[i])
                    bar.advance()
            elif todo:
                from dask.distributed import Client, as_completed

                client = Client(scheduler or (local.cluster() if local else None))
                try:
                    futures = {
                        client.submit(_safe, paths[i], out_dir, opts, fps[i], pure=False): i
                        for i in todo
                    }
                    for fut in as_completed(futures):
                        results[futures[fut]] = fut.result()
                        bar.advance()
                finally:
                    client.close()
        finally:
            bar.close()
    finally:
        if local is not None:
            local.close()
    done = [r for r in results if r is not None]
    lines = [
        "# Analysed runs",
        "",
        "| run | points | source | warnings | max ΔT (N) | check | report |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in done:
        if "error" in r:
            lines.append(f"| {Path(r['run']).name} | - | - | - | - | error: {r['error']} | - |")
        else:
            rel = Path(r["folder"]).name
            red = r["reduction"]
            lines.append(
                f"| {Path(r['run']).name} | {r['points']} | {red['point_source']} | "
                f"{', '.join(red['warnings']) or '-'} | {r['check_max_abs_dT_N']:.3f} | "
                f"{'pass' if r['check_pass'] else 'FAIL'} | [{rel}/report.md]({rel}/report.md) |"
            )
    index = Path(out_dir) / "index.md"
    index.parent.mkdir(parents=True, exist_ok=True)
    tmp = index.with_suffix(".md.part")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, index)
    return done
