"""``cdpr simulate`` end to end: the virtual rig sends through a real transport (slcan or the serial
line protocol on a pseudo-terminal, in a second process; or a python-can virtual bus), the recorder
writes the run; ``cdpr inspect``, the independent MCAP reader and the rig's truth agree; the run
exports to HDF5 (h5py + pandas)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
from test_recorder_helpers import node_read

from cdpr.daq.mcap_io import read_run

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
CDPR = [sys.executable, "-m", "cdpr.pipelines.cli"]

SCHEDULE = """
[schedule]
name = "short"
rate_hz = 200.0
tunnel_rate_hz = 10.0
seed = 5

[[segments]]
label = "tare"
tare = true
duration_s = 0.6
wind_mps = 0.0

[[segments]]
label = "v25"
duration_s = 0.9
wind_mps = 25.51
transition_s = 0.2
"""


def _cdpr(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CDPR, *args], capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("transport", ["slcan", "serial", "virtual"])
def test_simulate_inspect_independent_reader_truth_and_hdf5(tmp_path: Path, transport: str) -> None:
    sched = tmp_path / "schedule.toml"
    sched.write_text(SCHEDULE)
    out = tmp_path / "runs"
    res = _cdpr(
        "simulate", "--rig", str(RIG), "--schedule", str(sched), "--out", str(out),
        "--transport", transport, "--fault", "slack:0.8:0.3:2", "--label", f"sim-{transport}",
        "--quiet",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    (run,) = sorted(out.glob(f"*_sim-{transport}.mcap"))
    truth = np.load(run.with_name(run.stem + ".truth.npz"))
    n_samples = int(truth["sent"].sum())

    info = json.loads(_cdpr("inspect", str(run), "--json").stdout)
    node = node_read(run)
    assert node["complete"] and node["bad_json"] == 0 and info["complete"]
    counts = {s["topic"]: s["count"] for s in info["streams"]}
    # inspect == @mcap/core: messages, and samples of the column-block streams
    assert {k: v for k, v in counts.items() if v} == node["topics"] | node["samples"]
    assert counts["/tensions"] == n_samples  # every sample the rig sent
    assert counts["/tunnel"] == len(truth["tunnel_t_rel_ns"])
    if transport != "serial":
        assert counts["/can_raw"] == 4 * n_samples
    assert info["sources"]["loadcell"]["dropped"] == 0 and info["sources"]["loadcell"]["lost"] == 0
    md = info["metadata"]
    assert md["rig"] == "flat-optimum" and md["command"] == "simulate" and md["software_version"]
    assert "rig/flat_optimum.toml" in info["attachments"]

    rc = read_run(run)
    cables = [str(c) for c in truth["cable_names"]]
    rows = [b for _, b in rc.messages["/tensions"]]
    seq = np.array([b["seq"] for b in rows])
    T = np.array([[b[f"T_{c}_N"] for c in cables] for b in rows])
    np.testing.assert_array_equal(seq, np.flatnonzero(truth["sent"]))
    np.testing.assert_allclose(
        T, truth["tensions_sensor_N"][seq], rtol=0, atol=float(np.max(truth["gain_N_per_count"]))
    )
    slack = truth["channel_status"][seq, 2] & 2 != 0  # the fault: cable index 2 slack, 0.8-1.1 s
    assert 40 <= slack.sum() <= 80
    assert all(b["status_" + cables[2]] & 2 for b, s in zip(rows, slack, strict=True) if s)

    text = _cdpr("inspect", str(run)).stdout
    assert "/tensions" in text and f"{n_samples:9d}" in text and "complete" in text

    h5 = tmp_path / "run.h5"
    res = _cdpr("export", str(run), "--hdf5", str(h5))
    assert res.returncode == 0, res.stderr
    with h5py.File(h5, "r") as f:
        df = pd.DataFrame(f["streams/tensions"][()])
        assert len(df) == n_samples
        np.testing.assert_allclose(df[[f"T_{c}_N" for c in cables]].to_numpy(), T)
        assert f["metadata/run"].attrs["rig"] == "flat-optimum"
        tun = pd.DataFrame(f["streams/tunnel"][()])
        assert len(tun) == counts["/tunnel"]


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--fault", "melt:1:1"], "melt"),
        (["--fault", "slack:x:1"], "--fault"),
        (["--speed", "0"], "--speed"),
    ],
)
def test_simulate_bad_input_one_line_exit_2_nothing_written(
    tmp_path: Path, extra: list[str], needle: str
) -> None:
    sched = tmp_path / "schedule.toml"
    sched.write_text(SCHEDULE)
    out = tmp_path / "runs"
    res = _cdpr("simulate", "--rig", str(RIG), "--schedule", str(sched), "--out", str(out), *extra)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], res.stderr
    assert not out.exists() or not any(out.iterdir())
