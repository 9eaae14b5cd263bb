"""The reduction of a forced oscillation (cdpr.analysis.oscillation), each function on its own
against independent numbers: the samples' clock against known bursts; the derivatives against a
pitching and a yawing wrench written by hand; the motion fit, the clock offset, the cable wrench
and the inertia removed against the independent lab generator's truth (its own Newton-Euler,
controller and aero model, a 3 ms camera clock offset, 0.05 mm / 0.01 deg camera noise)."""

from __future__ import annotations

import math

import lab_generator as lg
import numpy as np
import pytest
from _dynamic_inputs import lab_samples

from cdpr.analysis.harmonics import grid_phases, harmonics_from_grid
from cdpr.analysis.motion import Oscillation
from cdpr.analysis.oscillation import (
    NAMED_DERIVATIVES,
    Body,
    MotionFit,
    OffsetInput,
    analysis_window,
    clock_offset,
    coverage_factor,
    dynamic_derivatives,
    fit_motion,
    remove_inertia,
    welch_satterthwaite,
    wrench_harmonics,
)
from cdpr.pipelines.config import load_rig

S, B, C = 0.014646, 0.2441, 0.060


# ---------------------------------------------------------------------------------------------
# pieces by hand


def test_analysis_window_by_hand() -> None:
    osc = Oscillation("pitch", 0.1, 2.0, 10, 2)
    a, b, n = analysis_window(0, 6_000_000_000, osc)
    assert (a, b, n) == (1_000_000_000, 6_000_000_000, 10)
    a, b, n = analysis_window(0, 3_490_000_000, osc)  # stopped early: 4 whole cycles (and 98 %)
    assert (a, b, n) == (1_000_000_000, 3_500_000_000, 5)
    assert analysis_window(0, 3_400_000_000, osc)[2] == 4


def _motion(axis: int, A: float, omega: float, mean: np.ndarray) -> MotionFit:
    coef = np.zeros((6, 7))
    coef[:, 0] = mean
    coef[axis, 1] = A
    cov = np.eye(42) * 1e-16
    return MotionFit(axis, omega, 0.0, 0, 0.0, coef, cov, 1000, 60, 59.0, np.zeros(6))


def test_derivatives_of_a_pitching_moment_written_by_hand() -> None:
    """A model pitching about P (the MRP) at the mean aoa 0: body y = {O} y, so the pitching
    moment in {O} is ``q S c (Cm0 + Cma A sin + D k A cos)``; the normal force ``CN q S`` along
    -z_B turns with the body (z_B = (-sin theta, 0, -cos theta) in {O})."""
    q, A, w, V = 900.0, math.radians(5.0), 2 * math.pi * 2.0, 41.42
    k = w * C / (2 * V)
    Cm0, Cma, D = 0.01, -0.55, -16.0
    CN0, CNa, E = 0.05, 4.2, 7.5
    g = grid_phases(256)
    theta = A * np.sin(g)
    Cm = Cm0 + Cma * theta + D * k * A * np.cos(g)
    CN = CN0 + CNa * theta + E * k * A * np.cos(g)
    # body axes (nose upstream, pitched by theta): z_B in {O} = (-sin th, 0, -cos th)
    F_B = np.zeros((256, 3))
    F_B[:, 2] = -CN * q * S
    zB = np.stack([-np.sin(theta), np.zeros(256), -np.cos(theta)], axis=1)
    F_O = F_B[:, 2:3] * zB
    W = np.zeros((256, 6))
    W[:, :3] = F_O
    W[:, 4] = Cm * q * S * C  # y_B = y_O
    aero = harmonics_from_grid(W, 3)
    mo = _motion(4, A, w, np.array([0.5, 0, 0.335, 0, 0, 0]))
    d = dynamic_derivatives(aero, {"x": np.eye(42) * 1e-20}, mo, "pitch", q, V, S, B, C)
    assert d.k == pytest.approx(k)
    assert d.named["Cma"][0] == pytest.approx(Cma, rel=1e-6)
    assert d.named["Cmq_plus_Cmadot"][0] == pytest.approx(D, rel=1e-6)
    assert d.named["CNa"][0] == pytest.approx(CNa, rel=1e-6)
    assert d.named["CNq_plus_CNadot"][0] == pytest.approx(E, rel=1e-6)
    assert d.coef[4, 0] == pytest.approx(Cm0, abs=1e-12)
    assert not d.nonlinear


