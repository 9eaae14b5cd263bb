"""The candump parser's fixed-width fast path (``_parse_fixed``: every line of a block of one
length and one layout, a load-cell log): on logs written here by a small generator of its own it
is taken, and its columns equal python-can's ``LogReader`` frame by frame and the general parser
(``_parse_general``) column by column; a block with any other line, or whose size is a multiple of
the first line's length by coincidence, goes to the general parser (same frames, same errors)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_storage_canlog import _fields, _python_can

from cdpr.analysis.errors import ConfigError
from cdpr.daq import canlog_candump as candump
from cdpr.daq.can_frames import FrameColumns
from cdpr.daq.canlog_candump import read_candump

COLUMNS = ("t_s", "arbitration_id", "flags", "dlc", "data", "length", "channel", "line")


def _lines(
    n: int,
    *,
    seed: int = 0,
    t0: int = 1_700_000_000,
    step_us: int = 250,
    us0: int = 0,
    frac: int = 6,
    id_len: int = 3,
    nbytes: int = 8,
    channel: str = "can0",
    direction: str = "",
    lower: bool = False,
) -> list[str]:
    """``n`` candump -L lines of one layout: ``(<t0 + i * step>.<frac digits>) <channel>
    <id>#<data><direction>`` with random ids (of ``id_len`` hex digits, no error-frame ids) and
    data bytes."""
    rng = np.random.default_rng(seed)
    id_max = min(16**id_len, 0x20000000)  # no error flag
    lines = []
    for i in range(n):
        us = us0 + i * step_us + int(rng.integers(0, step_us))
        sec, sub_us = t0 + us // 1_000_000, us % 1_000_000
        sub = f"{sub_us:06d}{int(rng.integers(0, 1000)):03d}"[:frac].ljust(frac, "0")
        cid = f"{int(rng.integers(0, id_max)):0{id_len}X}"
        data = bytes(rng.integers(0, 256, nbytes, dtype=np.uint8).tolist()).hex().upper()
        if lower:
            cid, data = cid.lower(), data.lower()
        lines.append(f"({sec}.{sub}) {channel} {cid}#{data}{direction}")
    return lines


def _write(path: Path, lines: list[str], eol: str = "\n") -> Path:
    path.write_bytes("".join(line + eol for line in lines).encode("ascii"))
    return path


def _block(path: Path) -> np.ndarray:
    return np.frombuffer(path.read_bytes(), np.uint8)


def _assert_same(got: FrameColumns, want: FrameColumns) -> None:
    """Every column the same: dtype, shape, values (channel: values and their types)."""
    for k in COLUMNS:
        g, w = getattr(got, k), getattr(want, k)
        assert g.dtype == w.dtype and g.shape == w.shape, k
        assert np.array_equal(g, w), k
    assert [type(c) for c in got.channel] == [type(c) for c in want.channel]


def _frames(path: Path, block_bytes: int = 8 << 20) -> list[tuple]:
    return [_fields(m) for c in read_candump(path, block_bytes=block_bytes) for m in c.messages()]


LAYOUTS: dict[str, dict[str, Any]] = {
    "load-cell log": {},
    "29-bit ids, R": {"id_len": 8, "direction": " R"},
    "T, 3 bytes": {"direction": " T", "nbytes": 3},
    "dlc 0, r": {"nbytes": 0, "direction": " r"},
    "int channel": {"channel": "0", "nbytes": 5},
    "lower-case hex, t": {"lower": True, "direction": " t", "id_len": 8},
    "1-digit ids, ns": {"id_len": 1, "frac": 9},
    "short timestamps": {"t0": 12_345, "frac": 3},
    "relative times": {"t0": 0, "frac": 6},
    "15 digits": {"t0": 1_700_000_000, "frac": 5},
    "crossing 2**31 s": {"t0": 2**31 - 1, "us0": 999_000, "step_us": 1},
    "crossing 2**30 s, ns": {"t0": 2**30 - 1, "us0": 999_000, "step_us": 1, "frac": 9},
}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_fixed_width_logs_equal_python_can_and_the_general_parser(
    tmp_path: Path, layout: str
) -> None:
    n = 3000
    log = _write(tmp_path / "f.log", _lines(n, **LAYOUTS[layout]))
    buf = _block(log)
    fast = candump._parse_fixed(buf, str(log), 1)
    assert fast is not None and len(fast) == n  # the fast path is taken
    _assert_same(fast, candump._parse_general(buf, str(log), 1))
    want = [_fields(m) for m in _python_can(log)]
    assert [_fields(m) for m in fast.messages()] == want
    assert _frames(log) == want
    if "crossing" in layout:  # the timestamps cross a power of two within the block
        assert len(np.unique(np.frexp(fast.t_s)[1])) == 2


def test_timestamps_convert_as_float_does() -> None:
    """Random timestamp texts of 1-12 integer and 1-15 fraction digits (one digit count per
    block, the integer part below 9e9): wherever the fast path takes the block (always up to 15
    digits in all), its values equal ``float()`` of the texts and the general parser's."""
    rng = np.random.default_rng(7)
    taken = {"short": 0, "long": 0}
    for ni in range(1, 13):
        for k in range(1, 16):
            ipart = rng.integers(0, min(10**ni, 9 * 10**9), 200)
            fpart = rng.integers(0, 10**k, 200)
            texts = [f"{i:0{ni}d}.{f:0{k}d}" for i, f in zip(ipart, fpart, strict=True)]
            buf = np.frombuffer("".join(f"({t}) can0 181#00\n" for t in texts).encode(), np.uint8)
            fast = candump._parse_fixed(buf, "x.log", 1)
            if ni + k <= 15:
                assert fast is not None, (ni, k)
            if fast is not None:
                taken["short" if ni + k <= 15 else "long"] += 1
                assert fast.t_s.tolist() == [float(t) for t in texts], (ni, k)
                _assert_same(fast, candump._parse_general(buf, "x.log", 1))
    assert taken["short"] > 100 and taken["long"] > 15, taken


