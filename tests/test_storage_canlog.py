"""CAN logs: the numpy candump parser against python-can's ``CanutilsLogReader`` on the same file,
bad lines named by line number, and ``cdpr import`` of real logs written by other tools (python-can's
test data: Vector ASC and BLF, PEAK TRC; candump versions written by python-can) compared frame by
frame, every field, with python-can's ``LogReader`` on the same file."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest
from _block_reader import samples

from cdpr.analysis.errors import ConfigError
from cdpr.daq.canlog_asc import read_asc
from cdpr.daq.canlog_candump import read_candump
from cdpr.daq.run_reader import open_run
from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "can"
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
REAL = sorted(p for p in DATA.iterdir() if p.suffix in (".asc", ".blf", ".trc"))

HAND = """(1700000000.000100) can0 181#0102030405060708
(1700000000.000200) can0 12345678#DEADBEEF
(1700000000.000300) can1 123#R
(1700000000.000400) can1 123#R5 T
(1700000000.000500) vcan0 7FF##3000102030405060708090A0B
(1700000000.000600) 2 20000080#0000000000000000
(1700000000.000700) can0 0000012A##1
(1700000000.000800) can0 010# R

(1700000000.000900) can0 1F334455#1122334455667788 r
(0.5) can0 181#
"""


def _fields(m: can.Message) -> tuple:
    return (
        m.timestamp, m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.is_error_frame,
        m.is_fd, m.bitrate_switch, m.error_state_indicator, m.dlc, bytes(m.data), m.channel,
        m.is_rx,
    )  # fmt: skip


def _python_can(path: Path) -> list[can.Message]:
    reader = can.LogReader(str(path))
    try:
        return list(reader)
    finally:
        if hasattr(reader, "stop"):
            reader.stop()


def _candump_of(src: Path, dst: Path) -> Path:
    """A candump -L version of a real log, written by python-can's own writer."""
    with can.CanutilsLogWriter(str(dst)) as w:
        for m in _python_can(src):
            w.on_message_received(m)
    return dst


def test_candump_parser_matches_python_can_on_every_frame_kind(tmp_path: Path) -> None:
    p = tmp_path / "hand.log"
    p.write_text(HAND)
    logs = [p] + [_candump_of(r, tmp_path / f"{r.stem}_{r.suffix[1:]}.log") for r in REAL]
    total = 0
    for log in logs:
        want = [_fields(m) for m in _python_can(log)]
        got = [_fields(m) for c in read_candump(log, block_bytes=64) for m in c.messages()]
        assert got == want, log.name  # small blocks: lines cut across block boundaries
        total += len(want)
    assert total > 60


def test_a_bad_line_is_named_by_file_and_line(tmp_path: Path) -> None:
    p = tmp_path / "bad.log"
    lines = HAND.splitlines()
    lines[3] = "(1700000000.000400) can1 1G3#0102"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=r"bad\.log: line 4: bad CAN id \(not hex\)"):
        list(read_candump(p))
    lines[3] = "(1700000000.0004 can1 123#0102"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=r"bad\.log: line 4: not a candump -L line"):
        list(read_candump(p))
    lines[3] = "(1700000000.000400) can1 123#010"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=r"line 4: bad data"):
        list(read_candump(p))
    lines[3] = "(10700000000.000400) can1 123#0102"  # its ns do not fit an int64
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=r"line 4: timestamp out of range"):
        list(read_candump(p))


def _import(log: Path, out: Path) -> int:
    return main(["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG),
                 "--raw-only", "--out", str(out)])  # fmt: skip


def _same_as_python_can(run_path: Path, log: Path) -> int:
    want = _python_can(log)
    with open_run(run_path) as run:
        df = run.table("/can_raw")
    assert len(df) == len(want)
    for i, m in enumerate(want):
        r = df.iloc[i]
        got = (
            r["arbitration_id"], bool(r["is_extended"]), bool(r["is_remote"]),
            bool(r["is_error_frame"]), bool(r["is_fd"]), bool(r["bitrate_switch"]),
            bool(r["error_state_indicator"]), r["dlc"], r["data"], r["channel"],
            bool(r["is_rx"]), r["t_bus_ns"],
        )  # fmt: skip
        f = _fields(m)
        assert got == (*f[1:10], f[10], f[11], round(m.timestamp * 1e9)), (log.name, i)
    return len(want)