def test_yaw_derivatives_carry_the_agreed_signs() -> None:
    """Yaw about the tunnel's vertical at aoa 0 (lab report, docs/lab_generator.md): sideslip =
    yaw, body r = -yaw_dot: ``Cn = Cnb psi + (-Cnr) psi_dot b/2V``; body z = -z_O, so
    ``M_zO = -q S b Cn``.  The names read Cnb and ``Cnr cos a - Cnp sin a - Cnbdot`` = Cnr."""
    q, A, w, V = 400.0, math.radians(0.6), 2 * math.pi, 25.51
    k = w * B / (2 * V)
    Cnb, Cnr = 0.09, -0.25
    g = grid_phases(256)
    psi = A * np.sin(g)
    Cn = Cnb * psi - Cnr * k * A * np.cos(g)
    W = np.zeros((256, 6))
    W[:, 5] = -q * S * B * Cn  # body z = -z_O (a yaw about z_O keeps it)
    aero = harmonics_from_grid(W, 3)
    mo = _motion(5, A, w, np.array([0.5, 0, 0.335, 0, 0, 0]))
    d = dynamic_derivatives(aero, {}, mo, "yaw", q, V, S, B, C)
    assert d.named["Cnb"][0] == pytest.approx(Cnb, rel=1e-6)
    assert d.named["Cnr_cosa_minus_Cnp_sina_minus_Cnbdot"][0] == pytest.approx(Cnr, rel=1e-6)
    assert {n for n, *_ in NAMED_DERIVATIVES["yaw"]} >= {"Cnb", "Clb", "CYb"}


def test_welch_satterthwaite_and_the_coverage_factor() -> None:
    # GUM G.4: two equal variances with 10 and infinite dof: nu = 4 * 10 = 40
    assert welch_satterthwaite({"a": 1.0, "b": 1.0}, {"a": 10, "b": math.inf}) == pytest.approx(40)
    assert coverage_factor(math.inf) == pytest.approx(1.959964, abs=1e-6)
    assert coverage_factor(9) == pytest.approx(2.262157, abs=1e-6)  # Student's t table


# ---------------------------------------------------------------------------------------------
# against the lab generator


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("osc") / "case"
    specs = (
        lg.OscSpec("pitch", 5.0, 2.0, (41.42,), 16),
        lg.OscSpec("yaw", 0.5, 1.0, (25.51,), 8, aoa_deg=4.0),
    )
    case = lg.oscillation_case(out, specs, seed=21)
    f = case.files
    t_ns, T, tc, q, cov = lab_samples(case)
    var = np.diagonal(cov, axis1=1, axis2=2)
    pts = {p["point"]: p for p in case.truth["points"]}
    fits, wins = {}, {}
    for lab_, p in pts.items():
        if "oscillation" not in p:
            continue
        o = p["oscillation"]
        osc = Oscillation(o["axis"], o["amplitude"], o["frequency_Hz"], o["cycles"], 2)
        a, b, _ = analysis_window(p["start_ns"], p["end_ns"], osc)
        fits[lab_] = fit_motion(tc, q, var, np.ones(len(tc), bool), (a, b), osc)
        wins[lab_] = (a, b)
    rig = load_rig(f["rig"])
    return {"case": case, "t": t_ns, "T": T, "pts": pts, "fits": fits, "wins": wins, "rig": rig}


def test_motion_fit_against_the_generators_motion(lab) -> None:
    """The amplitude and frequency of the commanded motion within 3 σ; the phase: the camera
    sees the motion ``A sin(w (t_cam - offset - t0))``, so at the load-cell time t0 with the true
    offset the fitted phase is 0 (mod 2 pi) within 3 σ; the mean pose the commanded one."""
    off = lab["case"].truth["camera"]["clock_offset_ns"]
    for name, f in lab["fits"].items():
        o = lab["pts"][name]["oscillation"]
        assert f.amplitude == pytest.approx(o["amplitude"], abs=3 * f.sd_amplitude + 1e-9)
        assert f.omega_rad_s == pytest.approx(o["omega_rad_s"], abs=3 * f.sd_omega_rad_s + 1e-9)
        ph = float(f.phase(np.array([o["t0_ns"]]), off)[0])
        wrapped = (ph + math.pi) % (2 * math.pi) - math.pi
        assert abs(wrapped) < 3 * f.sd_phase_rad + 1e-6, (name, wrapped, f.sd_phase_rad)
        assert f.coef[:, 0] == pytest.approx(o["q_mean"], abs=1e-5)


