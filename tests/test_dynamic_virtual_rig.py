"""The virtual rig moves (issue 22, section 3): its tensions along a forced oscillation against an
independent Newton-Euler and an independent aero model of a pitching model with its damping
derivatives (tests/_oscillation_truth.py), its truth file, the oscillation schedule's checks, and
``cdpr simulate --campaign`` of a short oscillation matrix read back with the mcap library: the
events' motion fields and the camera's clock offset in the /pose times."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _block_reader import messages
from _oscillation_truth import gravity, momentum_rate, motion, pitch_aero, read_rig, structure
from mcap.reader import make_reader
from test_dynamic_plan import HEAD  # the matrix's [campaign], [model] and [aero_estimate]

from cdpr.analysis.errors import ConfigError
from cdpr.daq.aero_model import AeroModel
from cdpr.daq.schema import load_rig
from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping
from cdpr.pipelines.campaign import load_test_matrix, schedule_from_matrix

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"

SMALL = (
    HEAD
    + """[virtual_rig]
rate_hz = 1000.0
seed = 5
camera_clock_offset_ns = 3000000
[virtual_rig.sensor]
latency_s = 0.0
[virtual_rig.pose_camera]
rate_hz = 200.0
[[points]]
label = "tare"
kind = "oscillation_tare"
axis = "pitch"
amplitude_deg = 5.0
frequency_Hz = 2.0
cycles = 3
transition_s = 0.2
[[points]]
label = "osc"
kind = "oscillation"
axis = "pitch"
amplitude_deg = 5.0
frequency_Hz = 2.0
cycles = 3
airspeed_mps = 25.51
transition_s = 0.2
"""
)


def _small(tmp_path: Path) -> Path:
    f = tmp_path / "small.toml"
    f.write_text(SMALL.format(rig=RIG.as_posix()))
    return f


def test_moving_tensions_obey_an_independent_newton_euler_and_aero(tmp_path: Path) -> None:
    m = load_test_matrix(_small(tmp_path))
    rig = load_rig(RIG)
    vr = VirtualRig(rig, schedule_from_matrix(m, rig))
    tr = vr.truth()
    trig = read_rig(RIG)
    model = AeroModel()
    coef = {"CL_alpha": model.CL_alpha, "CD0": model.CD0, "k_induced": model.k_induced,
            "Cm_alpha": model.Cm_alpha, "CLq_sum": 4.0, "Cmq_sum": -6.5, "S": 0.014646,
            "cref": 0.060}  # fmt: skip
    assert (model.CLq + model.CLadot, model.Cmq + model.Cmadot) == (4.0, -6.5)
    ev = {(e["point"], e["phase"]): e["t_rel_ns"] for e in vr.test_point_events()}
    mean = np.concatenate([trig.home, [0.0, 0.0, 0.0]])
    amp, f = math.radians(5.0), 2.0
    worst = {"A T": 0.0, "W": 0.0}
    for point, V in (("tare", 0.0), ("osc", 25.51)):
        t0 = ev[(point, "start")] * 1e-9  # the motion starts with the point
        assert (ev[(point, "end")] - ev[(point, "start")]) * 1e-9 == pytest.approx(5 / f)

        def pose(t: float, t0: float = t0) -> np.ndarray:
            return motion(np.array([t - t0]), mean, 4, amp, f, 2, 3)[0]

        rows = np.flatnonzero((tr["t_rel_ns"] * 1e-9 > t0) & (tr["t_rel_ns"] * 1e-9 < t0 + 3.0))
        for k in rows[::37]:
            t = tr["t_rel_ns"][k] * 1e-9
            q = pose(t)
            np.testing.assert_allclose(tr["position_O_m"][k], q[:3], atol=1e-12)
            np.testing.assert_allclose(tr["euler_rad"][k], q[3:], atol=1e-12)
            h = 1e-5
            theta_dot = (pose(t + h)[4] - pose(t - h)[4]) / (2 * h)
            W = pitch_aero(q[4], theta_dot, V, coef) if V > 0 else np.zeros(6)
            worst["W"] = max(worst["W"], float(np.abs(tr["wrench_aero_O"][k] - W).max()))
            need = momentum_rate(trig, pose, t) - gravity(trig, q) - W
            got = structure(trig, q) @ tr["tensions_true_N"][k]
            worst["A T"] = max(worst["A T"], float(np.abs(got - need).max()))
    assert worst["W"] < 1e-6 and worst["A T"] < 1e-4, worst
    # the inertia is there: at full amplitude its pitching moment peaks at I_yy A w^2
    t_rel = tr["t_rel_ns"] * 1e-9
    t0 = ev[("tare", "start")] * 1e-9
    win = (t_rel >= t0 + 1.0) & (t_rel < t0 + 2.5)
    assert np.abs(tr["wrench_inertia_O"][win, 4]).max() == pytest.approx(
        trig.inertia_P[1, 1] * amp * (2 * np.pi * f) ** 2, rel=0.02
    )


def test_truth_file_holds_the_motion_derivatives_and_clock_offset(tmp_path: Path) -> None:
    m = load_test_matrix(_small(tmp_path))
    rig = load_rig(RIG)
    vr = VirtualRig(rig, schedule_from_matrix(m, rig))
    path = vr.write_truth(tmp_path / "t.truth.npz")
    z = np.load(path)
    assert int(z["camera_clock_offset_ns"]) == 3_000_000
    assert list(z["segment_kinds"]) == ["oscillation_tare", "oscillation"]
    assert list(z["segment_motion_axis"]) == ["pitch", "pitch"]
    np.testing.assert_allclose(z["segment_motion_amplitude"], math.radians(5.0))
    assert list(z["segment_inertia_tare"]) == ["", "tare"]
    assert list(z["segment_motion_start_rel_ns"]) == [200_000_000, 3_400_000_000]
    names = list(z["derivative_names"])
    d = dict(zip(names, z["segment_derivatives"][1], strict=True))
    assert np.isnan(z["segment_derivatives"][0]).all()  # wind off: none
    # by hand for a pitching model at aoa 0 about its MRP: Cm = Cma a + (Cmq + Cmadot) q c / 2V
    assert d["Cm_inphase"] == pytest.approx(-0.4, abs=1e-3)
    assert d["Cm_quadrature"] == pytest.approx(-6.5, rel=1e-3)
    assert d["CL_inphase"] == pytest.approx(3.5, rel=1e-3)
    assert d["CL_quadrature"] == pytest.approx(4.0, rel=1e-3)
    assert d["k"] == pytest.approx(2 * np.pi * 2.0 * 0.060 / (2 * 25.51))
    model = dict(zip(z["aero_model_names"], z["aero_model_values"], strict=True))
    assert model["Cmq"] == -5.0 and model["Cmadot"] == -1.5 and model["Cnr"] == -0.15
    assert z["pose_rate"].shape == z["pose_accel"].shape == (vr.n_samples, 6)


def test_heave_and_yaw_rates_enter_the_aero_model_with_their_signs() -> None:
    m = AeroModel()
    V = 25.0
    # heave: the model moving up at w sees the air from above: aoa = -atan(w / V)
    q0 = np.array([0.5, 0.0, 0.3, 0.0, 0.0, 0.0])
    qd = np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0])
    W = m.wrench_moving_O(V, q0, qd, np.zeros(6))
    a = -math.atan(0.5 / V)
    W_still = m.wrench_O(V, np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0],
                                      [-math.sin(a), 0, math.cos(a)]]))  # fmt: skip
    # the same lift coefficient as the model pitched to that aoa, at |v|^2 = V^2 + w^2, lift
    # perpendicular to the relative wind
    qS = (
        0.5
        * float(m.air_density(m.static_pressure_Pa, m.temperature_K))
        * (V**2 + 0.25)
        * m.s_ref_m2
    )
    CL = m.CL_alpha * a
    assert W[2] == pytest.approx(qS * CL * math.cos(a) + qS * (m.CD0 + m.k_induced * CL**2)
                                 * math.sin(a), rel=1e-9)  # fmt: skip
    assert W_still[2] < 0 and W[2] < 0
    # yaw rate r_B = -yaw_dot at aoa 0 (body z down): Cn gains -Cnr yaw_dot b / 2V, Mz_O = -N_B
    qd = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.3])
    W = m.wrench_moving_O(V, q0, qd, np.zeros(6))
    qS = 0.5 * float(m.air_density(m.static_pressure_Pa, m.temperature_K)) * V**2 * m.s_ref_m2
    Cn = m.Cnr * (-0.3) * m.b_ref_m / (2 * V)  # beta_dot = yaw_dot, Cnbetadot = 0
    assert W[5] == pytest.approx(-qS * m.b_ref_m * Cn, rel=1e-9)
    assert W[3] == pytest.approx(-qS * m.b_ref_m * m.Clr * (-0.3) * m.b_ref_m / (2 * V), rel=1e-9)
    # wind off: no aero load, whatever the motion
    assert np.all(m.wrench_moving_O(0.0, q0, qd, np.zeros(6)) == 0.0)


@pytest.mark.parametrize(
    ("patch", "key", "problem"),
    [
        ({"motion_axis": ""}, "segments[0].motion_axis", "missing"),
        ({"motion_cycles": 0}, "segments[0].motion_cycles", ">= 1"),
        ({"duration_s": 2.0}, "segments[0].duration_s", "shorter than the ramp and the motion"),
        ({"kind": "wind_on"}, "segments[0].motion_axis", "only an oscillation point moves"),
        ({"motion_axis": "spin"}, "segments[0].motion_axis", "expected one of"),
    ],
)
def test_oscillation_segments_are_checked(patch: dict, key: str, problem: str) -> None:
    seg = {"kind": "oscillation", "duration_s": 3.5, "transition_s": 0.5, "wind_mps": 20.0,
           "motion_axis": "pitch", "motion_amplitude": 0.05, "motion_frequency_Hz": 2.0,
           "motion_cycles": 3, "motion_settling_cycles": 2}  # fmt: skip
    rig = load_rig(RIG)
    schedule_from_mapping({"segments": [seg]}, "s.toml", rig)  # the unpatched one is fine
    with pytest.raises(ConfigError) as ei:
        schedule_from_mapping({"segments": [{**seg, **patch}]}, "s.toml", rig)
    assert ei.value.key == key and problem in ei.value.problem, ei.value
    with pytest.raises(ConfigError) as ei:  # $TPT lines cannot carry a motion
        schedule_from_mapping(
            {"schedule": {"test_points_on_link": True}, "segments": [seg]}, "s.toml", rig
        )
    assert ei.value.key == "segments[0].kind" and "tunnel link" in ei.value.problem


def test_simulate_campaign_runs_oscillation_points_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "runs"
    res = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "simulate", "--campaign",
         str(_small(tmp_path)), "--out", str(out), "--quiet"],
        capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    (run,) = out.glob("*.mcap")
    truth = np.load(run.with_name(run.stem + ".truth.npz"))
    with run.open("rb") as fh:  # the mcap library's reader, column blocks row by row
        by_topic = messages(make_reader(fh))
    ev = [b for _, b in by_topic["/events"]]
    assert [(e["point"], e["phase"], e["kind"]) for e in ev] == [
        ("tare", "start", "oscillation_tare"), ("tare", "end", "oscillation_tare"),
        ("osc", "start", "oscillation"), ("osc", "end", "oscillation"),
    ]  # fmt: skip
    for e in ev:
        assert e["motion_axis"] == "pitch" and e["motion_cycles"] == 3
        assert e["motion_amplitude"] == pytest.approx(math.radians(5.0))
        assert e["motion_frequency_Hz"] == 2.0 and e["motion_settling_cycles"] == 2
    assert [e["inertia_tare"] for e in ev] == ["", "", "tare", "tare"]
    t_ev = np.array([t for t, _ in by_topic["/events"]])
    np.testing.assert_array_equal(np.diff(t_ev), [2.5e9, 0.7e9, 2.5e9])  # 5 cycles; ramp + 0.2 s
    # the camera: 200 Hz, its frames stamped 3 ms ahead of the load cells' clock
    pose = by_topic["/pose"]
    t_cam = np.array([t for t, _ in pose], dtype=np.int64)
    assert 0.8 * 200 * 6.4 < t_cam.size < 1.2 * 200 * 6.4
    pitch = np.array([_pitch_of(b) for _, b in pose])
    sel = (t_cam > truth["t_ns"][0] + 10**8) & (t_cam < truth["t_ns"][-1] - 10**8)
    rms = {
        off: float(np.sqrt(np.mean(
            (pitch[sel] - np.interp(t_cam[sel] - off, truth["t_ns"], truth["euler_rad"][:, 1])) ** 2
        )))
        for off in (0, 1_000_000, 2_000_000, 3_000_000, 4_000_000, 5_000_000)
    }  # fmt: skip
    assert min(rms, key=rms.__getitem__) == 3_000_000, rms
    assert rms[3_000_000] < 2 * math.radians(0.01) < rms[0]
    # the load cells' samples, one a millisecond
    n_T = len(by_topic["/tensions"])
    assert 0.9 * truth["t_ns"].size <= n_T <= truth["t_ns"].size


def _pitch_of(body: dict) -> float:
    o = body["pose"]["orientation"]
    w, x, y, z = o["w"], o["x"], o["y"], o["z"]
    return math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