def _variants(lines: list[str], j: int) -> dict[str, list[str]]:
    """``lines`` with line ``j`` changed in one way each."""
    t, rest = lines[j].split(") ", 1)
    ch, frame = rest.split(" ", 1)
    cid, data = frame.split("#")
    sec, sub = t[1:].split(".")

    def at(new: str) -> list[str]:
        return lines[:j] + [new] + lines[j + 1 :]

    return {
        "longer id": at(f"{t}) {ch} 0{cid}#{data}"),
        "shorter data": at(f"{t}) {ch} {cid}#{data[:-2]}"),
        "fewer timestamp digits": at(f"({sec}.{sub[:-1]}) {ch} {cid}#{data}"),
        "dot moved, same length": at(f"({sec[:-1]}.{sec[-1]}{sub}) {ch} {cid}#{data}"),
        "other channel, same length": at(f"{t}) can9 {cid}#{data}"),
        "direction token": at(f"{lines[j]} T"),
        "error frame": at(f"{t}) {ch} 20000080#{data}"),
        "remote frame": at(f"{t}) {ch} {cid}#R"),
        "leading blank": at(f" {lines[j]}"),
        "blank line": lines[:j] + [""] + lines[j:],
    }


def test_ids_with_the_error_flag(tmp_path: Path) -> None:
    """8-digit ids with bit 0x20000000: without the bus-error bit 0x80 a frame (id masked to 29
    bits: the fast path), with it an error frame (the general parser)."""
    lines = _lines(300, seed=11, id_len=8)
    for j, cid in ((10, "20000001"), (20, "E0000000"), (30, "3FFFFF7F")):
        lines[j] = lines[j].replace(lines[j].split(" ")[2].split("#")[0], cid)
    log = _write(tmp_path / "flag.log", lines)
    buf = _block(log)
    fast = candump._parse_fixed(buf, str(log), 1)
    assert fast is not None
    assert fast.arbitration_id[[10, 20, 30]].tolist() == [0x1, 0x0, 0x1FFFFF7F]
    _assert_same(fast, candump._parse_general(buf, str(log), 1))
    assert [_fields(m) for m in fast.messages()] == [_fields(m) for m in _python_can(log)]
    lines[40] = lines[40].replace(lines[40].split(" ")[2].split("#")[0], "200000C0")
    log = _write(tmp_path / "flag.log", lines)
    assert candump._parse_fixed(_block(log), str(log), 1) is None
    want = [_fields(m) for m in _python_can(log)]
    assert want[40][4] is True  # python-can: an error frame
    assert _frames(log) == want