@pytest.mark.parametrize("name", [p.name for p in REAL])
def test_import_of_real_logs_keeps_every_frame_as_python_can_reads_it(
    tmp_path: Path, name: str
) -> None:
    log = DATA / name
    out = tmp_path / "run.mcap"
    assert _import(log, out) == 0
    assert _same_as_python_can(out, log) > 0
    # the same frames through candump (python-can's writer) and the numpy parser
    dump = _candump_of(log, tmp_path / "same.log")
    out2 = tmp_path / "run2.mcap"
    assert _import(dump, out2) == 0
    _same_as_python_can(out2, dump)


def _sample_lines(counter: int, counts: list[int], t: float, frames: range) -> list[str]:
    """candump lines of one sample of the shipped DBC, by hand: two int24 counts, 0, counter."""
    out = []
    for j in frames:
        a, b = counts[2 * j], counts[2 * j + 1]
        data = (a & 0xFFFFFF).to_bytes(3, "little") + (b & 0xFFFFFF).to_bytes(3, "little")
        data += bytes([0, counter & 0xFF])
        out.append(f"({t + j * 1e-4:.6f}) can0 {0x181 + 0x100 * j:03X}#{data.hex().upper()}")
    return out


def test_import_drops_partial_samples_at_the_cut_ends_and_ignores_extended_ids(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = _sample_lines(0, [7] * 8, 1_700_000_000.0, range(2, 4))  # cut: frames 3, 4 only
    for c in range(1, 6):
        lines += _sample_lines(c, [c * 100 + k for k in range(8)], 1_700_000_000.0 + c * 0.01,
                               range(4))  # fmt: skip
        # an extended frame whose id equals the first load-cell id: not a load-cell frame
        lines.append(
            f"({1_700_000_000.0 + c * 0.01 + 5e-4:.6f}) can0 00000181#FFFFFFFFFFFF00{c:02X}"
        )
    lines += _sample_lines(6, [9] * 8, 1_700_000_000.06, range(0, 1))  # cut after frame 1
    log = tmp_path / "cut.log"
    log.write_text("\n".join(lines) + "\n")
    out = tmp_path / "cut.mcap"
    assert _import(log, out) == 0
    printed = capsys.readouterr().out
    assert "dropped 2 partial sample(s)" in printed
    with open_run(out) as run:
        ten = run.table("/tensions")
        raw = run.table("/can_raw")
    assert len(raw) == len(lines)  # every frame kept
    assert ten["counter"].tolist() == [1, 2, 3, 4, 5]
    counts = [c for c in ten.columns if c.startswith("raw_")]  # channel order of the rig's cables
    assert len(counts) == 8
    assert ten[counts[0]].tolist() == [100, 200, 300, 400, 500]
    assert ten[counts[7]].tolist() == [107, 207, 307, 407, 507]
    assert (ten["status"] == 0).all()


def test_import_of_a_malformed_log_names_the_line_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = HAND.splitlines()[:2] + ["(1700000000.1) can0 181#01020304050607080"]
    log = tmp_path / "m.log"
    log.write_text("\n".join(lines) + "\n")
    out = tmp_path / "m.mcap"
    assert main(["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG),
                 "--out", str(out)]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "m.log: line 3: bad data" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.log"]


def test_imported_samples_equal_the_frame_by_frame_rules(tmp_path: Path) -> None:
    """The import's decoding (whole blocks with numpy) against the separately written
    frame-by-frame reference of the rules (``tests/_can_reference.py``) on the frames python-can
    reads from the same log: counter wraps, lost samples (a gap), a sample missing a frame in the
    middle, status bits: every /tensions field equal."""
    from _can_reference import Frame, Reference
    from mcap.reader import make_reader

    from cdpr.pipelines.config import load_rig

    lines: list[str] = []
    for c in range(700):
        if 300 <= c < 310:  # ten lost samples
            continue
        counts = [(c * 37 + k * 1001) % (1 << 23) - (1 << 22) for k in range(8)]
        frames = range(3) if c == 500 else range(4)  # sample 500 misses its last frame
        new = _sample_lines(c, counts, 1_700_000_000.0 + c * 0.001, frames)
        if c % 50 == 7:  # status byte: bits of a channel (saturated, slack)
            new[1] = new[1][:-4] + "03" + new[1][-2:]
        lines += new
    log = tmp_path / "blocks.log"
    log.write_text("\n".join(lines) + "\n")
    out = tmp_path / "blocks.mcap"
    assert _import(log, out) == 0

    ref = Reference([0.0] * 8, [5e-5] * 8)  # the import's default calibration
    for m in _python_can(log):
        t = round(m.timestamp * 1e9)
        ref.feed(Frame(t, t, m.arbitration_id, bytes(m.data), m.is_extended_id))
    ref.flush()
    want = ref.samples[:-1] if ref.samples[-1]["status"] & 16 else ref.samples  # cut at the end

    with out.open("rb") as fh:
        rows = samples(make_reader(fh), "/tensions")
    cables = list(load_rig(RIG).cable_names)
    assert len(rows) == len(want) == 690
    for r, w in zip(rows, want, strict=True):
        assert r["t_ns"] == w["t_ns"] and r["status"] == w["status"]
        assert [r[f"raw_{c}_counts"] for c in cables] == w["raw"]
        assert [r[f"status_{c}"] for c in cables] == w["ch_status"]
        assert (r["counter"], r["seq"], r["t_bus_ns"]) == (w["counter"], w["seq"], w["t_bus_ns"])
        got_T = [np.nan if r[f"T_{c}_N"] is None else r[f"T_{c}_N"] for c in cables]
        assert np.array_equal(got_T, w["T"], equal_nan=True)
    with open_run(out) as run:
        ten = run.table("/tensions")
    assert ten["status"].astype(bool).sum() > 10  # status bits and the gap sample are there


def test_a_real_log_damaged_midway_is_an_error_naming_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A frame line of a real TRC log damaged (python-can's reader raises there): one error line
    naming the file and the line, exit 2, no output (never a silent stop with the frames read so
    far)."""
    src = (DATA / "test_CanMessage_V2_1.trc").read_text().splitlines()
    body = [k for k, line in enumerate(src) if line.strip() and not line.lstrip().startswith(";")]
    src[body[3]] = "     4      17.000 DT 1 0FF Rx - 8 zz zz"
    log = tmp_path / "bad.trc"
    log.write_text("\n".join(src) + "\n")
    with pytest.raises(ValueError):
        list(can.LogReader(str(log)))
    assert _import(log, tmp_path / "bad.mcap") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"bad.trc: line {body[3] + 1}: bad data" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.trc"]


def test_a_log_python_can_reads_for_us_damaged_midway_names_the_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A format read through python-can (its SQLite log, ``.db``) with a row its reader cannot
    make a frame of: the frame named, exit 2, no output."""
    import sqlite3

    log = tmp_path / "bad.db"
    with can.SqliteWriter(str(log)) as w:
        for m in _python_can(DATA / "test_CanMessage_V2_1.trc"):
            w.on_message_received(m)
    with sqlite3.connect(log) as db:  # the fourth frame's data: text, not bytes
        db.execute("UPDATE messages SET data = 'zz' WHERE rowid = 4")
    good = 0
    with pytest.raises(Exception):  # noqa: B017 - whatever python-can's reader raises
        for _ in can.LogReader(str(log)):
            good += 1
    assert _import(log, tmp_path / "bad.mcap") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"bad.db: frame {good + 1}: python-can cannot read it" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.db"]


# --- Vector ASC: the numpy parser (read_asc) against python-can's ASCReader ----------------------

ASC_HEAD = """date Wed Nov 25 15:06:13.191 2026
base {base}  timestamps {ts}
internal events logged
// version 9.0.0
Begin Triggerblock Wed Nov 25 15:06:13.191 2026
   0.000000 Start of measurement
"""


def _asc_lines(rng: np.random.Generator, n: int, base: int) -> list[str]:
    """``n`` random ASC body lines of every kind python-can reads, written here by hand from the
    Vector layout (not by python-can's writer): classic data frames (standard/extended ids, Rx/Tx,
    DLC 0-15, Vector's ``Length = ...`` attributes), remote frames with and without a DLC, error
    frames, CAN FD frames (symbolic names, BRS/ESI, 0-64 bytes, FD remote), events, comments."""

    def num(v: int, width: int = 0) -> str:
        return f"{v:0{width}X}" if base == 16 else str(v)

    out = []
    t = 0.0
    for _ in range(n):
        t += float(rng.integers(1, 2000)) * 1e-6
        ts = f"{t:{int(rng.integers(9, 13))}.{int(rng.choice([4, 6, 9]))}f}"
        ch = int(rng.integers(1, 5))
        ext = bool(rng.integers(0, 2))
        fid = int(rng.integers(0, 1 << 29 if ext else 1 << 11))
        sid = num(fid) + ("x" if ext else "")
        d = "Rx" if rng.integers(0, 2) else "Tx"
        kind = int(rng.choice(8, p=[0.55, 0.08, 0.05, 0.05, 0.15, 0.04, 0.04, 0.04]))
        if kind == 0:  # classic data frame
            dlc = int(rng.integers(0, 16))
            data = " ".join(num(int(b), 2) for b in rng.integers(0, 256, min(dlc, 8)))
            tail = "  Length = 244016 BitCount = 125 ID = 384" if rng.integers(0, 2) else ""
            sep = "\t" if rng.integers(0, 8) == 0 else " "
            out.append(f"{ts} {ch}  {sid:<15}{sep}{d}   d {num(dlc)} {data}{tail}".rstrip())
        elif kind == 1:  # remote
            tail = [" r", f" r {int(rng.integers(0, 9))}", " r Length = 1704000 BitCount = 145"]
            out.append(f"{ts} {ch} {sid} {d}" + tail[int(rng.integers(0, 3))])
        elif kind == 2:  # error frames
            out.append(
                [f"{ts} {ch} ErrorFrame", f"{ts} {ch} ErrorFrame ECC: 10100010",
                 f"{ts} CANFD {ch:>3} {d} ErrorFrame Not Acknowledge error, dominant error flag"
                 " fffe c7 31ca Arb. 556 44 0 0 f 64 00 00"][int(rng.integers(0, 3))]
            )  # fmt: skip
        elif kind == 3:  # events and comments, skipped
            out.append(
                [f"{ts} {ch}  Statistic: D 0 R 0 XD 0 XR 0 E 0 O 0 B 0.00%",
                 f"{ts} CAN {ch} Status:chip status error active", "// a comment",
                 f"{ts} {ch}  J1939TP FEE3p 6 0 0 - Rx d 23 A0 0F"][int(rng.integers(0, 4))]
            )  # fmt: skip
        else:  # CAN FD
            lens = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]
            dlc = int(rng.integers(0, 16))
            length = 0 if rng.integers(0, 6) == 0 else lens[dlc]  # 0: an FD remote frame
            data = " ".join(num(int(b), 2) for b in rng.integers(0, 256, length))
            name = f"Name_{int(rng.integers(0, 9))}" if rng.integers(0, 2) else ""
            brs, esi = int(rng.integers(0, 2)), int(rng.integers(0, 2))
            out.append(
                f"{ts} CANFD {ch:>3} {d} {sid:>8} {name:>20} {brs} {esi} {num(dlc).lower()} {length:>2}"
                f" {data} 140000 73 200050 7a60 46500250 460a0250 20011736 20010205".replace(
                    "  ", " "
                )
            )
    return out


def _write_asc(path: Path, lines: list[str], base: str = "hex", ts: str = "absolute") -> Path:
    path.write_text(ASC_HEAD.format(base=base, ts=ts) + "\n".join(lines) + "\nEnd TriggerBlock\n")
    return path


def _read_asc_fields(path: Path, block_bytes: int = 8 << 20) -> list[tuple]:
    return [_fields(m) for c in read_asc(path, block_bytes=block_bytes) for m in c.messages()]


@pytest.mark.parametrize("name", [p.name for p in REAL if p.suffix == ".asc"])
def test_asc_parser_matches_python_can_on_real_logs(name: str) -> None:
    want = [_fields(m) for m in _python_can(DATA / name)]
    assert want
    for block in (40, 8 << 20):  # small blocks: lines cut across block boundaries
        assert _read_asc_fields(DATA / name, block) == want


@pytest.mark.parametrize(("base", "ts"), [("hex", "absolute"), ("dec", "relative")])
def test_asc_parser_matches_python_can_on_generated_logs(
    tmp_path: Path, base: str, ts: str
) -> None:
    rng = np.random.default_rng(7 if base == "hex" else 8)
    log = _write_asc(tmp_path / f"gen_{base}.asc", _asc_lines(rng, 3000, 16 if base == "hex" else 10),
                     base, ts)  # fmt: skip
    want = [_fields(m) for m in _python_can(log)]
    assert len(want) > 2500
    kinds = {(f[2], f[3], f[4], f[5]) for f in want}  # extended, remote, error, FD
    assert len(kinds) >= 7
    assert _read_asc_fields(log, 4096) == want
    assert _read_asc_fields(log) == want


BAD_ASC = [
    ("   1.000100 1  181 Rx d 8 01 02 03 04 05 06 07", "fewer data bytes than the DLC says"),
    ("   1.000100 1  181 Rx d 8 01 02 03 04 05 06 07 08 09", "unexpected text after the data"),
    ("   1.000100 1  1G1 Rx d 2 01 02", "bad CAN id"),
    ("   1.000100 1  800 Rx d 2 01 02", "CAN id out of range"),
    ("   1.000100 1  181 Rx d 2 01 0G2", "bad data byte 2"),
    ("   1.000100 1  181 Rx d 2 01 102", "bad data byte 2"),
    ("   1.000100 1  181 Rx d G 01 02", "bad DLC"),
    ("   1.0001.00 1  181 Rx d 2 01 02", "bad timestamp"),
    ("   1.000100 1  181 rx d 2 01 02", "not an ASC frame, event or comment line"),
    ("   1.000100 A  181 Rx d 2 01 02", "not an ASC frame, event or comment line"),
    ("   1.000100 Start of measurment", "not an ASC frame, event or comment line"),
    ("garbage", "not an ASC frame, event or comment line"),
    ("   9300000000.000100 1  181 Rx d 2 01 02", "timestamp out of range"),
    ("   9300000000.000100 1 ErrorFrame", "timestamp out of range"),
    ("   1.000100 CANFD 1 Rx 181 1 0 9 8 01 02 03 04 05 06 07 08", "DLC and data length disagree"),
    ("   1.000100 CANFD 1 Rx 181 1 0 2 2 01", "bad CAN FD data bytes"),
]


@pytest.mark.parametrize(("line", "problem"), BAD_ASC)
def test_a_bad_asc_line_is_named_by_file_and_line(tmp_path: Path, line: str, problem: str) -> None:
    """python-can skips a line it does not recognise (or reads a short frame as it is): the
    parser names the file and the line instead."""
    good = _asc_lines(np.random.default_rng(1), 40, 16)
    log = _write_asc(tmp_path / "bad.asc", [*good[:20], line, *good[20:]])
    with pytest.raises(ConfigError) as exc:
        list(read_asc(log))
    assert str(exc.value).startswith(f"{log}: line 27: ")  # 6 header lines, 20 good ones
    assert problem in str(exc.value)


def test_import_of_a_malformed_asc_names_the_line_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = (DATA / "issue_1299.asc").read_bytes().splitlines(keepends=True)
    src[7] = src[7].replace(b"221 ", b"2\xe91 ")  # not UTF-8
    log = tmp_path / "m.asc"
    log.write_bytes(b"".join(src))
    out = tmp_path / "m.mcap"
    assert _import(log, out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "m.asc: line 8: not UTF-8 text" in err[0]
    src[7] = b"  13.258433 1  221             Tx   d 8 C2 4A 05 81 00 00 15\n"
    log.write_bytes(b"".join(src))
    assert _import(log, out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "m.asc: line 8: fewer data bytes than the DLC says" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.asc"]


def test_import_of_a_generated_asc_keeps_every_frame_as_python_can_reads_it(
    tmp_path: Path,
) -> None:
    log = _write_asc(tmp_path / "gen.asc", _asc_lines(np.random.default_rng(3), 500, 16))
    assert _import(log, tmp_path / "gen.mcap") == 0
    assert _same_as_python_can(tmp_path / "gen.mcap", log) > 400


def test_a_classic_asc_frame_of_64_bytes_is_read_as_python_can_reads_it_and_flagged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """python-can's real ``single_frame.asc``: a classic frame line ``d 40`` with 64 bytes (no
    classic bus carries it).  python-can reads it (dlc 64, the first 8 bytes); so does the import,
    which flags that frame bad (status 8) and says so, instead of refusing the file."""
    log = DATA / "single_frame.asc"
    out = tmp_path / "run.mcap"
    assert _import(log, out) == 0
    assert "1 frame(s) no classic CAN bus carries" in capsys.readouterr().out
    assert _same_as_python_can(out, log) == 1
    with open_run(out) as run:
        raw = run.table("/can_raw")
    assert raw["status"].tolist() == [8] and raw["dlc"].tolist() == [64]
    assert raw["data"].iloc[0] == bytes(range(8))
    # a normal frame of the same log layout is not flagged
    normal = DATA / "single_frame_us_locale.asc"
    assert _import(normal, tmp_path / "n.mcap") == 0
    with open_run(tmp_path / "n.mcap") as run:
        assert run.table("/can_raw")["status"].tolist() == [0]


@pytest.mark.parametrize("base", [16, 10])
def test_asc_classic_frames_with_a_long_dlc_match_python_can(tmp_path: Path, base: int) -> None:
    """Classic frame lines with DLC 9..15 (8 bytes on the bus) and past 15, carrying from 8 up to
    their DLC's length in bytes (as Vector's ``d 40`` line): the fields equal python-can's, and a
    frame is flagged ODD exactly when its DLC is past 15 or it carries more than 8 bytes."""
    from cdpr.daq.can_frames import ODD

    rng = np.random.default_rng(5)
    lens = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]
    lines, want_odd = [], []
    for i in range(300):
        dlc = int(rng.integers(9, 16) if i % 2 else rng.integers(9, 100 if base == 10 else 256))
        full = lens[dlc] if dlc <= 15 else 64
        nb = 8 if i % 4 == 1 else int(rng.integers(8, full + 1))  # a quarter: 8 bytes, DLC 9..15
        data = " ".join(f"{b:02X}" if base == 16 else str(b) for b in rng.integers(0, 256, nb))
        d = f"{dlc:X}" if base == 16 else str(dlc)
        tail = "  Length = 0 BitCount = 0" if i % 3 == 0 else ""
        lines.append(f"{0.001 * (i + 1):11.6f} 1  181             Rx   d {d} {data}{tail}")
        want_odd.append(dlc > 15 or nb > 8)
    log = _write_asc(tmp_path / "long.asc", lines, "hex" if base == 16 else "dec")
    want = [_fields(m) for m in _python_can(log)]
    assert len(want) == 300
    cols = list(read_asc(log, block_bytes=2048))
    assert [_fields(m) for c in cols for m in c.messages()] == want
    got_odd = np.concatenate([(c.flags & ODD) != 0 for c in cols])
    assert got_odd.tolist() == want_odd and 0 < sum(want_odd) < 300
