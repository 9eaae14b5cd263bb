"""Load-cell zero/gain calibration and check loads on the whole balance."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cdpr.analysis.conventions import POSE_COLUMNS, WRENCH_COLUMNS
from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rigs import flat_rig
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.tension import distribute
from cdpr.calibration.balance_fit import check_loads, fit_load_cell
from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
RIG_FILE = ROOT / "data_samples" / "flat_optimum.toml"


def test_exact_line_by_hand() -> None:
    load = np.array([0.0, 50.0, 100.0, 200.0])
    counts = 1000.0 + load / 5e-5  # 20000 counts per N, zero at 1000 counts
    f = fit_load_cell(load, counts)
    assert f.gain_N_per_count == pytest.approx(5e-5, rel=1e-12)
    assert f.offset_counts == pytest.approx(1000.0, abs=1e-6)
    assert f.residual_rms_N < 1e-9 and f.nonlinearity_pct < 1e-9


def test_noisy_fit_agrees_with_polyfit_and_its_covariance() -> None:
    rng = np.random.default_rng(2)
    load = np.repeat([0.0, 20.0, 50.0, 100.0, 150.0, 200.0, 300.0], 3)
    counts = 2500.0 + load / 4e-5 + rng.normal(0, 300, size=load.size)
    f = fit_load_cell(load, counts)
    slope, icpt = np.polyfit(counts, load, 1)
    assert f.gain_N_per_count == pytest.approx(slope, rel=1e-10)
    assert f.offset_counts == pytest.approx(-icpt / slope, rel=1e-9)
    _, cov = np.polyfit(counts, load, 1, cov=True)
    assert f.sd_gain_N_per_count == pytest.approx(np.sqrt(cov[0, 0]), rel=1e-6)


def test_fit_refuses_too_few_loads() -> None:
    from cdpr.analysis.errors import InputError

    with pytest.raises(InputError, match="at least 3 distinct loads"):
        fit_load_cell([0, 0, 10, 10], [1, 1, 2, 2])


def test_interaction_matrix_recovers_a_known_distortion() -> None:
    rng = np.random.default_rng(4)
    applied = rng.uniform(-5, 5, size=(30, 6))
    M = np.eye(6) + rng.normal(0, 0.02, size=(6, 6))  # what the balance gets wrong
    recovered = applied @ np.linalg.inv(M).T  # so applied = M @ recovered
    res = check_loads(recovered, applied)
    np.testing.assert_allclose(res.interaction, M, atol=1e-8)
    assert res.corrected_rms_error.max() < 1e-8 < res.rms_error.min()
    np.testing.assert_allclose(res.max_abs_error, np.abs(recovered - applied).max(axis=0))


def _write_points(path: Path, offsets, gains, names, noise=0.0, seed=0) -> None:
    rng = np.random.default_rng(seed)
    rows = []
    for name, off, g in zip(names, offsets, gains, strict=True):
        for load in (0.0, 25.0, 50.0, 100.0, 200.0, 280.0):
            rows.append((name, load, off + load / g + rng.normal(0, noise)))
    pd.DataFrame(rows, columns=["channel", "load_N", "counts"]).to_csv(path, index=False)


def test_cli_loadcells_writes_a_usable_calibration(tmp_path: Path) -> None:
    names = [f"T{i}" for i in range(8)]
    offsets = np.linspace(-5000, 5000, 8)
    gains = np.linspace(4e-5, 6e-5, 8)
    pts = tmp_path / "points.csv"
    _write_points(pts, offsets, gains, names, noise=20.0)
    out = tmp_path / "loadcells.toml"
    assert main(["calibrate", "loadcells", str(pts), "--out", str(out)]) == 0
    cal = tomllib.loads(out.read_text())["calibration"]
    assert cal["cables"] == names and cal["id"].startswith("loadcells@")
    np.testing.assert_allclose(cal["gain_N_per_count"], gains, rtol=2e-4)
    # 20 counts of noise is 1 mN at these gains: the zero is known to a few counts
    np.testing.assert_allclose(cal["offset_counts"], offsets, atol=40)
    assert max(cal["residual_rms_N"]) < 5e-3
    assert (tmp_path / "loadcells.png").stat().st_size > 0


def test_cli_loadcells_bad_channel_is_one_line_and_no_output(tmp_path: Path, capsys) -> None:
    pts = tmp_path / "points.csv"
    pts.write_text("channel,load_N,counts\nA,0,10\nA,10,20\nA,20,30\nB,0,5\nB,0,6\n")
    out = tmp_path / "cal.toml"
    assert main(["calibrate", "loadcells", str(pts), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "channel B" in err[0] and "points.csv" in err[0]
    assert not out.exists()


def _check_load_table(rig_true, rig_model_name: str, path: Path) -> np.ndarray:
    """Tensions the *true* rig needs (exact solver) for known loads at a few poses."""
    poses = np.array(
        [[0.5, 0.0, 0.335, 0, 0, 0], [0.5, 0.0, 0.335, 0, 0.05, 0], [0.51, 0.0, 0.335, 0, 0, 0]]
    )
    rng = np.random.default_rng(9)
    loads = rng.uniform([-3, -2, -5, -0.05, -0.1, -0.02], [3, 2, 5, 0.05, 0.1, 0.02], size=(8, 6))
    rows, applied = [], []
    for q in poses:
        for W in np.vstack([np.zeros(6), loads]):
            rows.append(q)
            applied.append(W)
    q = np.array(rows)
    W = np.array(applied)
    R = rotation_from_euler(q[:, 3:])
    A = structure_matrix(rig_true.anchors_O_m, rig_true.attach_P_m, q[:, :3], R)
    G = gravity_wrench(rig_true.mass_kg, rig_true.com_P_m, R, rig_true.gravity_O_mps2)
    res = distribute("exact", A, -(G + W), rig_true.t_min_N, rig_true.t_max_N)
    assert res.feasible.all()
    df = pd.DataFrame(q, columns=list(POSE_COLUMNS))
    for k, name in enumerate(rig_true.cable_names):
        df[f"T_{name}_N"] = res.tensions_N[:, k]
    for k, c in enumerate(WRENCH_COLUMNS):
        df[c] = W[:, k]
    df.to_csv(path, index=False)
    return W


def test_cli_balance_exact_model_has_no_check_load_error(tmp_path: Path) -> None:
    rig = flat_rig(51, 28, 0.67, 0.5, name="flat-optimum")
    table = tmp_path / "checkloads.csv"
    _check_load_table(rig, "flat-optimum", table)
    out = tmp_path / "balance.json"
    assert (
        main(["calibrate", "balance", str(table), "--rig", str(RIG_FILE), "--out", str(out)]) == 0
    )
    doc = json.loads(out.read_text())
    assert doc["n_check_loads"] == 24 and doc["n_tares"] == 3
    assert max(doc["max_abs_error"]) < 1e-6
    np.testing.assert_allclose(doc["interaction_matrix"], np.eye(6), atol=1e-6)


def test_cli_balance_measures_and_corrects_an_anchor_error(tmp_path: Path) -> None:
    true = flat_rig(51, 28, 0.67, 0.5)
    b = np.array(true.anchors_O_m)
    b[4] += [0.0, 0.004, -0.003]  # one back anchor 5 mm off its drawing position
    from cdpr.analysis.rig import Rig

    rig_true = Rig(
        name="true",
        cable_names=true.cable_names,
        anchors_O_m=b,
        attach_P_m=true.attach_P_m,
        mass_kg=true.mass_kg,
        com_P_m=true.com_P_m,
        inertia_P_kgm2=true.inertia_P_kgm2,
        t_min_N=true.t_min_N,
        t_max_N=true.t_max_N,
        reference_position_O_m=true.reference_position_O_m,
    )
    table = tmp_path / "checkloads.csv"
    _check_load_table(rig_true, "flat-optimum", table)
    out = tmp_path / "balance.json"
    assert (
        main(["calibrate", "balance", str(table), "--rig", str(RIG_FILE), "--out", str(out)]) == 0
    )
    doc = json.loads(out.read_text())
    rms, corrected = np.array(doc["rms_error"]), np.array(doc["corrected_rms_error"])
    assert rms[:3].max() > 1e-3  # the anchor error shows in the check loads
    assert (corrected <= rms + 1e-12).all() and corrected[:3].max() < 0.5 * rms[:3].max()


def _tunnel_config(tmp_path: Path, extra: str) -> Path:
    cfg = (ROOT / "data_samples" / "tunnel.toml").read_text()
    cfg = cfg.replace('rig = "flat_optimum.toml"', f'rig = "{RIG_FILE.as_posix()}"')
    cfg = cfg.replace('calibrations = ["loadcell.dbc"]', "calibrations = []")
    cfg = cfg.replace(
        'dbc = "loadcell.dbc"', f'dbc = "{(ROOT / "data_samples" / "loadcell.dbc").as_posix()}"'
    )
    cfg = cfg.replace("offset_counts = 0.0", extra).replace("gain_N_per_count = 5.0e-5\n", "")
    p = tmp_path / "tunnel.toml"
    p.write_text(cfg)
    return p


def test_a_source_takes_its_calibration_from_the_file(tmp_path: Path) -> None:
    from cdpr.pipelines.daq_config import build_sources, load_daq_config

    rig_names = list(flat_rig(51, 28, 0.67, 0.5).cable_names)
    offsets, gains = np.arange(8) * 100.0, np.linspace(4e-5, 6e-5, 8)
    pts = tmp_path / "points.csv"
    _write_points(pts, offsets, gains, rig_names)
    cal = tmp_path / "loadcells.toml"
    assert (
        main(["calibrate", "loadcells", str(pts), "--rig", str(RIG_FILE), "--out", str(cal)]) == 0
    )
    cfg = load_daq_config(_tunnel_config(tmp_path, 'calibration_file = "loadcells.toml"'))
    (lc,) = [s for s in cfg.sources if s.name == "loadcells"]
    np.testing.assert_allclose(lc.settings["gain_N_per_count"], gains, rtol=1e-9)
    np.testing.assert_allclose(lc.settings["offset_counts"], offsets, atol=1e-6)
    assert cal.resolve() in [p.resolve() for p in cfg.calibrations]  # attached to every run
    (src,) = [s for s in build_sources(cfg) if s.name == "loadcells"]
    assert src.settings()["gain_N_per_count"] == pytest.approx(list(gains), rel=1e-9)


def test_calibration_file_and_inline_values_conflict(tmp_path: Path) -> None:
    from cdpr.analysis.errors import ConfigError
    from cdpr.pipelines.daq_config import load_daq_config

    (tmp_path / "c.toml").write_text(
        "[calibration]\noffset_counts = 0.0\ngain_N_per_count = 5e-5\n"
    )
    p = _tunnel_config(tmp_path, 'calibration_file = "c.toml"\noffset_counts = 1.0')
    with pytest.raises(ConfigError, match="sources.loadcells.offset_counts"):
        load_daq_config(p)


def test_shipped_samples_calibrate_and_an_unloaded_component_has_no_full_scale(
    tmp_path: Path,
) -> None:
    samples = ROOT / "data_samples"
    out = tmp_path / "lc.toml"
    assert (
        main(
            [
                "calibrate",
                "loadcells",
                str(samples / "loadcell_points.csv"),
                "--rig",
                str(RIG_FILE),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    bal = tmp_path / "bal.json"
    assert (
        main(
            [
                "calibrate",
                "balance",
                str(samples / "checkloads_flat.csv"),
                "--rig",
                str(RIG_FILE),
                "--out",
                str(bal),
            ]
        )
        == 0
    )
    doc = json.loads(bal.read_text())
    assert doc["n_check_loads"] == 30 and doc["n_tares"] == 3
    assert doc["max_abs_error_pct_fs"][5] is None  # Mz is never loaded in the sample
    # 0.05 N cell noise through the tare method: force errors of a few tenths of a newton at most
    assert max(doc["max_abs_error"][:3]) < 0.6