BAD = {
    "bad hex": ("G", "bad data (not hex)"),
    "bad id": ("id", "bad CAN id (not hex)"),
    "bad timestamp": ("ts", "bad timestamp"),
    "too late": ("late", "timestamp out of range"),
    "control byte": ("ctrl", "control byte 0x01"),
}


def _bad_line(line: str, kind: str) -> str:
    t, rest = line.split(") ", 1)
    if kind == "G":
        return line[:-1] + "G"
    if kind == "id":
        ch, frame = rest.split(" ", 1)
        return f"{t}) {ch} x{frame[1:]}"
    if kind == "ts":
        return line[:5] + "x" + line[6:]
    if kind == "late":
        return "(9300000000" + line[11:]
    return line[:-1] + "\x01"


def test_a_differing_line_goes_to_the_general_parser(tmp_path: Path) -> None:
    lines = _lines(400, seed=3)
    for name, changed in _variants(lines, 123).items():
        log = _write(tmp_path / "v.log", changed)
        buf = _block(log)
        assert candump._parse_fixed(buf, str(log), 1) is None, name
        _assert_same(
            candump._parse_block(buf, str(log), 1), candump._parse_general(buf, str(log), 1)
        )
        assert _frames(log) == [_fields(m) for m in _python_can(log)], name
        assert _frames(log, block_bytes=1000) == _frames(log), name


@pytest.mark.parametrize("bad", BAD)
def test_a_bad_line_is_the_general_parsers_error(tmp_path: Path, bad: str) -> None:
    kind, problem = BAD[bad]
    lines = _lines(400, seed=4)
    lines[200] = _bad_line(lines[200], kind)
    assert len(lines[200]) == len(lines[0])  # same length: only the row checks can see it
    log = _write(tmp_path / "bad.log", lines)
    buf = _block(log)
    assert candump._parse_fixed(buf, str(log), 1) is None
    with pytest.raises(ConfigError) as general:
        candump._parse_general(buf, str(log), 1)
    for block_bytes in (8 << 20, 1000):
        with pytest.raises(ConfigError) as got:
            list(read_candump(log, block_bytes=block_bytes))
        assert str(got.value) == str(general.value)
    assert f"bad.log: line 201: {problem}" in str(general.value)


def test_crlf_lines_go_to_the_general_parser(tmp_path: Path) -> None:
    lines = _lines(300, seed=5)
    for log in (
        _write(tmp_path / "crlf.log", lines, eol="\r\n"),  # every line
        _write(tmp_path / "one.log", lines[:150] + [lines[150] + "\r"] + lines[151:]),
    ):
        buf = _block(log)
        assert candump._parse_fixed(buf, str(log), 1) is None, log.name
        assert _frames(log) == [_fields(m) for m in _python_can(log)], log.name


def test_a_size_that_is_a_multiple_of_the_first_line_by_coincidence(tmp_path: Path) -> None:
    """A first line of length L, then L lines of length L + 1 (a 4-digit id): L * (L + 2) bytes;
    then lines of lengths L - 1 and L + 1 in turn."""
    first = _lines(1, seed=6)
    width = len(first[0]) + 1
    longer = _lines(width, seed=7, id_len=4)
    a_log = _write(tmp_path / "a.log", first + longer)
    shorter = _lines(width, seed=8, id_len=2)
    third = _lines(width, seed=9, id_len=4, nbytes=8)
    mixed = [x for pair in zip(shorter, third, strict=True) for x in pair]
    b_log = _write(tmp_path / "b.log", first + mixed)
    for log in (a_log, b_log):
        buf = _block(log)
        assert len(buf) % width == 0 and len({len(x) for x in log.read_text().splitlines()}) > 1
        assert candump._parse_fixed(buf, str(log), 1) is None, log.name
        _assert_same(
            candump._parse_block(buf, str(log), 1), candump._parse_general(buf, str(log), 1)
        )
        assert _frames(log) == [_fields(m) for m in _python_can(log)], log.name


