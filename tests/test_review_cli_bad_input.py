"""Bad input found by review, one test per defect: every case is one line on stderr naming the file
(and key or row) at fault, exit code 2, no traceback and no output file."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import can
import pytest
import tomli_w

from cdpr.daq.virtual_rig import VirtualRig, _atomic_write_bytes, schedule_from_mapping
from cdpr.pipelines.cli import main
from cdpr.pipelines.config import load_rig

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
POSE_HEADER = "x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad"


def _files(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def _one_error_line(capsys: pytest.CaptureFixture[str], *needles: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for n in needles:
        assert n in err[0], (n, err[0])
    assert "Traceback" not in err[0]
    return err[0]


def _blocked(tmp_path: Path) -> Path:
    """A folder that cannot be created, even by root: its parent is a regular file."""
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder\n")
    return blocker / "sub"


# --- pipelines/config.py: unwritable output, unreadable input, the NaN message -------------------


def test_solve_output_folder_cannot_be_created(tmp_path: Path, capsys) -> None:
    out = _blocked(tmp_path) / "t.csv"
    assert main(["solve", "--rig", str(RIG), "--out", str(out)]) == 2
    _one_error_line(capsys, "cdpr solve: error:", str(out), "cannot write", "is not a folder")
    assert _files(tmp_path) == ["blocker"]


def test_rig_paper_output_folder_cannot_be_created(tmp_path: Path, capsys) -> None:
    assert main(["rig", "paper", "--out", str(_blocked(tmp_path))]) == 2
    _one_error_line(capsys, str(_blocked(tmp_path)), "cannot write")
    assert _files(tmp_path) == ["blocker"]


def test_pose_table_that_is_a_folder(tmp_path: Path, capsys) -> None:
    (tmp_path / "poses.csv").mkdir()
    out = tmp_path / "t.csv"
    assert (
        main(
            ["solve", "--rig", str(RIG), "--poses", str(tmp_path / "poses.csv"), "--out", str(out)]
        )
        == 2
    )
    _one_error_line(capsys, "poses.csv: cannot read")
    assert not out.exists()


@pytest.mark.parametrize(
    ("cell", "shown"),
    [
        ("", "an empty cell or nan"),
        ("nan", "an empty cell or nan"),
        ("inf", "got inf"),
        ("abc", "got 'abc'"),
    ],
)
def test_bad_cell_is_shown_as_typed(tmp_path: Path, capsys, cell: str, shown: str) -> None:
    poses = tmp_path / "p.csv"
    poses.write_text(f"{POSE_HEADER}\n0.5,0,0.335,0,0,0\n0.5,{cell},0.335,0,0,0\n")
    out = tmp_path / "t.csv"
    assert main(["solve", "--rig", str(RIG), "--poses", str(poses), "--out", str(out)]) == 2
    line = _one_error_line(capsys, "p.csv: row 3, column y_m", shown)
    assert "np.float64" not in line
    assert not out.exists()


# --- pipelines/cli.py: an OSError no command caught is one line, exit 2 ---------------------------


def test_analyze_output_folder_cannot_be_created(tmp_path: Path, capsys) -> None:
    run = tmp_path / "r.mcap"
    run.write_bytes(b"\x89MCAP0\r\n")  # the folder fails first
    out = _blocked(tmp_path)
    assert main(["analyze", str(run), "--out", str(out), "--workers", "1"]) == 2
    _one_error_line(capsys, "cdpr analyze: error:", "blocker")
    assert _files(tmp_path) == ["blocker", "r.mcap"]


def test_simulate_output_folder_cannot_be_created(tmp_path: Path, capsys) -> None:
    sched = tmp_path / "s.toml"
    sched.write_text(
        '[schedule]\nname = "x"\nrate_hz = 100.0\n'
        '[[segments]]\nlabel = "a"\nduration_s = 0.5\nwind_mps = 0.0\n'
    )
    out = _blocked(tmp_path)
    argv = ["simulate", "--rig", str(RIG), "--schedule", str(sched), "--out", str(out), "--quiet"]
    assert main(argv) == 2
    # one line: no "VirtualBus was not properly shut down" after it (no source was opened)
    _one_error_line(capsys, "cdpr simulate: error:", str(out), "cannot create")
    assert _files(tmp_path) == ["blocker", "s.toml"]


def test_truth_file_has_the_usual_permissions(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        _atomic_write_bytes(tmp_path / "t.npz", b"data")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "t.npz").stat().st_mode) == 0o644  # mkstemp alone gives 0600


# --- cdpr import ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def can_log(tmp_path_factory) -> Path:
    """A candump log of 20 samples of the virtual rig, written by python-can."""
    rig = load_rig(RIG)
    sched = schedule_from_mapping(
        {
            "schedule": {"name": "imp", "rate_hz": 100.0, "seed": 3},
            "segments": [{"label": "tare", "tare": True, "duration_s": 0.2, "wind_mps": 0.0}],
        },
        "<test>",
        rig,
    )
    ids, data = VirtualRig(rig, sched).can_frames()
    path = tmp_path_factory.mktemp("log") / "run.log"
    logger = can.Logger(str(path))
    for k in range(data.shape[0]):
        for j, fid in enumerate(ids):
            logger.on_message_received(
                can.Message(
                    arbitration_id=fid,
                    data=data[k, j].tobytes(),
                    is_extended_id=False,
                    timestamp=1_700_000_000.0 + k * 0.01 + j * 1e-4,
                    channel=0,
                )
            )
    logger.stop()
    return path


def _import(tmp_path: Path, log: Path, *extra: str) -> int:
    argv = ["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG)]
    return main([*argv, *extra, "--out", str(tmp_path / "o.mcap")])


def test_import_calibration_error_names_the_calibration_file(
    tmp_path: Path, can_log, capsys
) -> None:
    cal = tmp_path / "cal.toml"
    cal.write_text("[calibration]\noffset_counts = [1.0, 2.0, 3.0]\ngain_N_per_count = 1.0\n")
    assert _import(tmp_path, can_log, "--calibration", str(cal)) == 2
    line = _one_error_line(
        capsys, "cal.toml: calibration.offset_counts:", "expected 8 values, got 3"
    )
    assert "run.log" not in line  # it used to blame the CAN log's "sources.can.offset_counts"
    assert _files(tmp_path) == ["cal.toml"]


def test_import_dbc_error_names_the_dbc(tmp_path: Path, can_log, capsys) -> None:
    dbc = tmp_path / "bad.dbc"
    dbc.write_text("this is not a DBC\n")
    argv = ["import", "--can-log", str(can_log), "--dbc", str(dbc), "--rig", str(RIG)]
    assert main([*argv, "--out", str(tmp_path / "o.mcap")]) == 2
    line = _one_error_line(capsys, "cdpr import: error: " + str(dbc) + ": ")
    assert "run.log" not in line
    assert _files(tmp_path) == ["bad.dbc"]


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("t_s,x_m,y_m,z_m\n0.0,1,2,3\n", "line 1: not a candump -L line"),  # not a CAN log
        ("", "no CAN frames"),
    ],
)
def test_import_not_a_can_log_is_bad_input(tmp_path: Path, capsys, text: str, needle: str) -> None:
    log = tmp_path / "x.log"
    log.write_text(text)
    assert _import(tmp_path, log) == 2  # it used to write an empty run and exit 0
    _one_error_line(capsys, "x.log", needle)
    assert _files(tmp_path) == ["x.log"]


@pytest.mark.parametrize(
    ("rows", "needle"),
    [
        ("t_s,{h}\n0.0,{p}\nabc,{p}\n", "row 3, column t_s: expected a finite number, got 'abc'"),
        ("t_s,{h}\n0.0,{p}\n0.3,{p}\n0.2,{p}\n", "row 4, column t_s: time goes backwards"),
        ("t_ns,{h}\n0.0,{p}\n0.5,{p}\n", "row 3, column t_ns: expected integer ns"),
    ],
)
def test_import_bad_pose_times(tmp_path: Path, can_log, capsys, rows: str, needle: str) -> None:
    poses = tmp_path / "p.csv"
    poses.write_text(rows.format(h=POSE_HEADER, p="0.5,0,0.335,0,0,0"))
    assert _import(tmp_path, can_log, "--poses", str(poses)) == 2
    _one_error_line(capsys, "p.csv: " + needle)
    assert _files(tmp_path) == ["p.csv"]


@pytest.mark.parametrize("rate", ["-1", "nan"])
def test_import_bad_rate(tmp_path: Path, can_log, capsys, rate: str) -> None:
    assert _import(tmp_path, can_log, "--rate", rate) == 2
    _one_error_line(capsys, "--rate", rate)
    assert _files(tmp_path) == []


# --- cdpr record: the load-cell cables must be the rig's -----------------------------------------


@pytest.mark.parametrize(
    ("drop", "rename", "needle"),
    [
        (True, False, "no load-cell source measures cable 'back_right_bottom'"),
        (False, True, "sources.cells.cables: 'back_right_bottm' is not a cable of rig"),
    ],
)
def test_record_cables_must_match_the_rig(
    tmp_path: Path, capsys, drop: bool, rename: bool, needle: str
) -> None:
    cables = list(load_rig(RIG).cable_names)
    if drop:
        cables = cables[:-1]
    if rename:
        cables[-1] = "back_right_bottm"
    cfg = {
        "run": {"label": "tp", "rig": str(RIG)},
        "sources": {
            "cells": {
                "kind": "can_loadcell",
                "interface": "virtual",
                "channel": f"review-{os.getpid()}-{drop}",
                "bitrate": 1_000_000,
                "rate_hz": 100.0,
                "dbc": str(DBC),
                "cables": cables,
                "offset_counts": 0.0,
                "gain_N_per_count": 5e-5,
            }
        },
    }
    path = tmp_path / "cfg.toml"
    path.write_bytes(tomli_w.dumps(cfg).encode())
    out = tmp_path / "runs"
    assert (
        main(["record", "--config", str(path), "--out", str(out), "--duration", "1", "--quiet"])
        == 2
    )
    _one_error_line(capsys, "cfg.toml: ", needle)
    assert _files(tmp_path) == ["cfg.toml"]


# --- option values checked before any work --------------------------------------------------------


@pytest.mark.parametrize(
    ("opt", "value"), [("--workers", "0"), ("--check-limit-N", "-1"), ("--check-limit-N", "nan")]
)
def test_analyze_bad_options(tmp_path: Path, capsys, opt: str, value: str) -> None:
    run = tmp_path / "r.mcap"
    run.write_bytes(b"\x89MCAP0\r\n")
    out = tmp_path / "out"
    assert main(["analyze", str(run), "--out", str(out), opt, value]) == 2
    _one_error_line(
        capsys, opt, value
    )  # they used to pass: a FAIL for every run, or a local cluster of 0 workers
    assert not out.exists()


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--family", "flat", "--min-margin", "nan"], "--min-margin: expected a finite number"),
        (["--family", "flat", "--speed", "inf"], "--speed: expected a finite airspeed"),
        (["--family", "cubic", "--speed", "20"], "--speed: applies to --family flat only"),
    ],
)
def test_design_bad_options(tmp_path: Path, capsys, argv: list[str], needle: str) -> None:
    out = tmp_path / "out"
    assert main(["design", *argv, "--out", str(out)]) == 2
    _one_error_line(capsys, needle)
    assert not out.exists()


# --- cdpr solve: a rig whose cable count the method cannot handle names the rig file --------------


def _rig_with(tmp_path: Path, n_cables: int) -> Path:
    """flat_optimum.toml cut to ``n_cables`` cables, or grown by copies under new names."""
    import tomllib

    data = tomllib.loads(RIG.read_text())
    cables = data["cables"]
    if n_cables < len(cables):
        cables = cables[:n_cables]
    else:
        cables = cables + [
            {**c, "name": c["name"] + "_2"} for c in cables[: n_cables - len(cables)]
        ]
    data["cables"] = cables
    rig = tmp_path / "rig.toml"
    rig.write_bytes(tomli_w.dumps(data).encode())
    return rig


@pytest.mark.parametrize(("n_cables", "needle"), [(5, "m >= n"), (10, "m - n <= 2")])
def test_solve_cable_count_names_the_rig(
    tmp_path: Path, capsys, n_cables: int, needle: str
) -> None:
    rig = _rig_with(tmp_path, n_cables)
    out = tmp_path / "t.csv"
    assert main(["solve", "--rig", str(rig), "--method", "exact", "--out", str(out)]) == 2
    _one_error_line(capsys, f"rig.toml: cables: {n_cables} cables, --method exact", needle)
    assert not out.exists()


@pytest.mark.parametrize(("n_cables", "needle"), [(5, "m >= n"), (10, "m - n <= 2")])
def test_simulate_cable_count_names_the_rig(
    tmp_path: Path, capsys, n_cables: int, needle: str
) -> None:
    rig = _rig_with(tmp_path, n_cables)
    sched = tmp_path / "s.toml"
    sched.write_text(
        '[schedule]\nname = "x"\nrate_hz = 100.0\nmethod = "exact"\n'
        '[[segments]]\nlabel = "a"\nduration_s = 0.5\nwind_mps = 0.0\n'
    )
    out = tmp_path / "runs"
    argv = ["simulate", "--rig", str(rig), "--schedule", str(sched), "--out", str(out), "--quiet"]
    assert main(argv) == 2
    _one_error_line(capsys, f"rig.toml: cables: {n_cables} cables", needle)
    assert not out.exists()


def test_import_rig_with_more_cables_than_the_dbc(tmp_path: Path, can_log, capsys) -> None:
    rig = _rig_with(tmp_path, 10)
    argv = ["import", "--can-log", str(can_log), "--dbc", str(DBC), "--rig", str(rig)]
    assert main([*argv, "--out", str(tmp_path / "o.mcap")]) == 2
    line = _one_error_line(
        capsys, "loadcell.dbc: no Ch9_Counts signal for cable", "nor for 1 more", "rig.toml"
    )
    assert "run.log" not in line
    assert _files(tmp_path) == ["rig.toml"]


# --- inspect / recover / export: a folder given as the run file -----------------------------------


@pytest.mark.parametrize(
    "argv", [["inspect"], ["recover"], ["export", "--hdf5", "x.h5"]], ids=lambda a: a[0]
)
def test_run_file_that_is_a_folder(tmp_path: Path, capsys, argv: list[str]) -> None:
    run = tmp_path / "run.mcap"
    run.mkdir()
    argv = [a if a != "x.h5" else str(tmp_path / "x.h5") for a in argv]
    assert main([*argv, str(run)]) == 2
    _one_error_line(capsys, "run.mcap: a folder, not a run file")  # it used to say "file not found"
    assert _files(tmp_path) == ["run.mcap"]


def test_wrench_bad_moment_reference_point_names_its_option(tmp_path: Path, capsys) -> None:
    poses = tmp_path / "p.csv"
    poses.write_text(f"{POSE_HEADER}\n0.5,0,0.335,0,0,0\n")
    names = load_rig(RIG).cable_names
    tensions = tmp_path / "T.csv"
    tensions.write_text(",".join(f"T_{c}_N" for c in names) + "\n" + ",".join(["150"] * 8) + "\n")
    out = tmp_path / "w.csv"
    argv = ["wrench", "--rig", str(RIG), "--poses", str(poses), "--tensions", str(tensions)]
    argv += ["--airspeed-mps", "10", "--density-kgpm3", "1.2", "--area-m2", "0.1"]
    argv += ["--span-m", "1", "--chord-m", "0.1", "--mrp-P-m", "nan", "0", "0"]
    assert main([*argv, "--out", str(out)]) == 2
    line = _one_error_line(capsys, "command line: --mrp-P-m: mrp_P_m")
    assert "--nose-P" not in line  # it used to blame --nose-P/--up-P
    assert not out.exists()
