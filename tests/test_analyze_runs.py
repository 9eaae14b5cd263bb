"""``cdpr analyze`` on runs written through the normal MCAP writer from the independent generator
(tests/truth_rig.py): test-point events, the camera's covariance, a log starting mid-sample, a run
without tunnel data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from truth_rig import RIG_FILE, Sweep, alpha_sweep, exact_loadcell_calibration

from cdpr.analysis.conventions import WRENCH_COLUMNS
from cdpr.daq.mcap_io import McapRunWriter
from cdpr.daq.source import Reading
from cdpr.pipelines.cli import main

CABLES = [
    "front_left_top",
    "front_left_bottom",
    "front_right_top",
    "front_right_bottom",
    "back_left_top",
    "back_left_bottom",
    "back_right_top",
    "back_right_bottom",
]


def _H(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The paper's H: angular velocity in {O} from Euler-angle rates (alpha roll, beta, gamma)."""
    cb, sb, cg, sg = np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.array([[cb * cg, -sg, 0.0], [cb * sg, cg, 0.0], [-sb, 0.0, 1.0]])


def write_run(
    path: Path,
    sw: Sweep,
    events: bool = True,
    tunnel: bool = True,
    partial_first: bool = False,
    lost_every: int = 0,
) -> None:
    """``lost_every``: every so many camera frames is one without a pose (as the camera source
    gives it: NaN pose and covariance, flag no_pose, status bad frame)."""
    w = McapRunWriter(path)
    w.add_attachment(f"rig/{RIG_FILE.name}", sw.rig_text.encode())
    w.add_attachment(*exact_loadcell_calibration(CABLES))
    readings = []
    for i, t in enumerate(sw.t_ns):
        vals = {f"T_{c}_N": float(sw.tensions_N[i, k]) for k, c in enumerate(CABLES)}
        vals.update({f"status_{c}": 0 for c in CABLES})
        vals["seq"] = i
        if partial_first and i == 0:  # the log starts mid-sample: half the channels missing
            for c in CABLES[:4]:
                del vals[f"T_{c}_N"]
        readings.append(Reading("tensions", int(t), vals, 16 if partial_first and i == 0 else 0))
        if tunnel and i % 10 == 0:
            readings.append(
                Reading(
                    "tunnel",
                    int(t),
                    {"airspeed_mps": float(sw.airspeed_mps[i]), "density_kgpm3": 1.19},
                )
            )
        if i % 3 == 0:  # a 33 Hz camera
            q = sw.poses[i]
            xyzw = Rotation.from_euler("ZYX", [q[5], q[4], q[3]]).as_quat()
            C = np.zeros((6, 6))
            C[:3, :3] = sw.pose_cov[i, :3, :3]
            H = _H(*q[3:])
            C[3:, 3:] = H @ sw.pose_cov[i, 3:, 3:] @ H.T  # rotation-vector covariance in {O}
            lost = lost_every and (i // 3) % lost_every == lost_every - 1
            nan = float("nan")
            readings.append(
                Reading(
                    "pose",
                    int(t),
                    {
                        "position_O_m": [nan] * 3 if lost else q[:3].tolist(),
                        "quaternion_xyzw": [nan] * 4 if lost else xyzw.tolist(),
                        "covariance": [nan] * 36 if lost else C.reshape(-1).tolist(),
                        "flags": 1 if lost else 0,
                    },
                    8 if lost else 0,
                )
            )
    if events:
        for k, (a, b) in enumerate(zip(sw.start_ns, sw.stop_ns, strict=True)):
            base = {
                "name": "test_point",
                "point": f"P{k:02d}",
                "kind": sw.kind[k],
                "target_aoa_deg": float(np.rad2deg(sw.true_pose[k, 4])),
                "target_sideslip_deg": 0.0,
                "target_airspeed_mps": float(sw.speed_mps[k]),
                "repeat_of": "",
            }
            readings.append(Reading("events", int(a), {**base, "phase": "start"}))
            readings.append(Reading("events", int(b), {**base, "phase": "end"}))
    readings.sort(key=lambda r: r.t_ns)
    for r in readings:
        w.write(r)
    w.finish()


GEO = ["--area-m2", str(0.2441 * 0.0815), "--span-m", "0.2441", "--chord-m", "0.0815"]


@pytest.fixture(scope="module")
def sweep() -> Sweep:
    return alpha_sweep(21, rate_hz=50.0, point_s=2.0, ramp_s=0.6)


@pytest.fixture(scope="module")
def events_run(sweep: Sweep, tmp_path_factory) -> tuple[Path, Path, int, str]:
    """The sweep with events, tunnel and camera, analysed once: (run, output folder, exit code,
    stdout)."""
    import contextlib
    import io

    d = tmp_path_factory.mktemp("events")
    run = d / "sweep.mcap"
    write_run(run, sweep)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["analyze", str(run), "--out", str(d / "a"), *GEO])
    return run, d / "a" / "sweep", rc, buf.getvalue()


