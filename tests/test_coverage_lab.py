"""Honest error bars through the lab path (issue 21), each noise case of the independent lab
generator (tests/lab_generator.py: its own statics, controller and noise) through ``cdpr import``
(the camera's covariance columns, the tunnel log) and ``cdpr analyze --matrix``; truth is the
ensemble-mean aerodynamic wrench.  A lighter run than ``tests/measure_coverage.py`` (about 36
wind-on points a case instead of 100+, so the bounds are wider than the issue's 90-99 % and
0.8-1.25, which the measurement script shows): they still catch a σ several times too narrow or
too wide in any component, as the load cells' sd/sqrt(n) or a nominal camera constant gave.
The cubic rig's tare at a 0.05 mm / 0.01 deg camera: forces within 0.1 N, moments within
5 mN m."""

from __future__ import annotations

from pathlib import Path

import lab_generator as lg
import numpy as np
import pytest
from measure_coverage import coverage_table, run_lab_path

CASES = [
    "white",
    "ar1",
    "common",
    pytest.param(
        "mode",
        marks=pytest.mark.xfail(
            strict=True,
            reason="issue 21 open: the load that makes a ringing platform wander (its mean pose's "
            "own zero-frequency part) is not in sigma; mz cover 0.81, rms(e/sd) 1.56 over 108 points",
        ),
    ),
]


@pytest.mark.parametrize("case", CASES)
def test_intervals_cover_the_truth_under_each_noise(case: str, tmp_path: Path) -> None:
    lab = lg.steady_case(tmp_path / "case", case, 30, seed=5)
    points, _, _ = run_lab_path(lab, tmp_path)
    table = coverage_table(points, lab.points).set_index("component")
    assert (table["n"] >= 30).all(), table["n"]
    overall = float(np.average(table["cover95"], weights=table["n"]))
    assert 0.88 <= overall <= 1.0, (case, overall)
    low = table[table["cover95"] < 0.75]
    assert low.empty, (case, low[["cover95", "rms_e_over_sd"]])
    off = table[(table["rms_e_over_sd"] < 0.45) | (table["rms_e_over_sd"] > 1.6)]
    assert off.empty, (case, off[["cover95", "rms_e_over_sd"]])


def test_the_cubic_rig_tare_keeps_the_flat_rigs_accuracy(tmp_path: Path) -> None:
    """5 kg on the cubic rig, large tensions: the tare at the point's pose from the stiffness
    model and the camera by their covariances (not the camera's noise times the full tensions)."""
    lab = lg.steady_case(tmp_path / "case", "white", 12, rig="cubic", seed=2)
    points, _, _ = run_lab_path(lab, tmp_path)
    table = coverage_table(points, lab.points).set_index("component")
    forces = table.loc[["fx_N", "fy_N", "fz_N"], "max_abs_error"]
    moments = table.loc[["mx_Nm", "my_Nm", "mz_Nm"], "max_abs_error"]
    assert (forces < 0.1).all(), forces
    assert (moments < 5e-3).all(), moments
