"""Issue 22's goals through the lab path: the independent lab generator's forced oscillations
(its own Newton-Euler with the centre of mass off P, its own controller and aero model, 0.05 mm /
0.01 deg camera noise at 200 Hz and a 3 ms clock offset, 1 kHz load cells with 0.05 N noise) into
``cdpr import`` (candump, poses, tunnel and events) and ``cdpr analyze --matrix``, as a lab runs
them (subprocesses).

- pitch 5 deg at 1 and 2 Hz at 25.51 and 41.42 m/s, 60 s per point: in-phase Cma within 2 %,
  out-of-phase Cmq + Cmadot within 5 % (or 0.3 /rad) of the truth;
- every point (2 deg at 0.5 Hz at 17.27 m/s and the yaw case too): its U95 covers the truth, and
  the dwell time that reaches the goals is reported (longer than the window where they are not
  reached);
- the clock offset within 0.3 ms; the inertia removed both ways, shown with their difference;
- a wind-off oscillation point: its aerodynamic wrench's harmonics zero within their σ.

The coverage over many points is ``tests/measure_dynamic_coverage.py`` (docs/dynamic_tests.md).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import lab_generator as lg
import numpy as np
import pandas as pd
import pytest
from measure_coverage import cdpr_command, clean_env, run_lab_path

from cdpr.analysis.oscillation import NAMED_DERIVATIVES


def named_truth(o: dict, axis: str) -> dict[str, float]:
    """The lab's truth for each named derivative (its in-phase / out-of-phase harmonics of the
    model's coefficients, with the names' signs)."""
    return {
        n: s * (o["inphase"] if part == "in" else o["outphase"])[c]
        for n, c, part, s in NAMED_DERIVATIVES.get(axis, ())
    }


@pytest.fixture(scope="module")
def issue22(tmp_path_factory: pytest.TempPathFactory):
    work = tmp_path_factory.mktemp("issue22")
    case = lg.oscillation_case(work / "case", lg.ISSUE22_SPECS, seed=22)
    pts, _, out = run_lab_path(case, work)
    folder = work / "analysis" / "run"
    return case, pts, folder, out


def _truth(case: lg.LabCase) -> dict[str, dict]:
    return {p["point"]: p for p in case.truth["points"]}


def test_pitch_goals_at_60_s(issue22) -> None:
    case, pts, _, _ = issue22
    truth = _truth(case)
    done = 0
    for _, r in pts[pts["kind"] == "oscillation"].iterrows():
        o = truth[r["point"]]["oscillation"]
        if o["axis"] != "pitch" or abs(o["amplitude"] - np.radians(5)) > 1e-9:
            continue
        t = o["named"]
        assert abs(r["Cma"] - t["Cma"]) <= 0.02 * abs(t["Cma"]), r["point"]
        goal = max(0.05 * abs(t["Cmq_plus_Cmadot"]), 0.3)
        assert abs(r["Cmq_plus_Cmadot"] - t["Cmq_plus_Cmadot"]) <= goal, r["point"]
        assert r["inertia_method"] == "tare"
        assert r["dwell_s_Cma"] < r["window_s"]  # reached within the window
        done += 1
    assert done == 4


def test_every_point_is_covered_and_says_its_dwell(issue22) -> None:
    case, pts, _, _ = issue22
    truth = _truth(case)
    n = covered = 0
    on = pts[pts["kind"] == "oscillation"]
    assert len(on) == 6
    for _, r in on.iterrows():
        o = truth[r["point"]]["oscillation"]
        for name, t in named_truth(o, o["axis"]).items():
            n += 1
            covered += abs(r[name] - t) <= r[f"U95_{name}"]
            assert abs(r[name] - t) < 4 * r[f"sd_{name}"], (r["point"], name, r[name], t)
            assert r[f"dwell_s_{name}"] > 0
    assert covered >= 0.85 * n
    slow = on[on["motion_frequency_plan_Hz"] == 0.5].iloc[0]
    # 2 deg at 0.5 Hz at 17.27 m/s: no practical window reaches the damping goal
    assert slow["dwell_s_Cmq_plus_Cmadot"] > 5 * slow["window_s"]


def test_clock_offset_and_flags(issue22) -> None:
    case, pts, folder, out = issue22
    osc = pts[pts["kind"].isin(("oscillation", "oscillation_tare"))]
    true_ms = case.truth["camera"]["clock_offset_ns"] * 1e-6
    assert np.allclose(osc["clock_offset_ms"], osc["clock_offset_ms"].iloc[0])
    assert abs(osc["clock_offset_ms"].iloc[0] - true_ms) < 0.3
    assert abs(osc["clock_offset_ms"].iloc[0] - true_ms) < 0.02  # in fact, a few us
    summary = json.loads((folder / "summary.json").read_text())
    co = summary["reduction"]["clock_offset"]
    assert co["identified"] and len(co["per_tare_ms"]) == 4
    for flags in osc["flags"]:
        words = set(str(flags).split(";"))
        assert not words & {"too_few_cycles", "motion_amplitude_off_plan", "clock_offset_not_identified",
                            "tension_limit_in_cycle", "no_inertia_tare", "nonlinear_response"}  # fmt: skip


def test_yaw_signs_agree_with_the_lab(issue22) -> None:
    """Yaw about the tunnel's vertical at aoa 0 (the lab's report): Cn in phase = Cnb (0.09),
    out of phase -Cnr cos a + Cnp sin a + Cnbdot; the name Cnr_cosa_minus_... is its negative."""
    case, pts, _, _ = issue22
    r = pts[pts["motion_axis"] == "yaw"].query("kind == 'oscillation'").iloc[0]
    lin = _truth(case)[r["point"]]["oscillation"]["linear"]
    assert r["Cnb"] == pytest.approx(lin["Cn_inphase"], abs=3 * r["sd_Cnb"])
    assert r["Cnb"] > 5 * r["sd_Cnb"] > 0
    assert r["Cn_inphase"] == r["Cnb"]
    assert r["Cnr_cosa_minus_Cnp_sina_minus_Cnbdot"] == pytest.approx(-r["Cn_outphase"])


def test_outputs_harmonic_table_and_hysteresis(issue22) -> None:
    _, pts, folder, out = issue22
    h = pd.read_csv(folder / "harmonics.csv")
    assert {"measured", "inertia_tare", "inertia_model", "inertia_model_minus_tare", "aero",
            "aero_model", "motion"} <= set(h["source"])  # fmt: skip
    pitch = h[(h["point"] == "osc-pitch-A5d-f2-a0-v41.42") & (h["harmonic"] == 1)]
    it = pitch[(pitch["source"] == "inertia_tare") & (pitch["quantity"] == "my_Nm")].iloc[0]
    im = pitch[(pitch["source"] == "inertia_model") & (pitch["quantity"] == "my_Nm")].iloc[0]
    d = pitch[(pitch["source"] == "inertia_model_minus_tare") & (pitch["quantity"] == "my_Nm")]
    assert d.iloc[0]["mean_or_inphase"] == pytest.approx(
        im["mean_or_inphase"] - it["mean_or_inphase"]
    )
    assert 0.90 < im["mean_or_inphase"] / it["mean_or_inphase"] < 1.0  # the true body: +3 % inertia
    png = (folder / "hysteresis.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    report = (folder / "report.md").read_text()
    assert "## Dynamic points" in report and "hysteresis.png" in report
    assert "camera clock offset" in report


def test_wind_off_oscillation_gives_zero_aero_within_sigma(tmp_path: Path) -> None:
    """A wind-on oscillation point recorded with the tunnel off, served by its wind-off tare:
    no coefficients (flag wind_off_oscillation) and the aerodynamic wrench's harmonics, inertia
    removed, zero within their σ."""
    specs = (lg.OscSpec("pitch", 5.0, 2.0, (0.0,), 20),)
    case = lg.oscillation_case(tmp_path / "case", specs, seed=5)
    run, ana = tmp_path / "run.mcap", tmp_path / "analysis"
    imp, _ = lg.lab_argv(case, run, ana)
    env = clean_env()
    r = subprocess.run(cdpr_command() + imp, capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    an = ["analyze", str(run), "--out", str(ana), "--area-m2", "0.014646", "--span-m", "0.2441",
          "--chord-m", "0.060", "--workers", "1", "--no-progress"]  # fmt: skip
    r = subprocess.run(cdpr_command() + an, capture_output=True, text=True, env=env)
    assert r.returncode == 1, r.stderr  # a warning: the wind-off oscillation point
    pts = pd.read_csv(ana / "run" / "points.csv")
    on = pts[pts["kind"] == "oscillation"].iloc[0]
    assert "wind_off_oscillation" in on["flags"] and np.isnan(on["Cma"])
    h = pd.read_csv(ana / "run" / "harmonics.csv")
    a = h[(h["point"] == on["point"]) & (h["source"] == "aero") & (h["harmonic"] == 1)]
    z = np.concatenate(
        [a["mean_or_inphase"] / a["sd_inphase"], a["quadrature"] / a["sd_quadrature"]]
    )
    assert len(z) == 12 and np.all(np.abs(z) < 3.5), z
