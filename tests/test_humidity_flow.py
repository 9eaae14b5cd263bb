"""Humidity from the tunnel stream to the density of every point (issue 13): ``cdpr import --tunnel``
with a ``relative_humidity`` (or ``relative_humidity_pct``) column, then ``cdpr analyze --matrix``.

The expected moist-air density is the CIPM-2007 formula (Picard et al., Metrologia 45 (2008) 149),
written here: it is not the code's formula (the code uses the Buck vapour pressure and an ideal
mixture; CIPM has its own vapour pressure, the enhancement factor and the compressibility), so the
two agree to about 0.05 %, while dry air at the same p and T is 0.5 % off at 60 % humidity."""

from __future__ import annotations

import math
from pathlib import Path

import can
import numpy as np
import pandas as pd
import pytest

from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
P_PA, T_K, RH = 100_800.0, 296.15, 0.60
T_LOG0_NS = 1_700_000_000_000_000_000


def _can_log(path: Path, n_samples: int = 60) -> None:
    """A candump log at 100 Hz: 4 frames per sample (the DBC's ids), two 24-bit counts per frame
    (about 2e6 counts with a small deterministic ripple), status 0, the counter in byte 7."""
    logger = can.Logger(str(path))
    for k in range(n_samples):
        for j, fid in enumerate((385, 641, 897, 1153)):
            c1, c2 = (2_000_000 + 37 * ((k * (3 + 2 * j + i)) % 11) for i in (0, 1))
            data = c1.to_bytes(3, "little") + c2.to_bytes(3, "little") + bytes([0, k % 256])
            logger.on_message_received(
                can.Message(
                    arbitration_id=fid,
                    data=data,
                    is_extended_id=False,
                    timestamp=(T_LOG0_NS + k * 10_000_000 + j * 100_000) * 1e-9,
                    channel=0,
                )
            )
    logger.stop()


MATRIX = f"""
[campaign]
name = "humidity"
rig = "{RIG}"

[model]
name = "SDM"
area_m2 = 0.0199
span_m = 0.2441
chord_m = 0.0815
mrp_P_m = [0.0, 0.0, 0.0]

[[points]]
label = "t0"
kind = "tare"
"""
EVENTS = """t_s,point,phase,kind,target_aoa_deg,target_sideslip_deg,target_airspeed_mps,repeat_of
0.05,t0,start,tare,0,0,0,
0.25,t0,end,tare,0,0,0,
0.40,wet,start,wind_on,0,0,25,
0.60,wet,end,wind_on,0,0,25,
0.80,dry,start,wind_on,0,0,25,
1.00,dry,end,wind_on,0,0,25,
"""


def cipm2007_density(p_Pa: float, T_K: float, h: float, x_co2: float = 0.0004) -> float:
    """Moist-air density by the CIPM-2007 equation (Picard, Davis, Glaeser, Fujii 2008)."""
    t = T_K - 273.15
    psv = math.exp(1.2378847e-5 * T_K**2 - 1.9121316e-2 * T_K + 33.93711047 - 6.3431645e3 / T_K)
    f = 1.00062 + 3.14e-8 * p_Pa + 5.6e-7 * t**2
    xv = h * f * psv / p_Pa
    a0, a1, a2 = 1.58123e-6, -2.9331e-8, 1.1043e-10
    b0, b1, c0, c1 = 5.707e-6, -2.051e-8, 1.9898e-4, -2.376e-6
    d, e = 1.83e-11, -0.765e-8
    Z = (
        1
        - p_Pa / T_K * (a0 + a1 * t + a2 * t**2 + (b0 + b1 * t) * xv + (c0 + c1 * t) * xv**2)
        + (p_Pa / T_K) ** 2 * (d + e * xv**2)
    )
    Ma = (28.96546 + 12.011 * (x_co2 - 0.0004)) * 1e-3
    Mv, R = 18.01528e-3, 8.314472
    return p_Pa * Ma / (Z * R * T_K) * (1 - xv * (1 - Mv / Ma))


def _tunnel_csv(column: str, scale: float) -> str:
    """Rows every 0.1 s over 1.2 s; the humidity stops after 0.7 s (empty cells): the point 'wet'
    has it at every sample, the point 'dry' at none."""
    rows = [f"t_s,airspeed_mps,static_pressure_Pa,temperature_K,{column}"]
    for k in range(13):
        t = 0.1 * k
        v = 0.0 if t < 0.3 else 25.0
        rh = f"{RH * scale:g}" if t <= 0.7 else ""
        rows.append(f"{t:.1f},{v},{P_PA},{T_K},{rh}")
    return "\n".join(rows) + "\n"