def test_small_blocks_and_line_numbers(tmp_path: Path) -> None:
    """Blocks of whole lines cut at any byte count: the fast path block by block, the frames and
    their line numbers as in one block; a line of another layout midway sends its block (and only
    that one) to the general parser, unless the block is that line alone."""
    lines = _lines(2000, seed=10, direction=" R")
    lines[1500] = lines[1500][:-2]  # no direction token: that block goes the general way
    log = _write(tmp_path / "blocks.log", lines)
    want = [_fields(m) for m in _python_can(log)]
    calls = {"fixed": 0, "general": 0}
    fixed, general = candump._parse_fixed, candump._parse_general

    def count(kind: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def wrapped(*args: Any) -> Any:
            out = fn(*args)
            calls[kind] += kind == "general" or out is not None
            return out

        return wrapped

    for block_bytes in (7, 100, 1000, 4096, 65536):
        calls.update(fixed=0, general=0)
        mp = pytest.MonkeyPatch()
        mp.setattr(candump, "_parse_fixed", count("fixed", fixed))
        mp.setattr(candump, "_parse_general", count("general", general))
        try:
            cols = list(read_candump(log, block_bytes=block_bytes))
        finally:
            mp.undo()
        assert [_fields(m) for c in cols for m in c.messages()] == want, block_bytes
        assert np.concatenate([c.line for c in cols]).tolist() == list(range(1, 2001))
        if block_bytes == 7:  # a line a block: every block is of one layout
            assert calls == {"fixed": 2000, "general": 0}
        else:  # the block holding line 1501 and the lines around it
            assert calls["general"] == 1 and calls["fixed"] >= 1, block_bytes


def test_random_layouts_and_damage_give_the_general_parsers_result() -> None:
    """Random layouts, a few bytes of each block replaced, inserted or deleted at random: the
    block parser gives what the general parser gives (the same columns or the same error), and
    the fast path, when it takes a block, the general parser's columns."""
    rng = np.random.default_rng(12)
    alphabet = list(b"0123456789abcdefABCDEFG.() #RrTt\r\n\x01\x80xz-")
    taken = errors = 0

    def outcome(fn: Callable[..., FrameColumns], buf: np.ndarray) -> FrameColumns | str:
        try:
            return fn(buf, "f.log", 5)
        except ConfigError as exc:
            return str(exc)

    for it in range(600):
        lines = _lines(
            int(rng.integers(1, 40)),
            seed=it,
            t0=int(rng.choice([0, 12_345, 1_700_000_000, 2**31 - 1])),
            frac=int(rng.integers(1, 10)),
            id_len=int(rng.integers(1, 9)),
            nbytes=int(rng.integers(0, 9)),
            channel=str(rng.choice(["can0", "0", "vcan12", "x#)"])),
            direction=str(rng.choice(["", " R", " T", " r"])),
            lower=bool(rng.integers(0, 2)),
            us0=int(rng.integers(0, 1_000_000)),
            step_us=int(rng.integers(1, 300)),
        )
        b = bytearray("".join(x + "\n" for x in lines).encode())
        for _ in range(int(rng.integers(0, 3))):
            b[int(rng.integers(0, len(b)))] = int(rng.choice(alphabet))
        if rng.integers(0, 4) == 0:
            j = int(rng.integers(0, len(b) - 1))
            if rng.integers(0, 2):
                b.insert(j, int(rng.choice(alphabet)))
            else:
                del b[j]
        if not b.endswith(b"\n"):
            b += b"\n"
        buf = np.frombuffer(bytes(b), np.uint8)
        want = outcome(candump._parse_general, buf)
        got = outcome(candump._parse_block, buf)
        fast = candump._parse_fixed(buf, "f.log", 5)
        if isinstance(want, str):
            errors += 1
            assert got == want and fast is None, bytes(b)
        else:
            assert not isinstance(got, str)
            _assert_same(got, want)
            if fast is not None:
                taken += 1
                _assert_same(fast, want)
    assert taken > 150 and errors > 150, (taken, errors)
