"""``cdpr analyze --loadcell-calibration``: re-calibration after the run.  A short virtual-rig run
records raw counts beside the tensions; a second calibration file written here by hand re-derives
the tensions from those counts.  The expected tensions are ``(counts - offset') * gain'`` over each
point's samples, computed here from the counts read back with the ``mcap`` package and json; the
expected wrench change is ``-A_i dT_i + A_j dT_j`` (wind-on point i, its tare j) with the structure
matrix of tests/truth_rig.py (an independent implementation)."""

from __future__ import annotations

import hashlib
import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from mcap.reader import make_reader
from test_analyze_runs import write_run
from truth_rig import alpha_sweep, statics

from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_experiment2.toml"
RIG_DATA = tomllib.loads(RIG.read_text())
NAMES = [c["name"] for c in RIG_DATA["cables"]]
ANCHORS = np.array([c["anchor_O_m"] for c in RIG_DATA["cables"]], float)
ATTACH = np.array([c["attach_P_m"] for c in RIG_DATA["cables"]], float)
WRENCH = ["fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm"]

SCHEDULE = """
[schedule]
name = "recal"
rate_hz = 100.0
tunnel_rate_hz = 10.0
method = "exact"
seed = 5

[sensor]
noise_sd_N = 0.05

[[segments]]
label = "tare"
tare = true
duration_s = 1.0
wind_mps = 0.0

[[segments]]
label = "v41"
duration_s = 1.0
wind_mps = 41.42
transition_s = 0.2
"""

# the post-campaign calibration, in another cable order than the rig's (matched by name)
ORDER = [5, 2, 7, 0, 3, 1, 6, 4]
D_OFFSET = np.array([1200.0, -800.0, 300.0, 0.0, -2500.0, 40.0, 900.0, -60.0])
GAIN = np.array([5.10e-5, 4.95e-5, 5.03e-5, 4.90e-5, 5.20e-5, 5.00e-5, 4.85e-5, 5.07e-5])


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("recal")
    (d / "s.toml").write_text(SCHEDULE)
    argv = ["simulate", "--rig", str(RIG), "--schedule", str(d / "s.toml"), "--out", str(d)]
    assert main([*argv, "--quiet"]) == 0
    (r,) = d.glob("*.mcap")
    return r


def _raw(run: Path) -> tuple[np.ndarray, np.ndarray]:
    """Sample counters (n,) and raw counts (n, 8) of the run's ``/tensions``, read with
    mcap + json."""
    t, c = [], []
    with run.open("rb") as fh:
        for _, _, m in make_reader(fh).iter_messages(["/tensions"]):
            row = json.loads(m.data)
            t.append(row["seq"])
            c.append([row[f"raw_{n}_counts"] for n in NAMES])
    return np.array(t, np.int64), np.array(c, float)


def _recorded_calibration(run: Path) -> tuple[np.ndarray, np.ndarray]:
    """The virtual rig's own calibration (written beside the run), in rig order."""
    cal = tomllib.loads(run.with_name(run.stem + ".loadcells.toml").read_text())["calibration"]
    k = [cal["cables"].index(n) for n in NAMES]
    return np.array(cal["offset_counts"])[k], np.broadcast_to(cal["gain_N_per_count"], 8)[k]


def _write_cal(path: Path, offsets: np.ndarray, gains: np.ndarray, cal_id: str) -> Path:
    """A calibration file by hand (rig-order arrays, written in ORDER)."""
    names = ", ".join(f'"{NAMES[i]}"' for i in ORDER)
    offs = ", ".join(repr(float(offsets[i])) for i in ORDER)
    gns = ", ".join(repr(float(gains[i])) for i in ORDER)
    path.write_text(
        f'[calibration]\nkind = "loadcells"\nid = "{cal_id}"\ncreated_utc = "2026-11-20T10:00:00Z"\n'
        f"cables = [{names}]\noffset_counts = [{offs}]\ngain_N_per_count = [{gns}]\n"
    )
    return path


def _analyze(run: Path, out: Path, *extra: str) -> int:
    return main(["analyze", str(run), "--out", str(out), "--workers", "1", "--no-progress", *extra])


def _provenance(out: Path, run: Path) -> dict[str, Any]:
    """The summary's ``loadcell_calibration`` record."""
    rec: dict[str, Any] = json.loads((out / run.stem / "summary.json").read_text())
    return rec["loadcell_calibration"]  # type: ignore[no-any-return]


