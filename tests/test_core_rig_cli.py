"""Rig files, the paper's rigs and the `cdpr solve` / `cdpr rig` commands (errors included)."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import rig_to_mapping
from cdpr.analysis.rigs import cubic_rig, flat_rig, paper_rigs
from cdpr.daq.schema import rig_from_mapping
from cdpr.pipelines.cli import main
from cdpr.pipelines.config import load_rig, rig_toml

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"


def _rig_dict() -> dict:
    return tomllib.loads((SAMPLES / "flat_optimum.toml").read_text())


def test_shipped_rig_files_match_the_builders() -> None:
    for stem, rig in paper_rigs().items():
        loaded = load_rig(SAMPLES / f"{stem}.toml")
        np.testing.assert_array_equal(loaded.anchors_O_m, rig.anchors_O_m)
        np.testing.assert_array_equal(loaded.attach_P_m, rig.attach_P_m)
        np.testing.assert_array_equal(loaded.t_max_N, rig.t_max_N)
        assert loaded.mass_kg == rig.mass_kg


def test_paper_numbers_in_the_flat_rigs() -> None:
    opt = load_rig(SAMPLES / "flat_optimum.toml")
    ys = opt.anchors_O_m[:, 1]
    front, back = opt.anchors_O_m[:, 0] == 0.0, opt.anchors_O_m[:, 0] == 1.0
    # paper: front base width 0.51 m (K21 = 51, w1 = 0.01), back 1.12 m (K22 = 28, w2 = 0.04)
    assert ys[front].max() - ys[front].min() == pytest.approx(0.51)
    assert ys[back].max() - ys[back].min() == pytest.approx(1.12)
    assert opt.anchors_O_m[:, 2].max() == pytest.approx(0.67)
    np.testing.assert_allclose(opt.reference_position_O_m, [0.5, 0.0, 0.335])
    assert opt.mass_kg == 0.64 and set(opt.t_min_N) == {35.0} and set(opt.t_max_N) == {300.0}
    exp2 = load_rig(SAMPLES / "flat_experiment2.toml")
    assert set(exp2.t_max_N) == {285.0}
    np.testing.assert_allclose(exp2.reference_position_O_m, [0.5, 0.0, 0.36])


def test_cubic_rig_dimensions() -> None:
    rig = cubic_rig(0.15, 0.075, 0.1)
    np.testing.assert_allclose(np.ptp(rig.attach_P_m, axis=0), [0.3, 0.09, 0.14])
    np.testing.assert_allclose(np.ptp(rig.anchors_O_m, axis=0), [2.0, 1.2, 1.4])
    np.testing.assert_allclose(rig.reference_position_O_m, [0, 0, 0.7])


def test_round_trip_through_toml() -> None:
    rig = flat_rig(61, 34, 0.72, 0.5, t_max_N=285.0)
    again = rig_from_mapping(tomllib.loads(rig_toml(rig)), "round-trip")
    assert rig_to_mapping(again) == rig_to_mapping(rig)


@pytest.mark.parametrize(
    ("edit", "key", "problem"),
    [
        (lambda d: d["platform"].update(mass_kg=0.0), "platform.mass_kg", "must be > 0"),
        (lambda d: d["cables"][2].update(t_min_N=400.0), "cables[2].t_min_N", "must be <"),
        (
            lambda d: d["cables"][1].update(anchor_O_m=[0.0, 1.0]),
            "cables[1].anchor_O_m",
            "3 numbers",
        ),
        (lambda d: d["rig"].update(colour="red"), "rig.colour", "unknown key"),
        (lambda d: d["cables"][0].pop("t_max_N"), "cables[0].t_max_N", "missing"),
        (
            lambda d: d["cables"][3].update(anchor_O_m=[0.485, -0.005, 0.335]),
            "cables[3]",
            "zero-length",
        ),
        (
            lambda d: d["platform"].update(inertia_P_kgm2=[[1, 2, 0], [0, 1, 0], [0, 0, 1]]),
            "inertia",
            "symmetric",
        ),
    ],
)
def test_rig_errors_name_file_key_and_problem(edit, key, problem) -> None:
    d = _rig_dict()
    edit(d)
    with pytest.raises(ConfigError) as info:
        rig_from_mapping(d, "my_rig.toml")
    msg = str(info.value)
    assert msg.startswith("my_rig.toml: ") and key in msg and problem in msg


def _write_rig(tmp_path: Path, d: dict) -> Path:
    import tomli_w

    p = tmp_path / "rig.toml"
    p.write_text(tomli_w.dumps(d))
    return p


def test_cli_bad_rig_exits_2_with_one_line(tmp_path: Path, capsys) -> None:
    d = _rig_dict()
    d["platform"]["mass_kg"] = -1.0
    rig = _write_rig(tmp_path, d)
    out = tmp_path / "t.csv"
    assert main(["solve", "--rig", str(rig), "--method", "closed-form", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(rig) in err[0] and "platform.mass_kg" in err[0]
    assert not out.exists()


def _poses_csv(tmp_path: Path, rows: list[list[float]], header: str | None = None) -> Path:
    p = tmp_path / "poses.csv"
    head = header or "x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad"
    p.write_text(head + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    return p


def test_cli_solve_closed_form_is_in_equilibrium(tmp_path: Path) -> None:
    rows = [[0.5, 0.0, 0.335, 0, 0, 0], [0.52, 0.01, 0.33, 0.01, -0.02, 0.03]]
    poses = _poses_csv(tmp_path, rows)
    out = tmp_path / "t.csv"
    rigf = SAMPLES / "flat_optimum.toml"
    code = main(
        [
            "solve",
            "--rig",
            str(rigf),
            "--poses",
            str(poses),
            "--method",
            "closed-form",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    df = pd.read_csv(out, comment="#")
    rig = load_rig(rigf)
    T = df[[f"T_{n}_N" for n in rig.cable_names]].to_numpy()
    # Independent check of equilibrium: sum of cable forces balances the weight (0.64 kg * g)
    from cdpr.analysis.rotations import rotation_from_euler

    p = np.array(rows, dtype=float)
    R = rotation_from_euler(p[:, 3:])
    l = rig.anchors_O_m - p[:, None, :3] - np.einsum("nij,mj->nmi", R, rig.attach_P_m)
    u = l / np.linalg.norm(l, axis=-1, keepdims=True)
    F = np.einsum("nm,nmi->ni", T, u)
    np.testing.assert_allclose(F, np.tile([0, 0, 0.64 * 9.80665], (2, 1)), atol=1e-8)
    # and their moments about P cancel (the centre of mass is at P: gravity has no moment there)
    r = np.einsum("nij,mj->nmi", R, rig.attach_P_m)
    M = np.einsum("nm,nmi->ni", T, np.cross(r, u))
    np.testing.assert_allclose(M, 0.0, atol=1e-9)
    assert np.allclose(rig.com_P_m, 0.0)
    assert df["feasible"].iloc[0] == 1  # the reference pose is feasible wind-off


def test_cli_solve_missing_column_and_nan(tmp_path: Path, capsys) -> None:
    rigf = str(SAMPLES / "flat_optimum.toml")
    out = tmp_path / "t.csv"
    bad = _poses_csv(tmp_path, [[0.5, 0, 0.3, 0, 0]], header="x_m,y_m,z_m,roll_rad,pitch_rad")
    assert (
        main(
            [
                "solve",
                "--rig",
                rigf,
                "--poses",
                str(bad),
                "--method",
                "closed-form",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "column yaw_rad" in capsys.readouterr().err
    nan = _poses_csv(tmp_path, [[0.5, 0, 0.3, 0, 0, 0], [0.5, 0, "nan", 0, 0, 0]])
    assert (
        main(
            [
                "solve",
                "--rig",
                rigf,
                "--poses",
                str(nan),
                "--method",
                "closed-form",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "row 3, column z_m" in err and str(nan) in err
    assert not out.exists()


def test_cli_solve_flags_infeasible_rows(tmp_path: Path, capsys) -> None:
    rigf = str(SAMPLES / "flat_optimum.toml")
    poses = _poses_csv(tmp_path, [[0.5, 0, 0.335, 0, 0, 0]] * 2)
    wrench = tmp_path / "w.csv"
    wrench.write_text("fx_N,fy_N,fz_N,mx_Nm,my_Nm,mz_Nm\n0,0,0,0,0,0\n0,0,0,0,0,50\n")
    out = tmp_path / "t.csv"
    args = ["solve", "--rig", rigf, "--poses", str(poses), "--wrench", str(wrench)]
    assert main([*args, "--method", "closed-form", "--out", str(out)]) == 0
    assert list(pd.read_csv(out, comment="#")["feasible"]) == [1, 0]
    assert "1 of 2 poses infeasible" in capsys.readouterr().err
    out2 = tmp_path / "t2.csv"
    assert main([*args, "--method", "closed-form", "--strict", "--out", str(out2)]) == 2
    assert not out2.exists()


def test_console_script_runs_in_a_subprocess(tmp_path: Path) -> None:
    out = tmp_path / "rigs"
    r = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "rig", "paper", "--out", str(out)],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "flat_optimum.toml" in r.stdout
    assert (out / "flat_optimum.toml").read_text() == (SAMPLES / "flat_optimum.toml").read_text()