@pytest.fixture(scope="module", params=[("relative_humidity", 1.0), ("relative_humidity_pct", 100)])
def analysed(request, tmp_path_factory) -> pd.DataFrame:
    column, scale = request.param
    tmp = tmp_path_factory.mktemp("rh")
    log = tmp / "run.log"
    _can_log(log, n_samples=120)
    (tmp / "tunnel.csv").write_text(_tunnel_csv(column, scale))
    (tmp / "events.csv").write_text(EVENTS)
    (tmp / "matrix.toml").write_text(MATRIX)
    run = tmp / "run.mcap"
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    argv += ["--tunnel", str(tmp / "tunnel.csv"), "--events", str(tmp / "events.csv")]
    assert main([*argv, "--out", str(run)]) == 0
    out = tmp / "out"
    main(["analyze", str(run), "--out", str(out), "--matrix", str(tmp / "matrix.toml")])
    return pd.read_csv(out / "run" / "points.csv").set_index("point")


def test_moist_density_at_a_point_matches_cipm2007(analysed: pd.DataFrame) -> None:
    wet = analysed.loc["wet"]
    rho = cipm2007_density(P_PA, T_K, RH)
    assert wet.density_kgpm3 == pytest.approx(rho, rel=5e-4)
    assert abs(wet.density_kgpm3 - P_PA / (287.05287 * T_K)) > 4e-3  # dry air is 0.5 % denser
    assert wet.relative_humidity == pytest.approx(RH, abs=1e-12)
    assert wet.density_source == "p_T_humidity"
    assert "humidity_not_given" not in str(wet["flags"]).split(";")


def test_point_without_humidity_is_flagged_dry_never_silent(analysed: pd.DataFrame) -> None:
    dry = analysed.loc["dry"]
    assert "humidity_not_given" in str(dry["flags"]).split(";")
    assert dry.density_source == "p_T_dry"
    assert np.isnan(dry.relative_humidity)
    # dry air at the same p and T: the ideal gas by hand (R_d = 287.05287 J/(kg K))
    assert dry.density_kgpm3 == pytest.approx(P_PA / (287.05287 * T_K), rel=1e-9)


def test_imported_stream_carries_the_humidity_and_the_moist_density(tmp_path: Path) -> None:
    import json

    from mcap.reader import make_reader

    log = tmp_path / "run.log"
    _can_log(log)
    (tmp_path / "tunnel.csv").write_text(_tunnel_csv("relative_humidity_pct", 100))
    run = tmp_path / "run.mcap"
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    assert main([*argv, "--tunnel", str(tmp_path / "tunnel.csv"), "--out", str(run)]) == 0
    with run.open("rb") as fh:
        tun = [
            (m.log_time, json.loads(m.data))
            for _, ch, m in make_reader(fh).iter_messages()
            if ch.topic == "/tunnel"
        ]
    assert tun[0][0] == T_LOG0_NS
    first, last = tun[0][1], tun[-1][1]
    assert first["relative_humidity"] == pytest.approx(RH)
    assert first["density_kgpm3"] == pytest.approx(cipm2007_density(P_PA, T_K, RH), rel=5e-4)
    assert last["relative_humidity"] is None  # the empty cell: not measured, null in the stream