def test_clock_offset_from_the_wind_off_oscillations(lab) -> None:
    tares = [
        OffsetInput(
            lab["t"], lab["T"], np.ones(len(lab["t"]), bool), lab["fits"][k], lab["wins"][k]
        )
        for k, p in lab["pts"].items()
        if p["kind"] == "oscillation_tare"
    ]
    co = clock_offset(lab["rig"], tares)
    true = lab["case"].truth["camera"]["clock_offset_ns"]
    assert co.identified
    assert abs(co.offset_ns - true) < max(4 * co.sd_ns, 5_000)  # issue: within 0.3 ms
    assert co.sd_ns < 50_000
    assert clock_offset(lab["rig"], []).identified is False


def test_inertia_removed_by_the_tare_gives_the_true_aero_wrench(lab) -> None:
    """The cable wrench of the wind-on pitch oscillation less its wind-off tare, component by
    component at each harmonic, against the generator's own harmonics of the true aerodynamic
    wrench at P (aero_wrench_harmonics_P_O) within 4 σ (+ 0.2 mN m); beside it the rig file's
    mass and inertia (the true body is 2 % heavier, 3 % more inertia, its centre of mass 3 mm
    off) leave a visibly larger error in the pitching moment's in-phase part."""
    true_off = lab["case"].truth["camera"]["clock_offset_ns"]
    u = np.ones(len(lab["t"]), bool)
    on, tare = "osc-pitch-A5d-f2-a0-v41.42", "osc-tare-pitch-A5d-f2-a0"
    w_on = wrench_harmonics(
        lab["rig"], lab["t"], lab["T"], u, lab["fits"][on], true_off, lab["wins"][on]
    )
    w_t = wrench_harmonics(
        lab["rig"], lab["t"], lab["T"], u, lab["fits"][tare], true_off, lab["wins"][tare]
    )
    r = remove_inertia(w_on, w_t)
    truth = np.array(lab["pts"][on]["oscillation"]["aero_wrench_harmonics_P_O"])  # (6, 7)
    sd = np.sqrt(np.diag(sum(r.terms.values()))).reshape(6, 7)
    err = r.aero - truth
    assert np.all(np.abs(err[:, :3]) <= 4 * sd[:, :3] + 2e-4), err[:, :3] / sd[:, :3]
    model_err = abs(r.aero_model[4, 1] - truth[4, 1])
    assert model_err > 5 * abs(err[4, 1]) and model_err > 4 * sd[4, 1]
    # the model's inertia is the rig file's, the tare's the true body's: ~3 % apart in pitch
    ratio = r.inertia_model[4, 1] / r.inertia_tare[4, 1]
    assert 0.93 < ratio < 0.995
    # no tare: the model, said as such
    m = remove_inertia(w_on, None)
    assert m.method == "model" and np.isnan(m.inertia_tare).all()


