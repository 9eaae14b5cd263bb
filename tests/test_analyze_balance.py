"""Steady segments, segment statistics and the batch analysis of a simulated run end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cdpr.analysis.balance import (
    SegmentRule,
    interpolate_at,
    nearest_tare,
    segment_stats,
    steady_segments,
)
from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_segments_follow_airspeed_steps_and_pose_changes() -> None:
    # 100 Hz for 6 s: V = 0 (0-2 s), 20 (2-4 s), 20 but pitched 5 deg (4-6 s)
    t_ns = np.arange(600, dtype=np.int64) * 10_000_000
    v = np.where(t_ns < 2e9, 0.0, 20.0)
    poses = np.zeros((600, 6))
    poses[t_ns >= 4e9, 4] = np.deg2rad(5.0)
    rule = SegmentRule(settle_s=0.5, min_duration_s=0.5)
    segs = steady_segments(t_ns, v, poses, rule)
    # each stretch loses its first 0.5 s (50 samples)
    assert segs == [(50, 200), (250, 400), (450, 600)]


def test_short_and_transient_stretches_are_dropped() -> None:
    t_ns = np.arange(300, dtype=np.int64) * 10_000_000
    v = np.concatenate([np.zeros(100), np.linspace(0, 30, 50), np.full(150, 30.0)])
    segs = steady_segments(
        t_ns, v, np.zeros((300, 6)), SegmentRule(settle_s=0.3, min_duration_s=0.5)
    )
    starts = [a for a, _ in segs]
    assert len(segs) == 2 and starts[0] == 30
    a, b = segs[1]
    assert np.ptp(v[a:b]) < 0.9 and b == 300  # the ramp is never a segment


def test_segment_stats_equal_plain_slices() -> None:
    rng = np.random.default_rng(3)
    t_ns = np.arange(500, dtype=np.int64) * 1_000_000
    T = rng.normal(100, 2, size=(500, 8))
    q = rng.normal(size=(500, 6))
    v = rng.uniform(0, 40, size=500)
    segs = [(10, 120), (200, 201 + 99), (400, 500)]
    st = segment_stats(t_ns, T, q, v, segs)
    for k, (a, b) in enumerate(segs):
        np.testing.assert_allclose(st.tension_mean_N[k], T[a:b].mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(st.tension_sd_N[k], T[a:b].std(axis=0, ddof=1), rtol=1e-8)
        np.testing.assert_allclose(st.pose_mean[k], q[a:b].mean(axis=0), atol=1e-12)
        assert st.n[k] == b - a and st.start_ns[k] == t_ns[a] and st.stop_ns[k] == t_ns[b - 1]


def test_nearest_tare_by_hand() -> None:
    q = np.zeros((4, 6))
    q[2, 4] = 0.1  # segment 2 is pitched: no tare at its pose
    is_tare = np.array([True, False, False, True])
    start = np.array([0, 10, 20, 30])
    assert nearest_tare(q, is_tare, start, 1e-3, 1e-3).tolist() == [0, 0, -1, 3]


def test_interpolate_holds_outside_and_is_linear_inside() -> None:
    out = interpolate_at([0, 5, 10, 20], [0, 10], [[1.0, 2.0], [3.0, 6.0]])
    np.testing.assert_allclose(out, [[1, 2], [2, 4], [3, 6], [3, 6]])


SCHEDULE = """
[schedule]
name = "analyze-test"
rate_hz = 200.0
tunnel_rate_hz = 10.0
method = "exact"
seed = 11

[sensor]
noise_sd_N = 0.05

[[segments]]
label = "tare"
tare = true
duration_s = 1.2
wind_mps = 0.0

[[segments]]
label = "v25"
duration_s = 1.2
wind_mps = 25.51
transition_s = 0.2