@pytest.mark.parametrize(
    ("column", "value", "problem"),
    [
        ("relative_humidity", "1.2", "0..1"),
        ("relative_humidity", "-0.1", "0..1"),
        ("relative_humidity_pct", "101", "0..100 %"),
        ("relative_humidity_pct", "wet", "0..100 %"),
    ],
)
def test_humidity_out_of_range_is_one_line_exit_2(
    tmp_path: Path, capsys, column: str, value: str, problem: str
) -> None:
    log = tmp_path / "run.log"
    _can_log(log)
    csv = tmp_path / "tunnel.csv"
    text = _tunnel_csv(column, 1.0).splitlines()
    text[3] = text[3].rsplit(",", 1)[0] + f",{value}"  # row 4 as a spreadsheet counts
    csv.write_text("\n".join(text) + "\n")
    out = tmp_path / "run.mcap"
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    assert main([*argv, "--tunnel", str(csv), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert str(csv) in err[0] and f"row 4, column {column}" in err[0] and problem in err[0]
    assert not out.exists()


@pytest.mark.parametrize("rh", [None, 0.7])
def test_virtual_rig_sends_the_humidity_only_when_configured(rh: float | None) -> None:
    """``[aero] relative_humidity`` of a schedule: the rig's ``$TUN`` lines carry it (default: not
    sent, the four-value line) and its true aerodynamic wrench uses the moist-air density."""
    from cdpr.analysis.rigs import paper_rigs
    from cdpr.daq.serial_protocol import parse_tunnel_line
    from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping

    rig = paper_rigs()["flat_optimum"]
    seg = {"label": "v25", "duration_s": 0.2, "wind_mps": 25.0, "euler_deg": [0, 4, 0]}

    def sim(aero: dict) -> VirtualRig:
        doc = {"schedule": {"name": "rh", "rate_hz": 50.0, "seed": 3}, "segments": [seg]}
        return VirtualRig(rig, schedule_from_mapping({**doc, "aero": aero}, "<test>", rig))

    air = {"static_pressure_Pa": P_PA, "temperature_K": 303.15}
    vr = sim({**air, **({} if rh is None else {"relative_humidity": rh})})
    line = vr.tunnel_line(0)
    assert parse_tunnel_line(line).relative_humidity == rh
    assert line.count(b",") == (4 if rh is None else 5)
    if rh is not None:  # the aero wrench scales with the density: CIPM-2007 ratio moist / dry
        dry = sim(air)
        ratio = vr.wrench_aero_O[-1, 0] / dry.wrench_aero_O[-1, 0]
        want = cipm2007_density(P_PA, 303.15, rh) / cipm2007_density(P_PA, 303.15, 0.0)
        assert ratio == pytest.approx(want, rel=1e-3)
        assert ratio < 0.99  # 70 % at 30 deg C: 1.3 % lighter


def test_schedule_humidity_out_of_range_names_the_key() -> None:
    from cdpr.analysis.errors import ConfigError
    from cdpr.analysis.rigs import paper_rigs
    from cdpr.daq.virtual_rig import schedule_from_mapping

    rig = paper_rigs()["flat_optimum"]
    doc = {"segments": [{"label": "a", "duration_s": 0.2}], "aero": {"relative_humidity": 60}}
    with pytest.raises(ConfigError, match="aero.relative_humidity"):
        schedule_from_mapping(doc, "<test>", rig)


SIM_MATRIX = """
[campaign]
name = "rh-sim"
rig = "{rig}"
[model]
area_m2 = 0.0146
span_m = 0.2441
chord_m = 0.06
mrp_P_m = [0.0, 0.0, 0.0]
[virtual_rig]
rate_hz = 200.0
seed = 3
[virtual_rig.aero]
temperature_K = 303.15
{rh}
[[points]]
label = "tare"
kind = "tare"
duration_s = 0.6
transition_s = 0.0
[[points]]
label = "on"
kind = "wind_on"
airspeed_mps = 25.0
duration_s = 0.8
transition_s = 0.2
"""


@pytest.mark.parametrize("rh", [None, 0.7])
def test_simulate_then_analyze_humidity_through_the_serial_link(tmp_path: Path, rh) -> None:
    """The virtual rig's $TUN lines (a pty, read by the serial_tunnel driver) carry the humidity
    when the matrix sets it, and the analysis uses it; by default they do not, and the wind-on
    point is flagged humidity_not_given (dry air)."""
    import subprocess
    import sys

    m = tmp_path / "m.toml"
    line = "" if rh is None else f"relative_humidity = {rh}"
    m.write_text(SIM_MATRIX.format(rig=RIG.as_posix(), rh=line))
    runs = tmp_path / "runs"
    cmd = [sys.executable, "-m", "cdpr.pipelines.cli", "simulate", "--campaign", str(m),
           "--out", str(runs), "--quiet", "--transport", "virtual"]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr
    (run,) = runs.glob("*.mcap")
    main(["analyze", str(run), "--out", str(tmp_path / "a"), "--matrix", str(m)])
    (pts,) = (tmp_path / "a").glob("*/points.csv")
    on = pd.read_csv(pts).set_index("point").loc["on"]
    flags = str(on["flags"]).split(";")
    report = (pts.parent / "report.md").read_text()
    assert ("p_T_dry" if rh is None else "p_T_humidity") in report  # the density's source shown
    if rh is None:
        assert "humidity_not_given" in flags and on.density_source == "p_T_dry"
        assert on.density_kgpm3 == pytest.approx(101325.0 / (287.05287 * 303.15), rel=2e-4)
    else:
        assert "humidity_not_given" not in flags and on.density_source == "p_T_humidity"
        assert on.relative_humidity == pytest.approx(rh, abs=1e-4)
        # p and T carry the rig's sensor noise (2 Pa, 0.02 K): well inside 5e-4
        assert on.density_kgpm3 == pytest.approx(cipm2007_density(101325.0, 303.15, rh), rel=5e-4)


def test_humidity_impossible_at_that_p_and_t_names_the_row(tmp_path: Path, capsys) -> None:
    """Saturated air at 90 deg C holds about 70 kPa of vapour: not at a static pressure of 50 kPa."""
    log = tmp_path / "run.log"
    _can_log(log)
    csv = tmp_path / "tunnel.csv"
    csv.write_text(
        "t_s,airspeed_mps,static_pressure_Pa,temperature_K,relative_humidity\n"
        "0.0,0,101325,293.15,0.5\n0.1,10,50000,363.15,1.0\n"
    )
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    assert main([*argv, "--tunnel", str(csv), "--out", str(tmp_path / "r.mcap")]) == 2
    (err,) = capsys.readouterr().err.strip().splitlines()
    assert "row 3, column relative_humidity" in err and "static pressure" in err
    assert not (tmp_path / "r.mcap").exists()