def test_derivatives_of_the_lab_points_against_their_truth(lab) -> None:
    """The whole chain on the lab's files: the named derivatives within their U95 (and the
    pitch ones within the issue's 2 % / 5 % goals at 5 deg, 2 Hz, 41.42 m/s here after 8 s)."""
    true_off = lab["case"].truth["camera"]["clock_offset_ns"]
    u = np.ones(len(lab["t"]), bool)
    body = Body.of(lab["rig"])
    for on, tare in (
        ("osc-pitch-A5d-f2-a0-v41.42", "osc-tare-pitch-A5d-f2-a0"),
        ("osc-yaw-A0.5d-f1-a4-v25.51", "osc-tare-yaw-A0.5d-f1-a4"),
    ):
        ws = [
            wrench_harmonics(
                lab["rig"], lab["t"], lab["T"], u, lab["fits"][k], true_off, lab["wins"][k], body
            )
            for k in (on, tare)
        ]
        r = remove_inertia(*ws)
        p = lab["pts"][on]
        o = p["oscillation"]
        d = dynamic_derivatives(
            r.aero, r.terms, lab["fits"][on], o["axis"], p["q_Pa"], p["airspeed_mps"], S, B, C,
            dof=r.dof,
        )  # fmt: skip
        assert d.k == pytest.approx(o["reduced_frequency"], rel=1e-4)
        sign = {n: (c, part, s) for n, c, part, s in NAMED_DERIVATIVES[o["axis"]]}
        for n, (v, sd) in d.named.items():
            c, part, s = sign[n]
            truth = s * (o["inphase"] if part == "in" else o["outphase"])[c]
            u95 = coverage_factor(d.named_dof[n]) * sd
            assert abs(v - truth) <= u95 * 1.5, (on, n, v, truth, u95)
        if o["axis"] == "pitch":
            assert d.named["Cma"][0] == pytest.approx(o["named"]["Cma"], rel=0.02)
            goal = max(0.05 * abs(o["named"]["Cmq_plus_Cmadot"]), 0.3)
            assert abs(d.named["Cmq_plus_Cmadot"][0] - o["named"]["Cmq_plus_Cmadot"]) < goal
        else:  # the lab's yaw report: Cn out of phase = -Cnr cos a + Cnp sin a + Cnbdot
            lin = o["linear"]
            assert d.named["Cnb"][0] == pytest.approx(lin["Cn_inphase"], abs=4 * d.named["Cnb"][1])


def test_short_points_missing_tares_and_no_offset_are_flagged_not_silent(lab) -> None:
    """Through the dynamic order on the lab's samples: a point cut after 5 of its 16 cycles is
    analysed on those (flag too_few_cycles), one cut after 2 is not (motion_not_fitted, NaN, no
    crash); an oscillation point without its tare takes the model's inertia (no_inertia_tare,
    inertia_method model); a run without any wind-off oscillation has no clock offset
    (clock_offset_not_identified, none removed)."""
    from _dynamic_inputs import dynamic_inputs

    from cdpr.analysis.aero import ModelGeometry
    from cdpr.analysis.reduction import run_stages, with_updates
    from cdpr.analysis.stages import dynamic_stages

    pts, samples, labels = dynamic_inputs(lab["case"])
    i = labels.index("osc-pitch-A5d-f2-a0-v41.42")
    j = labels.index("osc-yaw-A0.5d-f1-a4-v25.51")
    a, _ = samples.ranges[i]
    ranges = list(samples.ranges)
    ranges[i] = (a, a + int((2 + 5.5) / 2.0 * 1000))  # 2 settling cycles, then 5.5 at 2 Hz
    a, _ = samples.ranges[j]
    ranges[j] = (a, a + int((2 + 2.5) / 1.0 * 1000))
    tix = pts["inertia_tare_index"].copy()
    tix[j] = -1
    pts = with_updates(pts, arrays={"inertia_tare_index": tix})
    geo = ModelGeometry(area_m2=S, span_m=B, chord_m=C)
    from dataclasses import replace

    out = run_stages(pts, dynamic_stages(lab["rig"], geo, replace(samples, ranges=ranges)))
    assert "too_few_cycles" in out.flags[i] and out["cycles_analysed"][i] == 5
    assert np.isfinite(out["Cma"][i]) and out["inertia_method"][i] == "tare"
    assert "motion_not_fitted" in out.flags[j] and np.isnan(out["Cnb"][j])
    # the yaw point with its tare named away but a cut motion: nothing fitted, still no crash;
    # the pitch point without its tare: the model
    tix2 = pts["inertia_tare_index"].copy()
    tix2[i] = -1
    out2 = run_stages(with_updates(pts, arrays={"inertia_tare_index": tix2}),
                      dynamic_stages(lab["rig"], geo, samples))  # fmt: skip
    assert "no_inertia_tare" in out2.flags[i] and out2["inertia_method"][i] == "model"
    assert np.isfinite(out2["Cma"][i])
    # no wind-off oscillation at all: the offset is not identified, and said
    kinds = np.where(pts["kind"] == "oscillation_tare", "zero", pts["kind"])
    out3 = run_stages(with_updates(pts, arrays={"kind": kinds}),
                      dynamic_stages(lab["rig"], geo, samples))  # fmt: skip
    assert "clock_offset_not_identified" in out3.flags[i]
    assert out3["clock_offset_ns"][i] == 0.0
