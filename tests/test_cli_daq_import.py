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
