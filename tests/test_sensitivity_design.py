"""`cdpr design`: the optimum meets its constraints when re-checked through an independent path
(the written rig file, the Rig + kinematics + numpy), the Pareto front, and clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import quadprog

from cdpr.analysis import sensitivity as sens
from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.kinematics import structure_matrix
from cdpr.pipelines.cli import main
from cdpr.pipelines.commands.design import pareto_front
from cdpr.pipelines.config import load_rig
from cdpr.pipelines.sensitivity_report import StudyOptions, flat_loads

FAST = ["--maxiter", "4", "--popsize", "6", "--samples", "300", "--seed", "3"]


def test_flat_design_meets_constraints_independently(tmp_path: Path) -> None:
    out = tmp_path / "d"
    rc = main(
        ["design", "--family", "flat", "--objective", "sensitivity", "--out", str(out), *FAST]
    )
    assert rc == 0
    for name in ("design.md", "design_rig.toml", "pareto.png", "pareto_samples.csv"):
        assert (out / name).stat().st_size > 0
    rig = load_rig(out / "design_rig.toml")
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, rig.reference_position_O_m, np.eye(3))
    assert np.linalg.cond(A) <= 1000.0 * (1 + 1e-9)
    o = StudyOptions()
    W = flat_loads(o.aero, [max(o.aero.speeds_mps)])[0]
    res = sens.sensitivity_of_rig(rig, W, "exact")
    assert bool(res.feasible)
    md = (out / "design.md").read_text()
    assert f"{float(res.S_N):.4g}" in md
    s = pd.read_csv(out / "pareto_samples.csv", comment="#")
    best_random = s[s.meets_constraints == 1].S_N.max()
    assert float(res.S_N) >= best_random * (1 - 1e-9)  # no worse than the random search


def test_cubic_design_runs(tmp_path: Path) -> None:
    rc = main(
        ["design", "--family", "cubic", "--objective", "margin", "--out", str(tmp_path), *FAST]
    )
    assert rc == 0
    rig = load_rig(tmp_path / "design_rig.toml")
    x = np.abs(rig.attach_P_m).max(axis=0) * 2 / np.array([2.0, 1.2, 1.4])  # k1, k2, k3
    assert x[2] <= x[1] + 1e-12 <= x[0] + 2e-12
    # the constraints, re-checked with quadprog as the oracle: with --min-margin 0 every load of the
    # study (each force along +-x and +-y) plus gravity is held within the written rig's limits
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, rig.reference_position_O_m, np.eye(3))
    assert np.linalg.cond(A) <= 1000.0 * (1 + 1e-9)
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, np.eye(3), rig.gravity_O_mps2)
    C = np.vstack([A, np.eye(8), -np.eye(8)]).T
    mid = 0.5 * (rig.t_min_N + rig.t_max_N)
    for F in StudyOptions().cubic.forces_N:
        for axis in (0, 1):
            for sign in (1.0, -1.0):
                W = np.zeros(6)
                W[axis] = sign * F
                b = np.concatenate([-(G + W), rig.t_min_N - 1e-6, -rig.t_max_N - 1e-6])
                quadprog.solve_qp(np.eye(8), mid, C, b, meq=6)  # raises ValueError if infeasible


def test_pareto_front_brute_force() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=200), rng.normal(size=200)
    front = pareto_front(a, b)
    dominated = np.array(
        [np.any((a >= a[i]) & (b >= b[i]) & ((a > a[i]) | (b > b[i]))) for i in range(200)]
    )
    np.testing.assert_array_equal(front, ~dominated)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--bound", "K21=90:50"], "--bound K21"),
        (["--bound", "Q=1:2"], "--bound Q"),
        (["--bound", "X_m=0.5:1.5"], "--bound X_m"),
        (["--bound", "K22=0.5:30"], "--bound K22"),
        (["--min-margin", "500"], "--min-margin"),
        (["--method", "magic"], "--method"),
        (["--max-condition", "0.5"], "--max-condition"),
    ],
)
def test_design_bad_arguments_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], needle: str
) -> None:
    rc = main(["design", "--family", "flat", "--out", str(tmp_path / "o"), *FAST, *args])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and "Traceback" not in err
    assert not (tmp_path / "o" / "design.md").exists()
