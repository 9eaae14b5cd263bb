"""The correction stages of the reduction core on small hand-made point sets: each stage records
what it did and leaves a flag when it cannot run (no zero, no closing zero, no windage tare and no
test section, no section for the wall corrections), the windage source is chosen measured >
modelled > none, and the [tunnel] table of the test matrix loads (or fails in one line)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.reduction import new_points, with_updates
from cdpr.analysis.rigs import paper_rigs
from cdpr.analysis.stages import (
    repeatability_stage,
    wall_corrections_stage,
    windage_stage,
    zero_drift_stage,
)
from cdpr.pipelines.campaign import test_matrix_from_mapping
from cdpr.pipelines.tunnel_section import tunnel_section_from_mapping

ROOT = Path(__file__).resolve().parents[1]
OCTAGON = ROOT / "data_samples" / "tunnel_section_octagon.toml"
S = 1_000_000_000


def _points(kind, t_s, T, V=None, aoa_rad=None):
    s, m = np.shape(T)
    pose = np.zeros((s, 6))
    pose[:, :3] = paper_rigs()["flat_optimum"].reference_position_O_m
    if aoa_rad is not None:
        pose[:, 4] = aoa_rad  # pitch = aoa for the nose-upstream mounting
    return new_points(
        kind=kind,
        start_ns=(np.asarray(t_s) * S).astype(np.int64),
        tension_N=T,
        tension_cov_N2=np.broadcast_to(np.eye(m) * 1e-4, (s, m, m)),
        pose_O_m_rad=pose,
        pose_cov_O_m_rad=np.broadcast_to(np.eye(6) * 1e-10, (s, 6, 6)),
        airspeed_mps=np.zeros(s) if V is None else V,
        density_kgpm3=np.full(s, 1.2),
    )


def test_zero_drift_removes_a_linear_drift_and_flags_the_missing_closing_zero() -> None:
    rate = np.array([0.01, -0.02])  # N/s, by hand: the drift at t is rate * (t - 0)
    t = np.array([0.0, 10.0, 20.0, 30.0])
    T = 100.0 + rate * t[:, None]
    p = zero_drift_stage(_points(["zero", "wind_on", "zero", "wind_on"], t, T))
    np.testing.assert_allclose(p["zero_drift_N"][:3], rate * t[:3, None], atol=1e-12)
    np.testing.assert_allclose(p["tension_N"][:3], 100.0, atol=1e-12)
    # the last point is after the last zero: held there, and flagged
    np.testing.assert_allclose(p["zero_drift_N"][3], rate * 20.0)
    assert p.flags[3] == ("no_closing_zero",) and p.flags[1] == ()
    assert p.steps[-1].name == "zero_drift" and p.steps[-1].flagged == 1
    assert p.meta["corrections"][0]["name"] == "zero_drift"
    # no zero at all: nothing subtracted, every point flagged, the record says why
    q = zero_drift_stage(_points(["wind_on", "wind_on"], t[:2], T[:2]))
    assert all("no_zero_drift_correction" in f for f in q.flags)
    np.testing.assert_array_equal(q["tension_N"], T[:2])
    assert q.meta["corrections"][0]["source"] == "not applied"


def _windage_points(kinds, V, aoa, W):
    m = paper_rigs()["flat_optimum"].n_cables
    p = _points(kinds, np.arange(len(kinds)), np.full((len(kinds), m), 150.0), V, aoa)
    mu = np.full(len(kinds), 1.81e-5)
    return with_updates(p, arrays={"wrench_P_O_N_Nm": np.asarray(W, float), "viscosity_Pas": mu})


def test_windage_source_is_measured_then_modelled_then_none() -> None:
    rig = paper_rigs()["flat_optimum"]
    section = tunnel_section_from_mapping(tomllib.loads(OCTAGON.read_text()), str(OCTAGON))
    aoa = np.deg2rad([-4.0, 0.0, 4.0, 8.0, 2.0, 2.0])
    V = np.array([20.0, 20.0, 20.0, 20.0, 20.0, 30.0])
    # model-off points: a tare Fx = 0.3 + 0.5 aoa (N) at 20 m/s; two wind-on points
    W = np.zeros((6, 6))
    W[:4, 0] = 0.3 + 0.5 * aoa[:4]
    W[4:, 0] = 2.0
    kinds = ["windage"] * 4 + ["wind_on"] * 2
    p = windage_stage(
        _windage_points(kinds, V, aoa, W), rig=rig, section=section.geometry, geometry=None
    )
    # at 20 m/s the measured tare (the line above, by hand); at 30 m/s no tare: the model
    assert list(p["windage_source"][4:]) == ["measured", "model"]
    np.testing.assert_allclose(p["windage_N"][4, 0], 0.3 + 0.5 * aoa[4], atol=1e-9)
    np.testing.assert_allclose(p["wrench_P_O_N_Nm"][4, 0], 2.0 - (0.3 + 0.5 * aoa[4]), atol=1e-9)
    assert p["windage_N"][5, 0] > 0.1  # the cables' drag at 30 m/s, tenths of a newton
    assert "windage_tare" in p.flags[4] and "windage_modelled" in p.flags[5]
    assert "windage_tare_missing" in p.flags[5]
    assert p.cov_terms["windage"][5, 0, 0] > 0  # the model's σ is carried
    # a windage point alone at its speed (a ramp caught in its window) is left out and flagged;
    # the 20 m/s tare is still fitted
    kinds7 = [*kinds, "windage"]
    V7, aoa7, W7 = np.append(V, 26.0), np.append(aoa, 0.0), np.vstack([W, W[:1]])
    p7 = windage_stage(
        _windage_points(kinds7, V7, aoa7, W7), rig=rig, section=section.geometry, geometry=None
    )
    assert "windage_tare_unfit" in p7.flags[6] and p7["windage_source"][4] == "measured"
    # neither a tare nor a section: nothing subtracted, flagged
    q = windage_stage(
        _windage_points(["wind_on"], V[4:5], aoa[4:5], W[4:5]), rig=rig, section=None,
        geometry=None,
    )  # fmt: skip
    assert q.flags[0] == ("no_windage_correction",) and q["windage_source"][0] == "none"
    np.testing.assert_array_equal(q["wrench_P_O_N_Nm"], W[4:5])


def test_wall_corrections_without_a_section_are_flagged_and_repeatability_by_hand() -> None:
    m = 2
    p = _points(["wind_on"] * 4, np.arange(4), np.full((4, m), 1.0))
    CL = np.array([0.50, 0.52, 0.30, 0.33])
    arrays = {c: np.full(4, 0.1) for c in ("CD", "CY", "Cl", "Cm", "Cn")}
    arrays.update({f"sd_{c}": np.full(4, 0.01) for c in ("CD", "CY", "CL", "Cl", "Cm", "Cn")})
    arrays.update(CL=CL, aoa_rad=np.zeros(4), q_Pa=np.full(4, 400.0))
    arrays["repeat_group"] = np.array([0, 0, 2, 2])
    p = with_updates(p, arrays=arrays)
    w = wall_corrections_stage(p, walls=None)
    assert all(f == ("no_wall_correction",) for f in w.flags)
    assert np.isnan(w["CL_corrected"]).all()
    r = repeatability_stage(w)
    # pooled σ of two pairs: sqrt(((0.02)^2/2 + (0.03)^2/2) / 2)
    np.testing.assert_allclose(r["sd_repeat_CL"], np.sqrt((0.02**2 / 2 + 0.03**2 / 2) / 2))
    np.testing.assert_allclose(r["sd_propagated_CL"], 0.01)


MATRIX = {
    "campaign": {"rig": "flat_optimum.toml"},
    "model": {"area_m2": 0.0125, "span_m": 0.2441, "chord_m": 0.051, "mrp_P_m": [0, 0, 0]},
    "points": [{"label": "z", "kind": "zero"}],
}


def test_the_test_matrix_carries_the_tunnel_section() -> None:
    octagon = tomllib.loads(OCTAGON.read_text())
    model = {**MATRIX["model"], **octagon["model"]}
    m = test_matrix_from_mapping(
        {**MATRIX, "tunnel": octagon["tunnel"], "model": model}, "m.toml", ROOT / "data_samples"
    )
    assert m.tunnel is not None and m.tunnel.walls.reference_area_m2 == 0.0125
    assert abs(m.tunnel.walls.area_m2 - 2 * (1 + 2**0.5) * 0.376**2) < 1e-9
    bad = {**model, "reference_area_m2": 0.02}
    with pytest.raises(ConfigError, match="model.reference_area_m2"):
        test_matrix_from_mapping(
            {**MATRIX, "tunnel": octagon["tunnel"], "model": bad}, "m", ROOT / "data_samples"
        )
    with pytest.raises(ConfigError, match="model.blockage_K3.*needs a \\[tunnel\\]"):
        test_matrix_from_mapping({**MATRIX, "model": model}, "m.toml", ROOT / "data_samples")
    assert test_matrix_from_mapping(MATRIX, "m.toml", ROOT / "data_samples").tunnel is None


def test_spectrum_flags_a_tension_peak_at_a_mode_and_a_short_window() -> None:
    from cdpr.analysis.stages import PointSamples, spectrum_stage
    from cdpr.analysis.stiffness import point_spectra

    rig = paper_rigs()["flat_optimum"]
    rng = np.random.default_rng(4)
    fs, n = 100.0, 300
    t_ns = (np.arange(3 * n) * 1e9 / fs).astype(np.int64)
    T = 150.0 + rng.normal(0, 0.01, (3 * n, rig.n_cables))
    # point 1 rings at 9.2 Hz, the flat optimum's yaw mode (docs/corrections.md: 9.22 Hz)
    T[n : 2 * n] += 0.5 * np.sin(2 * np.pi * 9.2 * t_ns[n : 2 * n] * 1e-9)[:, None]
    ranges = [(0, n), (n, 2 * n), (2 * n, 2 * n + 50)]  # the last: 0.5 s, < 10 periods
    pose = np.tile(np.concatenate([rig.reference_position_O_m, [0.0, 0.0, 0.0]]), (3, 1))
    sp = point_spectra(rig, t_ns, T, ranges, pose)
    np.testing.assert_allclose(sp.modes_Hz[:, 0], 9.22, atol=0.01)
    p = _points(["wind_on"] * 3, [0.0, 3.0, 6.0], np.full((3, rig.n_cables), 150.0))
    p = with_updates(p, arrays={"pose_O_m_rad": pose})
    out = spectrum_stage(p, rig=rig, samples=PointSamples(t_ns, T, ranges))
    assert out.flags[0] == ()
    assert out.flags[1] == ("spectrum_peak_near_mode",)
    assert "too_few_periods" in out.flags[2]
    np.testing.assert_allclose(out["lowest_mode_Hz"], 9.22, atol=0.01)


def test_a_bad_reference_polar_names_the_file_row_and_column(tmp_path: Path) -> None:
    from cdpr.pipelines.report import read_reference_polars

    p = tmp_path / "ref.csv"
    p.write_text("aoa_deg,CL\n0,0.1\n2,abc\n")
    with pytest.raises(ConfigError, match=r"ref.csv: row 3, column CL: expected a finite number"):
        read_reference_polars(p)
    p.write_text("aoa_deg,lift\n0,0.1\n")
    with pytest.raises(ConfigError, match="expected at least one of"):
        read_reference_polars(p)


def test_flow_conditions_by_hand_and_no_temperature_flagged() -> None:
    from cdpr.analysis.stages import flow_conditions_stage

    p = _points(["wind_on", "wind_on"], [0.0, 1.0], np.full((2, 2), 1.0), V=np.array([30.0, 30.0]))
    p = with_updates(p, arrays={"temperature_K": np.array([288.15, np.nan])})
    out = flow_conditions_stage(p, chord_m=0.05)
    mu = 1.716e-5 * (288.15 / 273.15) ** 1.5 * (273.15 + 110.4) / (288.15 + 110.4)  # Sutherland
    np.testing.assert_allclose(out["reynolds"][0], 1.2 * 30.0 * 0.05 / mu, rtol=1e-6)
    np.testing.assert_allclose(out["mach"][0], 30.0 / 340.29, rtol=1e-3)  # ISA sea level a
    assert np.isnan(out["reynolds"][1]) and out.flags[1] == ("no_temperature",)


def test_simulate_refuses_a_tunnel_matrix_over_a_second_process_transport(
    tmp_path: Path, capsys
) -> None:
    from cdpr.pipelines.cli import main

    octagon = OCTAGON.read_text().split("\n[model]")[0].strip()
    m = tmp_path / "m.toml"
    m.write_text(
        f'[campaign]\nrig = "{ROOT / "data_samples" / "flat_optimum.toml"}"\n'
        "[model]\narea_m2 = 0.0125\nspan_m = 0.2441\nchord_m = 0.051\nmrp_P_m = [0, 0, 0]\n"
        "volume_m3 = 5.6e-4\nblockage_K3 = 0.94\n"
        f'{octagon}\n[[points]]\nlabel = "z"\nkind = "zero"\n'
    )
    args = ["simulate", "--campaign", str(m), "--out", str(tmp_path / "r"), "--transport", "slcan"]
    assert main(args) == 2
    assert "use --transport virtual" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
