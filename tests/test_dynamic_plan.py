"""``cdpr plan`` and the oscillation points of the test matrix (issue 22, sections 1-2).

The plan's refusals and flags are checked against an independent computation written here and
in tests/_oscillation_truth.py / tests/_stiffness_truth.py: the motion of the issue's formula,
Newton-Euler from momentum differences, feasibility by scipy's linprog at sampled phases, tensions
by quadprog, and the natural modes by a finite-difference stiffness and scipy's generalized
eigenproblem."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.linalg
from _oscillation_truth import (
    controller,
    feasible,
    gravity,
    lengths,
    momentum_rate,
    motion,
    read_rig,
    structure,
)
from _stiffness_truth import fd_stiffness, rigid_mass

from cdpr.analysis.errors import ConfigError
from cdpr.daq.schema import load_rig
from cdpr.pipelines.campaign import load_test_matrix
from cdpr.pipelines.motion_plan import plan_matrix

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
AXES = {"pitch": 4, "yaw": 5, "roll": 3}

HEAD = """
[campaign]
name = "t"
rig = "{rig}"
[model]
area_m2 = 0.014646
span_m = 0.2441
chord_m = 0.060
mrp_P_m = [0.0, 0.0, 0.0]
[aero_estimate]
Cmq = -5.0
"""


def _osc(label: str, axis: str, amp_deg: float, f: float, kind: str = "oscillation_tare",
         extra: str = "", cycles: int = 2) -> str:  # fmt: skip
    return (
        f'[[points]]\nlabel = "{label}"\nkind = "{kind}"\naxis = "{axis}"\n'
        f"amplitude_deg = {amp_deg}\nfrequency_Hz = {f}\ncycles = {cycles}\nsettling_cycles = 2\n"
        + extra
    )


def _matrix(tmp_path: Path, body: str, rig: Path = RIG) -> Path:
    p = tmp_path / "m.toml"
    p.write_text(HEAD.format(rig=rig.as_posix()) + body)
    return p


# --------------------------------------------------------------------------------------------
# refusals: an independent feasibility check at sampled phases (linprog, Newton-Euler)
# --------------------------------------------------------------------------------------------
CASES = [  # label, axis, amplitude deg, frequency Hz
    ("yaw2", "yaw", 2.0, 1.0),  # the issue: the flat optimum cannot hold 2 deg of yaw
    ("yaw05", "yaw", 0.5, 1.0),  # about 0.5-0.7 deg is feasible
    ("pitch30", "pitch", 30.0, 2.0),  # the issue: 30 deg of pitch at 2 Hz
    ("pitch5", "pitch", 5.0, 2.0),
    ("roll25", "roll", 25.0, 1.5),
]


def _independent(trig, axis: str, amp: float, f: float) -> tuple[bool, float]:
    """(feasible at every sampled instant, smallest margin to t_min of quadprog's tensions)."""
    j, n_set, n_cyc = AXES[axis], 2, 2
    mean = np.concatenate([trig.home, [0.0, 0.0, 0.0]])

    def pose(t: float) -> np.ndarray:
        return motion(np.array([t]), mean, j, amp, f, n_set, n_cyc)[0]

    ok, margin = True, math.inf
    # 48 phases of a full-amplitude cycle and 24 instants of each ramp
    t_full = n_set / f + np.arange(48) / (48 * f)
    t_ramps = np.concatenate([np.linspace(0.02, n_set / f, 24), (n_set + n_cyc) / f
                              + np.linspace(0.0, 1 / f, 24)])  # fmt: skip
    for t in np.concatenate([t_full, t_ramps]):
        q = pose(t)
        A = structure(trig, q)
        w = momentum_rate(trig, pose, t) - gravity(trig, q)
        if not feasible(A, w, trig.tmin, trig.tmax):
            ok = False
            continue
        margin = min(margin, float((controller(A, w, trig.tmin, trig.tmax) - trig.tmin).min()))
    return ok, margin


def test_plan_refuses_slack_points_as_linprog_finds_them(tmp_path: Path) -> None:
    body = "".join(_osc(*c) for c in CASES)
    m = load_test_matrix(_matrix(tmp_path, body))
    plans = {p.point.label: p for p in plan_matrix(m, load_rig(RIG), rate_hz=400.0)}
    trig = read_rig(RIG)
    seen = {}
    for label, axis, amp, f in CASES:
        ok, margin = _independent(trig, axis, math.radians(amp), f)
        p = plans[label]
        refused_slack = any(r.startswith("slack") for r in p.refused)
        assert refused_slack == (not ok), (label, p.refused, ok)
        seen[label] = ok
        if ok:  # the margin it reports is quadprog's over the motion (finer sampling: <= it)
            assert p.numbers["t_min_margin_N"] <= margin + 1e-6
            assert p.numbers["t_min_margin_N"] == pytest.approx(margin, abs=0.5)
        else:
            text = p.refused[0]
            assert label not in text and "t_min" in text and "% of the motion" in text
    assert seen == {"yaw2": False, "yaw05": True, "pitch30": False, "pitch5": True,
                    "roll25": True}  # fmt: skip


# --------------------------------------------------------------------------------------------
# modes: an independent stiffness (finite differences of the cable wrench) and scipy's eigh
# --------------------------------------------------------------------------------------------
def _independent_modes(trig) -> np.ndarray:
    q = np.concatenate([trig.home, [0.0, 0.0, 0.0]])
    A = structure(trig, q)
    T0 = controller(A, -gravity(trig, q), trig.tmin, trig.tmax)
    K = fd_stiffness(trig.anchors, trig.attach, trig.home, T0, trig.EA, trig.mass, trig.com)
    M = rigid_mass(trig.mass, trig.com, trig.inertia_P)
    w2 = scipy.linalg.eigh(0.5 * (K + K.T), M, eigvals_only=True)
    return np.sqrt(w2) / (2 * np.pi)


def test_plan_flags_a_harmonic_on_a_mode_and_refuses_resonance(tmp_path: Path) -> None:
    modes = _independent_modes(read_rig(RIG))
    f_yaw, f_pitch = modes[0], modes[1]  # 9.2 and 12.9 Hz on the flat optimum
    f_flag = round(f_yaw / 2, 2)  # its 2nd harmonic on the lowest mode
    f_res = round(0.97 * f_pitch, 2)  # the fundamental 3 % under the pitch mode
    f_ok = 2.0
    body = (
        _osc("flag", "pitch", 1.0, f_flag)
        + _osc("res", "pitch", 0.5, f_res)
        + _osc("ok", "pitch", 5.0, f_ok)
    )
    m = load_test_matrix(_matrix(tmp_path, body))
    plans = {p.point.label: p for p in plan_matrix(m, load_rig(RIG), rate_hz=400.0)}

    def near(f: float) -> list[int]:  # harmonics within 10 % of an independent mode
        return [h for h in (1, 2, 3) if np.any(np.abs(h * f - modes) <= 0.1 * modes)]

    assert 2 in near(f_flag) and 1 not in near(f_flag) and near(f_res)[0] == 1
    assert near(f_ok) == []
    for label, f in (("flag", f_flag), ("res", f_res), ("ok", f_ok)):  # the same harmonics
        mc = plans[label].modes
        assert mc is not None
        assert [h + 1 for h in np.flatnonzero(mc.harmonics.near)] == near(f), label
    p = plans["flag"]
    assert p.verdict == "flagged" and p.flags == ["harmonic_near_mode"]
    assert any("harmonic 2" in t and "mode 1 (yaw" in t for t in p.notes), p.notes
    p = plans["res"]
    assert p.verdict == "refused" and p.refused[0].startswith("resonance")
    assert f"({f_res:g} Hz)" in p.refused[0] and "mode 2 (pitch" in p.refused[0]
    assert plans["ok"].verdict == "ok" and not plans["ok"].flags
    # the plan's modes over the cycle bracket the independent ones (tensions differ a little)
    mc = plans["ok"].modes
    assert mc is not None
    np.testing.assert_allclose(0.5 * (mc.lo_Hz + mc.hi_Hz), modes, rtol=0.05)


# --------------------------------------------------------------------------------------------
# winch limits from the rig file
# --------------------------------------------------------------------------------------------
def test_plan_refuses_a_cable_faster_than_its_winch(tmp_path: Path) -> None:
    text = RIG.read_text().replace('t_max_N = 300.0\n', 't_max_N = 300.0\nmax_speed_mps = 0.006\n'
                                   'max_accel_mps2 = 1.0\n')  # fmt: skip
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(text)
    m = load_test_matrix(_matrix(tmp_path, _osc("fast", "pitch", 5.0, 2.0)
                                 + _osc("slow", "pitch", 5.0, 1.0), rig=rig_file))  # fmt: skip
    plans = {p.point.label: p for p in plan_matrix(m, load_rig(rig_file), rate_hz=1000.0)}
    trig = read_rig(RIG)
    mean = np.concatenate([trig.home, [0.0, 0.0, 0.0]])
    for label, f, refused in (("fast", 2.0, True), ("slow", 1.0, False)):
        t = np.arange(0.0, 5.0 / f, 1e-4)  # own lengths, own differences
        L = np.array([lengths(trig, q) for q in motion(t, mean, 4, math.radians(5), f, 2, 2)])
        v = np.abs(np.gradient(L, t, axis=0)).max()
        assert (v > 0.006) == refused
        p = plans[label]
        assert p.numbers["max_cable_speed"] == pytest.approx(v, rel=1e-3)
        assert (p.verdict == "refused") == refused
        assert not any("not checked" in n for n in p.notes)
    assert (
        plans["fast"].refused[0].startswith("cable speed:")
        and "0.006 m/s" in plans["fast"].refused[0]
    )


# --------------------------------------------------------------------------------------------
# the command: tables, summary, figures, exit codes
# --------------------------------------------------------------------------------------------
def test_cdpr_plan_writes_tables_a_summary_and_figures(tmp_path: Path) -> None:
    body = (
        _osc("tare", "pitch", 5.0, 2.0)
        + _osc("osc", "pitch", 5.0, 2.0, "oscillation", "airspeed_mps = 25.51\n")
        + _osc("yaw2", "yaw", 2.0, 1.0)
        + '[[points]]\nlabel = "zero"\nkind = "zero"\n'
    )
    out = tmp_path / "plan"
    res = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "plan", str(_matrix(tmp_path, body)),
         "--out", str(out), "--rate-hz", "200"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 3, res.stderr  # a point refused
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("cdpr plan: refused: yaw2: slack:"), lines
    assert "ok: osc:" in res.stdout and "ok: tare:" in res.stdout
    assert not (out / "yaw2.csv").exists()  # no table to follow for a refused point
    # the controller's table: rows, columns, lengths by the test's own kinematics
    df = pd.read_csv(out / "osc.csv", comment="#")
    assert len(df) == int(5 / 2.0 * 200) + 1
    names = load_rig(RIG).cable_names
    assert list(df.columns[:7]) == ["t_s", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]
    trig = read_rig(RIG)
    mean = np.concatenate([trig.home, [0.0, 0.0, 0.0]])
    t = df["t_s"].to_numpy()
    np.testing.assert_allclose(t, np.arange(len(df)) / 200.0, atol=1e-9)
    q = motion(t, mean, 4, math.radians(5), 2.0, 2, 2)
    np.testing.assert_allclose(df[["x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]], q,
                               atol=1e-8)  # fmt: skip
    L = np.array([lengths(trig, x) for x in q])
    np.testing.assert_allclose(df[[f"L_{c}_m" for c in names]], L, atol=1e-8)
    T = df[[f"T_{c}_N" for c in names]].to_numpy()
    assert T.min() >= 35.0 - 1e-6 and T.max() <= 300.0 + 1e-6
    for c in ("Ldot", "Lddot"):
        assert all(f"{c}_{n}_{'mps' if c == 'Ldot' else 'mps2'}" in df.columns for n in names)
    head = [x for x in (out / "osc.csv").read_text().splitlines() if x.startswith("#")]
    assert any(x.startswith("# matrix:") and "sha256=" in x for x in head)
    s = pd.read_csv(out / "summary.csv", comment="#")
    assert list(s["point"]) == ["tare", "osc", "yaw2"]
    assert list(s["verdict"]) == ["ok", "ok", "refused"]
    assert s.loc[2, "reason"].startswith("slack") and s.loc[1, "inertia_tare"] == "tare"
    md = (out / "summary.md").read_text()
    assert "## Refused" in md and "yaw2: slack" in md
    for label in ("tare", "osc", "yaw2"):
        png = (out / f"{label}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


def test_cdpr_plan_flags_give_exit_1_and_bad_options_exit_2(tmp_path: Path) -> None:
    body = _osc("osc", "pitch", 5.0, 2.0, "oscillation", "airspeed_mps = 25.51\n")
    m = _matrix(tmp_path, body)  # no tare serves it: no_inertia_tare
    run = [sys.executable, "-m", "cdpr.pipelines.cli", "plan", str(m), "--no-plots"]
    res = subprocess.run([*run, "--out", str(tmp_path / "a")], capture_output=True, text=True,
                         timeout=300)  # fmt: skip
    assert res.returncode == 1 and "flags: no_inertia_tare" in res.stdout, res.stdout
    res = subprocess.run([*run, "--out", str(tmp_path / "b"), "--point", "nope"],
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "'nope'" in res.stderr
    assert not (tmp_path / "b").exists()


# --------------------------------------------------------------------------------------------
# the test matrix: oscillation points, their tares, one-line errors
# --------------------------------------------------------------------------------------------
def test_oscillation_points_expand_and_find_their_inertia_tares(tmp_path: Path) -> None:
    m = load_test_matrix(ROOT / "data_samples" / "campaign_oscillation.toml")
    osc = [p for p in m.points if p.kind == "oscillation"]
    assert [p.label for p in osc] == [
        "osc-A5-f1-a0-b0-v25.51", "osc-A5-f2-a0-b0-v25.51",
        "osc-A5-f1-a0-b0-v41.42", "osc-A5-f2-a0-b0-v41.42", "yaw",
    ]  # fmt: skip
    assert [p.inertia_tare for p in osc] == [
        "osc-tare-A5-f1-a0-b0-v0", "osc-tare-A5-f2-a0-b0-v0",
        "osc-tare-A5-f1-a0-b0-v0", "osc-tare-A5-f2-a0-b0-v0", "yaw-tare",
    ]  # fmt: skip
    assert m.missing_inertia_tares() == []
    p = m.point("osc-A5-f2-a0-b0-v41.42")
    assert p.motion_amplitude == pytest.approx(math.radians(5.0))
    assert p.duration_s == pytest.approx((2 + 60 + 1) / 2.0)
    ev = p.event_fields()
    assert ev["motion_axis"] == "pitch" and ev["motion_cycles"] == 60
    assert ev["motion_settling_cycles"] == 2 and ev["motion_frequency_Hz"] == 2.0
    assert ev["inertia_tare"] == "osc-tare-A5-f2-a0-b0-v0"
    assert "motion_axis" not in m.point("zero-start").event_fields()
    # a tare of another frequency does not serve; none: listed as missing
    body = _osc("t", "pitch", 5.0, 1.0) + _osc("o", "pitch", 5.0, 2.0, "oscillation",
                                              "airspeed_mps = 20.0\n")  # fmt: skip
    m2 = load_test_matrix(_matrix(tmp_path, body))
    assert m2.point("o").inertia_tare == "" and m2.missing_inertia_tares() == ["o"]


OSC = 'kind = "oscillation"\naxis = "pitch"\namplitude_deg = 5.0\nfrequency_Hz = 1.0\ncycles = 3\n'


@pytest.mark.parametrize(
    ("body", "key", "problem"),
    [
        ('label = "o"\nkind = "oscillation"\namplitude_deg = 5.0\nfrequency_Hz = 1.0\ncycles = 3\n'
         "airspeed_mps = 20.0\n", "points[0].axis", "missing"),
        (OSC.replace('"pitch"', '"twist"') + "airspeed_mps = 20.0\n", "points[0].axis",
         "expected one of"),
        (OSC.replace("amplitude_deg", "amplitude_m") + "airspeed_mps = 20.0\n",
         "points[0].amplitude_m", "takes amplitude_deg"),
        (OSC.replace("frequency_Hz = 1.0", "frequency_Hz = [1.0, 0.0]") + "airspeed_mps = 20.0\n",
         "points[0].frequency_Hz", "> 0"),
        (OSC.replace("cycles = 3", "cycles = 2.5") + "airspeed_mps = 20.0\n", "points[0].cycles",
         "whole number"),
        (OSC + "settling_cycles = 0\nairspeed_mps = 20.0\n", "points[0].settling_cycles", ">= 1"),
        (OSC + "duration_s = 4.0\nairspeed_mps = 20.0\n", "points[0].duration_s", "lasts its cycles"),
        (OSC, "points[0].airspeed_mps", "airspeed > 0"),
        (OSC.replace('"oscillation"', '"oscillation_tare"') + "airspeed_mps = 20.0\n",
         "points[0].airspeed_mps", "wind-off"),
        (OSC.replace('"oscillation"', '"oscillation_tare"') + 'inertia_tare = "x"\n',
         "points[0].inertia_tare", "only an oscillation point"),
        (OSC + 'airspeed_mps = 20.0\ninertia_tare = "nope"\n', "points[0].inertia_tare",
         "no point labelled"),
        ('kind = "wind_on"\nairspeed_mps = 20.0\naxis = "pitch"\n', "points[0].axis",
         "only an oscillation point"),
        (OSC + "amplitude_m = 0.01\nairspeed_mps = 20.0\n", "points[0].amplitude_m",
         "takes amplitude_deg"),
    ],
)  # fmt: skip
def test_bad_oscillation_points_name_file_and_key(
    tmp_path: Path, body: str, key: str, problem: str
) -> None:
    f = _matrix(tmp_path, '[[points]]\nlabel = "o"\n' + body if "label" not in body else
                "[[points]]\n" + body)  # fmt: skip
    with pytest.raises(ConfigError) as ei:
        load_test_matrix(f)
    assert ei.value.source == str(f) and ei.value.key == key, ei.value
    assert problem in ei.value.problem, ei.value


def test_an_inertia_tare_of_another_motion_is_refused(tmp_path: Path) -> None:
    body = _osc("t", "pitch", 4.0, 1.0) + _osc(
        "o", "pitch", 5.0, 1.0, "oscillation", 'airspeed_mps = 20.0\ninertia_tare = "t"\n'
    )
    with pytest.raises(ConfigError) as ei:
        load_test_matrix(_matrix(tmp_path, body))
    assert ei.value.key == "points[1].inertia_tare" and "another motion" in ei.value.problem


def test_a_repeat_of_another_motion_is_refused(tmp_path: Path) -> None:
    wind = "airspeed_mps = 20.0\n"
    body = _osc("o1", "pitch", 5.0, 1.0, "oscillation", wind) + _osc(
        "o2", "pitch", 5.0, 2.0, "oscillation", wind + 'repeat_of = "o1"\n'
    )
    with pytest.raises(ConfigError) as ei:
        load_test_matrix(_matrix(tmp_path, body))
    assert ei.value.key == "points[1].repeat_of" and "another target" in ei.value.problem
    ok = body.replace("frequency_Hz = 2.0", "frequency_Hz = 1.0")
    assert load_test_matrix(_matrix(tmp_path, ok)).point("o2").repeat_of == "o1"


def test_simulate_refuses_a_point_the_plan_refuses_before_recording(tmp_path: Path) -> None:
    body = _osc("fine", "pitch", 5.0, 2.0) + _osc("yaw2", "yaw", 2.0, 1.0)
    out = tmp_path / "runs"
    res = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "simulate", "--campaign",
         str(_matrix(tmp_path, body)), "--out", str(out), "--quiet"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert res.returncode == 2
    assert res.stderr.count("\n") == 1 and "points (yaw2): refused by the motion plan" in res.stderr
    assert "slack" in res.stderr
    assert not out.exists() or not list(out.iterdir())
