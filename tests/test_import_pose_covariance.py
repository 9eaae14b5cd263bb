"""The camera's pose covariance through the lab path (issue 21 item 3): ``cdpr import --poses`` reads
``cov_00 .. cov_55`` (a 6x6 covariance of ``(x, y, z, roll, pitch, yaw)`` per row), stores it in the
recorder's ``/pose`` parametrisation ``[position, rotation vector in {O}]``, and ``cdpr analyze``
gives each point the pose σ a hand computation gives; ``--pose-sd`` states one when the CSV has
none; a half-filled set is one line, exit 2, no run.

The parametrisation change is checked against a numerical Jacobian built with scipy's ``Rotation``
(independent of :mod:`cdpr.analysis.rotations`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation
from test_humidity_flow import MATRIX, _can_log  # the same CAN log and test matrix

from cdpr.analysis.rotations import pose_cov_from_euler, pose_cov_to_euler
from cdpr.daq.run_reader import open_run
from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
T_LOG0_NS = 1_700_000_000_000_000_000
COV = [f"cov_{i}{j}" for i in range(6) for j in range(6)]
#: the pose of every row (a tilted platform: H differs from the identity everywhere)
POSE = (0.50, 0.0, 0.335, 0.02, -0.03, 0.04)


def _rotvec_jacobian(psi: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """d(rotation vector in {O}, left perturbation R' = exp([dtheta]x) R) / d(roll, pitch, yaw),
    by central differences of scipy rotations."""

    def R(p: np.ndarray) -> Rotation:
        return Rotation.from_euler("ZYX", [p[2], p[1], p[0]])  # R = Rz(yaw) Ry(pitch) Rx(roll)

    J = np.zeros((3, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        plus = (R(psi + e) * R(psi).inv()).as_rotvec()
        minus = (R(psi - e) * R(psi).inv()).as_rotvec()
        J[:, k] = (plus - minus) / (2 * eps)
    return J


def _spd(rng: np.random.Generator, sd: np.ndarray) -> np.ndarray:
    """A covariance with standard deviations ``sd`` and random correlations."""
    A = rng.normal(size=(6, 6))
    corr = A @ A.T
    d = np.sqrt(np.diag(corr))
    corr = corr / d[:, None] / d[None, :]
    return corr * sd[:, None] * sd[None, :]


def test_euler_covariance_to_rotation_vector_matches_a_numerical_jacobian() -> None:
    rng = np.random.default_rng(4)
    sd = np.array([5e-5, 4e-5, 6e-5, 2e-4, 3e-4, 1e-4])
    for _ in range(20):
        psi = rng.uniform([-1.0, -1.2, -3.0], [1.0, 1.2, 3.0])
        C = _spd(rng, sd)
        J = np.eye(6)
        J[3:, 3:] = _rotvec_jacobian(psi)
        want = J @ C @ J.T
        got = pose_cov_from_euler(psi, C)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-8 * np.abs(want).max())
        np.testing.assert_allclose(pose_cov_to_euler(psi, got), C, rtol=1e-10, atol=1e-20)


EVENTS = """t_s,point,phase,kind,target_aoa_deg,target_sideslip_deg,target_airspeed_mps,repeat_of
0.05,t0,start,tare,0,0,0,
0.25,t0,end,tare,0,0,0,
0.40,a,start,wind_on,0,0,25,
0.60,a,end,wind_on,0,0,25,
"""
TUNNEL = "t_s,airspeed_mps,density_kgpm3\n0.0,0.0,1.2\n0.3,25.0,1.2\n1.2,25.0,1.2\n"


def _pose_rows(cov_of: list[np.ndarray] | None) -> tuple[np.ndarray, list[str]]:
    """A pose CSV at 50 Hz over 1 s (times t_s), with the covariance ``cov_of[k]`` of row k."""
    t = np.round(np.arange(50) * 0.02, 6)
    head = "t_s,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad" + ("," + ",".join(COV) if cov_of else "")
    rows = [head]
    for k, tk in enumerate(t):
        cells = [f"{tk:.6f}", *(repr(v) for v in POSE)]
        if cov_of:
            cells += [repr(float(v)) for v in cov_of[k].reshape(-1)]
        rows.append(",".join(cells))
    return t, rows


def _import_and_analyze(tmp: Path, rows: list[str], extra: list[str]) -> tuple[Path, pd.DataFrame]:
    log = tmp / "run.log"
    _can_log(log, 110)
    (tmp / "poses.csv").write_text("\n".join(rows) + "\n")
    (tmp / "events.csv").write_text(EVENTS)
    (tmp / "tunnel.csv").write_text(TUNNEL)
    (tmp / "matrix.toml").write_text(MATRIX)
    run = tmp / "run.mcap"
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    argv += ["--poses", str(tmp / "poses.csv"), "--events", str(tmp / "events.csv")]
    argv += ["--tunnel", str(tmp / "tunnel.csv"), *extra, "--out", str(run)]
    assert main(argv) == 0
    main(["analyze", str(run), "--out", str(tmp / "out"), "--matrix", str(tmp / "matrix.toml")])
    return run, pd.read_csv(tmp / "out" / "run" / "points.csv").set_index("point")


def _frames_in(t_rel_s: np.ndarray, point: pd.Series) -> np.ndarray:
    """Rows of the pose CSV inside the point's span (its first and last tension sample times)."""
    t_ns = T_LOG0_NS + np.round(t_rel_s * 1e9).astype(np.int64)
    return (t_ns >= int(point.start_ns)) & (t_ns <= int(point.stop_ns))


SD_COLUMNS = ["sd_x_m", "sd_y_m", "sd_z_m", "sd_roll_rad", "sd_pitch_rad", "sd_yaw_rad"]


def test_a_pose_csv_with_covariance_round_trips_to_the_point_sigma(tmp_path: Path) -> None:
    """Per-row covariances with correlations (two cameras' worth: the first half of the rows noisier
    than the second): the /pose covariance is J C J^T (numerical J), and each point's pose σ is
    sqrt(mean of the frames' variances / frames) by hand."""
    rng = np.random.default_rng(11)
    sd1 = np.array([5e-5, 4e-5, 6e-5, np.deg2rad(0.01), np.deg2rad(0.012), np.deg2rad(0.008)])
    covs = [_spd(rng, sd1 * (2.0 if k < 25 else 1.0) * (1 + 0.1 * (k % 3))) for k in range(50)]
    t, rows = _pose_rows(covs)
    run, pts = _import_and_analyze(tmp_path, rows, [])
    with open_run(run) as r:
        pose = r.table("/pose")
        meta = r.metadata["run"]
    assert "cov_00 .. cov_55" in meta["pose_covariance"]
    J = np.eye(6)
    J[3:, 3:] = _rotvec_jacobian(np.array(POSE[3:]))
    stored = pose[COV].to_numpy().reshape(-1, 6, 6)
    want = np.array([J @ C @ J.T for C in covs])
    np.testing.assert_allclose(stored, want, rtol=1e-7, atol=1e-7 * np.abs(want).max())
    for label in ("t0", "a"):
        pt = pts.loc[label]
        use = _frames_in(t, pt)
        n = int(use.sum())
        assert n == int(pt.n_pose_frames) and n >= 8
        mean_var = np.mean([np.diag(covs[k]) for k in np.flatnonzero(use)], axis=0)
        np.testing.assert_allclose(pt[SD_COLUMNS].to_numpy(float), np.sqrt(mean_var / n),
                                   rtol=1e-7)  # fmt: skip
        assert "pose_cov_nominal" not in str(pt["flags"]).split(";")


def test_pose_sd_stamps_a_stated_covariance_and_none_is_flagged(tmp_path: Path, capsys) -> None:
    sd = [1e-4, 2e-4, 3e-4, 1e-4, 2e-4, 3e-4]
    t, rows = _pose_rows(None)
    (tmp_path / "a").mkdir()
    run, pts = _import_and_analyze(tmp_path / "a", rows, ["--pose-sd", *map(str, sd)])
    with open_run(run) as r:
        assert "--pose-sd" in r.metadata["run"]["pose_covariance"]
    for label in ("t0", "a"):
        pt = pts.loc[label]
        n = int(_frames_in(t, pt).sum())
        np.testing.assert_allclose(pt[SD_COLUMNS].to_numpy(float), np.array(sd) / np.sqrt(n),
                                   rtol=1e-7)  # fmt: skip
        assert "pose_cov_nominal" not in str(pt["flags"]).split(";")
    # neither: imported as before, said at import, flagged by the analysis
    (tmp_path / "b").mkdir()
    capsys.readouterr()
    run, pts = _import_and_analyze(tmp_path / "b", rows, [])
    assert "no covariance columns" in capsys.readouterr().out
    with open_run(run) as r:
        assert "covariance" not in json.dumps(list(r.table("/pose").columns))
        assert r.metadata["run"]["pose_covariance"].startswith("none")
    assert all("pose_cov_nominal" in str(f).split(";") for f in pts["flags"])


def _refused(tmp: Path, capsys, rows: list[str], extra: list[str] = ()) -> str:
    log = tmp / "run.log"
    _can_log(log, 20)
    (tmp / "poses.csv").write_text("\n".join(rows) + "\n")
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    argv += ["--poses", str(tmp / "poses.csv"), *extra, "--out", str(tmp / "run.mcap")]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert sorted(p.name for p in tmp.iterdir()) == ["poses.csv", "run.log"]
    return err[0]


def _edit(rows: list[str], row: int, column: str, value: str) -> list[str]:
    out = [r.split(",") for r in rows]
    j = out[0].index(column)
    out[row - 1][j] = value  # row as a spreadsheet counts it (the header is row 1)
    return [",".join(r) for r in out]


def test_a_half_filled_covariance_is_refused_in_one_line(tmp_path: Path, capsys) -> None:
    rng = np.random.default_rng(2)
    covs = [_spd(rng, np.array([1e-4] * 3 + [2e-4] * 3)) for _ in range(50)]
    _, rows = _pose_rows(covs)
    cases = []
    # a column left out
    j = rows[0].split(",").index("cov_34")
    cases.append(([",".join(c for i, c in enumerate(r.split(",")) if i != j) for r in rows],
                  "poses.csv: column cov_34: missing", []))  # fmt: skip
    cases.append(
        (_edit(rows, 6, "cov_22", ""), "poses.csv: row 6, column cov_22: expected a finite", [])
    )
    cases.append(
        (_edit(rows, 9, "cov_05", "nan"), "poses.csv: row 9, column cov_05: expected a finite", [])
    )
    cases.append(
        (_edit(rows, 4, "cov_12", "1e-3"), "poses.csv: row 4, column cov_12: not symmetric", [])
    )
    cases.append(
        (_edit(rows, 3, "cov_33", "-1e-8"), "poses.csv: row 3, column cov_33: negative", [])
    )
    cases.append((rows, "--pose-sd: ", ["--pose-sd", *["1e-4"] * 6]))
    for k, (bad_rows, needle, extra) in enumerate(cases):
        d = tmp_path / f"c{k}"
        d.mkdir()
        line = _refused(d, capsys, bad_rows, extra)
        assert needle in line, (k, line)
