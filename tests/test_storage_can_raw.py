"""``/can_raw`` keeps every frame as it was on the bus: every field python-can gives a
``can.Message`` survives recording (the CAN driver's batches on a python-can virtual bus, and single
readings) and reads back identical through ``open_run``; the load-cell decoder matches ids with
their extended flag."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import can
import numpy as np
from test_recorder_helpers import node_read

import cdpr.daq.drivers  # noqa: F401  (registers the drivers)
from cdpr.daq.can_raw import CanFrameBatch, raw_reading
from cdpr.daq.mcap_io import McapRunWriter
from cdpr.daq.run_reader import open_run
from cdpr.daq.source import FieldDescription, Reading, StreamDescription, create_source

T0 = 1_700_000_000_000_000_000
FIELDS = (
    "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "is_fd",
    "bitrate_switch", "error_state_indicator", "dlc", "channel", "is_rx",
)  # fmt: skip


def _frames() -> list[can.Message]:
    """Every kind of frame, written out by hand."""
    return [
        can.Message(timestamp=1.0, arbitration_id=0x181, data=bytes(range(8)), is_extended_id=False,
                    channel="can0"),
        can.Message(timestamp=1.5, arbitration_id=0x181, data=b"\x01\x02", is_extended_id=True,
                    channel="can0"),
        can.Message(timestamp=2.0, arbitration_id=0x1FFFFFFF, is_extended_id=True,
                    is_remote_frame=True, dlc=4, channel=1),
        can.Message(timestamp=2.25, is_error_frame=True, channel="can1", is_rx=False),
        can.Message(timestamp=3.0, arbitration_id=0x7FF, is_extended_id=False, is_fd=True,
                    bitrate_switch=True, error_state_indicator=True, data=bytes(range(64)),
                    channel="can0"),
        can.Message(timestamp=3.5, arbitration_id=0x123, is_extended_id=False, is_fd=True,
                    data=bytes(range(12)), channel="can0", is_rx=False),
        can.Message(timestamp=4.0, arbitration_id=0x10, is_extended_id=False, data=b"",
                    channel=None),
        can.Message(timestamp=1_700_000_123.456789, arbitration_id=0x182, is_extended_id=False,
                    data=bytes(8), channel="can0"),
    ]  # fmt: skip


def _same(df, frames: list[can.Message]) -> None:  # type: ignore[no-untyped-def]
    assert len(df) == len(frames)
    cols = {
        "arbitration_id": "arbitration_id", "is_extended_id": "is_extended",
        "is_remote_frame": "is_remote", "is_error_frame": "is_error_frame", "is_fd": "is_fd",
        "bitrate_switch": "bitrate_switch", "error_state_indicator": "error_state_indicator",
        "dlc": "dlc", "channel": "channel", "is_rx": "is_rx",
    }  # fmt: skip
    for i, m in enumerate(frames):
        row = df.iloc[i]
        for attr in FIELDS:
            want = getattr(m, attr)
            got = row[cols[attr]]
            assert (got == want) if not isinstance(want, bool) else (bool(got) is want), (i, attr)
        assert row["data"] == bytes(m.data), i
        assert row["t_bus_ns"] == round(m.timestamp * 1e9), i
        assert row["status"] == (8 if m.is_error_frame else 0)


def test_every_field_round_trips_through_single_readings_and_batches(tmp_path: Path) -> None:
    frames = _frames()
    p = tmp_path / "raw.mcap"
    w = McapRunWriter(p)
    for i, m in enumerate(frames):  # one reading at a time
        w.write(raw_reading(m, T0 + i))
    batch = CanFrameBatch("bus/can_raw")  # the driver's batch: the numpy formatter + the others
    for i, m in enumerate(frames * 3):
        batch.add_frame(m, T0 + 100 + i)
    w.write_many(batch)
    w.finish()
    with open_run(p) as run:
        _same(run.table("/can_raw"), frames)
        _same(run.table("/bus/can_raw"), frames * 3)
        assert run.streams["/can_raw"].fields["data"].type == "array"


def test_single_readings_into_a_declared_stream_are_frame_blocks(tmp_path: Path) -> None:
    """A source that gives ``can_raw`` readings one by one (not the driver's batches) into a stream
    declared with the frame description: the same frame blocks as the batches, every field back;
    a ``can_raw`` stream declared with other fields stays one JSON message per reading."""
    from cdpr.daq.can_raw import DESCRIPTION

    frames = _frames()
    p = tmp_path / "raw.mcap"
    w = McapRunWriter(p)
    w.add_stream("can_raw", DESCRIPTION)
    w.add_stream("bus/can_raw", StreamDescription({"i": FieldDescription("", "int64")}, 0.0, ""))
    for i, m in enumerate(frames):
        w.write(raw_reading(m, T0 + i))
    w.write(Reading("bus/can_raw", T0, {"i": 7}))
    w.finish()
    with open_run(p) as run:
        _same(run.table("/can_raw"), frames)
        assert run.table("/bus/can_raw")["i"].tolist() == [7]
    node = node_read(p)
    assert node["samples"]["/can_raw"] == len(frames) and node["topics"]["/bus/can_raw"] == 1


def test_recorded_frames_from_a_virtual_bus_read_back_identical(tmp_path: Path) -> None:
    """The CAN driver on a python-can virtual bus: FD, remote, error and extended frames among the
    load-cell frames are recorded as they arrived; an extended frame with a load-cell id is not
    decoded as a load-cell sample."""
    ch = f"test-{uuid.uuid4().hex}"
    src = create_source(
        "can_loadcell",
        "lc",
        {"interface": "virtual", "channel": ch, "bitrate": 1_000_000, "rate_hz": 10.0,
         "bus_options": {"receive_own_messages": False}},
        "test.toml",
    )  # fmt: skip
    sent = []
    for c in range(3):
        for j, fid in enumerate((0x181, 0x281, 0x381, 0x481)):
            data = (1000 * c + j).to_bytes(3, "little") * 2 + bytes([0, c])
            sent.append(can.Message(arbitration_id=fid, data=data, is_extended_id=False,
                                    timestamp=10.0 + c + j * 1e-3))  # fmt: skip
        # an extended frame whose id is a load-cell id, with another counter: not a sample
        sent.append(can.Message(arbitration_id=0x181, data=bytes([9] * 7 + [200]),
                                is_extended_id=True, timestamp=10.5 + c))  # fmt: skip
    # the other kinds of frame (virtual buses drop error frames; a standard 0x181 is a load cell's)
    sent += [
        m
        for m in _frames()
        if not m.is_error_frame and (m.is_extended_id or m.arbitration_id != 0x181)
    ]
    p = tmp_path / "rec.mcap"
    w = McapRunWriter(p)
    for stream, desc in src.describe().items():
        w.add_stream(stream, desc)
    got_frames = 0
    received: list[can.Message] = []
    with src:
        with can.Bus(interface="virtual", channel=ch, receive_own_messages=False) as tx:
            for m in sent:
                tx.send(m)
        end = time.monotonic() + 20.0
        while got_frames < len(sent) and time.monotonic() < end:
            batch = src.read(0.2)
            got_frames += len(batch.messages)
            received += batch.messages
            w.write_many(batch)
        for r in src.decoder.flush().readings():
            w.write(r)
    w.finish()
    assert got_frames == len(sent)
    with open_run(p) as run:
        raw = run.table("/can_raw")
        # what python-can gave the driver reads back identical (the virtual bus stamps the time)
        _same(raw, received)
        _same(
            raw.drop(columns="t_bus_ns").assign(
                t_bus_ns=[round(m.timestamp * 1e9) for m in received]
            ),
            [_on(m, ch, r.timestamp) for m, r in zip(sent, received, strict=True)],
        )
        ten = run.table("/tensions")
    assert ten["counter"].tolist() == [0, 1, 2]  # no sample from the extended frames
    assert ten["raw_c1_counts"].tolist() == [0, 1000, 2000]
    assert (ten["status"] == 0).all()


def _on(m: can.Message, channel: str, timestamp: float) -> can.Message:
    """``m`` as a receiver sees it: on ``channel``, received, at ``timestamp``."""
    out = can.Message(
        timestamp=timestamp, arbitration_id=m.arbitration_id, is_extended_id=m.is_extended_id,
        is_remote_frame=m.is_remote_frame, is_error_frame=m.is_error_frame, is_fd=m.is_fd,
        bitrate_switch=m.bitrate_switch, error_state_indicator=m.error_state_indicator,
        dlc=m.dlc, data=m.data, channel=channel, is_rx=True,
    )  # fmt: skip
    return out


def test_reader_gives_numpy_columns(tmp_path: Path) -> None:
    p = tmp_path / "raw.mcap"
    w = McapRunWriter(p)
    for i, m in enumerate(_frames()):
        w.write(raw_reading(m, T0 + i))
    w.finish()
    with open_run(p) as run:
        df = run.table("/can_raw", columns=["arbitration_id", "t_bus_ns"])
    assert df["arbitration_id"].to_numpy().dtype == np.int64
    assert df["t_bus_ns"].tolist()[-1] == round(1_700_000_123.456789 * 1e9)  # exact int64