def _point_means(run: Path, df: pd.DataFrame, off: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """(points, 8) mean of (counts - off) * gain over each point's samples, by hand."""
    k, c = _raw(run)
    out = []
    for r in df.itertuples():  # the point's samples by their counter, whatever the clock
        sel = (k >= r.first_sample) & (k <= r.last_sample)
        assert sel.sum() == r.n_samples and r.n_masked == 0
        out.append(((c[sel] - off) * gain).mean(axis=0))
    return np.array(out)


def test_tensions_are_rederived_from_raw_counts_and_the_wrench_follows(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    off0, g0 = _recorded_calibration(run)
    off1 = off0 + D_OFFSET
    cal = _write_cal(tmp_path / "post_campaign.toml", off1, GAIN, "lc-2026-11-20")
    assert _analyze(run, tmp_path / "a") == 1  # warnings: no camera stream, no geometry
    assert _analyze(run, tmp_path / "b", "--loadcell-calibration", str(cal)) == 1
    said = capsys.readouterr().out
    assert "post_campaign.toml (given by --loadcell-calibration)" in said
    a = pd.read_csv(tmp_path / "a" / run.stem / "points.csv")
    b = pd.read_csv(tmp_path / "b" / run.stem / "points.csv")
    assert list(a.kind) == list(b.kind) == ["tare", "wind_on"]
    assert (a[["start_ns", "stop_ns"]].to_numpy() == b[["start_ns", "stop_ns"]].to_numpy()).all()
    cols = [f"T_{n}_N" for n in NAMES]
    T_a = _point_means(run, a, off0, g0)
    T_b = _point_means(run, b, off1, GAIN)
    np.testing.assert_allclose(a[cols].to_numpy(), T_a, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(b[cols].to_numpy(), T_b, rtol=1e-12, atol=1e-9)
    dT = T_b - T_a
    assert np.abs(dT).max() > 0.1  # the re-calibration really moves the tensions (N)

    # W_i = -A_i T_i + A_j T_j + (weight terms, the same in both analyses to ~1e-6: one pose),
    # A_i at the point's pose as the core used it: its tare's plus the deflection it reports
    i, j = 1, 0
    assert b.tare_point[i] == b.point[j]
    pose = ["x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]
    A_j = statics(ANCHORS, ATTACH, b[pose].to_numpy()[j])

    def cables(df: pd.DataFrame, T: np.ndarray) -> np.ndarray:
        q_i = df[pose].to_numpy()[j] + df[[f"deflection_{c}" for c in pose]].to_numpy()[i]
        return -statics(ANCHORS, ATTACH, q_i) @ T[i] + A_j @ T[j]

    dW = cables(b, T_b) - cables(a, T_a)
    got = b[WRENCH].to_numpy()[i] - a[WRENCH].to_numpy()[i]
    np.testing.assert_allclose(got, dW, rtol=1e-6, atol=1e-6)
    # the offsets cancel against the tare; the gains scale T0 - Tw (the aero load, about 1 N):
    # a change of a few mN, resolved 1000 times finer than the tolerance above
    assert np.abs(dW[:3]).max() > 1e-3

    # said everywhere: summary, report, points.csv
    s = json.loads((tmp_path / "b" / run.stem / "summary.json").read_text())
    lc = s["loadcell_calibration"]
    assert lc["applied"] and lc["name"] == "post_campaign.toml"
    assert lc["sha256"] == hashlib.sha256(cal.read_bytes()).hexdigest()
    assert lc["id"] == "lc-2026-11-20" and lc["created_utc"] == "2026-11-20T10:00:00Z"
    assert lc["given_by"] == "--loadcell-calibration"
    assert set(b.tensions_from) == {lc["tensions_from"]} and lc["sha256"] in lc["tensions_from"]
    assert "re-derived from raw" in lc["tensions_from"]
    report = (tmp_path / "b" / run.stem / "report.md").read_text()
    assert "re-derived from the recorded raw counts" in report and lc["sha256"] in report
    sa = json.loads((tmp_path / "a" / run.stem / "summary.json").read_text())
    assert sa["loadcell_calibration"]["applied"] is False
    assert (a.tensions_from == "recorded tensions (no load-cell re-calibration)").all()


def test_the_runs_own_calibration_changes_nothing(run: Path, tmp_path: Path) -> None:
    own = run.with_name(run.stem + ".loadcells.toml")
    assert _analyze(run, tmp_path / "a") == 1
    assert _analyze(run, tmp_path / "b", "--loadcell-calibration", str(own)) == 1
    a = pd.read_csv(tmp_path / "a" / run.stem / "points.csv")
    b = pd.read_csv(tmp_path / "b" / run.stem / "points.csv")
    cols = [f"T_{n}_N" for n in NAMES] + WRENCH
    np.testing.assert_array_equal(a[cols].to_numpy(), b[cols].to_numpy())
    s = json.loads((tmp_path / "b" / run.stem / "summary.json").read_text())
    assert set(s["loadcell_calibration"]["max_abs_change_N"].values()) == {0.0}


def test_a_changed_calibration_file_makes_the_run_not_current(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    off0, g0 = _recorded_calibration(run)
    cal = _write_cal(tmp_path / "lc.toml", off0, g0 * 1.01, "v1")
    out = tmp_path / "a"
    assert _analyze(run, out, "--loadcell-calibration", str(cal)) == 1
    first = pd.read_csv(out / run.stem / "points.csv")
    capsys.readouterr()
    assert _analyze(run, out, "--loadcell-calibration", str(cal)) == 1
    assert "current, skipped" in capsys.readouterr().out
    _write_cal(cal, off0, g0 * 1.02, "v2")  # same name, other gains
    assert _analyze(run, out, "--loadcell-calibration", str(cal)) == 1
    assert "current, skipped" not in capsys.readouterr().out
    second = pd.read_csv(out / run.stem / "points.csv")
    col = f"T_{NAMES[0]}_N"
    np.testing.assert_allclose(second[col] / first[col], 1.02 / 1.01, rtol=1e-12)
    s = json.loads((out / run.stem / "summary.json").read_text())
    assert s["loadcell_calibration"]["id"] == "v2"


def test_the_matrix_names_the_calibration_and_the_option_wins(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    off0, g0 = _recorded_calibration(run)
    _write_cal(tmp_path / "matrix_lc.toml", off0, g0 * 1.05, "from-matrix")
    o_cal = _write_cal(tmp_path / "option_lc.toml", off0, g0 * 0.97, "from-option")
    matrix = tmp_path / "m.toml"
    matrix.write_text(
        f'[campaign]\nname = "t"\nrig = "{RIG.as_posix()}"\n'
        'loadcell_calibration = "matrix_lc.toml"\n'
        "[model]\narea_m2 = 0.0146\nspan_m = 0.2441\nchord_m = 0.06\nmrp_P_m = [0.0, 0.0, 0.0]\n"
        '[[points]]\nlabel = "tare"\nkind = "tare"\n'
    )
    assert _analyze(run, tmp_path / "m", "--matrix", str(matrix)) in (0, 1)
    said = capsys.readouterr().out
    assert f"matrix_lc.toml (given by the test matrix {matrix}" in said
    lc = _provenance(tmp_path / "m", run)
    assert lc["id"] == "from-matrix" and "test matrix" in lc["given_by"]
    args = ["--matrix", str(matrix), "--loadcell-calibration", str(o_cal)]
    assert _analyze(run, tmp_path / "o", *args) in (0, 1)
    said = capsys.readouterr().out
    assert "option_lc.toml (given by --loadcell-calibration (over the test matrix's" in said
    lc = _provenance(tmp_path / "o", run)
    assert lc["id"] == "from-option" and lc["given_by"].startswith("--loadcell-calibration")
    m = pd.read_csv(tmp_path / "m" / run.stem / "points.csv")
    o = pd.read_csv(tmp_path / "o" / run.stem / "points.csv")
    col = f"T_{NAMES[3]}_N"
    np.testing.assert_allclose(o[col] / m[col], 0.97 / 1.05, rtol=1e-12)


def _one_error_no_output(out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert not out.exists() or not any(out.iterdir())
    return err[0]


def test_a_run_without_raw_counts_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    r = tmp_path / "imported.mcap"
    write_run(r, alpha_sweep(7, point_s=1.0, ramp_s=0.4))  # tensions only, no raw counts
    cal = _write_cal(tmp_path / "lc.toml", np.zeros(8), np.full(8, 5e-5), "x")
    out = tmp_path / "out"
    assert _analyze(r, out, "--loadcell-calibration", str(cal)) == 2
    line = _one_error_no_output(out, capsys)
    assert "imported.mcap" in line and "no raw counts column raw_" in line


def test_a_calibration_for_other_cables_names_the_missing_ones(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cal = tmp_path / "lc.toml"
    names = [*NAMES[:6], "spare_a", "spare_b"]
    cal.write_text(
        "[calibration]\ncables = [" + ", ".join(f'"{n}"' for n in names) + "]\n"
        "offset_counts = 0.0\ngain_N_per_count = 5e-5\n"
    )
    out = tmp_path / "out"
    assert _analyze(run, out, "--loadcell-calibration", str(cal)) == 2
    line = _one_error_no_output(out, capsys)
    assert "lc.toml" in line and "calibration.cables" in line and run.name in line
    assert f"no calibration for {NAMES[6]}, {NAMES[7]}" in line


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ('[calibration]\nkind = "balance"\noffset_counts = 0.0\ngain_N_per_count = 5e-5\n',
         "calibration.kind"),
        ("[calibration]\noffset_counts = 0.0\n", "calibration.gain_N_per_count"),
        ("[calibration]\noffset_counts = 0.0\ngain_N_per_count = 0.0\n", "gain_N_per_count"),
    ],
)  # fmt: skip
def test_a_calibration_failing_its_schema_is_refused(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, key: str
) -> None:
    cal = tmp_path / "bad.toml"
    cal.write_text(text)
    out = tmp_path / "out"
    assert _analyze(run, out, "--loadcell-calibration", str(cal)) == 2
    line = _one_error_no_output(out, capsys)
    assert "bad.toml" in line and key in line
