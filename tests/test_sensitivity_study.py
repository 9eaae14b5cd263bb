"""The sensitivity study pipeline and `cdpr sensitivity`: sweeps against the single-configuration
path (Rig builders + kinematics), the written files, and clear errors for bad options."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cdpr.analysis import rigs
from cdpr.analysis import sensitivity as sens
from cdpr.analysis.errors import ConfigError
from cdpr.pipelines import sensitivity_report as sr
from cdpr.pipelines.cli import main

SMALL = """
[cubic]
k1_values = [0.15, 0.3]
k2_values = [0.075, 0.15]
k3_values = [0.05, 0.075]
Z_values_m = [0.5, 0.7, 0.9]
deflection_values_m = [-0.1, 0.0, 0.1]
methods = ["exact"]

[flat]
K21_values = [46, 51]
K22_values = [25, 28]
H_values_m = [0.62, 0.67]
X_values_m = [0.5, 0.6]
methods = ["improved-closed-form"]
"""


# The penalty method iterates until the active set of a whole chunk settles, so a batch and a single
# configuration can stop after different numbers of Newton steps: equal to ~1e-6, not to rounding.
TOL = {"exact": 1e-9, "improved-closed-form": 1e-9, "closed-form": 1e-9, "penalty": 1e-5}


def _small(tmp_path: Path, extra: str = "") -> Path:
    p = tmp_path / "study.toml"
    p.write_text(SMALL + extra)
    return p


def test_cubic_sweeps_equal_single_configuration(tmp_path: Path) -> None:
    o = sr.options_from_toml(str(_small(tmp_path)))
    o.cubic.methods = ("exact", "penalty")
    cub = sr.run_cubic(o)
    grid = cub["grid"]
    assert len(grid) == 2 * 12 * len(list(sr._cubic_grid(o.cubic)))
    W, _, _ = sr.cubic_loads(o.cubic.forces_N)
    for method in o.cubic.methods:
        for k in {tuple(r) for r in grid[["k1", "k2", "k3"]].to_numpy()}:
            one = sens.sensitivity_of_rig(rigs.cubic_rig(*k), W, method)
            rows = grid[
                (grid.method == method) & (grid.k1 == k[0]) & (grid.k2 == k[1]) & (grid.k3 == k[2])
            ]
            np.testing.assert_allclose(rows.S_N.to_numpy(), one.S_N, rtol=TOL[method])
        z = cub["Z"][cub["Z"].method == method]
        for Z in o.cubic.Z_values_m:
            one = sens.sensitivity_of_rig(rigs.cubic_rig(*o.cubic.baseline_k, Z_m=Z), W, method)
            np.testing.assert_allclose(z[z.Z_m == Z].S_N.to_numpy(), one.S_N, rtol=TOL[method])
        d = cub["deflection"]
        e = d[(d.method == method) & (d.case == "fig10_force_y_offset_x") & (d.deflection_m == 0.1)]
        F = np.asarray(o.cubic.forces_N)
        Wd = np.zeros((len(F), 6))
        Wd[:, 1] = F
        Wd[:, 5] = 0.1 * F  # force along y applied at (0.1, 0, 0): Mz = x Fy
        one = sens.sensitivity_of_rig(rigs.cubic_rig(*o.cubic.baseline_k), Wd, method)
        np.testing.assert_allclose(e.S_N.to_numpy(), one.S_N, rtol=TOL[method])


def test_flat_sweeps_equal_single_configuration(tmp_path: Path) -> None:
    o = sr.options_from_toml(str(_small(tmp_path)))
    flat = sr.run_flat(o)
    W = sr.flat_loads(o.aero, o.aero.speeds_mps)
    sw = flat["sweeps"]
    for _, r in sw.sample(8, random_state=1).iterrows():
        rig = rigs.flat_rig(r.K21, r.K22, r.H_m, r.X_m)
        one = sens.sensitivity_of_rig(rig, W, r.method)
        i = list(o.aero.speeds_mps).index(r.speed_mps)
        np.testing.assert_allclose(r.S_N, one.S_N[i], rtol=1e-9, equal_nan=True)
    g = flat["grid"]
    assert len(g) == 16
    r = g.iloc[5]
    one = sens.sensitivity_of_rig(
        rigs.flat_rig(r.K21, r.K22, r.H_m, r.X_m), W, "improved-closed-form"
    )
    assert r["S_improved-closed-form_41.42mps_N"] == pytest.approx(float(one.S_N[2]), rel=1e-9)


def test_cli_writes_figures_csv_and_report(tmp_path: Path) -> None:
    import matplotlib.image as mpimg

    out = tmp_path / "out"
    rc = main(
        [
            "sensitivity",
            "--paper",
            "--config",
            str(_small(tmp_path)),
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert rc == 0
    report = (out / "report.md").read_text()
    for needle in ("K21 = 51", "Z = 0.7 m", "peak at zero deflection", "no effect", "singular"):
        assert needle in report
    assert "**agrees**" in report or "**differs**" in report
    for fig in (
        "fig06",
        "fig07",
        "fig08",
        "fig09",
        "fig10",
        "fig11",
        "fig12",
        "fig13",
        "fig14",
        "fig15",
    ):
        pngs = sorted(out.glob(f"{fig}_*.png"))
        assert pngs, fig
        img = mpimg.imread(pngs[0])
        assert img.ndim == 3 and img.shape[0] > 300 and img.std() > 0.01  # not blank
    df = pd.read_csv(out / "cubic_k_grid.csv", comment="#")
    assert {"S_N", "condition", "sigma_min", "margin_N", "std_fx_N", "singular"} <= set(df.columns)


@pytest.mark.parametrize(
    ("extra_or_replace", "key"),
    [
        ({"k1_values = [0.15, 0.3]": "k1_values = [0.15, 0.5]"}, "cubic.k1_values"),
        ({"Z_values_m = [0.5, 0.7, 0.9]": "Z_values_m = [0.01, 0.7]"}, "cubic.Z_values_m"),
        ({"K21_values = [46, 51]": "K21_values = [0.5, 51]"}, "flat.K21_values"),
        ({"X_values_m = [0.5, 0.6]": "X_values_m = [0.5, 1.6]"}, "flat.X_values_m"),
        ({'methods = ["exact"]': 'methods = ["magic"]'}, "cubic.methods"),
        ({"[flat]": "[flat]\nwidth = 3"}, "flat.width"),
        ({"[cubic]": "[cubic]\nmass_kg = 2000.0"}, "cubic.mass_kg"),  # cannot hold the platform
        ({"[flat]": "[flat]\nt_max_N = 20.0"}, "flat.t_min_N"),
    ],
)
def test_cli_bad_options_exit_2_naming_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra_or_replace: dict, key: str
) -> None:
    text = SMALL
    for a, b in extra_or_replace.items():
        assert a in text
        text = text.replace(a, b, 1)
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    out = tmp_path / "out"
    rc = main(["sensitivity", "--config", str(cfg), "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert key in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not (out / "report.md").exists()


def test_unholdable_rig_message() -> None:
    o = sr.StudyOptions()
    o.cubic.mass_kg = 2000.0
    o.cubic.methods = ("exact",)
    with pytest.raises(ConfigError, match="cannot hold its platform"):
        sr.run_cubic(o)


def test_cube_layout_at_the_papers_optimum_is_reported_singular(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = _small(tmp_path)
    rc = main(["sensitivity", "--config", str(cfg), "--layout", "cube", "--out", str(tmp_path / "o"),
               "--no-progress"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2 and "cubic.baseline_k" in err and "singular" in err


def test_cli_needs_paper_or_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sensitivity", "--out", str(tmp_path / "o")]) == 2
    assert "--paper" in capsys.readouterr().err


def test_print_config_round_trips(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sensitivity", "--print-config"]) == 0
    text = capsys.readouterr().out
    cfg = tmp_path / "defaults.toml"
    cfg.write_text(text)
    assert sr.options_from_toml(str(cfg)) == sr.StudyOptions()
    assert "k1_values" in text and "coefficients" in text
