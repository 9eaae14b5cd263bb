"""``cdpr wrench`` end to end: known loads come back, standard deviations by hand, bad input exits 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
G0 = 9.80665
MASS = 0.64  # flat_optimum.toml, com at P
NAMES = [
    "front_left_top",
    "front_left_bottom",
    "front_right_top",
    "front_right_bottom",
    "back_left_top",
    "back_left_bottom",
    "back_right_top",
    "back_right_bottom",
]
WF, WB, H, L = 0.51, 1.12, 0.67, 1.0  # K21 w1, K22 w2, H, L of flat_optimum.toml
ANCHORS = np.array(
    [[x, sy * w / 2, z] for x, w in ((0.0, WF), (L, WB)) for sy in (1, -1) for z in (H, 0.0)]
)
ATTACH = np.array(
    [
        [x, sy * w, 0.0]
        for x, w in ((-0.015, 0.005), (0.015, 0.02))
        for sy in (1, -1)
        for _ in (0, 1)
    ]
)


def _A(q: np.ndarray) -> np.ndarray:
    """Structure matrix written out independently (scipy rotation, per-cable loop)."""
    R = Rotation.from_euler("ZYX", q[3:][::-1]).as_matrix()
    cols = []
    for b, pp in zip(ANCHORS, ATTACH, strict=True):
        r = R @ pp
        d = b - q[:3] - r
        u = d / np.linalg.norm(d)
        cols.append(np.concatenate([u, np.cross(r, u)]))
    return np.array(cols).T


def _write(tmp: Path, n: int = 4, seed: int = 1, load: np.ndarray | None = None):
    """Pose, wind-on and wind-off tension CSVs for known loads (random, or ``load`` at P_ref)."""
    rng = np.random.default_rng(seed)
    q = np.column_stack(
        [
            0.5 + rng.normal(0, 0.005, n),
            rng.normal(0, 0.005, n),
            0.335 + rng.normal(0, 0.005, n),
            rng.normal(0, 0.01, (n, 3)),
        ]
    )
    W = rng.normal(0, [2.0, 0.3, 3.0, 0.005, 0.02, 0.005], (n, 6))
    if load is not None:
        q = np.tile([0.5, 0.0, 0.335, 0.0, 0.0, 0.0], (n, 1))
        W = np.tile(load, (n, 1))
    G = np.array([0, 0, -MASS * G0, 0, 0, 0])
    Tw, T0 = [], []
    for i in range(n):
        A = _A(q[i])
        Ap = np.linalg.pinv(A)
        mid = np.full(8, 160.0)
        Tw.append(mid + Ap @ (-(G + W[i]) - A @ mid))
        T0.append(mid + Ap @ (-G - A @ mid))
    cols = ["x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]
    poses = pd.DataFrame(q, columns=cols)
    poses.insert(0, "t_ns", np.arange(n, dtype=np.int64) * 10_000_000)
    poses.to_csv(tmp / "poses.csv", index=False)
    tcols = [f"T_{c}_N" for c in NAMES]
    pd.DataFrame(np.array(Tw), columns=tcols).to_csv(tmp / "T.csv", index=False)
    pd.DataFrame(np.array(T0), columns=tcols).to_csv(tmp / "T0.csv", index=False)
    return q, W, np.array(Tw), np.array(T0)


def _read(path: Path) -> pd.DataFrame:
    return pd.read_csv(path, comment="#")


WCOLS = ["fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm"]


def test_absolute_and_tare_recover_the_load(tmp_path: Path) -> None:
    q, W, Tw, T0 = _write(tmp_path)
    base = ["wrench", "--rig", str(RIG), "--poses", str(tmp_path / "poses.csv")]
    base += ["--tensions", str(tmp_path / "T.csv")]
    assert main([*base, "--out", str(tmp_path / "abs.csv")]) == 0
    assert (
        main([*base, "--tare", str(tmp_path / "T0.csv"), "--out", str(tmp_path / "tare.csv")]) == 0
    )
    for name in ("abs.csv", "tare.csv"):
        df = _read(tmp_path / name)
        np.testing.assert_allclose(df[WCOLS].to_numpy(), W, atol=1e-6)
        assert list(df.columns[:7]) == [
            "t_ns",
            "x_m",
            "y_m",
            "z_m",
            "roll_rad",
            "pitch_rad",
            "yaw_rad",
        ]
        assert [f"sd_{c}" for c in WCOLS] == list(df.columns[-6:])
        assert (df[[f"sd_{c}" for c in WCOLS]].to_numpy() > 0).all()
    text = (tmp_path / "tare.csv").read_text()
    assert "# method: tare" in text and "sha256=" in text


def test_standard_deviation_from_tension_noise_by_hand(tmp_path: Path) -> None:
    # pose noise off: sd = sqrt(diag(A A^T)) sigma_T (absolute), sqrt(2) times that with a tare
    q, _, _, _ = _write(tmp_path, n=2)
    s = 0.2
    args = ["wrench", "--rig", str(RIG), "--poses", str(tmp_path / "poses.csv")]
    args += ["--tensions", str(tmp_path / "T.csv"), "--tension-sigma-N", str(s)]
    args += ["--pose-sigma-m", "0", "--pose-sigma-rad", "0"]
    assert main([*args, "--out", str(tmp_path / "a.csv")]) == 0
    assert main([*args, "--tare", str(tmp_path / "T0.csv"), "--out", str(tmp_path / "b.csv")]) == 0
    sd_cols = [f"sd_{c}" for c in WCOLS]
    for i in range(2):
        A = _A(q[i])
        expect = s * np.sqrt(np.sum(A * A, axis=1))
        np.testing.assert_allclose(
            _read(tmp_path / "a.csv")[sd_cols].to_numpy()[i], expect, rtol=1e-9
        )
        np.testing.assert_allclose(
            _read(tmp_path / "b.csv")[sd_cols].to_numpy()[i], np.sqrt(2) * expect, rtol=1e-9
        )


def test_dynamic_option_on_a_static_series_changes_nothing(tmp_path: Path) -> None:
    q, W, Tw, _ = _write(tmp_path, n=5)
    # make the platform static: same pose in every row, so M qdd + C = 0
    df = pd.read_csv(tmp_path / "poses.csv")
    for c in ["x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]:
        df[c] = df[c].iloc[0]
    df.to_csv(tmp_path / "static.csv", index=False)
    A = _A(q[0])
    G = np.array([0, 0, -MASS * G0, 0, 0, 0])
    expect = -(Tw @ A.T) - G
    args = ["wrench", "--rig", str(RIG), "--poses", str(tmp_path / "static.csv"), "--dynamic"]
    args += ["--tensions", str(tmp_path / "T.csv"), "--out", str(tmp_path / "d.csv")]
    assert main(args) == 0
    np.testing.assert_allclose(_read(tmp_path / "d.csv")[WCOLS].to_numpy(), expect, atol=1e-9)


def test_dynamic_option_adds_m_a_of_an_accelerating_platform(tmp_path: Path) -> None:
    """Pure translation with constant acceleration a (no rotation, centre of mass at P): the inertia
    wrench is (m a, 0) by hand, and Newton (A T + G + W_ext = m a) makes --dynamic give the
    absolute result plus m a at every row."""
    a = np.array([0.8, -0.3, 0.5])  # m/s^2
    n, dt = 7, 0.01
    t = np.arange(n) * dt
    q = np.zeros((n, 6))
    q[:, :3] = [0.5, 0.0, 0.335] + 0.5 * a * t[:, None] ** 2  # x = x0 + a t^2 / 2
    poses = pd.DataFrame(q, columns=["x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"])
    poses.insert(0, "t_ns", np.arange(n, dtype=np.int64) * 10_000_000)
    poses.to_csv(tmp_path / "p.csv", index=False)
    T = np.full((n, 8), 150.0)
    pd.DataFrame(T, columns=[f"T_{c}_N" for c in NAMES]).to_csv(tmp_path / "T.csv", index=False)
    args = ["wrench", "--rig", str(RIG), "--poses", str(tmp_path / "p.csv")]
    args += ["--tensions", str(tmp_path / "T.csv")]
    assert main([*args, "--dynamic", "--out", str(tmp_path / "d.csv")]) == 0
    G = np.array([0, 0, -MASS * G0, 0, 0, 0])
    absolute = np.array([-(_A(q[i]) @ T[i]) - G for i in range(n)])  # independent A
    expect = absolute + np.concatenate([MASS * a, np.zeros(3)])
    got = _read(tmp_path / "d.csv")[WCOLS].to_numpy()
    np.testing.assert_allclose(got, expect, rtol=0, atol=1e-6)
    assert np.abs(absolute - expect).max() > 0.5  # the correction is really there (m a ~ 0.5 N)


def _run_bad(tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str]) -> str:
    out = tmp_path / "out.csv"
    args = ["wrench", "--rig", str(RIG), "--poses", str(tmp_path / "poses.csv")]
    code = main([*args, *extra, "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert not out.exists()
    assert not list(tmp_path.glob(".out.csv.*"))
    assert len(err.splitlines()) == 1
    return err


def test_bad_inputs_exit_2_naming_file_row_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write(tmp_path)
    T = pd.read_csv(tmp_path / "T.csv")
    # missing column
    T.drop(columns=["T_back_left_top_N"]).to_csv(tmp_path / "miss.csv", index=False)
    err = _run_bad(tmp_path, capsys, ["--tensions", str(tmp_path / "miss.csv")])
    assert "miss.csv" in err and "T_back_left_top_N" in err and "missing" in err
    # NaN in row 3 (data row 2 -> spreadsheet row 3 counting the header)
    bad = T.copy()
    bad.loc[1, "T_front_right_top_N"] = np.nan
    bad.to_csv(tmp_path / "nan.csv", index=False)
    err = _run_bad(tmp_path, capsys, ["--tensions", str(tmp_path / "nan.csv")])
    assert "nan.csv" in err and "row 3" in err and "T_front_right_top_N" in err
    # a ninth cable: wrong count of cables
    extra = T.copy()
    extra["T_spare_N"] = 100.0
    extra.to_csv(tmp_path / "nine.csv", index=False)
    err = _run_bad(tmp_path, capsys, ["--tensions", str(tmp_path / "nine.csv")])
    assert "nine.csv" in err and "T_spare_N" in err
    # row count mismatch (3 tension rows for 4 poses)
    T.iloc[:3].to_csv(tmp_path / "short.csv", index=False)
    err = _run_bad(tmp_path, capsys, ["--tensions", str(tmp_path / "short.csv")])
    assert "short.csv" in err and "rows" in err and "expected 4" in err
    # tare with 2 rows for 4 poses
    T.iloc[:2].to_csv(tmp_path / "tare2.csv", index=False)
    err = _run_bad(
        tmp_path,
        capsys,
        ["--tensions", str(tmp_path / "T.csv"), "--tare", str(tmp_path / "tare2.csv")],
    )
    assert "tare2.csv" in err and "rows" in err
    # bad pose value in the pose file
    lines = (tmp_path / "poses.csv").read_text().splitlines()
    head = lines[0].split(",")
    row = lines[4].split(",")  # the 4th data row, spreadsheet row 5
    row[head.index("pitch_rad")] = "abc"
    lines[4] = ",".join(row)
    (tmp_path / "poses.csv").write_text("\n".join(lines) + "\n")
    err = _run_bad(tmp_path, capsys, ["--tensions", str(tmp_path / "T.csv")])
    assert "poses.csv" in err and "row 5" in err and "pitch_rad" in err


def test_subprocess_exit_code_and_message(tmp_path: Path) -> None:
    _write(tmp_path)
    pd.read_csv(tmp_path / "T.csv").drop(columns=["T_front_left_top_N"]).to_csv(
        tmp_path / "miss.csv", index=False
    )
    out = tmp_path / "w.csv"
    proc = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "wrench", "--rig", str(RIG)]
        + ["--poses", str(tmp_path / "poses.csv"), "--tensions", str(tmp_path / "miss.csv")]
        + ["--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1
    assert "miss.csv" in proc.stderr and "T_front_left_top_N" in proc.stderr
    assert not out.exists()


def test_aero_coefficients_by_hand(tmp_path: Path) -> None:
    # level platform, 2 N drag, 3 N lift, 0.01 N m about +y_O (= +y_B: nose-up pitching moment)
    _write(tmp_path, n=2, load=np.array([2.0, 0.0, 3.0, 0.0, 0.01, 0.0]))
    V, p, T, S, b, c = 20.0, 101325.0, 288.15, 0.02, 0.2441, 0.08
    q = 0.5 * p / (287.05287 * T) * V**2  # ideal gas, about 245 Pa
    args = ["wrench", "--rig", str(RIG), "--poses", str(tmp_path / "poses.csv")]
    args += ["--tensions", str(tmp_path / "T.csv"), "--tare", str(tmp_path / "T0.csv")]
    args += ["--airspeed-mps", str(V), "--pressure-Pa", str(p), "--temperature-K", str(T)]
    args += ["--area-m2", str(S), "--span-m", str(b), "--chord-m", str(c)]
    assert main([*args, "--out", str(tmp_path / "aero.csv")]) == 0
    df = _read(tmp_path / "aero.csv")
    np.testing.assert_allclose(df["aoa_rad"], 0.0, atol=1e-12)
    np.testing.assert_allclose(df["sideslip_rad"], 0.0, atol=1e-12)
    np.testing.assert_allclose(df["CD"], 2.0 / (q * S), rtol=1e-6)
    np.testing.assert_allclose(df["CL"], 3.0 / (q * S), rtol=1e-6)
    np.testing.assert_allclose(df["Cm"], 0.01 / (q * S * c), rtol=1e-5)
    np.testing.assert_allclose(df[["CY", "Cl", "Cn"]].to_numpy(), 0.0, atol=1e-6)
    # at zero angles with the MRP at P the coefficients are scaled wrench components
    np.testing.assert_allclose(df["sd_CD"], df["sd_fx_N"] / (q * S), rtol=1e-6)
    np.testing.assert_allclose(df["sd_CL"], df["sd_fz_N"] / (q * S), rtol=1e-6)
    np.testing.assert_allclose(df["sd_Cl"], df["sd_mx_Nm"] / (q * S * b), rtol=1e-6)
    np.testing.assert_allclose(df["sd_Cm"], df["sd_my_Nm"] / (q * S * c), rtol=1e-6)
    assert "# aero: V 20 m/s" in (tmp_path / "aero.csv").read_text()


def test_aero_options_incomplete_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _write(tmp_path, n=2)
    err = _run_bad(
        tmp_path,
        capsys,
        ["--tensions", str(tmp_path / "T.csv"), "--airspeed-mps", "20", "--density-kgpm3", "1.2"],
    )
    assert "--area-m2" in err
    err = _run_bad(tmp_path, capsys, ["--tensions", str(tmp_path / "T.csv"), "--span-m", "0.2"])
    assert "--span-m" in err and "--airspeed-mps" in err


def test_single_tare_row_for_differing_poses_warns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write(tmp_path, n=3)
    pd.read_csv(tmp_path / "T0.csv").iloc[:1].to_csv(tmp_path / "T0one.csv", index=False)
    args = ["wrench", "--rig", str(RIG), "--poses", str(tmp_path / "poses.csv")]
    args += ["--tensions", str(tmp_path / "T.csv"), "--tare", str(tmp_path / "T0one.csv")]
    assert main([*args, "--out", str(tmp_path / "w.csv")]) == 0
    assert "one tare row" in capsys.readouterr().err
    assert len(_read(tmp_path / "w.csv")) == 3
