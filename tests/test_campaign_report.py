"""Campaign outputs (``pipelines/report.py``, ``cdpr campaign``) from per-point tables this test
writes with its own small generator: the table read back with pandas and h5py, the envelope and
label spreading against hand values, flags and missing points in the report and the exit code, and
the HTML page rendered by headless Chromium (a screenshot with the plots in it)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
from matplotlib.colors import rgb_to_hsv

from cdpr.calibration.cv import read_image, to_gray
from cdpr.pipelines.cli import main
from cdpr.pipelines.report import REQUIRED_COLUMNS, campaign_table, envelope, spread_labels

ROOT = Path(__file__).resolve().parents[1]
SPEEDS = (17.27, 25.51)
AOAS = (-4.0, 0.0, 4.0, 8.0)


def _points(run: str, flagged: str = "") -> pd.DataFrame:
    """A run's per-point table: a tare polar and an aoa sweep at two speeds, a repeat point;
    CL = 3.5 aoa, CD = 0.035 + 0.09 CL^2, Cm = -0.4 aoa (rad); err_* small known numbers."""
    rows = []
    t = 1_700_000_000_000_000_000
    pts = [("tare", a, 0.0, "") for a in AOAS]
    pts += [("wind_on", a, v, "") for v in SPEEDS for a in AOAS]
    pts += [("wind_on", 4.0, 25.51, "wind_on-a4-v25.51")]
    for i, (kind, a, v, rep) in enumerate(pts):
        label = f"{kind}-a{a:g}-v{v:g}" + ("-rep" if rep else "")
        ar = np.radians(a)
        cl = 3.5 * ar if kind == "wind_on" else np.nan
        r: dict[str, object] = {c: 0.0 for c in REQUIRED_COLUMNS}
        flags = flagged if label == "wind_on-a0-v17.27" else ""
        on = kind == "wind_on"
        r.update(
            run=run, point=label, kind=kind, source="events", flags=flags,
            start_ns=t + i * 2 * 10**9, stop_ns=t + (2 * i + 1) * 10**9,
            n_samples=200, n_masked=0, z_m=0.36, pitch_rad=ar, airspeed_mps=v, density_kgpm3=1.2,
            q_Pa=0.6 * v * v, aoa_rad=ar, target_aoa_deg=a, target_airspeed_mps=v, repeat_of=rep,
            target_sideslip_deg=0.0,
            CL=cl, CD=0.035 + 0.09 * cl**2, Cm=-0.4 * ar if on else np.nan,
            sd_CL=0.01, sd_CD=0.002, sd_Cm=0.003, fz_N=0.6 * v * v * 0.0146 * (cl if on else 0),
            err_fx_N=0.01 * i, err_fy_N=-0.002, err_fz_N=0.03, err_mx_Nm=0.001, err_my_Nm=-0.002,
            err_mz_Nm=0.0005,
        )  # fmt: skip
        rows.append(r)
    return pd.DataFrame(rows)


def _write(tmp: Path, run: str, **kw: str) -> Path:
    d = tmp / "analysis" / run
    d.mkdir(parents=True)
    _points(run, **kw).to_csv(d / "points.csv", index=False)
    return d / "points.csv"


def test_table_stacks_runs_in_matrix_order_and_reads_back(tmp_path: Path) -> None:
    a, b = _write(tmp_path, "run_a"), _write(tmp_path, "run_b")
    labels = ["absent-point", *_points("x")["point"]]
    t = campaign_table([a, b], labels)
    assert t.missing_points == ["absent-point"] and len(t.df) == 2 * 13
    from cdpr.pipelines.report import write_campaign_table

    csv, h5 = write_campaign_table(t, tmp_path / "out")
    back = pd.read_csv(csv)
    assert list(back["point"][:2]) == ["tare-a-4-v0", "tare-a-4-v0"]  # matrix order, both runs
    with h5py.File(h5) as f:
        g = f["points"]
        assert [s.decode() for s in g["point"][:2]] == ["tare-a-4-v0", "tare-a-4-v0"]
        np.testing.assert_allclose(g["aoa_deg"][:], back["aoa_deg"])
        np.testing.assert_allclose(g["CL"][:], back["CL"], equal_nan=True)
        assert list(f.attrs["missing_points"]) == ["absent-point"]
        assert any(str(a) in s for s in f.attrs["inputs"])
    # aoa in degrees from the radians column: the generator's targets
    on = back[back["kind"] == "wind_on"]
    np.testing.assert_allclose(on["aoa_deg"], on["target_aoa_deg"], atol=1e-12)
    assert back["is_repeat"].sum() == 2


def test_envelope_against_hand_values() -> None:
    t = np.arange(10.0)
    y = np.stack([np.arange(10.0), -np.arange(10.0)], axis=1)
    y[3, 0] = np.nan
    tc, lo, hi = envelope(t, y, 5)
    np.testing.assert_allclose(tc, [0.5, 2.5, 4.5, 6.5, 8.5])
    np.testing.assert_allclose(lo[:, 0], [0, 2, 4, 6, 8])
    np.testing.assert_allclose(hi[:, 0], [1, 2, 5, 7, 9])  # the NaN sample is ignored
    np.testing.assert_allclose(hi[:, 1], [0, -2, -4, -6, -8])
    # 7 samples in 3 bins: they start at k n // 3 = 0, 2, 4 (2, 2 and 3 samples)
    tc, lo, hi = envelope(np.arange(7.0), np.arange(7.0)[:, None], 3)
    np.testing.assert_allclose(tc, [0.5, 2.5, 5.0])
    np.testing.assert_allclose(lo[:, 0], [0, 2, 4])
    np.testing.assert_allclose(hi[:, 0], [1, 3, 6])


def test_spread_labels_fans_out_overlaps_and_keeps_separated_ones() -> None:
    # by hand: stacked upwards 100, 105, 110, 200; the mean shift (0 + 5 + 10 + 0) / 4 removed
    y = spread_labels(np.array([100.0, 100.0, 100.0, 200.0]), 5.0)
    np.testing.assert_allclose(np.sort(y), [96.25, 101.25, 106.25, 196.25], atol=1e-9)
    np.testing.assert_allclose(spread_labels(np.array([3.0, 50.0, 10.0]), 5.0), [3.0, 50.0, 10.0])


def test_bad_points_table_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = _write(tmp_path, "r")
    df = pd.read_csv(p).drop(columns=["sd_CL"])
    df.to_csv(p, index=False)
    assert main(["campaign", str(tmp_path / "analysis"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(p) in err[0] and "column sd_CL" in err[0]
    df["sd_CL"] = 0.01
    df["CL"] = df["CL"].astype(object)
    df.loc[3, "CL"] = "abc"
    df.to_csv(p, index=False)
    assert main(["campaign", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "row 5, column CL" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    assert exe, "chromium is not installed (make install installs it: Debian package chromium)"
    return exe


def _screenshot(page: Path, png: Path, tmp: Path) -> np.ndarray:
    cmd = [
        _chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        f"--user-data-dir={tmp / 'chrome-profile'}", "--hide-scrollbars",
        "--window-size=1200,2400", f"--screenshot={png}", page.as_uri(),
    ]  # fmt: skip
    env = {**os.environ, "HOME": str(tmp)}
    subprocess.run(cmd, capture_output=True, timeout=120, env=env, check=False)
    img = read_image(png, gray=False)  # BGR, through the project's OpenCV adapter
    assert img is not None, "no screenshot written"
    return img


def test_cli_reports_flags_and_renders_in_chromium(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write(tmp_path, "run_a", flagged="slack:front_left_top")
    _write(tmp_path, "run_b")
    out = tmp_path / "out"
    rc = main(["campaign", str(tmp_path / "analysis"), "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 1  # a flagged point: said in the exit code ...
    assert "1 point(s) flagged: wind_on-a0-v17.27 [slack:front_left_top]" in text  # ... here
    page = (out / "campaign.html").read_text()
    assert "slack:front_left_top" in page and "class='warn'" in page  # ... and in the report
    assert page.count("src='data:image/png;base64,") == 3  # CL-aoa, drag polar, Cm-aoa inline
    assert "<link" not in page and "src='http" not in page  # self-contained
    assert "recovered - true wrench" in text and "+0.1200" in text  # err_fx_N of point 12
    assert (out / "campaign.md").read_text().count("](") == 3
    assert (out / "run_run_a.html").is_file() and (out / "run_run_b.md").is_file()

    img = _screenshot(out / "campaign.html", tmp_path / "shot.png", tmp_path)
    assert to_gray(img).std() > 20  # not blank
    hsv = rgb_to_hsv(img[..., ::-1] / 255.0)  # hue, saturation, value in [0, 1]
    h, sat, val = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    coloured = (sat > 0.31) & (val > 0.24)  # plot lines and markers (viridis)
    rows = np.flatnonzero(coloured.any(axis=1))
    assert coloured.sum() > 2000 and rows.size > 300  # plots drawn, over several hundred rows
    red = ((h < 0.045) | (h > 0.945)) & (sat > 0.47) & (val > 0.24)
    assert red.sum() > 50  # the flag warning and the flagged marker are red


def test_info_flags_are_not_warnings_and_detected_points_are_said(tmp_path: Path) -> None:
    from cdpr.pipelines.report import report_content

    df = _points("r")
    df["flags"] = ["tare"] * len(df)
    df.loc[5, "flags"] = "tare;no_tare"
    df = df.drop(columns=["target_aoa_deg", "target_sideslip_deg", "repeat_of"])
    df["source"] = "detected"
    p = tmp_path / "points.csv"
    df.to_csv(p, index=False)
    t = campaign_table([p], info_flags=frozenset({"tare"}))
    assert list(t.flagged["point"]) == [df.loc[5, "point"]]
    assert t.df["target_aoa_deg"].isna().all() and (t.df["repeat_of"] == "").all()
    w = report_content("x", t, [], {}).warnings
    assert w[0] == f"1 point(s) flagged: {df.loc[5, 'point']} [no_tare]"
    assert w[1].startswith("13 point(s) found by steady-point detection")


def test_run_page_has_the_run_tensions_from_the_run_file(tmp_path: Path) -> None:
    from cdpr.daq.mcap_io import McapRunWriter
    from cdpr.daq.source import FieldDescription, Reading, StreamDescription

    runs = tmp_path / "runs"
    runs.mkdir()
    names = [f"c{i}" for i in range(8)]
    w = McapRunWriter(runs / "run_a.mcap", flush_interval_s=1.0)
    w.add_stream("tensions", StreamDescription({f"T_{n}_N": FieldDescription("N") for n in names}))
    t0 = 1_700_000_000_000_000_000
    for k in range(3000):  # longer than the plot's 2000 bins: drawn as an envelope
        vals = {
            f"T_{n}_N": 100.0 + 10.0 * (i // 2) + 0.1 * np.sin(k / 50) for i, n in enumerate(names)
        }
        w.write(Reading("tensions", t0 + k * 5_000_000, vals))
    w.finish()
    df = _points("run_a.mcap")
    df["start_ns"] = t0 + np.arange(len(df)) * 10**9
    df["stop_ns"] = df["start_ns"] + 5 * 10**8
    (tmp_path / "analysis" / "a").mkdir(parents=True)
    df.to_csv(tmp_path / "analysis" / "a" / "points.csv", index=False)
    out = tmp_path / "out"
    argv = ["campaign", str(tmp_path / "analysis"), "--runs", str(runs), "--out", str(out)]
    assert main(argv) == 0
    page = (out / "run_run_a.html").read_text()
    assert page.count("src='data:image/png;base64,") == 4 and "Cable tensions" in page
    img = read_image(out / "plots" / "run_a" / "tensions.png", gray=False)
    assert img is not None and img.shape[1] > 900


def test_a_sideslip_sweep_gets_the_lateral_plot(tmp_path: Path) -> None:
    from cdpr.pipelines.report import sweep_figures

    df = _points("r")
    on = df.index[df["kind"] == "wind_on"][:4]  # four points at 17.27 m/s become a sideslip sweep
    df.loc[on, "target_aoa_deg"] = 0.0
    df.loc[on, "aoa_rad"] = 0.0
    df.loc[on, "target_sideslip_deg"] = [-4.0, 0.0, 4.0, 8.0]
    df.loc[on, "sideslip_rad"] = np.radians([-4.0, 0.0, 4.0, 8.0])
    for c, slope in (("CY", -0.6), ("Cl", -0.08), ("Cn", 0.1)):
        df[c] = np.nan
        df.loc[on, c] = slope * df.loc[on, "sideslip_rad"]
        df[f"sd_{c}"] = 0.002
    p = tmp_path / "points.csv"
    df.to_csv(p, index=False)
    figs = sweep_figures(campaign_table([p]), tmp_path / "plots")
    assert [f.name for f in figs][-1] == "lateral_sideslip.png"
    img = read_image(tmp_path / "plots" / "lateral_sideslip.png", gray=True)
    assert img is not None and img.shape[0] > img.shape[1]  # three panels stacked


def test_bars_are_the_expanded_uncertainty_and_the_plot_says_so() -> None:
    """A point with ``U95_CL`` gets that bar (random + systematic), one without gets 2 sigma, and
    the plot's note says which."""
    from cdpr.pipelines.report import _bar_note, _bars

    d = pd.DataFrame({"CL": [0.5, 0.6], "sd_CL": [0.01, 0.02], "U95_CL": [0.05, np.nan]})
    assert _bars(d, "CL") == pytest.approx([0.05, 0.04])
    assert "U95" in _bar_note(d, ["CL"]) and "sigma where a point has none" in _bar_note(d, ["CL"])
    full = d.assign(U95_CL=[0.05, 0.07])
    assert _bar_note(full, ["CL"]).startswith("bars: U95 (random + systematic")
    assert _bars(d.drop(columns="U95_CL"), "CL") == pytest.approx([0.02, 0.04])
    assert "the runs give no U95" in _bar_note(d.drop(columns="U95_CL"), ["CL"])
