"""Raw CAN frames of ``cdpr import`` stored as frame blocks (column blocks, layout ``can_frames``,
docs/recording.md): every field python-can gives a frame reads back identical through three
independent readers (``open_run``, the streaming ``read_run``, and the stdlib block decoder over the
``mcap`` package's reader), the JavaScript checker (@mcap/core) counts every frame, and a values
table (the channel) is kept right across pieces and blocks."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest
from _block_reader import samples
from mcap.reader import make_reader
from test_recorder_helpers import node_read

from cdpr.analysis.errors import InputError
from cdpr.daq.column_blocks import BlockBuffer, decode_blocks, encode_block
from cdpr.daq.mcap_io import read_run
from cdpr.daq.run_reader import open_run, summarize
from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"

# every kind of frame candump writes: classic, 29-bit, remote (with and without a dlc), CAN FD with
# bit-rate switch / error-state indicator, an error frame, a transmitted frame, three channels (one
# of them a number), and a classic frame of 0 bytes
LOG = """(1700000000.000100) can0 181#0102030405060708
(1700000000.000200) can0 12345678#DEADBEEF
(1700000000.000300) can1 123#R
(1700000000.000400) can1 123#R5 T
(1700000000.000500) vcan0 7FF##3000102030405060708090A0B0C0D0E0F
(1700000000.000600) 2 20000080#0000000000000000
(1700000000.000700) can0 0000012A##1
(1700000000.000800) can0 010#
(1700000000.000900) can0 1F334455#1122334455667788 T
"""


def _python_can(path: Path) -> list[can.Message]:
    reader = can.LogReader(str(path))
    try:
        return list(reader)
    finally:
        reader.stop()


def _expected(m: can.Message) -> dict:
    """The per-frame values, from python-can's own reading of the log."""
    return {
        "arbitration_id": m.arbitration_id, "is_extended": int(m.is_extended_id),
        "is_remote": int(m.is_remote_frame), "is_error_frame": int(m.is_error_frame),
        "is_fd": int(m.is_fd), "bitrate_switch": int(m.bitrate_switch),
        "error_state_indicator": int(m.error_state_indicator), "dlc": m.dlc,
        "data": list(m.data or b""), "channel": m.channel, "is_rx": int(m.is_rx),
        "t_bus_ns": round(m.timestamp * 1e9), "status": 8 if m.is_error_frame else 0,
    }  # fmt: skip


@pytest.fixture(scope="module")
def imported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[can.Message]]:
    d = tmp_path_factory.mktemp("frames")
    log = d / "mixed.log"
    log.write_text(LOG)
    out = d / "mixed.mcap"
    assert main(["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG),
                 "--raw-only", "--out", str(out)]) == 0  # fmt: skip
    return out, _python_can(log)


def test_every_field_reads_back_as_python_can_reads_the_log(imported) -> None:
    out, want = imported
    assert len(want) == 9
    expected = [_expected(m) for m in want]
    # 1. the mcap package's reader and the stdlib block decoder (tests/_block_reader.py)
    with out.open("rb") as fh:
        reader = make_reader(fh)
        rows = samples(reader, "/can_raw")
        channel = next(c for c in reader.get_summary().channels.values() if c.topic == "/can_raw")
    assert channel.metadata["layout"] == "can_frames"
    assert [{k: r[k] for k in expected[0]} for r in rows] == expected
    # 2. open_run
    with open_run(out) as run:
        df = run.table("/can_raw")
    got = [
        {k: (list(v) if k == "data" else v) for k, v in r.items() if k != "t_ns"}
        for r in df.to_dict("records")
    ]
    assert got == expected
    assert df["channel"].dtype == object
    # 3. the streaming reader (read_run), as the per-frame JSON layout reads back
    rc = read_run(out)
    assert [v for _, v in rc.messages["/can_raw"]] == expected
    assert [t for t, _ in rc.messages["/can_raw"]] == df["t_ns"].tolist()


def test_the_javascript_checker_counts_every_frame(imported) -> None:
    out, want = imported
    node = node_read(out)
    assert node["complete"] and node["bad_json"] == 0 and node["bad_blocks"] == 0
    assert node["samples"]["/can_raw"] == len(want)


def test_a_values_table_grows_across_pieces_and_blocks() -> None:
    buf = BlockBuffer(max_samples=10)
    t = np.arange(3, dtype=np.int64)
    buf.add_columns(t, {"channel": np.array([0, 1, 0], np.uint8)}, 0, {"channel": ["can0", 1]})
    buf.add_columns(t + 3, {"channel": np.array([1, 0], np.uint8)[[0, 1, 0]]}, 0,
                    {"channel": [None, 1]})  # fmt: skip
    got = buf.take()
    assert got is not None
    t_all, cols = got
    assert buf.values == {"channel": ["can0", 1, None]}
    assert cols["channel"].tolist() == [0, 1, 0, 1, 2, 1]  # [1, None, 1] in the stream table
    first = encode_block(
        t_all[:2], {k: v[:2] for k, v in cols.items()}, 0, {"channel": ["can0", 1]}
    )
    second = encode_block(t_all[2:], {k: v[2:] for k, v in cols.items()}, 2, buf.values)
    back = decode_blocks([first, second])
    assert back["channel"].tolist() == ["can0", 1, "can0", 1, None, 1]
    assert back["status"].dtype == np.int64


def test_a_bad_index_or_table_is_named() -> None:
    t = np.arange(2, dtype=np.int64)
    body = encode_block(t, {"channel": np.array([0, 3], np.uint8)}, 0, {"channel": ["can0"]})
    with pytest.raises(InputError, match=r"run\.mcap: a column block is malformed \(an index past"):
        decode_blocks([body], "run.mcap")
    buf = BlockBuffer()
    with pytest.raises(InputError, match="channel: an index past its table of 1"):
        buf.add_columns(t, {"channel": np.array([0, 1], np.uint8)}, 0, {"channel": ["can0"]})


def test_inspect_counts_frames_and_bad_status_from_the_blocks(imported) -> None:
    out, want = imported
    with open_run(out) as run:
        rows = {s.topic: s for s in summarize(run)}
        times = run.times("/can_raw")
    raw = rows["/can_raw"]
    assert raw.count == len(want) == len(times)
    assert raw.bad_status == sum(m.is_error_frame for m in want) == 1
    assert times.tolist() == [round(m.timestamp * 1e9) for m in want]
    assert raw.first_ns == times[0] and raw.last_ns == times[-1]


def test_every_message_of_the_import_validates_against_its_schema(imported) -> None:
    import json

    import jsonschema

    out, want = imported
    n = 0
    with out.open("rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages():
            jsonschema.Draft202012Validator(json.loads(schema.data)).validate(json.loads(msg.data))
            if channel.topic == "/can_raw":
                assert schema.name == "cdpr.column_block"
                n += json.loads(msg.data)["count"]
    assert n == len(want)


def test_a_table_of_more_than_256_values_keeps_every_index() -> None:
    names = [f"can{i}" for i in range(300)]
    codes = np.arange(600, dtype=np.int64) % 300
    buf = BlockBuffer()
    t = np.arange(600, dtype=np.int64)
    buf.add_columns(t, {"channel": codes}, 0, {"channel": names})
    got = buf.take()
    assert got is not None
    body = encode_block(got[0], got[1], 0, buf.values)
    assert decode_blocks([body])["channel"].tolist() == [names[c] for c in codes]