def test_events_define_the_points_and_the_accuracy_holds(
    sweep: Sweep, events_run: tuple[Path, Path, int, str]
) -> None:
    _, folder, rc, said = events_run
    assert rc == 0
    assert "(events), 0 with warnings" in said and "warning:" not in said
    df = pd.read_csv(folder / "points.csv")
    assert (df.source == "events").all() and list(df.point) == [f"P{k:02d}" for k in range(25)]
    on = (df.kind == "wind_on").to_numpy()
    err = df.loc[on, list(WRENCH_COLUMNS)].to_numpy() - sweep.true_wrench[on]
    assert np.abs(err[:, :3]).max() < 0.1 and np.abs(err[:, 3:]).max() < 0.005
    np.testing.assert_allclose(df.target_airspeed_mps[on], sweep.speed_mps[on])
    np.testing.assert_allclose(df.aoa_rad[on], np.deg2rad(df.target_aoa_deg[on]), atol=1e-3)
    # σ came from the camera's covariance (no nominal fallback) and is small
    assert not df["flags"].fillna("").str.contains("pose_cov_nominal").any()
    assert (df.loc[on, "sd_fz_N"] < 0.05).all()
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["reduction"]["point_source"] == "events"
    names = [s["stage"] for s in summary["reduction"]["stages"]]
    assert names.index("weight_model") < names.index("weight_tare") < names.index("coefficients")


def test_frames_without_a_pose_are_flagged_and_the_camera_covariance_kept(
    sweep: Sweep, tmp_path: Path
) -> None:
    """Every 10th camera frame without a pose (a covered mark): the points that lose frames say
    ``pose_flagged``, none falls back to a nominal pose σ (before: one such frame made the run's
    covariance count as missing, ``pose_cov_nominal`` on every point), the accuracy holds."""
    run = tmp_path / "lost.mcap"
    write_run(run, sweep, lost_every=10)
    assert main(["analyze", str(run), "--out", str(tmp_path / "a"), *GEO]) == 1  # the flags
    df = pd.read_csv(tmp_path / "a" / "lost" / "points.csv")
    flags = df["flags"].fillna("")
    assert not flags.str.contains("pose_cov_nominal").any()
    assert flags.str.contains("pose_flagged").sum() >= len(df) // 2
    on = (df.kind == "wind_on").to_numpy()
    err = df.loc[on, list(WRENCH_COLUMNS)].to_numpy() - sweep.true_wrench[on]
    assert np.abs(err[:, :3]).max() < 0.1 and np.abs(err[:, 3:]).max() < 0.005
    assert (df.loc[on, "sd_fz_N"] < 0.05).all()


def test_mid_sample_start_and_no_tunnel_say_so(sweep: Sweep, tmp_path: Path, capsys) -> None:
    run = tmp_path / "imported.mcap"
    write_run(run, sweep, tunnel=False, partial_first=True)
    assert main(["analyze", str(run), "--out", str(tmp_path / "a"), *GEO]) == 1
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if "no airspeed" in ln]
    assert len(lines) == 1
    df = pd.read_csv(tmp_path / "a" / "imported" / "points.csv")
    on = (df.kind == "wind_on").to_numpy()
    assert df.loc[on, "flags"].str.contains("no_airspeed").all()
    assert df.loc[on, "CL"].isna().all()
    # the wrench itself is tare-referenced and right; never zero
    err = df.loc[on, list(WRENCH_COLUMNS)].to_numpy() - sweep.true_wrench[on]
    assert np.abs(err[:, :3]).max() < 0.1
    assert "no airspeed" in (tmp_path / "a" / "imported" / "report.md").read_text()


def test_no_events_and_no_tunnel_reports_no_wind_on_wrench(
    sweep: Sweep, tmp_path: Path, capsys
) -> None:
    run = tmp_path / "bare.mcap"
    write_run(run, sweep, events=False, tunnel=False)
    assert main(["analyze", str(run), "--out", str(tmp_path / "a"), *GEO]) == 1
    out = capsys.readouterr().out
    assert "cannot be told apart" in out
    df = pd.read_csv(tmp_path / "a" / "bare" / "points.csv")
    assert (df.source == "detected").all() and len(df) == 25
    assert df[list(WRENCH_COLUMNS)].isna().all().all()  # NaN, never 0
    assert df["flags"].str.contains("no_tare").all()


def test_balance_calibration_with_second_order_is_applied(
    events_run: tuple[Path, Path, int, str], tmp_path: Path
) -> None:
    run, plain_folder, _, _ = events_run
    c = 0.01
    K2 = np.zeros((6, 21))
    K2[2, 2] = c  # index 2 of the upper triangle is Fx * Fz: Fz' = Fz + c Fx Fz
    doc = {
        "interaction_matrix": np.eye(6).tolist(),
        "second_order": {"K1": np.eye(6).tolist(), "K2": K2.tolist()},
    }
    bal = tmp_path / "balance.json"
    bal.write_text(json.dumps(doc))
    args = ["analyze", str(run), "--out", str(tmp_path / "cal"), "--balance", str(bal), *GEO]
    assert main(args) == 1  # a balance calibration without its fit covariance: said, exit 1
    plain = pd.read_csv(plain_folder / "points.csv")
    cal = pd.read_csv(tmp_path / "cal" / "sweep" / "points.csv")
    on = plain.kind == "wind_on"
    np.testing.assert_allclose(
        cal.fz_N[on], plain.fz_N[on] + c * plain.fx_N[on] * plain.fz_N[on], rtol=1e-9
    )
    np.testing.assert_allclose(cal.fx_N[on], plain.fx_N[on], rtol=1e-12)
    summary = json.loads((tmp_path / "cal" / "sweep" / "summary.json").read_text())
    notes = {s["stage"]: s["note"] for s in summary["reduction"]["stages"]}
    assert notes["balance_interaction"] == "second-order balance model applied"
    assert summary["balance_file"].startswith(str(bal))
    assert cal["flags"].str.contains("interaction_matrix_sd_not_given").all()
    assert (
        "no fit covariance (term left out)" in summary["systematic_sources"]["interaction_matrix"]
    )
