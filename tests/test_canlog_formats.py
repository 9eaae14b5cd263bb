"""The numpy readers of Vector BLF, PEAK TRC (1.0 to 2.1) and python-can's CSV against python-can's
own ``LogReader`` on the same files, every field of every frame: logs written by python-can's
writers and by hand from the formats' layouts (every kind of frame, objects straddling BLF
containers, ``LOBJ`` inside a payload, CRLF lines, right-aligned fields), in small blocks; and a bad
line or a cut file named in one ConfigError (python-can skips or stops silently)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import can
import numpy as np
import pytest
from test_storage_canlog import DATA, _fields, _python_can

from cdpr.analysis.errors import ConfigError
from cdpr.daq.canlog import read_log
from cdpr.daq.canlog_blf import read_blf
from cdpr.daq.canlog_csv import read_csv
from cdpr.daq.canlog_trc import read_trc


def _ours(reader, path: Path, **kw) -> list[tuple]:  # noqa: ANN001
    return [_fields(m) for c in reader(path, **kw) for m in c.messages()]


def _random_messages(rng: np.random.Generator, n: int, fd: bool = True) -> list[can.Message]:
    """Frames of every kind a bus gives: standard and extended ids, remote, error, CAN FD with
    BRS/ESI and up to 64 bytes, transmitted ones, several channels, a payload holding b"LOBJ"."""
    out = []
    t = 1_700_000_000.0
    lens = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]
    for i in range(n):
        t += float(rng.integers(1, 3000)) * 1e-6
        ext = bool(rng.integers(0, 2))
        fid = int(rng.integers(0, 1 << 29 if ext else 1 << 11))
        kind = int(rng.choice(5, p=[0.6, 0.1, 0.05, 0.2 if fd else 0.0, 0.05 if fd else 0.25]))
        kw = dict(timestamp=t, arbitration_id=fid, is_extended_id=ext,
                  is_rx=bool(rng.integers(0, 4)), channel=int(rng.integers(0, 3)))  # fmt: skip
        if kind == 0:
            data = rng.integers(0, 256, int(rng.integers(0, 9))).astype(np.uint8).tobytes()
            if i % 97 == 3:
                data = b"LOBJ" + data[4:8].ljust(4, b"\0")  # a signature inside a payload
            out.append(can.Message(data=data, **kw))
        elif kind == 1:
            out.append(can.Message(is_remote_frame=True, dlc=int(rng.integers(0, 9)), **kw))
        elif kind == 2:
            out.append(can.Message(is_error_frame=True, timestamp=t, channel=kw["channel"]))
        elif kind == 3:
            k = lens[int(rng.integers(0, 16))]
            data = rng.integers(0, 256, k).astype(np.uint8).tobytes()
            out.append(can.Message(is_fd=True, bitrate_switch=bool(rng.integers(0, 2)),
                                   error_state_indicator=bool(rng.integers(0, 2)), data=data,
                                   **kw))  # fmt: skip
        else:
            out.append(can.Message(data=bytes(8), **kw))
    return out


# --- BLF ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("container", [120, 4096, 128 * 1024])
def test_blf_reader_matches_python_can(tmp_path: Path, container: int) -> None:
    """python-can's BLFWriter with small containers (objects cut across them), every frame kind."""
    path = tmp_path / "gen.blf"
    w = can.BLFWriter(str(path))
    w.max_container_size = container
    for m in _random_messages(np.random.default_rng(container), 3000):
        w.on_message_received(m)
    w.stop()
    want = [_fields(m) for m in _python_can(path)]
    assert len(want) == 3000
    assert _ours(read_blf, path, block_bytes=1000) == want
    assert _ours(read_blf, path) == want


@pytest.mark.parametrize("name", [p.name for p in sorted(DATA.glob("*.blf"))])
def test_blf_reader_on_real_logs(name: str) -> None:
    want = [_fields(m) for m in _python_can(DATA / name)]
    assert want and _ours(read_blf, DATA / name) == want


