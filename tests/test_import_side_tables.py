"""``cdpr import --tunnel --events``: another tool's tunnel log and test-point list make the imported
CAN log a full run (``/tunnel`` and ``/events``), read back with the mcap library's reader and with
@mcap/core; bad side tables are one line naming file, row and column, exit 2, no output."""

from __future__ import annotations

from pathlib import Path

import can
import pytest
from _block_reader import messages
from mcap.reader import make_reader
from test_recorder_helpers import node_read

from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
T_LOG0_NS = 1_700_000_000_000_000_000


def _can_log(path: Path, n_samples: int = 60) -> None:
    """A candump log of 4 frames per sample at 100 Hz (all-zero counts: content is not the point)."""
    logger = can.Logger(str(path))
    for k in range(n_samples):
        for j, fid in enumerate((385, 641, 897, 1153)):  # the DBC ids
            data = bytes([k % 256] + [0] * 7) if j == 0 else bytes(8)
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


TUNNEL_PT = """# tunnel log, p and T
t_s,airspeed_mps,static_pressure_Pa,temperature_K
0.0,0.0,101325,293.15
0.2,12.5,101300,293.2
0.4,25.51,101280,293.25
"""
EVENTS = """t_s,point,phase,kind,target_aoa_deg,target_sideslip_deg,target_airspeed_mps,repeat_of
0.05,tare-a0,start,tare,0,0,0,
0.15,tare-a0,end,tare,0,0,0,
0.30,a0-v25,start,wind_on,0,0,25.51,
0.55,a0-v25,end,wind_on,0,,25.51,
"""


def _read(path: Path) -> dict[str, list[tuple[int, dict]]]:
    """Every message with the mcap package's reader (column blocks row by row)."""
    with path.open("rb") as fh:
        return messages(make_reader(fh))


def _argv(tmp: Path, *extra: str) -> list[str]:
    log = tmp / "run.log"
    if not log.exists():
        _can_log(log)
    return ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG), *extra]


def test_import_tunnel_and_events_make_a_full_run(tmp_path: Path) -> None:
    (tmp_path / "tunnel.csv").write_text(TUNNEL_PT)
    (tmp_path / "events.csv").write_text(EVENTS)
    out = tmp_path / "imported.mcap"
    argv = _argv(tmp_path, "--tunnel", str(tmp_path / "tunnel.csv"))
    argv += ["--events", str(tmp_path / "events.csv"), "--out", str(out)]
    assert main(argv) == 0
    msgs = _read(out)
    tun, ev = msgs["/tunnel"], msgs["/events"]
    assert len(msgs["/tensions"]) == 60 and msgs["/tensions"][0][0] == T_LOG0_NS
    # times: t_s counted from the first CAN frame of the log
    assert [t for t, _ in tun] == [T_LOG0_NS, T_LOG0_NS + 200_000_000, T_LOG0_NS + 400_000_000]
    assert [b["airspeed_mps"] for _, b in tun] == [0.0, 12.5, 25.51]
    # density by hand: p / (R T), R = 287.05287 J/(kg K)
    assert tun[2][1]["density_kgpm3"] == pytest.approx(101280 / (287.05287 * 293.25), rel=1e-12)
    assert tun[1][1]["static_pressure_Pa"] == 101300.0
    assert [(b["point"], b["phase"], b["kind"]) for _, b in ev] == [
        ("tare-a0", "start", "tare"), ("tare-a0", "end", "tare"),
        ("a0-v25", "start", "wind_on"), ("a0-v25", "end", "wind_on"),
    ]  # fmt: skip
    assert all(b["name"] == "test_point" for _, b in ev)
    assert ev[2][0] == T_LOG0_NS + 300_000_000 and ev[2][1]["target_airspeed_mps"] == 25.51
    assert ev[3][1]["target_sideslip_deg"] is None  # an empty cell: unknown, never 0
    node = node_read(out)  # the independent JavaScript reader agrees
    assert node["complete"] and node["topics"]["/tunnel"] == 3 and node["topics"]["/events"] == 4
    names = {a["name"] for a in node["attachments"]}
    assert {"tunnel/tunnel.csv", "events/events.csv"} <= names


OSC_EVENTS = """t_s,point,phase,kind,target_aoa_deg,target_airspeed_mps,motion_axis,\
motion_amplitude,motion_frequency_Hz,motion_cycles,motion_settling_cycles,inertia_tare
0.05,zero,start,zero,0,0,,,,,,
0.10,zero,end,zero,0,0,,,,,,
0.15,ot,start,oscillation_tare,0,0,pitch,0.0873,2.0,60,2,
0.25,ot,end,oscillation_tare,0,0,pitch,0.0873,2.0,60,2,
0.30,o,start,oscillation,0,25.51,pitch,0.0873,2.0,60,2,ot
0.55,o,end,oscillation,0,25.51,pitch,0.0873,2.0,60,2,ot
"""  # the backslash joins the header's two lines


