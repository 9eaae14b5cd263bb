"""The one CAN decoding path (``LoadCellDecoder.decode_frames``) against a frame-by-frame reference of
the documented rules written separately (``tests/_can_reference.py``: the shipped DBC's layout by
hand, no numpy, no cantools), on frame streams with the mess a bus and a logger give: lost samples
and counter wraps, missing, reordered, repeated and truncated frames, a sample that completes and
goes on with the same counter, other ids, extended ids equal to a load-cell id, error and remote
frames, status bits, long pauses; fed in blocks split at random places (a sample and its marks
across blocks), including blocks with no load-cell frame at all."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _can_reference import IDS, Frame, Reference

from cdpr.daq.can_dbc import DEFAULT_DBC, load_dbc
from cdpr.daq.can_decoder import LoadCellDecoder
from cdpr.daq.can_frames import ERROR, EXTENDED, REMOTE, RX, FrameColumns
from cdpr.daq.loadcell import Calibration

CABLES = [f"k{i}" for i in range(1, 9)]


def _stream(rng: np.random.Generator, n_samples: int) -> list[Frame]:
    out: list[Frame] = []
    t = 1_700_000_000_000_000_000
    c = int(rng.integers(0, 256))
    for _ in range(n_samples):
        u = rng.random()
        if u < 0.03:
            c = (c + int(rng.integers(2, 300))) % 256  # lost samples
        else:
            c = (c + 1) % 256
        t += 1_000_000 if rng.random() > 0.005 else int(3e9)  # now and then a pause
        frames = []
        for fid in IDS:
            counts = rng.integers(-(1 << 23), 1 << 23, 2)
            data = b"".join(int(x & 0xFFFFFF).to_bytes(3, "little") for x in counts)
            st = (
                int(rng.integers(0, 8)) | int(rng.integers(0, 8)) << 4 if rng.random() < 0.05 else 0
            )
            frames.append([fid, data + bytes([st, c])])
        r = rng.random()
        if r < 0.04:
            del frames[int(rng.integers(0, 4))]  # a missing frame
        elif r < 0.07:
            rng.shuffle(frames)  # reordered
        elif r < 0.10:
            frames.insert(int(rng.integers(0, 4)), list(frames[int(rng.integers(0, 4))]))  # repeat
        elif r < 0.12:
            frames += [list(f) for f in frames[: int(rng.integers(1, 4))]]  # complete, then more
        elif r < 0.15:
            k = int(rng.integers(0, len(frames)))
            frames[k][1] = frames[k][1][: int(rng.integers(0, 8))]  # truncated
        elif r < 0.16:
            frames[int(rng.integers(0, 4))][1] += b"\0\0\0\0"  # too long (12 bytes)
        for j, (fid, data) in enumerate(frames):
            out.append(_frame(t + j * 10_000, fid, data))
        r = rng.random()
        if r < 0.03:
            out.append(_frame(t + 50_000, 0x181, bytes(8), extended=True))
        elif r < 0.05:
            out.append(_frame(t + 60_000, 0x7FF, bytes(3)))
        elif r < 0.06:
            out.append(_frame(t + 70_000, 0, bytes(8), error=True))
        elif r < 0.07:
            out.append(_frame(t + 80_000, 0x281, b"", remote=True))
    return out


def _frame(t_ns: int, fid: int, data: bytes, **kw: bool) -> Frame:
    """A frame received at ``t_ns`` whose bus time a log keeps as float seconds (``t_bus_ns`` is
    their ``round(t_s * 1e9)``)."""
    t_s = (t_ns + 7) * 1e-9
    return Frame(t_ns, round(t_s * 1e9), fid, data, t_s=t_s, **kw)


def _columns(frames: list[Frame]) -> tuple[FrameColumns, np.ndarray]:
    n = len(frames)
    w = max([8, *(len(f.data) for f in frames)])
    data = np.zeros((n, w), np.uint8)
    for i, f in enumerate(frames):
        data[i, : len(f.data)] = np.frombuffer(f.data, np.uint8)
    flags = np.array(
        [EXTENDED * f.extended | ERROR * f.error | REMOTE * f.remote | RX for f in frames],
        np.uint8,
    )
    ch = np.empty(n, object)
    ch[:] = ["can0"] * n
    cols = FrameColumns(
        np.array([f.t_s for f in frames]),
        np.array([f.arbitration_id for f in frames], np.int64),
        flags,
        np.array([len(f.data) for f in frames], np.int64),
        data,
        np.array([len(f.data) for f in frames], np.int64),
        ch,
        np.zeros(n, np.int64),
    )
    return cols, np.array([f.t_ns for f in frames], np.int64)


@pytest.mark.parametrize("seed", range(6))
def test_block_decoding_equals_the_frame_by_frame_rules(seed: int) -> None:
    """Seeds 0-4: the numpy unpacking of the shipped DBC; seed 5: cantools frame by frame (the
    path of a DBC with big-endian or float signals), the same samples."""
    rng = np.random.default_rng(seed)
    frames = _stream(rng, 1500)
    off = rng.uniform(-1e5, 1e5, 8).tolist()
    gain = rng.uniform(1e-5, 1e-4, 8).tolist()
    ref = Reference(off, gain, rate_hz=1000.0)
    for f in frames:
        ref.feed(f)
    ref.flush()

    dec = LoadCellDecoder(load_dbc(DEFAULT_DBC), CABLES, Calibration(off, gain), 1000.0)
    if seed == 5:
        dec.dbc._fast.clear()  # every frame through cantools
    cols, t_ns = _columns(frames)
    cuts = np.sort(rng.choice(np.arange(1, len(frames)), size=40, replace=False))
    cuts = np.concatenate([[0], cuts, [len(frames)]])
    got: list[dict] = []
    bad = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        for sub in ((a, b),) if rng.random() < 0.8 else ((a, a + 1), (a + 1, b)):
            if sub[1] <= sub[0]:
                continue
            s = dec.decode_frames(cols.take(slice(*sub)), t_ns[sub[0] : sub[1]])
            assert np.all(np.diff(s.done_at) >= 0) and np.all(s.done_at < sub[1] - sub[0])
            got += _rows(s)
            bad.append(s.bad)
    got += _rows(dec.flush())
    assert len(got) == len(ref.samples) > 1000
    for g, w in zip(got, ref.samples, strict=True):
        for key in ("t_ns", "raw", "ch_status", "counter", "seq", "t_bus_ns", "status"):
            assert g[key] == w[key], (key, g, w)
        assert all(
            (math.isnan(a) and math.isnan(b)) or a == b for a, b in zip(g["T"], w["T"], strict=True)
        )
    assert np.concatenate(bad).tolist() == ref.bad_frames
    assert (dec.lost, dec.bad, dec.partial, dec.n_pauses) == (
        ref.lost, ref.bad, ref.partial, ref.pauses,
    )  # fmt: skip
    kinds = {s["status"] for s in ref.samples}
    assert {0, 16, 8 | 16, 8} <= kinds  # clean, gap, bad frame in a gap, a repeat's flag


def _rows(s) -> list[dict]:  # noqa: ANN001
    c = s.columns
    out = []
    for i in range(len(s)):
        out.append(
            {
                "t_ns": int(s.t_ns[i]),
                "T": [float(c[f"T_{k}_N"][i]) for k in CABLES],
                "raw": [int(c[f"raw_{k}_counts"][i]) for k in CABLES],
                "ch_status": [int(c[f"status_{k}"][i]) for k in CABLES],
                "counter": int(c["counter"][i]),
                "seq": int(c["seq"][i]),
                "t_bus_ns": int(c["t_bus_ns"][i]),
                "status": int(s.status[i]),
            }
        )
    return out
