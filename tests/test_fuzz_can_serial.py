"""Property-based fuzzing (hypothesis) of the CAN and serial readers: candump and ASC logs and the
DBC through ``cdpr import`` (so the contract holds whatever parser is behind it), serial lines and
CAN frames through the drivers' decoders.  Contract for files: ``tests/_fuzz_contract.py``."""

from __future__ import annotations

import math
import re
import tempfile
from pathlib import Path

import can
import numpy as np
from _fuzz_contract import FUZZ, check_cli, mutated
from hypothesis import given
from hypothesis import strategies as st

from cdpr.daq.can_dbc import DEFAULT_DBC, load_dbc
from cdpr.daq.can_decoder import LoadCellDecoder
from cdpr.daq.can_frames import FrameColumns
from cdpr.daq.loadcell import Calibration
from cdpr.daq.schema import load_rig
from cdpr.daq.serial_protocol import LineError, format_loadcell_line, parse_loadcell_line
from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
T0_S = 1_700_000_000.0


def _frames() -> tuple[list[int], np.ndarray]:
    rig = load_rig(RIG)
    sched = schedule_from_mapping(
        {
            "schedule": {"name": "fz", "rate_hz": 100.0, "seed": 3},
            "segments": [{"label": "tare", "tare": True, "duration_s": 0.1, "wind_mps": 0.0}],
        },
        "<fuzz>",
        rig,
    )
    return VirtualRig(rig, sched).can_frames()


IDS, DATA = _frames()


def _log_text(suffix: str) -> str:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"run{suffix}"
        writer = can.Logger(str(path))
        for k in range(DATA.shape[0]):
            for j, fid in enumerate(IDS):
                msg = can.Message(
                    arbitration_id=fid,
                    data=DATA[k, j].tobytes(),
                    is_extended_id=False,
                    timestamp=T0_S + k * 0.01 + j * 1e-4,
                    channel=0,
                )
                writer.on_message_received(msg)
        writer.stop()
        return path.read_text()


CANDUMP, ASC, DBC_TEXT = _log_text(".log"), _log_text(".asc"), DEFAULT_DBC.read_text()


# ids of 1-8 hex digits: can-utils writes 3 or 8, python-can's writer other lengths too (CAN FD),
# and python-can's reader reads them all (more than 3: extended); a channel is printable ASCII
_CANDUMP_LINE = re.compile(r"\(\d+\.\d+\) [!-~]+ [0-9A-Fa-f]{1,8}#([0-9A-Fa-f]{2}){0,8}( [RT])?")
_ASC_FRAME = re.compile(
    r"[0-9]+\.[0-9]+[ \t]+[0-9]+[ \t]+[0-9A-Fa-f]{1,8}x?[ \t]+(Rx|Tx)[ \t]+d[ \t]+([0-9A-Fa-f])"
    r"((?:[ \t]+[0-9A-Fa-f]{2})*)"
)
_ASC_HEADER = ("date ", "base ", "internal events", "no internal events", "Begin Triggerblock",
               "Begin TriggerBlock", "End TriggerBlock", "End Triggerblock", "// ")  # fmt: skip
_DLC_BYTES = [0, 1, 2, 3, 4, 5, 6, 7, 8, 8, 8, 8, 8, 8, 8, 8]  # classic CAN: DLC 9-15 mean 8 bytes


def _candump_ok(data: bytes) -> bool:
    """Every line a candump -L frame (the grammar python-can writes and reads)."""
    try:
        lines = data.decode("ascii").splitlines()
    except UnicodeDecodeError:
        return False
    return all(_CANDUMP_LINE.fullmatch(x.strip()) for x in lines if x.strip())


def _asc_ok(data: bytes) -> bool:
    """Every line an ASC header line, the start event or a classic frame with as many bytes as
    its DLC (DLC 9-15: 8 bytes, as in the real ``issue_1299.asc``); UTF-8 text, as python-can
    reads it; fields separated by spaces or tabs."""
    try:
        lines = data.decode("utf-8").splitlines()
    except UnicodeDecodeError:
        return False
    for x in (x.strip() for x in lines):
        if (
            not x
            or x.replace("\t", " ").startswith(_ASC_HEADER)
            or x.endswith("Start of measurement")
        ):
            continue
        m = _ASC_FRAME.fullmatch(x)
        if not m or len(m[3].split()) != _DLC_BYTES[int(m[2], 16)]:
            return False
    return True