def test_a_cut_or_damaged_blf_is_named(tmp_path: Path) -> None:
    src = tmp_path / "gen.blf"
    w = can.BLFWriter(str(src))
    w.max_container_size = 2048
    for m in _random_messages(np.random.default_rng(1), 500, fd=False):
        w.on_message_received(m)
    w.stop()
    raw = src.read_bytes()
    cut = tmp_path / "cut.blf"
    cut.write_bytes(raw[: len(raw) * 2 // 3])  # a logger killed mid-write
    with pytest.raises(ConfigError, match=r"cut\.blf: byte \d+: the file ends inside an object"):
        list(read_blf(cut))
    bad = tmp_path / "bad.blf"
    bad.write_bytes(raw[:144] + b"JUNK" + raw[148:])  # the first object's signature damaged
    with pytest.raises(ConfigError, match=r"bad\.blf: byte 144: not a BLF object"):
        list(read_blf(bad))
    other = tmp_path / "other.blf"
    other.write_bytes(b"not a blf file at all" * 20)
    with pytest.raises(ConfigError, match=r"other\.blf: byte 0: not a BLF file"):
        list(read_log(other))


def test_blf_by_hand_fd64_and_version_2_headers(tmp_path: Path) -> None:
    """Objects python-can's writer does not write, built from the layout by hand: header version
    2, CAN_FD_MESSAGE_64 with fewer stored bytes than valid (python-can issue 1905: zero padded),
    CAN_MESSAGE2, 1 ns and 10 us time units, a container stored uncompressed."""
    objs = []

    def obj(kind: int, body: bytes, ts: int, version: int = 1, unit: int = 2) -> bytes:
        if version == 1:
            head = struct.pack("<LHHQ", unit, 0, 0, ts)
        else:
            head = struct.pack("<LBxHQ8x", unit, 0, 0, ts)
        size = 16 + len(head) + len(body)
        return struct.pack("<4sHHLL", b"LOBJ", 16 + len(head), version, size, kind) + head + body

    for i in range(40):
        data = bytes(range(i, i + 8))
        objs.append(obj(86, struct.pack("<HBBL8s", 2, 0, 8, 0x100 + i, data), 1000 * i, 2, 2))
        body = struct.pack("<BBBBLLLLLLLHBBL", 1, 13, 32, 0, 0x80000123, 0, 0x3000, 0, 0, 0, 0,
                           0, 0, 0, 0) + bytes(range(20))  # 20 of 32 bytes stored  # fmt: skip
        objs.append(obj(101, body, 7 * i, 1, 1))
        objs.append(obj(73, struct.pack("<HHLBBBxLLH2x8s", 1, 0, 0, 0, 0, 4, 0, 0x5, 0, bytes(8)),
                        1500 * i))  # fmt: skip
    inner = b"".join(o + b"\0" * (len(o) % 4) for o in objs)
    half = len(inner) // 2
    conts = []
    for k, part in enumerate((inner[:half], inner[half:])):
        stored = zlib.compress(part) if k == 0 else part
        body = struct.pack("<H6xL4x", 2 if k == 0 else 0, len(part)) + stored
        size = 16 + len(body)  # a container has the base header only
        c = struct.pack("<4sHHLL", b"LOBJ", 16, 1, size, 10) + body
        conts.append(c + b"\0" * (size % 4))
    start = (2026, 11, 0, 28, 8, 0, 0, 0)
    header = struct.pack("<4sLBBBBBBBBQQLL8H8H", b"LOGG", 144, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
                         len(objs), 0, *start, *start).ljust(144, b"\0")  # fmt: skip
    path = tmp_path / "hand.blf"
    path.write_bytes(header + b"".join(conts))
    want = [_fields(m) for m in _python_can(path)]
    assert len(want) == 120 and any(f[5] for f in want)  # FD frames among them
    assert _ours(read_blf, path, block_bytes=512) == want


# --- TRC ------------------------------------------------------------------------------------------

TRC_HEAD = {
    "1.0": ";##########\n;   Start time: 18.12.2021 14:28:07.062.0\n;##########\n",
    "1.1": ";$FILEVERSION=1.1\n;$STARTTIME=44548.6028595139\n;\n;   Message Number\n",
    "1.3": ";$FILEVERSION=1.3\n;$STARTTIME=44548.6028595139\n;\n",
    "2.0": ";$FILEVERSION=2.0\n;$STARTTIME=44548.6028595139\n;$COLUMNS=N,O,T,I,d,l,D\n;\n",
    "2.1": ";$FILEVERSION=2.1\n;$STARTTIME=44548.6028595139\n;$COLUMNS=N,O,T,B,I,d,R,L,D\n;\n",
}


def _trc_lines(rng: np.random.Generator, version: str, n: int) -> list[str]:
    """``n`` body lines of a TRC version written by hand from PEAK's layouts (right-aligned
    numbers, RTR, status lines python-can skips, FD types in 2.x)."""
    out = []
    t = 0.0
    for i in range(1, n + 1):
        t += float(rng.integers(1, 5000)) / 10
        ext = bool(rng.integers(0, 2))
        fid = f"{int(rng.integers(0, 1 << 29 if ext else 1 << 11)):0{8 if ext else 4}X}"
        d = "Rx" if rng.integers(0, 2) else "Tx"
        r = rng.random()
        if version in ("1.0", "1.1", "1.3"):
            dlc = int(rng.integers(0, 9))
            data = " ".join(f"{b:02X}" for b in rng.integers(0, 256, dlc))
            if r < 0.05:
                data = "RTR"
            tt = f"{t:11.1f}" if version != "1.0" else f"{int(t):9d}"
            if version == "1.0":
                line = f"{i:6d}) {tt}  {fid:>8}  {dlc}  {data}"
                if r > 0.97:
                    line = f"{i:6d}) {tt}  FFFFFFFF  4  00 00 00 08 -- -- -- -- BUSHEAVY"
            elif version == "1.1":
                line = f"{i:6d}) {tt}  {d:<5}  {fid:>8}  {dlc}  {data}"
                if r > 0.97:
                    line = f"{i:6d}) {tt}  Warng  FFFFFFFF  4  00 00 00 08  BUSHEAVY"
            else:
                line = f"{i:6d}) {tt} {int(rng.integers(1, 4))}  {d:<5} {fid:>8} -  {dlc}    {data}"
                if r > 0.97:
                    line = f"{i:6d}) {tt} 1  Warng FFFFFFFF -  4    00 00 00 08 BUSHEAVY"
        else:
            kinds = ["DT", "DT", "DT", "RR", "FD", "FB", "FE", "BI", "ST"]
            kind = kinds[int(rng.integers(0, len(kinds)))]
            lens = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]
            length = lens[int(rng.integers(0, 16 if kind in ("FD", "FB", "FE", "BI") else 9))]
            data = " ".join(f"{b:02X}" for b in rng.integers(0, 256, length))
            if kind == "RR":
                data = ""
            if version == "2.0":
                line = f"{i:7d} {t:13.3f} {kind} {fid:>8} {d} {length:<2} {data}"
            else:
                dlc = [k for k, x in enumerate(lens) if x >= length][0]
                line = (f"{i:7d} {t:13.3f} {kind} {int(rng.integers(1, 4)):>2} {fid:>8} {d} -  "
                        f"{dlc:<4} {data}")  # fmt: skip
        out.append(line.rstrip())
    return out


@pytest.mark.parametrize("version", ["1.0", "1.1", "1.3", "2.0", "2.1"])
def test_trc_reader_matches_python_can(tmp_path: Path, version: str) -> None:
    rng = np.random.default_rng(int(float(version) * 10))
    path = tmp_path / f"v{version}.trc"
    lines = _trc_lines(rng, version, 2000)
    path.write_bytes((TRC_HEAD[version] + "\r\n".join(lines) + "\r\n").encode())  # CRLF: PEAK
    want = [_fields(m) for m in _python_can(path)]
    assert len(want) > 1700  # status lines skipped
    assert _ours(read_trc, path, block_bytes=3000) == want
    assert _ours(read_trc, path) == want


def test_trc_written_by_python_can_and_real_logs_match(tmp_path: Path) -> None:
    path = tmp_path / "py.trc"
    with can.TRCWriter(str(path)) as w:
        for m in _random_messages(np.random.default_rng(3), 1500, fd=False):
            if not (m.is_error_frame or m.is_remote_frame):  # the writer refuses them
                w.on_message_received(m)
    for p in [path, *sorted(DATA.glob("*.trc"))]:
        want = [_fields(m) for m in _python_can(p)]
        assert want and _ours(read_trc, p) == want, p.name


@pytest.mark.parametrize(
    ("line", "problem"),
    [
        ("     12     48937.600 DT 1      07G4 Rx -  1    00", "bad CAN id"),
        ("     12     48937.6x0 DT 1      0704 Rx -  1    00", "bad time offset"),
        ("     12     48937.600 DT 1      0704 Rx -  1    0", "pairs of hex digits"),
        ("     12     48937.600 DT", "fewer fields"),
    ],
)
def test_a_bad_trc_line_is_named(tmp_path: Path, line: str, problem: str) -> None:
    src = (DATA / "test_CanMessage_V2_1.trc").read_text().splitlines()
    head = sum(1 for x in src if x.startswith(";"))
    body = [x for x in src if not x.startswith(";")]
    path = tmp_path / "bad.trc"
    path.write_text("\n".join(src[:head] + body[:5] + [line] + body[5:]) + "\n")
    with pytest.raises(ConfigError, match=rf"bad\.trc: line {head + 6}: .*{problem}"):
        list(read_trc(path))


# --- python-can's CSV -----------------------------------------------------------------------------


def test_csv_reader_matches_python_can(tmp_path: Path) -> None:
    """python-can's CSVWriter: timestamps as repr() writes them (up to 17 digits, exponents for
    small ones), hex ids, flags, base64 data of every length; remote and error frames."""
    msgs = _random_messages(np.random.default_rng(9), 3000, fd=False)
    for k, m in enumerate(msgs[:50]):
        m.timestamp = k * 1e-6  # relative times: '1e-06'
    path = tmp_path / "gen.csv"
    with can.CSVWriter(str(path)) as w:
        for m in msgs:
            w.on_message_received(m)
    want = [_fields(m) for m in _python_can(path)]
    assert len(want) == 3000
    assert _ours(read_csv, path, block_bytes=5000) == want
    assert _ours(read_csv, path) == want


@pytest.mark.parametrize(
    ("line", "problem"),
    [
        ("1700000000.5,0x181,0,0,0,8", "expected 7 comma-separated fields"),
        ("1700000000.5,0x18G,0,0,0,8,AAAAAAAAAAA=", "bad arbitration id"),
        ("1700000000.5,0x181,0,0,0,8,AAAAAAAAAA=", "not a multiple of 4"),
        ("1700000000.5,0x181,0,0,0,8,AAAA*AAAAAA=", "not base64"),
        ("17000x0000.5,0x181,0,0,0,8,AAAAAAAAAAA=", "bad timestamp"),
    ],
)
def test_a_bad_csv_line_is_named(tmp_path: Path, line: str, problem: str) -> None:
    path = tmp_path / "bad.csv"
    good = "1700000000.25,0x181,0,0,0,8,AAECAwQFBgc="
    path.write_text("timestamp,arbitration_id,extended,remote,error,dlc,data\n"
                    + "\n".join([good, good, line, good]) + "\n")  # fmt: skip
    with pytest.raises(ConfigError, match=rf"bad\.csv: line 4: .*{problem}"):
        list(read_csv(path))
