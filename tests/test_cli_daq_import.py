"""``cdpr import``: CAN logs written by python-can's own writers (candump .log, ASC, BLF) plus a pose
CSV become a normal run; tensions checked against the virtual rig's truth counts."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest
from test_recorder_helpers import node_read

from cdpr.daq.mcap_io import read_run
from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping
from cdpr.pipelines.cli import main
from cdpr.pipelines.config import load_rig

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
T_LOG0 = 1_700_000_000.0  # log start, s since the epoch


@pytest.fixture(scope="module")
def rig_frames() -> tuple[VirtualRig, list[int], np.ndarray]:
    rig = load_rig(RIG)
    sched = schedule_from_mapping(
        {
            "schedule": {"name": "imp", "rate_hz": 100.0, "seed": 3},
            "segments": [
                {"label": "tare", "tare": True, "duration_s": 0.5, "wind_mps": 0.0},
                {"label": "v25", "duration_s": 0.5, "wind_mps": 25.51, "transition_s": 0.1},
            ],
        },
        "<test>",
        rig,
    )
    vr = VirtualRig(rig, sched)
    ids, data = vr.can_frames()
    return vr, ids, data


def _write_log(path: Path, ids: list[int], data: np.ndarray) -> int:
    logger = can.Logger(str(path))
    n = 0
    for k in range(data.shape[0]):
        for j, fid in enumerate(ids):
            logger.on_message_received(
                can.Message(
                    arbitration_id=fid,
                    data=data[k, j].tobytes(),
                    is_extended_id=False,
                    timestamp=T_LOG0 + k * 0.01 + j * 1e-4,
                    channel=0,
                )
            )
            n += 1
    logger.stop()
    return n


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_import_can_log_and_poses(tmp_path: Path, suffix: str, rig_frames, capsys) -> None:
    vr, ids, data = rig_frames
    log = tmp_path / f"run{suffix}"
    n_frames = _write_log(log, ids, data)
    n = data.shape[0]
    poses = tmp_path / "poses.csv"
    truth = vr.truth()
    rows = ["t_s,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad"]
    for k in range(0, n, 10):
        p, e = truth["position_O_m"][k], truth["euler_rad"][k]
        rows.append(f"{k * 0.01},{p[0]},{p[1]},{p[2]},{e[0]},{e[1]},{e[2]}")
    poses.write_text("\n".join(rows) + "\n")
    cal = tmp_path / "cal.toml"
    cal.write_text(
        "[calibration]\n"
        "offset_counts = [" + ", ".join(str(float(x)) for x in truth["offset_counts"]) + "]\n"
        "gain_N_per_count = [" + ", ".join(str(float(x)) for x in truth["gain_N_per_count"]) + "]\n"
    )
    out = tmp_path / "imported.mcap"
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--poses", str(poses)]
    argv += ["--rig", str(RIG), "--calibration", str(cal), "--out", str(out)]
    assert main(argv) == 0
    node = node_read(out)
    assert node["complete"] and node["bad_json"] == 0
    assert node["samples"]["/can_raw"] == n_frames  # frame blocks (docs/recording.md)
    assert node["samples"]["/tensions"] == n  # column blocks (docs/recording.md)
    assert node["topics"]["/pose"] == len(rows) - 1
    assert node["schemas"]["/pose"] == "foxglove.PoseInFrame"
    assert {a["name"] for a in node["attachments"]} == {
        "rig/flat_optimum.toml",
        "calibration/loadcell.dbc",
        "calibration/cal.toml",
        "poses/poses.csv",
    }
    rc = read_run(out)
    cables = list(load_rig(RIG).cable_names)
    T = np.array([[b[f"T_{c}_N"] for c in cables] for _, b in rc.messages["/tensions"]])
    expected = (truth["counts"] - truth["offset_counts"]) * truth["gain_N_per_count"]
    np.testing.assert_allclose(T, expected, rtol=0, atol=1e-9)
    t_first = rc.messages["/can_raw"][0][0]
    assert abs(t_first - int(T_LOG0 * 1e9)) < 1000 or suffix == ".asc"  # ASC keeps relative times
    pose = rc.messages["/pose"][3][1]
    assert pose["pose"]["position"]["z"] == pytest.approx(truth["position_O_m"][30][2])
    assert rc.messages["/pose"][3][0] - rc.messages["/can_raw"][0][0] == 300_000_000
    assert rc.metadata["run"]["command"] == "import"
    # never overwritten
    assert main(argv) == 2
    assert "never overwritten" in capsys.readouterr().err


def test_import_bad_inputs_one_line_and_no_output(tmp_path: Path, capsys) -> None:
    log = tmp_path / "x.log"
    log.write_text("(1700000000.000000) can0 181#0011223344556677\n")
    poses = tmp_path / "p.csv"
    poses.write_text("t_s,x_m,y_m,z_m,roll_rad,pitch_rad\n0,0,0,0,0,0\n")
    out = tmp_path / "o.mcap"
    base = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    assert main([*base, "--poses", str(poses), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "p.csv" in err[0] and "yaw_rad" in err[0]
    bad_cal = tmp_path / "c.toml"
    bad_cal.write_text("gain = 1\n")
    assert main([*base, "--calibration", str(bad_cal), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "c.toml" in err[0] and "gain" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.toml", "p.csv", "x.log"]


# --- issue 19: what import must refuse or count ---------------------------------------------------


def _write_frames(
    path: Path, ids: list[int], data: np.ndarray, cut: dict[tuple[int, int], int]
) -> None:
    """The rig's frames through python-can's own writer for the suffix; frame ``(k, j)`` in
    ``cut`` keeps only its first ``cut[k, j]`` bytes (a truncated frame, as a faulty amplifier or
    a logger with the wrong DLC gives it)."""
    logger = can.Logger(str(path))
    for k in range(data.shape[0]):
        for j, fid in enumerate(ids):
            payload = data[k, j].tobytes()[: cut.get((k, j), 8)]
            logger.on_message_received(
                can.Message(arbitration_id=fid, data=payload, is_extended_id=False,
                            timestamp=T_LOG0 + k * 0.01 + j * 1e-4, channel=0)
            )  # fmt: skip
    logger.stop()


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_a_truncated_load_cell_frame_is_counted_and_flags_its_sample(
    tmp_path: Path, suffix: str, rig_frames, capsys
) -> None:
    """A 3-byte frame of an 8-byte load-cell message: counted bad (run_end, inspect), the frame
    flagged in /can_raw, its sample flagged gap + bad frame with its two channels NaN; every other
    sample exactly the truth's counts."""
    from cdpr.daq.run_reader import open_run
    from cdpr.daq.source import STATUS_BAD_FRAME, STATUS_GAP

    vr, ids, data = rig_frames
    log = tmp_path / f"short{suffix}"
    _write_frames(log, ids, data, {(5, 2): 3})
    out = tmp_path / "short.mcap"
    assert main(["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG),
                 "--out", str(out)]) == 0  # fmt: skip
    assert "1 load-cell frame(s) of the wrong length" in capsys.readouterr().out
    truth = vr.truth()
    cables = list(load_rig(RIG).cable_names)
    with open_run(out) as run:
        ten = run.table("/tensions")
        raw = run.table("/can_raw")
        end = run.metadata["run_end"]
    assert len(ten) == data.shape[0] and len(raw) == data.size // 8
    status = ten["status"].to_numpy()
    assert status[5] == STATUS_GAP | STATUS_BAD_FRAME
    assert (np.delete(status, 5) == 0).all()
    counts = ten[[f"raw_{c}_counts" for c in cables]].to_numpy()
    want = truth["counts"].astype(np.int64)
    from cdpr.daq.loadcell import RAW_MISSING_COUNTS

    want[5, 4:6] = RAW_MISSING_COUNTS  # the frame of channels 5 and 6 of sample 5
    assert np.array_equal(counts, want)
    assert np.isnan(ten[f"T_{cables[4]}_N"][5]) and np.isnan(ten[f"T_{cables[5]}_N"][5])
    bad = raw[raw["status"] != 0]
    assert (
        len(bad) == 1 and bad["arbitration_id"].iloc[0] == ids[2] and len(bad["data"].iloc[0]) == 3
    )
    assert '"bad": 1' in end["source_stats"] and '"bad_frames": 1' in end["can_log"]
    assert main(["inspect", str(out)]) == 0
    shown = capsys.readouterr().out.splitlines()
    row = next(line.split() for line in shown if line.strip().startswith("can_log"))
    assert row[1:] == [str(data.size // 8), "0", "0", "1", "0"]  # read dropped lost bad errors
    assert next(line.split() for line in shown if line.strip().startswith("/can_raw"))[-1] == "1"


def test_a_dbc_without_a_cable_s_counts_is_refused(tmp_path: Path, capsys) -> None:
    """A DBC with Ch8's status bits but not its counts (the rig has 8 cables): one line naming the
    DBC and the cable, exit 2, no run (the cable would otherwise read 0.0 N, status 0)."""
    dbc = tmp_path / "no_ch8.dbc"
    text = DBC.read_text()
    line = ' SG_ Ch8_Counts : 24|24@1- (1,0) [-8388608|8388607] "counts" DAQ\n'
    assert line in text
    dbc.write_text(text.replace(line, ""))
    log = tmp_path / "x.log"
    log.write_text("(1700000000.000000) can0 181#0011223344556677\n")
    out = tmp_path / "o.mcap"
    assert main(["import", "--can-log", str(log), "--dbc", str(dbc), "--rig", str(RIG),
                 "--out", str(out)]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    last = list(load_rig(RIG).cable_names)[7]
    assert len(err) == 1 and "no_ch8.dbc" in err[0] and repr(last) in err[0], err
    assert "Ch8_Counts" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["no_ch8.dbc", "x.log"]


def test_an_unknown_key_in_the_calibration_table_is_refused(tmp_path: Path, capsys) -> None:
    log = tmp_path / "x.log"
    log.write_text("(1700000000.000000) can0 181#0011223344556677\n")
    cal = tmp_path / "c.toml"
    cal.write_text("[calibration]\noffset_counts = 0.0\ngain_N_per_count = 5e-5\n"
                   "gian_N_per_count = 1.0\n")  # fmt: skip
    assert main(["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG),
                 "--calibration", str(cal), "--out", str(tmp_path / "o.mcap")]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "c.toml: calibration.gian_N_per_count: unknown key" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.toml", "x.log"]