def test_import_events_carry_an_oscillations_motion(tmp_path: Path) -> None:
    (tmp_path / "events.csv").write_text(OSC_EVENTS)
    out = tmp_path / "imported.mcap"
    assert main(_argv(tmp_path, "--events", str(tmp_path / "events.csv"), "--out", str(out))) == 0
    ev = [b for _, b in _read(out)["/events"]]
    assert [(b["point"], b["kind"]) for b in ev[::2]] == [
        ("zero", "zero"), ("ot", "oscillation_tare"), ("o", "oscillation"),
    ]  # fmt: skip
    assert "motion_axis" not in ev[0]  # a steady point has no motion
    for b in ev[2:]:
        assert (b["motion_axis"], b["motion_amplitude"], b["motion_frequency_Hz"]) == (
            "pitch", 0.0873, 2.0,
        )  # fmt: skip
        assert (b["motion_cycles"], b["motion_settling_cycles"]) == (60, 2)
    assert [b["inertia_tare"] for b in ev[2:]] == ["", "", "ot", "ot"]


@pytest.mark.parametrize(
    ("old", "new", "where", "problem"),
    [
        ("0,0,pitch,0.0873,2.0,60,2,\n0.25", "0,0,,0.0873,2.0,60,2,\n0.25",
         "row 4, column motion_axis", "needs it"),
        ("0,0,pitch,0.0873,2.0,60,2,\n0.25", "0,0,twist,0.0873,2.0,60,2,\n0.25",
         "row 4, column motion_axis", "expected one of"),
        ("0,0,pitch,0.0873,2.0,60,2,\n0.25", "0,0,pitch,0.0873,2.0,60.5,2,\n0.25",
         "row 4, column motion_cycles", "whole number"),
        ("0,0,pitch,0.0873,2.0,60,2,\n0.25", "0,0,pitch,0.0873,0,60,2,\n0.25",
         "row 4, column motion_frequency_Hz", "> 0"),
        ("0.10,zero,end,zero,0,0,,,,,,", "0.10,zero,end,zero,0,0,pitch,,,,,",
         "row 3, column motion_axis", "only an oscillation row"),
    ],
)  # fmt: skip
def test_bad_oscillation_events_name_row_and_column(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    old: str,
    new: str,
    where: str,
    problem: str,
) -> None:
    assert old in OSC_EVENTS
    (tmp_path / "events.csv").write_text(OSC_EVENTS.replace(old, new, 1))
    out = tmp_path / "imported.mcap"
    assert main(_argv(tmp_path, "--events", str(tmp_path / "events.csv"), "--out", str(out))) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and where in err and problem in err, err
    assert not out.exists()


def test_import_tunnel_with_density_and_epoch_times(tmp_path: Path) -> None:
    t0 = T_LOG0_NS + 123
    (tmp_path / "tunnel.csv").write_text(
        f"t_ns,airspeed_mps,density_kgpm3\n{t0},17.27,1.2\n{t0 + 10**8},17.3,1.19\n"
    )
    out = tmp_path / "imported.mcap"
    assert main(_argv(tmp_path, "--tunnel", str(tmp_path / "tunnel.csv"), "--out", str(out))) == 0
    tun = _read(out)["/tunnel"]
    assert [t for t, _ in tun] == [t0, t0 + 10**8]
    assert [b["density_kgpm3"] for _, b in tun] == [1.2, 1.19]
    assert "static_pressure_Pa" not in tun[0][1]  # not made up


@pytest.mark.parametrize(
    ("which", "text", "where"),
    [
        ("tunnel", "t_s,airspeed_mps\n0,1\n", "column density_kgpm3"),
        (
            "tunnel",
            "t_s,airspeed_mps,density_kgpm3\n0,1,1.2\n0.1,-2,1.2\n",
            "row 3, column airspeed_mps",
        ),
        (
            "tunnel",
            "t_s,airspeed_mps,density_kgpm3\n0,1,1.2\n0.1,2,0\n",
            "row 3, column density_kgpm3",
        ),
        ("tunnel", "t_s,airspeed_mps,density_kgpm3\n0.2,1,1.2\n0.1,2,1.2\n", "row 3, column t_s"),
        ("tunnel", "t_ns,airspeed_mps,density_kgpm3\n1.5,1,1.2\n", "row 2, column t_ns"),
        ("tunnel", "t_s,airspeed_mps,static_pressure_Pa\n0,1,101325\n", "column temperature_K"),
        ("events", "t_s,point,phase,kind\n0,a,begin,tare\n", "row 2, column phase"),
        ("events", "t_s,point,phase,kind\n0,a,start,wind\n", "row 2, column kind"),
        ("events", "t_s,point,phase,kind\n0,a,end,tare\n", "row 2, column phase"),
        ("events", "t_s,point,phase,kind\n0,a,start,tare\n", "never ends"),
        ("events", "t_s,point,phase,kind\n0,a,start,tare\n1,b,start,tare\n", "row 3, column phase"),
        ("events", "t_s,point,phase\n0,a,start\n", "column kind"),
        (
            "events",
            "t_s,point,phase,kind,target_aoa_deg\n0,a,start,tare,x\n1,a,end,tare,0\n",
            "row 2, column target_aoa_deg",
        ),
    ],
)
def test_bad_side_table_is_one_line_exit_2_no_output(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], which: str, text: str, where: str
) -> None:
    f = tmp_path / f"{which}.csv"
    f.write_text(text)
    out = tmp_path / "imported.mcap"
    assert main(_argv(tmp_path, f"--{which}", str(f), "--out", str(out))) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(f) in err and where in err, err
    assert not out.exists() and not list(tmp_path.glob(".*part"))
