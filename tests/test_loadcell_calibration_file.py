"""One load-cell calibration file: ``cdpr calibrate loadcells`` writes it; ``cdpr simulate`` (the
virtual amplifiers), ``cdpr import`` and ``cdpr record`` (a source's ``calibration_file``) read it;
``cdpr simulate`` writes its rig's calibration in the same format, which ``cdpr import`` reads.
Expected numbers come from the known offsets and gains of the points the test generates."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import can
import numpy as np
import pytest
from _block_reader import samples
from mcap.reader import make_reader

from cdpr.analysis.errors import ConfigError
from cdpr.daq.loadcell import read_calibration_file
from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping
from cdpr.pipelines.cli import main
from cdpr.pipelines.config import load_rig

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
NAMES = list(load_rig(RIG).cable_names)
OFFSETS = np.array([-30000.0, -12000.0, 0.0, 4000.0, 9000.0, 15000.0, 21000.0, 40000.0])
GAINS = np.array([4.2e-5, 4.6e-5, 4.8e-5, 5.0e-5, 5.1e-5, 5.3e-5, 5.6e-5, 5.9e-5])


def _calibrate(tmp_path: Path, order: list[int] | None = None) -> Path:
    """Exact points (no noise) through ``cdpr calibrate loadcells``; ``order`` shuffles the rows."""
    rows = ["channel,load_N,counts"]
    for i in order or range(8):
        for load in (0.0, 50.0, 150.0, 280.0):
            rows.append(f"{NAMES[i]},{load},{float(OFFSETS[i] + load / GAINS[i])!r}")
    pts = tmp_path / "points.csv"
    pts.write_text("\n".join(rows) + "\n")
    out = tmp_path / "loadcells.toml"
    assert main(["calibrate", "loadcells", str(pts), "--out", str(out)]) == 0
    return out


def test_calibrate_writes_what_the_reader_reads_in_rig_order(tmp_path: Path) -> None:
    order = [3, 1, 7, 0, 2, 6, 5, 4]  # the lab calibrated the cells in another order
    f = read_calibration_file(_calibrate(tmp_path, order))
    assert f.cables == tuple(NAMES[i] for i in order) and f.id.startswith("loadcells@")
    cal = f.for_cables(NAMES)  # matched by name
    np.testing.assert_allclose(cal.offset_counts, OFFSETS, atol=1e-4)
    np.testing.assert_allclose(cal.gain_N_per_count, GAINS, rtol=1e-9)
    assert "residual_rms_N" in f.extra


def _tensions(path: Path) -> np.ndarray:
    """(n, 8) tensions of a run's ``/tensions`` samples, read with the mcap library (column blocks
    decoded by tests/_block_reader.py)."""
    with path.open("rb") as fh:
        rows = samples(make_reader(fh), "/tensions")
    return np.array([[r[f"T_{n}_N"] for n in NAMES] for r in rows])


def _schedule() -> str:
    return (
        '[schedule]\nname = "cal"\nrate_hz = 100.0\nseed = 4\n'
        '[[segments]]\nlabel = "tare"\ntare = true\nduration_s = 0.6\nwind_mps = 0.0\n'
    )


def test_simulate_uses_the_file_and_writes_its_own(tmp_path: Path) -> None:
    cal = _calibrate(tmp_path)
    sched = tmp_path / "s.toml"
    sched.write_text(_schedule())
    out = tmp_path / "runs"
    res = subprocess.run(
        [sys.executable, "-m", "cdpr.pipelines.cli", "simulate", "--rig", str(RIG),
         "--schedule", str(sched), "--out", str(out), "--quiet",
         "--loadcell-calibration", str(cal)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    (run,) = out.glob("*.mcap")
    truth = np.load(run.with_name(run.stem + ".truth.npz"))
    np.testing.assert_allclose(truth["offset_counts"], OFFSETS, atol=1e-4)
    np.testing.assert_allclose(truth["gain_N_per_count"], GAINS, rtol=1e-9)
    T = _tensions(run)
    with run.open("rb") as fh:
        atts = {a.name for a in make_reader(fh).iter_attachments()}
    assert "calibration/loadcells.toml" in atts
    # the driver decoded the counts with the file's gains: the sensor tensions within rounding
    sent = truth["tensions_sensor_N"][truth["sent"]]
    assert T.shape == sent.shape
    np.testing.assert_allclose(T, sent, atol=0.51 * GAINS.max())
    own = read_calibration_file(run.with_name(run.stem + ".loadcells.toml"))
    np.testing.assert_allclose(own.for_cables(NAMES).gain_N_per_count, GAINS, rtol=1e-12)


def test_import_reads_the_file_the_virtual_rig_writes(tmp_path: Path) -> None:
    rig = load_rig(RIG)
    sch = schedule_from_mapping(
        {
            "schedule": {"name": "imp", "rate_hz": 100.0, "seed": 9},
            "segments": [{"label": "v", "duration_s": 0.3, "wind_mps": 20.0}],
        },
        "<test>",
        rig,
    )
    vr = VirtualRig(rig, sch)  # random offsets from the seed
    cal = vr.write_calibration(tmp_path / "vr.loadcells.toml")
    ids, data = vr.can_frames()
    log = tmp_path / "run.log"
    logger = can.Logger(str(log))
    for k in range(data.shape[0]):
        for j, fid in enumerate(ids):
            msg = can.Message(arbitration_id=fid, data=data[k, j].tobytes(), is_extended_id=False)
            msg.timestamp = 1.7e9 + k * 0.01 + j * 1e-4
            logger.on_message_received(msg)
    logger.stop()
    out = tmp_path / "imp.mcap"
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    assert main([*argv, "--calibration", str(cal), "--out", str(out)]) == 0
    T = _tensions(out)
    expect = (vr.counts - vr.calibration.offset_counts) * vr.calibration.gain_N_per_count
    np.testing.assert_allclose(T, expect, atol=1e-9)


@pytest.mark.parametrize(
    ("text", "key", "problem"),
    [
        ("offset_counts = 0.0\ngain_N_per_count = 5e-5\n", "gain_N_per_count", "one [calibration]"),
        ('[calibration]\nkind = "balance"\n', "calibration.kind", "'loadcells'"),
        ("[calibration]\ngain_N_per_count = 5e-5\n", "calibration.offset_counts", "missing"),
        (
            '[calibration]\ncables = ["a", "b"]\noffset_counts = [0.0]\ngain_N_per_count = 5e-5\n',
            "calibration.offset_counts",
            "expected 2 values",
        ),
        (
            '[calibration]\ncables = ["a", "b"]\noffset_counts = 0.0\ngain_N_per_count = [1e-5, 0]\n',
            "calibration.gain_N_per_count",
            "non-zero",
        ),
        # a misspelt key inside the table (issue 19): refused as a top-level one is
        (
            "[calibration]\noffset_counts = 0.0\ngain_N_per_count = 5e-5\ngian_N_per_count = 1.0\n",
            "calibration.gian_N_per_count",
            "unknown key",
        ),
    ],
)
def test_bad_calibration_file_names_file_and_key(
    tmp_path: Path, text: str, key: str, problem: str
) -> None:
    f = tmp_path / "c.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as ei:
        read_calibration_file(f)
    assert ei.value.source == str(f) and ei.value.key == key and problem in ei.value.problem


def test_a_file_for_other_cables_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text(
        '[calibration]\ncables = ["a", "b"]\noffset_counts = 0.0\ngain_N_per_count = 5e-5\n'
    )
    with pytest.raises(ConfigError) as ei:
        read_calibration_file(f).for_cables(NAMES)
    assert ei.value.key == "calibration.cables" and "the rig has" in ei.value.problem
