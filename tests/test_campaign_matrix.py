"""The test matrix (``pipelines/campaign.py``): the aoa/sideslip -> attitude convention, the sample
campaign, one-line errors naming file and key, the virtual rig driven by the matrix (test-point
events, model-off windage, targets) and ``cdpr simulate --campaign`` read back with the mcap
library's own reader."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _block_reader import messages
from mcap.reader import make_reader

from cdpr.analysis.aero import attitude_from_flow_angles, flow_angles
from cdpr.analysis.errors import ConfigError
from cdpr.daq.aero_model import AeroModel
from cdpr.daq.files import load_toml
from cdpr.daq.schema import rig_from_mapping
from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping
from cdpr.pipelines.campaign import load_test_matrix, schedule_mapping

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data_samples" / "campaign_alpha_sweep.toml"
RIG = ROOT / "data_samples" / "flat_experiment2.toml"


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@pytest.mark.parametrize(("aoa_deg", "sideslip_deg"), [(0, 0), (5, 0), (-4, 0), (3, 7), (-6, -2)])
def test_attitude_is_pitch_aoa_yaw_sideslip_for_the_default_mounting(
    aoa_deg: float, sideslip_deg: float
) -> None:
    # hand derivation: nose along -x_P, z_B = -z_P; with R = Rz(y) Ry(p) the model's velocity
    # relative to the air in body axes is (cy cp, sy, cy sp): aoa = p, sideslip = y
    a, b = math.radians(aoa_deg), math.radians(sideslip_deg)
    R = attitude_from_flow_angles(a, b)
    np.testing.assert_allclose(R, _rot_z(b) @ _rot_y(a), atol=1e-12)
    # the virtual rig's aero model computes the angles with its own code
    al, be = AeroModel().angles(R)
    assert float(al) == pytest.approx(a, abs=1e-12) and float(be) == pytest.approx(b, abs=1e-12)


def test_attitude_inverts_flow_angles_for_another_mounting() -> None:
    nose, up = (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)  # model mounted nose along +y_P
    a = np.radians([-4.0, 0.0, 6.0, 10.0])
    b = np.radians([2.0, -3.0, 0.0, 5.0])
    R = attitude_from_flow_angles(a, b, nose, up)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    al, be = flow_angles(R, nose, up)
    np.testing.assert_allclose(al, a, atol=1e-12)
    np.testing.assert_allclose(be, b, atol=1e-12)


def test_sample_campaign_expands_in_run_order() -> None:
    m = load_test_matrix(SAMPLE)
    labels = [p.label for p in m.points]
    assert len(labels) == len(set(labels)) == 1 + 6 + 18 + 18 + 1 + 1
    assert labels[0] == "zero-start" and labels[-1] == "zero-end"
    assert labels[1:7] == [f"tare-a{a}-b0-v0" for a in (-4, -2, 0, 2, 4, 6)]
    # airspeed outer, aoa inner; the model-off windage points before the sweep
    assert labels[7] == "windage-a-4-b0-v17.27" and labels[13] == "windage-a-4-b0-v25.51"
    assert {m.point(x).kind for x in labels[7:25]} == {"windage"}
    assert labels[25] == "alpha-a-4-b0-v17.27" and labels[31] == "alpha-a-4-b0-v25.51"
    speeds = sorted({p.airspeed_mps for p in m.points if p.kind == "wind_on"})
    assert speeds == [17.27, 25.51, 41.42]
    rep = m.point("repeat-a2-v25.51")
    assert rep.repeat_of == "alpha-a2-b0-v25.51" and rep.aoa_deg == 2.0
    assert m.missing_tares() == []
    assert m.rig_path == RIG and m.model.chord_m == 0.060 and m.model.mrp_P_m == (0, 0, 0)
    assert m.point("tare-a6-b0-v0").euler_rad == pytest.approx((0.0, math.radians(6), 0.0))


BASE = """
[campaign]
name = "t"
rig = "{rig}"
[model]
area_m2 = 0.0146
span_m = 0.2441
chord_m = 0.06
mrp_P_m = [0.0, 0.0, 0.0]
"""


@pytest.mark.parametrize(
    ("body", "key", "problem"),
    [
        ('[[points]]\nlabel = "a"\nkind = "wind_on"\n', "points[0].airspeed_mps", "airspeed > 0"),
        (
            '[[points]]\nlabel = "a"\nkind = "tare"\nairspeed_mps = 10.0\n',
            "points[0].airspeed_mps",
            "wind-off",
        ),
        ('[[points]]\nlabel = "z"\nkind = "zero"\naoa_deg = 2.0\n', "points[0].aoa_deg", "level"),
        ('[[points]]\nlabel = "a"\nkind = "wind"\n', "points[0].kind", "expected one of"),
        ('[[points]]\nlabel = "a"\nkind = "zero"\nspeed = 1\n', "points[0].speed", "unknown key"),
        (
            '[[points]]\nlabel = "a"\nkind = "zero"\n[[points]]\nlabel = "a"\nkind = "zero"\n',
            "points[1].label",
            "already used",
        ),
        (
            '[[points]]\nlabel = "r"\nkind = "wind_on"\nairspeed_mps = 20.0\nrepeat_of = "x"\n',
            "points[0].repeat_of",
            "no earlier point",
        ),
        (
            '[[points]]\nlabel = "a"\nkind = "wind_on"\nairspeed_mps = 20.0\n'
            '[[points]]\nlabel = "r"\nkind = "wind_on"\nairspeed_mps = 25.0\nrepeat_of = "a"\n',
            "points[1].repeat_of",
            "another target",
        ),
        (
            '[[points]]\nlabel = "s"\nkind = "tare"\naoa_deg = [0.0, 2.0, 0.0]\n',
            "points[0].aoa_deg",
            "repeated value",
        ),
        (
            '[[points]]\nlabel = "a"\nkind = "zero"\nduration_s = 0\n',
            "points[0].duration_s",
            "> 0",
        ),
        ("", "points", "non-empty"),
        (
            '[virtual_rig.aero]\nc_ref_m = 0.08\n[[points]]\nlabel = "a"\nkind = "zero"\n',
            "virtual_rig.aero.c_ref_m",
            "[model] only",
        ),
    ],
)
def test_bad_matrix_names_file_key_and_problem(
    tmp_path: Path, body: str, key: str, problem: str
) -> None:
    f = tmp_path / "m.toml"
    f.write_text(BASE.format(rig=RIG.as_posix()) + body)
    with pytest.raises(ConfigError) as ei:
        load_test_matrix(f)
    assert ei.value.source == str(f) and ei.value.key == key and problem in ei.value.problem


def test_missing_rig_file_is_named(tmp_path: Path) -> None:
    f = tmp_path / "m.toml"
    f.write_text(BASE.format(rig="nope.toml") + '[[points]]\nlabel = "a"\nkind = "zero"\n')
    with pytest.raises(ConfigError) as ei:
        load_test_matrix(f)
    assert ei.value.key == "campaign.rig" and "nope.toml" in ei.value.problem


SMALL = """
[virtual_rig]
rate_hz = 200.0
seed = 3
[[points]]
label = "tare"
kind = "tare"
aoa_deg = 4.0
duration_s = 0.5
transition_s = 0.0
[[points]]
label = "on"
kind = "wind_on"
aoa_deg = 4.0
airspeed_mps = 25.0
duration_s = 0.6
transition_s = 0.2
[[points]]
label = "windage"
kind = "windage"
airspeed_mps = 25.0
duration_s = 0.4
transition_s = 0.2
"""


def _small(tmp_path: Path) -> Path:
    f = tmp_path / "small.toml"
    f.write_text(BASE.format(rig=RIG.as_posix()) + SMALL)
    return f


def test_virtual_rig_runs_the_matrix(tmp_path: Path) -> None:
    m = load_test_matrix(_small(tmp_path))
    rig = rig_from_mapping(load_toml(RIG), str(RIG))
    sch = schedule_from_mapping(schedule_mapping(m), "x", rig)
    vr = VirtualRig(rig, sch)
    ev = vr.test_point_events()
    # start after each ramp, end at the segment end: 0 / 0.5, 0.7 / 1.3, 1.5 / 1.9 s
    got = [(e["point"], e["phase"], e["t_rel_ns"]) for e in ev]
    assert got == [
        ("tare", "start", 0), ("tare", "end", 500_000_000),
        ("on", "start", 700_000_000), ("on", "end", 1_300_000_000),
        ("windage", "start", 1_500_000_000), ("windage", "end", 1_900_000_000),
    ]  # fmt: skip
    assert ev[2]["kind"] == "wind_on" and ev[2]["target_airspeed_mps"] == 25.0
    assert ev[2]["target_aoa_deg"] == 4.0 and ev[0]["name"] == "test_point"
    t = vr.truth()
    k_on = np.flatnonzero((t["t_rel_ns"] >= 700_000_000) & (t["t_rel_ns"] < 1_300_000_000))
    k_wg = np.flatnonzero(t["t_rel_ns"] >= 1_500_000_000)
    # the commanded attitude plus the platform's yield under the load (a few hundredths of a degree)
    d = vr.deflection[t["segment_index"][k_on[0]]]
    assert 0 < abs(d[4]) < math.radians(0.1)
    expect = [[d[3], math.radians(4.0) + d[4], d[5]]] * len(k_on)
    np.testing.assert_allclose(t["euler_rad"][k_on], expect, atol=1e-12)
    np.testing.assert_allclose(t["wind_mps"][k_on], 25.0)
    # the aero model's geometry comes from [model]: q S CL at the aoa, rho from p/(R T)
    rho = 101325.0 / (287.05287 * 293.15)
    aoa = math.radians(4.0) + d[4]
    lift = 0.5 * rho * 25.0**2 * 0.0146 * 3.5 * aoa
    drag = 0.5 * rho * 25.0**2 * 0.0146 * (0.035 + 0.09 * (3.5 * aoa) ** 2)
    W = t["wrench_aero_O"][k_on[0]]
    assert W[2] == pytest.approx(lift, rel=1e-3) and W[0] == pytest.approx(drag, rel=1e-3)
    # model off: wind in the tunnel, no aero load on the model
    np.testing.assert_allclose(t["wind_mps"][k_wg], 25.0)
    assert np.all(t["wrench_aero_O"][k_wg] == 0.0)


@pytest.mark.parametrize("transport", ["virtual", "slcan"])
def test_simulate_campaign_records_test_point_events(tmp_path: Path, transport: str) -> None:
    # slcan: the rig runs in a second process; the events follow its start time
    out = tmp_path / "runs"
    res = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "simulate", "--campaign",
         str(_small(tmp_path)), "--out", str(out), "--quiet", "--transport", transport],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    (run,) = out.glob("*.mcap")
    with run.open("rb") as fh:  # column blocks row by row (tests/_block_reader.py)
        by_topic = messages(make_reader(fh))
    msgs = [(top, t, b) for top in ("/events", "/tensions") for t, b in by_topic[top]]
    ev = [(t, b) for top, t, b in msgs if top == "/events"]
    assert [(b["point"], b["phase"]) for _, b in ev] == [
        ("tare", "start"), ("tare", "end"), ("on", "start"), ("on", "end"),
        ("windage", "start"), ("windage", "end"),
    ]  # fmt: skip
    assert all(b["name"] == "test_point" for _, b in ev)
    assert ev[2][1]["target_airspeed_mps"] == 25.0 and ev[4][1]["kind"] == "windage"
    t_ev = np.array([t for t, _ in ev])
    np.testing.assert_array_equal(np.diff(t_ev), [5e8, 2e8, 6e8, 2e8, 4e8])  # schedule times
    t_T = np.array([t for top, t, _ in msgs if top == "/tensions"])
    # the wind-on point's tension samples fall inside its events: 120 at 200 Hz, +-50 % for the
    # reception times of a starved recorder (a pty delivers in bursts on a loaded machine)
    n_on = int(np.sum((t_T >= t_ev[2]) & (t_T < t_ev[3])))
    assert 60 <= n_on <= 180, n_on


@pytest.mark.parametrize(
    ("extra", "key"),
    [
        ("[virtual_rig.sensor]\nbogus = 1.0\n", "virtual_rig.sensor.bogus"),
        ('[virtual_rig]\nmethod = "nope"\n', "virtual_rig.method"),
    ],
)
def test_virtual_rig_errors_name_the_matrix_key(tmp_path: Path, extra: str, key: str) -> None:
    from cdpr.pipelines.campaign import schedule_from_matrix

    f = tmp_path / "m.toml"
    f.write_text(
        BASE.format(rig=RIG.as_posix()) + extra + '[[points]]\nlabel = "a"\nkind = "zero"\n'
    )
    rig = rig_from_mapping(load_toml(RIG), str(RIG))
    with pytest.raises(ConfigError) as ei:
        schedule_from_matrix(load_test_matrix(f), rig)
    assert ei.value.source == str(f) and ei.value.key == key


def test_faults_from_the_command_line_join_the_matrix_schedule(tmp_path: Path) -> None:
    from cdpr.pipelines.campaign import schedule_from_matrix

    m = load_test_matrix(_small(tmp_path))
    rig = rig_from_mapping(load_toml(RIG), str(RIG))
    fault = {"kind": "slack", "start_s": 0.8, "duration_s": 0.2, "cable": 2}
    sch = schedule_from_matrix(m, rig, [fault])
    assert [(f.kind, f.start_s, f.cable) for f in sch.faults] == [("slack", 0.8, 2)]
    bad = {"kind": "slack", "start_s": 99.0, "duration_s": 0.2, "cable": 2}
    with pytest.raises(ConfigError) as ei:
        schedule_from_matrix(m, rig, [bad])
    assert (ei.value.source, ei.value.key) == ("--fault", "#1.start_s")
    assert "after the end" in ei.value.problem