def _import(capsys, folder: Path, log: Path, dbc: Path, bad: Path) -> int:
    out = folder / "run.mcap"
    argv = [
        "import",
        "--can-log",
        str(log),
        "--dbc",
        str(dbc),
        "--rig",
        str(RIG),
        "--out",
        str(out),
    ]
    return check_cli(capsys, argv, folder, bad, [out])


@FUZZ
@given(data=mutated(CANDUMP, "#"))
def test_fuzz_candump_log(capsys, data):
    d = Path(tempfile.mkdtemp(prefix="fuzz-"))
    log = d / "run.log"
    log.write_bytes(data)
    if _import(capsys, d, log, DEFAULT_DBC, log) == 0:
        assert _candump_ok(data), "a malformed candump log imported with exit 0"


@FUZZ
@given(data=mutated(ASC, " "))
def test_fuzz_asc_log(capsys, data):
    d = Path(tempfile.mkdtemp(prefix="fuzz-"))
    log = d / "run.asc"
    log.write_bytes(data)
    if _import(capsys, d, log, DEFAULT_DBC, log) == 0:
        assert _asc_ok(data), "a malformed ASC log imported with exit 0"


@FUZZ
@given(data=mutated(DBC_TEXT, " :"))
def test_fuzz_dbc(capsys, data):
    d = Path(tempfile.mkdtemp(prefix="fuzz-"))
    log, dbc = d / "run.log", d / "cells.dbc"
    log.write_text(CANDUMP)
    dbc.write_bytes(data)
    _import(capsys, d, log, dbc, dbc)


LINE = format_loadcell_line(7, 123456, [1000, -2000, 3, 4, 5, 6, 7, 8], 0)


@FUZZ
@given(
    data=mutated(LINE.decode(errors="replace"), ","),
    counts=st.lists(st.integers(-(2**31), 2**31 - 1), min_size=8, max_size=8),
)
def test_fuzz_serial_lines(data, counts):
    """A mangled line is a LineError (never another exception); a good line reads back exactly."""
    try:
        got = parse_loadcell_line(data, 8)
    except LineError:
        pass
    else:
        assert len(got.counts) == 8 and all(isinstance(c, int) for c in got.counts)
    good = parse_loadcell_line(format_loadcell_line(3, 99, counts, 1), 8)
    assert (good.seq, good.t_device_us, list(good.counts), good.status) == (3, 99, counts, 1)


@FUZZ
@given(
    frames=st.lists(
        st.tuples(st.sampled_from([*IDS, 0x7FF, 0x000]), st.binary(min_size=0, max_size=8)),
        min_size=1,
        max_size=24,
    )
)
def test_fuzz_can_frames(frames):
    """Random frames (wrong lengths, unknown ids, random payloads): the decoder never raises and
    every tension it emits is finite or carries a non-zero status."""
    db = load_dbc(DEFAULT_DBC)
    names = [f"c{i}" for i in range(8)]
    dec = LoadCellDecoder(db, names, Calibration(np.zeros(8), np.full(8, 1e-3)), 100.0)
    out = []
    msgs = [can.Message(arbitration_id=fid, data=p, is_extended_id=False) for fid, p in frames]
    cut = len(msgs) // 2  # two blocks: a sample may straddle them
    for a, b in ((0, cut), (cut, len(msgs))):
        block = FrameColumns.from_messages(msgs[a:b])
        out += dec.decode_frames(block, 1_000_000 * np.arange(a, b)).readings()
    out += dec.flush().readings()
    for r in out:
        vals = [v for key, v in r.values.items() if key.startswith("T_")]
        assert r.status != 0 or all(math.isfinite(v) for v in vals), r