[[segments]]
label = "v41"
duration_s = 1.2
wind_mps = 41.42
transition_s = 0.2
"""


def _simulate(folder: Path, rig_name: str, extra: list[str] | None = None) -> None:
    """``cdpr simulate`` of SCHEDULE on a shipped rig into ``folder/runs``."""
    sched = folder / "schedule.toml"
    sched.write_text(SCHEDULE)
    rig = ROOT / "data_samples" / rig_name
    args = ["simulate", "--rig", str(rig), "--schedule", str(sched), "--out", str(folder / "runs")]
    assert main([*args, "--quiet", *(extra or [])]) == 0


@pytest.fixture(scope="module")
def simulated_run(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("sim")
    _simulate(d, "flat_experiment2.toml")
    (run,) = sorted((d / "runs").glob("*.mcap"))
    return run


def test_analyze_recovers_the_virtual_rigs_wrench(simulated_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "analysis"
    assert main(["analyze", str(simulated_run.parent), "--out", str(out)]) == 0
    folder = out / simulated_run.stem
    for f in (
        "segments.csv",
        "summary.json",
        "report.md",
        "tensions.png",
        "wrench.png",
        "check.png",
    ):
        assert (folder / f).stat().st_size > 0
    df = pd.read_csv(folder / "segments.csv")
    on = df[df.wind_off == 0]
    np.testing.assert_allclose(sorted(on.airspeed_mps), [25.51, 41.42], atol=0.3)
    assert (on.tare_segment == 0).all()  # both test points share the wind-off pose
    # the truth comes from the virtual rig's aero model, not from the analysis
    for c in ("fx_N", "fy_N", "fz_N"):
        err = np.abs(on[f"tare_{c}"] - on[f"true_{c}"])
        assert (err <= 5 * on[f"tare_sd_{c}"] + 0.02).all(), (c, err.tolist())
    assert (on["true_fx_N"] > 0.1).all()  # drag downstream is really there
    assert (df.check_max_abs_dT_N < 1.0).all()
    assert "pass" in (out / "index.md").read_text()


def test_analyze_bad_file_is_one_line_and_no_output(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "broken.mcap"
    bad.write_bytes(b"not an mcap file at all")
    out = tmp_path / "analysis"
    assert main(["analyze", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "broken.mcap" in err[0]
    assert not (out / "broken").exists()


def test_simulated_camera_poses_drive_the_analysis(tmp_path: Path) -> None:
    """A run with the virtual camera: the analysis takes the camera's /pose stream, and its poses
    match the virtual rig's truth within the vision figures (0.15 mm, 0.03 deg RMS)."""
    import json

    cam = ["--camera", str(ROOT / "data_samples" / "camera_virtual.json")]
    _simulate(
        tmp_path,
        "flat_optimum.toml",
        cam + ["--markers", str(ROOT / "data_samples" / "markers_flat_ir6.toml")],
    )
    out = tmp_path / "analysis"
    assert main(["analyze", str(tmp_path / "runs"), "--out", str(out)]) == 0
    (folder,) = [p for p in out.iterdir() if p.is_dir()]
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["pose_source"].startswith("camera")
    pe = summary["camera_pose_error_vs_truth"]
    assert pe["n_poses"] >= 10
    assert pe["position_rms_mm"] <= 0.15 and pe["rotation_rms_deg"] <= 0.03
    df = pd.read_csv(folder / "segments.csv")
    on = df[df.wind_off == 0]
    for c in ("fx_N", "fy_N", "fz_N"):
        err = np.abs(on[f"tare_{c}"] - on[f"true_{c}"])
        assert (err <= 5 * on[f"tare_sd_{c}"] + 0.05).all(), (c, err.tolist())


def test_camera_without_markers_is_refused(tmp_path: Path, capsys) -> None:
    rig = ROOT / "data_samples" / "flat_optimum.toml"
    args = [
        "simulate",
        "--rig",
        str(rig),
        "--schedule",
        str(ROOT / "data_samples" / "schedule_demo.toml"),
    ]
    args += [
        "--out",
        str(tmp_path / "runs"),
        "--camera",
        str(ROOT / "data_samples" / "camera_virtual.json"),
    ]
    assert main(args) == 2
    assert "--markers" in capsys.readouterr().err
    assert not list((tmp_path / "runs").glob("*.mcap")) if (tmp_path / "runs").exists() else True
