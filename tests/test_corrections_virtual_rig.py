"""The virtual rig's cable drag: its tensions balance gravity, the aero wrench and the drag of an
own taut-string model (tests/_cable_drag_truth.py), and nothing changes without a test section."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
from _cable_drag_truth import string_end_force

from cdpr.analysis.flow import air_density, sutherland_viscosity
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rigs import paper_rigs
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping
from cdpr.pipelines.tunnel_section import tunnel_section_from_mapping

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"


def test_virtual_rig_tensions_carry_the_cable_drag() -> None:
    rig = paper_rigs()["flat_optimum"]
    ts = tunnel_section_from_mapping(
        tomllib.loads((SAMPLES / "tunnel_section_octagon.toml").read_text()), "octagon"
    )
    sched = schedule_from_mapping(
        {
            "schedule": {"name": "drag", "rate_hz": 50.0, "seed": 3, "method": "exact"},
            "segments": [
                {"label": "v41", "duration_s": 0.2, "wind_mps": 41.42, "euler_deg": [0, 4, 0]}
            ],
        },
        "<test>",
        rig,
    )
    vr = VirtualRig(rig, sched, section=ts.geometry)
    bare = VirtualRig(rig, sched)
    assert np.all(bare.wrench_cable_drag_O == 0.0)
    k = -1
    p, psi = vr.position_O_m[k], vr.euler_rad[k]
    R = rotation_from_euler(psi)
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, p, R)
    T = vr.tensions_true_N[k]
    drag = -(A @ T) - vr.wrench_gravity_O[k] - vr.wrench_aero_O[k]
    # the own model, with the rig's air: p and T of the aero model
    rho = float(air_density(vr.aero.static_pressure_Pa, vr.aero.temperature_K))
    mu = float(sutherland_viscosity(vr.aero.temperature_K))
    g = ts.geometry
    apothem = 0.376 * (1 + 2**0.5) / 2
    yc, zc = np.mean(g.polygon_yz_m, axis=0)
    truth = np.zeros(6)
    for i in range(rig.n_cables):
        r = R @ rig.attach_P_m[i]
        F, _ = string_end_force(
            p + r,
            rig.anchors_O_m[i],
            T[i],
            41.42,
            apothem,
            yc,
            zc,
            g.x_start_m,
            g.x_end_m,
            rho=rho,
            mu=mu,
        )
        truth += np.concatenate([F, np.cross(r, F)])
    assert 1.0 < truth[0] < 1.5
    np.testing.assert_allclose(drag, truth, rtol=3e-3, atol=2e-4)
    np.testing.assert_allclose(vr.wrench_cable_drag_O[k], truth, rtol=3e-3, atol=2e-4)


def test_simulate_with_tunnel_puts_the_drag_in_the_truth(tmp_path: Path) -> None:
    import subprocess
    import sys

    sched = tmp_path / "s.toml"
    sched.write_text(
        '[schedule]\nname = "drag"\nrate_hz = 100.0\nseed = 2\n\n'
        '[[segments]]\nlabel = "v41"\nduration_s = 0.5\nwind_mps = 41.42\n'
    )
    cmd = [sys.executable, "-m", "cdpr.pipelines.cli", "simulate", "--rig",
           str(SAMPLES / "flat_optimum.toml"), "--schedule", str(sched), "--out",
           str(tmp_path / "runs"), "--transport", "virtual", "--quiet", "--tunnel",
           str(SAMPLES / "tunnel_section_octagon.toml")]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    (truth,) = (tmp_path / "runs").glob("*.truth.npz")
    drag = np.load(truth)["wrench_cable_drag_O"]
    assert 1.0 < drag[-1, 0] < 1.5
    serial = [("serial" if a == "virtual" else a) for a in cmd]
    bad = subprocess.run(serial, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--tunnel" in bad.stderr and len(bad.stderr.splitlines()) == 1
