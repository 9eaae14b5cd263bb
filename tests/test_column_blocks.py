"""Column blocks (docs/recording.md, "Column blocks"): a 1 kHz stream written by readings and by
columns reads back exactly with ``open_run`` and with an independent decoder (the ``mcap`` package's
reader + tests/_block_reader.py), every message validates against its channel's JSON schema, the
per-sample view holds the first sample of every 20 ms, and a low-rate stream keeps per-sample
messages."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from _block_reader import messages
from mcap.reader import make_reader

from cdpr.analysis.errors import InputError
from cdpr.daq.mcap_writer import McapRunWriter
from cdpr.daq.run_reader import open_run
from cdpr.daq.source import FieldDescription, Reading, StreamDescription

T0 = 1_700_000_000_000_000_000
DESC = StreamDescription(
    {"T_a_N": FieldDescription("N"), "raw_a_counts": FieldDescription("counts", "int64")},
    1000.0,
    "test",
)


def _mixed_run(p: Path) -> dict[str, list]:
    """Readings (one with a missing field, one with an extra field, a NaN), then columns, then
    readings again; returns the values written, row by row."""
    w = McapRunWriter(p, chunk_size=2048)
    w.add_stream("tensions", DESC)
    rows: dict[str, list] = {"t": [], "T": [], "raw": [], "extra": [], "status": []}

    def keep(t: int, T: float, raw: float, extra: float, status: int) -> None:
        for k, v in zip(rows, (t, T, raw, extra, status), strict=True):
            rows[k].append(v)

    for i in range(300):
        t = T0 + i * 1_000_000 + 3
        v: dict[str, object] = {"T_a_N": 100.0 + i / 7, "raw_a_counts": 5000 + i}
        extra = math.nan
        if i == 10:
            v["T_a_N"] = math.nan
        if i == 20:
            del v["raw_a_counts"]
        if i == 30:
            v["extra_x"] = 2.5
            extra = 2.5
        w.write(Reading("tensions", t, v, 16 if i == 10 else 0))
        keep(t, v["T_a_N"], v.get("raw_a_counts", math.nan), extra, 16 if i == 10 else 0)
    t_cols = T0 + np.arange(300, 2300, dtype=np.int64) * 1_000_000 + 3
    T_cols = 150.0 + np.sin(np.arange(2000))
    raw_cols = np.arange(2000, dtype=np.int64) - 1000
    w.write_columns("tensions", t_cols, {"T_a_N": T_cols, "raw_a_counts": raw_cols}, 0)
    for i in range(2000):
        keep(int(t_cols[i]), float(T_cols[i]), int(raw_cols[i]), math.nan, 0)
    for i in range(2300, 2500):
        t = T0 + i * 1_000_000 + 3
        w.write(Reading("tensions", t, {"T_a_N": -1.0 * i, "raw_a_counts": i}))
        keep(t, -1.0 * i, i, math.nan, 0)
    w.write(Reading("tunnel", T0, {"airspeed_mps": 25.5}))
    w.finish()
    return rows


def test_readings_and_columns_read_back_exactly_both_ways(tmp_path: Path) -> None:
    p = tmp_path / "run.mcap"
    truth = _mixed_run(p)
    want_t = np.array(truth["t"], np.int64)
    with open_run(p) as run:
        info = run.streams["/tensions"]
        assert info.count == 2500 and (info.start_ns, info.stop_ns) == (want_t[0], want_t[-1])
        assert info.fields["raw_a_counts"].type == "integer" and info.units["T_a_N"] == "N"
        df = run.table("/tensions")
        assert np.array_equal(df["t_ns"].to_numpy(), want_t)
        assert np.array_equal(df["T_a_N"].to_numpy(), np.array(truth["T"]), equal_nan=True)
        assert np.array_equal(
            df["raw_a_counts"].to_numpy(np.float64), np.array(truth["raw"], float), equal_nan=True
        )
        assert np.array_equal(df["extra_x"].to_numpy(), np.array(truth["extra"]), equal_nan=True)
        assert df["status"].tolist() == truth["status"]
        # a window cut inside blocks: exactly the samples in [a, b)
        a, b = int(want_t[123]), int(want_t[2222])
        win = run.table("/tensions", columns=["T_a_N"], start_ns=a, stop_ns=b)
        assert list(win.columns) == ["t_ns", "T_a_N"]
        assert np.array_equal(win["t_ns"].to_numpy(), want_t[123:2222])
        with pytest.raises(InputError, match="no column 'T_b_N'"):
            run.table("/tensions", columns=["T_b_N"])
        assert np.array_equal(run.times("/tensions"), want_t)
        assert run.table("/tunnel")["airspeed_mps"].tolist() == [25.5]  # low rate: per sample
    # the independent decoder on the same file
    with p.open("rb") as fh:
        msgs = messages(make_reader(fh))
    got_t = np.array([t for t, _ in msgs["/tensions"]], np.int64)
    assert np.array_equal(got_t, want_t)
    got_T = np.array([r["T_a_N"] for _, r in msgs["/tensions"]])
    assert np.array_equal(got_T, np.array(truth["T"]), equal_nan=True)
    assert [r["status"] for _, r in msgs["/tensions"]] == truth["status"]


def test_every_block_and_view_message_validates_and_the_view_is_20_ms(tmp_path: Path) -> None:
    import jsonschema

    p = tmp_path / "run.mcap"
    truth = _mixed_run(p)
    n_block = n_view = 0
    view_t: list[int] = []
    with p.open("rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages(log_time_order=False):
            body = json.loads(msg.data)
            jsonschema.Draft202012Validator(json.loads(schema.data)).validate(body)
            if channel.topic == "/tensions":
                assert channel.metadata["storage"] == "column_blocks"
                assert schema.name == "cdpr.column_block" and body["count"] >= 1
                n_block += 1
            elif channel.topic == "/tensions/view":
                assert channel.metadata["view_of"] == "/tensions"
                view_t.append(msg.log_time)
                assert body["T_a_N"] is None or isinstance(body["T_a_N"], float)
                n_view += 1
    # chunk_size 2048 B bounds a block to 2048 // (8 * 4) = 64 samples
    assert n_block >= 2500 // 64
    # the first sample of every 20 ms bin of time, counted here from the times written
    t = np.array(truth["t"], np.int64)
    first_of_bin = t[np.flatnonzero(np.diff(t // 20_000_000, prepend=-1) != 0)]
    assert view_t == first_of_bin.tolist() and n_view == 125


def test_a_low_rate_stream_and_blocks_false_keep_per_sample_messages(tmp_path: Path) -> None:
    p = tmp_path / "run.mcap"
    w = McapRunWriter(p)
    w.add_stream("slow", StreamDescription({"x": FieldDescription("m")}, 100.0, "slow"))
    w.add_stream("fast_json", DESC, blocks=False)
    w.add_stream("shaped", StreamDescription({"v": FieldDescription("m", shape=(3,))}, 1000.0, ""))
    for i in range(5):
        w.write(Reading("slow", T0 + i, {"x": float(i)}))
        w.write(Reading("fast_json", T0 + i, {"T_a_N": 1.0, "raw_a_counts": i}))
        w.write(Reading("shaped", T0 + i, {"v": [1.0, 2.0, 3.0]}))
    w.finish()
    with p.open("rb") as fh:
        chans = {c.topic: c for c in make_reader(fh).get_summary().channels.values()}
    assert set(chans) == {"/slow", "/fast_json", "/shaped"}  # no view: no blocks
    assert not any(c.metadata.get("storage") for c in chans.values())
    with open_run(p) as run:
        assert run.streams["/fast_json"].count == 5
        assert run.table("/fast_json")["raw_a_counts"].tolist() == list(range(5))


def test_a_block_stream_refuses_strings_and_the_record_path(tmp_path: Path) -> None:
    from cdpr.daq.mcap_writer import FrameRecords

    w = McapRunWriter(tmp_path / "run.mcap")
    w.add_stream("tensions", DESC)
    w.write(Reading("tensions", T0, {"T_a_N": "12.5"}))
    with pytest.raises(InputError, match="expected numbers"):
        w.flush()
    with pytest.raises(InputError, match="write_columns"):
        w.write_records("tensions", [T0], FrameRecords(np.ones(1, bool), np.zeros((1, 3))), None)


def test_integer_columns_are_stored_narrow_and_read_back_int64(tmp_path: Path) -> None:
    """Integers that fit are stored as uint8 or int32 (fewer bytes to encode, compress and read);
    every reader gives the exact values back, int64 from open_run."""
    p = tmp_path / "narrow.mcap"
    desc = StreamDescription(
        {k: FieldDescription("", "int64") for k in ("small", "mid", "neg", "big")}, 1000.0, "t"
    )
    n = 3000
    t = T0 + np.arange(n, dtype=np.int64) * 1_000_000
    cols = {
        "small": np.arange(n, dtype=np.int64) % 256,  # 0..255: uint8
        "mid": np.arange(n, dtype=np.int64) * 700_000,  # up to 2.1e9: int32
        "neg": -np.arange(n, dtype=np.int64),  # negative: int32
        "big": np.arange(n, dtype=np.int64) + 2**40,  # int64
    }
    w = McapRunWriter(p)
    w.add_stream("tensions", desc)
    w.write_columns("tensions", t, cols, 0)
    w.finish()
    with p.open("rb") as fh:
        reader = make_reader(fh)
        bodies = [m.data for _, _, m in reader.iter_messages(["/tensions"])]
    dtypes = dict(
        zip(json.loads(bodies[0])["columns"], json.loads(bodies[0])["dtypes"], strict=True)
    )
    assert dtypes == {"t_ns": "<i8", "small": "|u1", "mid": "<i4", "neg": "<i4", "big": "<i8",
                      "status": "|u1"}  # fmt: skip
    with open_run(p) as run:
        df = run.table("/tensions")
    for k, v in cols.items():
        assert df[k].dtype == np.int64 and df[k].tolist() == v.tolist(), k
    with p.open("rb") as fh:
        rows = messages(make_reader(fh))["/tensions"]
    for k, v in cols.items():
        assert [r[k] for _, r in rows] == v.tolist(), k
