"""The raw-CAN hot path: the CAN driver's frame batches (``CanFrameBatch``) written as ``/can_raw``
frame blocks, checked against hand-built expectations and the independent reader."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import can
from test_recorder_helpers import node_read

import cdpr.daq.drivers  # noqa: F401  (registers the drivers)
from cdpr.daq.can_raw import CanFrameBatch
from cdpr.daq.mcap_io import McapRunWriter, read_run
from cdpr.daq.recorder import Recorder
from cdpr.daq.source import Reading, create_source

T0 = 1_700_000_000_000_000_000


def _expected(m: can.Message) -> dict:
    """The /can_raw body of a frame, written out by hand from docs/recording.md."""
    return {
        "arbitration_id": m.arbitration_id,
        "is_extended": 1 if m.is_extended_id else 0,
        "is_remote": 1 if m.is_remote_frame else 0,
        "is_error_frame": 1 if m.is_error_frame else 0,
        "is_fd": 1 if m.is_fd else 0,
        "bitrate_switch": 1 if m.bitrate_switch else 0,
        "error_state_indicator": 1 if m.error_state_indicator else 0,
        "dlc": m.dlc,
        "data": list(m.data),
        "channel": m.channel,
        "is_rx": 1 if m.is_rx else 0,
        "t_bus_ns": round(m.timestamp * 1e9),
        "status": 8 if m.is_error_frame else 0,
    }


def _mixed_frames(n: int) -> list[can.Message]:
    """Mostly 8-byte frames (the formatted-at-once path), with error frames, short and empty frames,
    29-bit ids, zero and epoch timestamps in between (the one-at-a-time path)."""
    out = []
    for i in range(n):
        if i % 97 == 5:
            out.append(can.Message(is_error_frame=True, timestamp=1.5 + i))
        elif i % 89 == 7:
            out.append(
                can.Message(arbitration_id=0x7FF, data=bytes([i & 0xFF, 1, 2]), timestamp=2.0)
            )
        elif i % 83 == 3:
            out.append(can.Message(arbitration_id=0x100, data=b"", is_extended_id=False))
        else:
            out.append(
                can.Message(
                    arbitration_id=(0x1FFFFFFF - i) if i % 3 == 0 else 0x181 + i % 4,
                    data=bytes((i * 13 + 7 * j) & 0xFF for j in range(8)),
                    is_extended_id=i % 3 == 0,
                    timestamp=0.0 if i == 1 else 1_700_000_000.0 + i * 1.25e-4,
                )
            )
    return out


def test_batch_is_a_sequence_of_readings() -> None:
    frames = [
        can.Message(arbitration_id=0x181 + k, data=bytes([k] * 8), is_extended_id=False)
        for k in range(4)
    ]
    ten = [Reading("tensions", T0 + 10, {"T_c1_N": 1.0}), Reading("tensions", T0 + 20, {"x": 2})]
    b = CanFrameBatch()
    b.add_frame(frames[0], T0)
    b.add_frame(frames[1], T0 + 1)
    b.add_reading(ten[0])  # came after two frames
    b.add_frame(frames[2], T0 + 2)
    b.add_frame(frames[3], T0 + 3)
    b.add_reading(ten[1])  # at the end
    assert len(b) == 6
    order = [(r.stream, r.t_ns) for r in b]
    assert order == [
        ("can_raw", T0),
        ("can_raw", T0 + 1),
        ("tensions", T0 + 10),
        ("can_raw", T0 + 2),
        ("can_raw", T0 + 3),
        ("tensions", T0 + 20),
    ]
    assert [(r.stream, r.t_ns) for r in b[:]] == order
    assert b[2] is ten[0] and b[-1] is ten[1]
    assert b[3].values["data"] == bytes([2] * 8) and b[3].values["arbitration_id"] == 0x183
    assert [r.t_ns for r in b[-3:]] == [T0 + 2, T0 + 3, T0 + 20]
    j = CanFrameBatch.join([b, b])
    assert len(j) == 12 and [(r.stream, r.t_ns) for r in j] == order + order
    ren = b.renamed({"can_raw": "bus_a/can_raw", "tensions": "bus_a/tensions"})
    assert [r.stream for r in ren] == ["bus_a/can_raw"] * 2 + ["bus_a/tensions"] + [
        "bus_a/can_raw"
    ] * 2 + ["bus_a/tensions"]
    latest = ren.latest()
    assert latest["bus_a/can_raw"].t_ns == T0 + 3 and latest["bus_a/tensions"] is not ten[1]
    assert latest["bus_a/tensions"].values == {"x": 2}


def test_frame_batches_written_exactly_with_small_chunks(tmp_path: Path) -> None:
    """The driver's batches into a declared /can_raw (as the recorder writes it): frame blocks,
    every frame read back equal to its hand-written body by the streaming reader, the columnar
    reader (a time window too) and @mcap/core; blocks closed at every chunk close."""
    from cdpr.daq.can_raw import DESCRIPTION
    from cdpr.daq.run_reader import open_run

    frames = _mixed_frames(3000)
    p = tmp_path / "frames.mcap"
    w = McapRunWriter(p, chunk_size=4096)
    w.add_stream("can_raw", DESCRIPTION)
    ten = Reading("tensions", T0 + 5, {"T_c1_N": 3.5})
    for a in range(0, 3000, 700):  # batches of 700 frames; a tension reading in the second one
        chunk = frames[a : a + 700]
        b = CanFrameBatch("can_raw", chunk, [T0 + i for i in range(a, a + len(chunk))])
        if a == 700:
            b.add_reading(ten)
        w.write_many(b)
        if a == 1400:
            w.flush()  # a chunk closed mid-run: the open block goes with it
    w.finish()
    node = node_read(p)  # also compares the indexed reader (chunk + message indexes)
    assert node["samples"]["/can_raw"] == 3000 and node["topics"]["/tensions"] == 1
    assert node["topics"]["/can_raw"] >= 3  # blocks: at most 2048 frames, cut at the flush
    rc = read_run(p)
    got = rc.messages["/can_raw"]
    assert [t for t, _ in got] == [T0 + i for i in range(3000)]
    assert [body for _, body in got] == [_expected(m) for m in frames]
    assert rc.messages["/tensions"] == [(T0 + 5, {"T_c1_N": 3.5, "status": 0})]
    with open_run(p) as run:
        win = run.table("/can_raw", start_ns=T0 + 1000, stop_ns=T0 + 1500)
    assert win["t_ns"].tolist() == list(range(T0 + 1000, T0 + 1500))
    assert win["data"].tolist() == [bytes(m.data) for m in frames[1000:1500]]


def _sender(channel: str, frames: list[can.Message]) -> None:
    tx = can.Bus(
        interface="virtual",
        channel=channel,
        bitrate=1_000_000,
        receive_own_messages=False,
        preserve_timestamps=True,  # the receivers see the frames' own timestamps
    )
    try:
        for m in frames:
            tx.send(m)
    finally:
        tx.shutdown()


def test_two_can_drivers_recorded_through_batches(tmp_path: Path) -> None:
    """Two CAN load-cell drivers (same streams -> /<source>/<stream> topics) on python-can virtual
    buses: every frame sent is in the file, byte for byte, and the decoded samples too."""

    def tpdo(counter: int, counts: list[int]) -> list[can.Message]:
        # the shipped DBC's layout, by hand: two int24 little-endian counts, status, counter
        out = []
        for j, fid in enumerate((0x181, 0x281, 0x381, 0x481)):
            a, b = counts[2 * j], counts[2 * j + 1]
            data = (a & 0xFFFFFF).to_bytes(3, "little") + (b & 0xFFFFFF).to_bytes(3, "little")
            out.append(
                can.Message(
                    arbitration_id=fid,
                    data=data + bytes([0, counter & 0xFF]),
                    is_extended_id=False,
                    timestamp=1_700_000_000.0 + counter * 0.01 + j * 1e-4,
                )
            )
        return out

    chans = {name: f"test-{uuid.uuid4().hex}" for name in ("bus_a", "bus_b")}
    sources = [
        create_source(
            "can_loadcell",
            name,
            {
                "interface": "virtual",
                "channel": ch,
                "bitrate": 1_000_000,
                # nominal rate only used for the counter-wrap check over outages: a low one
                # (a wrap = 25.6 s) keeps a stall of this process on a loaded machine harmless
                "rate_hz": 10.0,
                "bus_options": {"receive_own_messages": False},
            },
            "test.toml",
        )
        for name, ch in chans.items()
    ]
    n_samples = {"bus_a": 300, "bus_b": 200}
    sent = {
        name: [m for c in range(n) for m in tpdo(c, [c * 10 + k for k in range(8)])]
        for name, n in n_samples.items()
    }
    p = tmp_path / "two.mcap"
    rec = Recorder(sources, p)
    rec.start()
    end = time.monotonic() + 10.0
    while time.monotonic() < end and not all(s.is_open for s in sources):
        time.sleep(0.01)  # the acquisition threads open their buses
    for name, ch in chans.items():
        _sender(ch, sent[name])
    want = {f"{k}/tensions": n for k, n in n_samples.items()}
    end = time.monotonic() + 30.0
    while time.monotonic() < end and any(
        rec.status().counts.get(k, 0) < n for k, n in want.items()
    ):
        time.sleep(0.05)
    rec.stop()
    assert rec.dropped == 0
    node = node_read(p)
    rc = read_run(p)
    for name, n in n_samples.items():
        assert node["samples"][f"/{name}/can_raw"] == 4 * n  # frame blocks
        bodies = [b for _, b in rc.messages[f"/{name}/can_raw"]]
        # received frames carry the channel of the bus they came in on
        assert bodies == [{**_expected(m), "channel": chans[name]} for m in sent[name]]
        ten = [b for _, b in rc.messages[f"/{name}/tensions"]]
        # a sample is complete (and written) once its four frames are in
        assert [b["counter"] for b in ten] == [c & 0xFF for c in range(n)]
        assert [b["seq"] for b in ten] == list(range(n))
        assert [b["raw_c3_counts"] for b in ten] == [c * 10 + 2 for c in range(n)]
    assert "/can_raw" not in node["topics"]
