"""``cdpr analyze`` on a folder of runs: results that are current are skipped (``--force``
recomputes), and the batch runs on a real ``dask scheduler`` process given by ``--scheduler``."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from test_analyze_runs import GEO, write_run
from truth_rig import alpha_sweep

from cdpr.pipelines.cli import main


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("runs")
    for seed in (31, 32):
        write_run(d / f"sweep{seed}.mcap", alpha_sweep(seed, point_s=1.0, ramp_s=0.4))
    return d


def _points_mtimes(out: Path) -> dict[str, int]:
    return {p.parent.name: p.stat().st_mtime_ns for p in out.glob("*/points.csv")}


def test_second_call_skips_current_results_and_force_recomputes(
    runs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "a"
    assert main(["analyze", str(runs), "--out", str(out), "--workers", "1", *GEO]) == 0
    first = _points_mtimes(out)
    assert sorted(first) == ["sweep31", "sweep32"]
    capsys.readouterr()

    assert main(["analyze", str(runs), "--out", str(out), "--workers", "1", *GEO]) == 0
    said = capsys.readouterr().out
    assert said.count("current, skipped") == 2, said
    assert _points_mtimes(out) == first  # nothing rewritten

    # another option makes the results stale; so does a changed run file
    assert main(["analyze", str(runs), "--out", str(out), "--workers", "1", *GEO[:-1], "0.09"]) == 0
    assert "current, skipped" not in capsys.readouterr().out
    second = _points_mtimes(out)
    assert all(second[k] != first[k] for k in first)

    assert main(["analyze", str(runs), "--out", str(out), "--workers", "1", *GEO[:-1], "0.09",
                 "--force"]) == 0  # fmt: skip
    assert "current, skipped" not in capsys.readouterr().out
    assert all(v != second[k] for k, v in _points_mtimes(out).items())


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _wait_for(pred, what: str, timeout_s: float = 120.0) -> None:  # type: ignore[no-untyped-def]
    t_end = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def test_batch_on_a_real_dask_scheduler_process(runs: Path, tmp_path: Path) -> None:
    sched_file = tmp_path / "scheduler.json"
    env = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
    common = dict(
        cwd=tmp_path, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL, preexec_fn=_default_sigint,
    )  # fmt: skip
    procs = [
        subprocess.Popen(  # type: ignore[call-overload]
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(sched_file),
            ],
            **common,
        )  # fmt: skip
    ]
    try:
        _wait_for(lambda: sched_file.exists() and sched_file.stat().st_size > 0, "the scheduler")
        procs.append(
            subprocess.Popen(  # type: ignore[call-overload]
                [
                    sys.executable,
                    "-m",
                    "distributed.cli.dask_worker",
                    "--scheduler-file",
                    str(sched_file),
                    "--nworkers",
                    "1",
                    "--nthreads",
                    "1",
                    "--no-dashboard",
                ],
                **common,
            )  # fmt: skip
        )
        address = json.loads(sched_file.read_text())["address"]
        out = tmp_path / "b"
        assert main(["analyze", str(runs), "--out", str(out), "--scheduler", address, *GEO]) == 0
        local = tmp_path / "c"
        assert main(["analyze", str(runs), "--out", str(local), "--workers", "1", *GEO]) == 0
        _same_points(out, local)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_batch_on_a_local_cluster_of_two_workers(runs: Path, tmp_path: Path) -> None:
    """``--workers 2``: a local Dask cluster whose workers are forked from the command's process
    (a separate process here, as a user runs it) gives the results of one worker in-process."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
    out = tmp_path / "two"
    res = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "analyze", str(runs), "--out", str(out),
         "--workers", "2", "--no-progress", *GEO],
        env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=600,
        preexec_fn=_default_sigint,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert res.stdout.count(" points (") == 2, res.stdout
    local = tmp_path / "one"
    assert main(["analyze", str(runs), "--out", str(local), "--workers", "1", *GEO]) == 0
    _same_points(out, local)


def _same_points(out: Path, local: Path) -> None:
    """The points of both runs in ``out`` equal those of ``local`` (one worker in-process)."""
    for name in ("sweep31", "sweep32"):
        a = pd.read_csv(out / name / "points.csv")
        b = pd.read_csv(local / name / "points.csv")
        pd.testing.assert_frame_equal(a, b)
