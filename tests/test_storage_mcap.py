"""MCAP run files: channels and schemas, time-bounded chunks, recovery of truncated files, never
overwrite.  Every file is also read by the independent reader (@mcap/core via node)."""

from __future__ import annotations

import base64
import json
import math
import shutil
import time
from pathlib import Path

import pytest
from test_recorder_helpers import node_read

from cdpr.analysis.errors import CdprError, InputError
from cdpr.daq.mcap_io import McapRunWriter, read_run, recover_run
from cdpr.daq.runs import new_run_path, run_name
from cdpr.daq.source import FieldDescription, Reading, StreamDescription

T0 = 1_700_000_000_000_000_000


def _tension_desc() -> StreamDescription:
    return StreamDescription(
        {"T_c1_N": FieldDescription("N"), "raw_c1_counts": FieldDescription("", "int64")},
        100.0,
        "tensions",
    )


def test_channels_schemas_and_bodies_match_an_independent_reader(tmp_path: Path) -> None:
    p = tmp_path / "run.mcap"
    w = McapRunWriter(p)
    w.add_stream("tensions", _tension_desc())
    w.add_metadata("run", {"rig": "flat", "calibration_ids": {"lc": "abc"}})
    w.add_attachment("rig/flat.toml", b"[rig]\nname='flat'\n", "application/toml")
    for i in range(500):
        w.write(Reading("tensions", T0 + i * 10_000_000, {"T_c1_N": 40.0 + i, "raw_c1_counts": i}))
    w.write(
        Reading("tensions", T0 + 501 * 10_000_000, {"T_c1_N": math.nan, "raw_c1_counts": -1}, 16)
    )
    for i in range(7):
        w.write(
            Reading(
                "pose",
                T0 + i,
                {
                    "position_O_m": [0.5, 0.0, 0.3 + i],
                    "quaternion_xyzw": [0, 0, 0, 1],
                    "rms_px": 0.2,
                },
            )
        )
    w.write(
        Reading(
            "pose", T0 + 7, {"position_O_m": [1, 2, 3], "quaternion_wxyz": [0.5, 0.1, 0.2, 0.3]}
        )
    )
    w.write(Reading("image_cam0", T0, {"data": b"\xff\xd8\xff\xe0jpeg", "format": "jpeg"}))
    w.write(Reading("event", T0, {"message": "wind on", "level": "warning"}))
    w.finish()

    node = node_read(p)
    assert node["complete"] and node["error"] is None and node["bad_json"] == 0
    assert node["topics"] == {
        "/tensions": 501,
        "/pose": 8,
        "/pose_status": 8,
        "/image_cam0": 1,
        "/event": 1,
    }
    assert node["statistics"]["per_topic"] == node["topics"]
    assert node["schemas"] == {
        "/tensions": "cdpr.tensions",
        "/pose": "foxglove.PoseInFrame",
        "/pose_status": "cdpr.pose_status",
        "/image_cam0": "foxglove.CompressedImage",
        "/event": "foxglove.Log",
    }
    assert [m["name"] for m in node["metadata"]] == ["run"]
    assert node["attachments"] == [
        {"name": "rig/flat.toml", "media_type": "application/toml", "size": 18}
    ]

    rc = read_run(p)
    assert rc.complete and rc.error is None
    t, body = rc.messages["/tensions"][3]
    assert t == T0 + 3 * 10_000_000 and body == {"T_c1_N": 43.0, "raw_c1_counts": 3, "status": 0}
    assert rc.messages["/tensions"][-1][1]["T_c1_N"] is None  # NaN -> null (strict JSON)
    pose = rc.messages["/pose"][2][1]
    assert pose["pose"]["position"] == {"x": 0.5, "y": 0.0, "z": 2.3}
    assert pose["pose"]["orientation"]["w"] == 1.0 and set(pose) == {
        "timestamp",
        "frame_id",
        "pose",
    }
    assert pose["timestamp"] == {"sec": 1_700_000_000, "nsec": 2}
    assert rc.messages["/pose_status"][2] == (T0 + 2, {"rms_px": 0.2, "has_pose": 1, "status": 0})
    q = rc.messages["/pose"][7][1]["pose"]["orientation"]
    assert q == {"x": 0.1, "y": 0.2, "z": 0.3, "w": 0.5}
    img = rc.messages["/image_cam0"][0][1]
    assert base64.b64decode(img["data"]) == b"\xff\xd8\xff\xe0jpeg" and img["format"] == "jpeg"
    assert rc.messages["/event"][0][1]["level"] == 3  # foxglove.Log WARNING
    assert json.loads(rc.metadata["run"]["calibration_ids"]) == {"lc": "abc"}
    sch = rc.channels["/tensions"].schema
    assert sch["properties"]["T_c1_N"] == {
        "type": ["number", "null"],
        "description": "unit: N; null: missing (NaN)",
    }
    assert json.loads(rc.channels["/tensions"].metadata["units"]) == {"T_c1_N": "N"}


def test_a_chunk_is_on_disk_within_the_flush_interval_while_the_file_is_open(
    tmp_path: Path,
) -> None:
    """The python mcap writer alone keeps everything below 1 MiB in memory; ours closes chunks by
    time: a copy of the open file, read by the independent reader, has the old messages."""
    p = tmp_path / "open.mcap"
    w = McapRunWriter(p, chunk_size=1 << 20, flush_interval_s=0.2)
    w.add_stream("tensions", _tension_desc())
    n = 0
    t_end = time.monotonic() + 0.7
    while time.monotonic() < t_end:
        w.write(Reading("tensions", time.time_ns(), {"T_c1_N": 1.0, "raw_c1_counts": n}))
        n += 1
        w.maybe_flush()
        time.sleep(0.002)
    snap = tmp_path / "snap.mcap"
    shutil.copyfile(p, snap)
    w.finish()
    node = node_read(snap)
    assert not node["complete"] and node["error"] is None
    got = node["topics"].get("/tensions", 0)
    # at most one flush interval (0.2 s at <= 500 Hz -> <= 100 messages) plus one loop is missing
    assert n - 110 <= got < n, (got, n)
    assert node["chunks"] >= 2


@pytest.mark.parametrize("cut_fraction", [0.35, 0.6, 0.97])
def test_recover_salvages_every_complete_chunk(tmp_path: Path, cut_fraction: float) -> None:
    p = tmp_path / "full.mcap"
    w = McapRunWriter(p, chunk_size=4096)
    w.add_metadata("run", {"label": "x"})
    w.add_stream("tensions", _tension_desc())
    for i in range(5000):
        w.write(Reading("tensions", T0 + i, {"T_c1_N": float(i), "raw_c1_counts": i}))
    w.finish()
    data = p.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * cut_fraction)])
    ind = node_read(cut)  # what an independent streaming reader gets from the damaged file
    assert not ind["complete"]
    out, contents = recover_run(cut)
    assert out == tmp_path / "cut.recovered.mcap"
    assert not contents.complete and contents.error is not None
    node = node_read(out)
    assert node["complete"] and node["error"] is None
    n = node["topics"]["/tensions"]
    assert n == ind["topics"].get("/tensions", 0) == len(contents.messages["/tensions"])
    assert 0 < n <= 5000
    if cut_fraction < 0.9:
        assert n < 5000
    # the salvaged messages are the first n, intact
    rc = read_run(out)
    assert [b["raw_c1_counts"] for _, b in rc.messages["/tensions"]] == list(range(n))
    assert rc.metadata["run"] == {"label": "x"}
    assert rc.metadata["recovery"]["source_complete"] == "false"
    with pytest.raises(InputError, match="never overwritten"):
        recover_run(cut)


def test_recover_struct_error_cut_inside_a_record_header(tmp_path: Path) -> None:
    p = tmp_path / "a.mcap"
    w = McapRunWriter(p, chunk_size=2048)
    w.add_stream("tensions", _tension_desc())
    for i in range(2000):
        w.write(Reading("tensions", T0 + i, {"T_c1_N": 0.5, "raw_c1_counts": i}))
    w.flush()
    size_after_flush = p.stat().st_size
    w.finish()
    cut = tmp_path / "b.mcap"
    cut.write_bytes(p.read_bytes()[: size_after_flush + 5])  # 5 bytes of the next record header
    out, contents = recover_run(cut)
    assert len(contents.messages["/tensions"]) == 2000
    assert node_read(out)["topics"]["/tensions"] == 2000


def test_overwrite_refused_and_names(tmp_path: Path) -> None:
    p = tmp_path / "r.mcap"
    p.write_bytes(b"precious")
    with pytest.raises(InputError, match="never overwritten"):
        McapRunWriter(p)
    assert p.read_bytes() == b"precious"
    t = 1_763_800_000_123_000_000  # 2025-11-22 08:26:40 UTC
    assert run_name("TP 3 / alpha=5°", t) == "20251122_082640_TP-3-alpha-5"
    first = new_run_path(tmp_path, "tp", t)
    first.write_bytes(b"x")
    second = new_run_path(tmp_path, "tp", t)
    assert first.name == "20251122_082640_tp.mcap" and second.name == "20251122_082640_tp_2.mcap"


def test_not_an_mcap_file_is_a_clear_error(tmp_path: Path) -> None:
    p = tmp_path / "x.mcap"
    p.write_text("hello")
    with pytest.raises(CdprError, match="not an MCAP file"):
        read_run(p)
    with pytest.raises(CdprError, match="file not found"):
        read_run(tmp_path / "missing.mcap")


def test_can_raw_frames_read_back_exactly(tmp_path: Path) -> None:
    """The fast can_raw encoder gives the same JSON as the values (all frame shapes)."""
    import can

    from cdpr.daq.can_raw import raw_reading

    frames = [
        can.Message(
            arbitration_id=0x181, data=bytes(range(8)), is_extended_id=False, timestamp=1.0
        ),
        can.Message(arbitration_id=0x1FFFFFFF, data=b"\xff\x00\x7f", timestamp=2.25),
        can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False, timestamp=3.5),
        can.Message(is_error_frame=True, timestamp=4.0),
    ]
    readings = [raw_reading(m, T0 + i) for i, m in enumerate(frames)]
    readings.append(Reading("can_raw", T0 + 9, {"arbitration_id": 5, "data": b"\x01", "note": "x"}))
    p = tmp_path / "can.mcap"
    w = McapRunWriter(p)
    for r in readings:
        w.write(r)
    w.finish()
    assert node_read(p)["topics"] == {"/can_raw": 5}
    got = [b for _, b in read_run(p).messages["/can_raw"]]
    want = [
        {
            **{k: list(v) if isinstance(v, bytes) else v for k, v in r.values.items()},
            "status": r.status,
        }
        for r in readings[:4]
    ]
    # a reading with only some fields gets the defaults of the layout (docs/recording.md)
    want.append(
        {"arbitration_id": 5, "is_extended": 0, "is_remote": 0, "is_error_frame": 0, "is_fd": 0,
         "bitrate_switch": 0, "error_state_indicator": 0, "dlc": 1, "data": [1], "channel": None,
         "is_rx": 1, "t_bus_ns": T0 + 9, "note": "x", "status": 0}
    )  # fmt: skip
    assert got == want
    assert got[1]["data"] == [255, 0, 127] and got[1]["is_extended"] == 1 and got[3]["status"] == 8


def test_summary_indexes_serve_time_range_queries(tmp_path: Path) -> None:
    """Chunk and message indexes (written by our chunk writer) used by the mcap package's indexed
    reader: a time-range query returns exactly the messages in the range, in time order."""
    from mcap.reader import make_reader

    p = tmp_path / "idx.mcap"
    w = McapRunWriter(p, chunk_size=2048)
    for i in range(3000):  # times shuffled (coprime stride), two channels
        w.write(Reading("a" if i % 3 else "b", T0 + (i * 7919) % 3000, {"i": i}))
    w.finish()
    with p.open("rb") as fh:
        r = make_reader(fh)
        st = r.get_summary().statistics
        assert st.message_count == 3000 and sorted(st.channel_message_counts.values()) == [
            1000,
            2000,
        ]
        assert (st.message_start_time, st.message_end_time) == (T0, T0 + 2999)
        it = r.iter_messages(log_time_order=True, starting_at=T0 + 1500, ending_before=T0 + 2000)
        got = [m.log_time for _, _, m in it]
    assert got == list(range(T0 + 1500, T0 + 2000))
    assert node_read(p)["indexed"]["topics"] == {"/a": 2000, "/b": 1000}


def test_every_message_is_valid_against_its_channel_schema(tmp_path: Path) -> None:
    """A lost CAN frame (NaN tension), a failed camera pose (NaN position) and the recorded raw
    frames: each message validates against its own channel's JSON schema (jsonschema, Draft 2020-12
    validator), and the reader gives NaN back for the missing numbers."""
    import jsonschema
    import numpy as np
    from mcap.reader import make_reader

    from cdpr.daq.run_reader import open_run

    p = tmp_path / "run.mcap"
    w = McapRunWriter(p)
    w.add_stream("tensions", _tension_desc())
    w.write(Reading("tensions", T0, {"T_c1_N": 40.0, "raw_c1_counts": 7}))
    w.write(Reading("tensions", T0 + 1, {"T_c1_N": math.nan, "raw_c1_counts": -(2**31)}, 16))
    w.write(
        Reading(
            "pose",
            T0,
            {"position_O_m": [math.nan] * 3, "quaternion_wxyz": [math.nan] * 4, "flags": 4},
            4,
        )
    )
    w.write(Reading("event", T0, {"message": "point 1", "level": "info"}))
    w.finish()
    topics = []
    with p.open("rb") as fh:
        for schema, ch, msg in make_reader(fh).iter_messages():
            jsonschema.Draft202012Validator(json.loads(schema.data)).validate(json.loads(msg.data))
            topics.append(ch.topic)
    # the failed pose is no PoseInFrame message: only its status
    assert sorted(topics) == ["/event", "/pose_status", "/tensions", "/tensions"]
    with open_run(p) as run:
        t = run.table("/tensions")
        assert np.isnan(t["T_c1_N"][1]) and t["status"].tolist() == [0, 16]
        assert run.table("/pose")[["x_m", "qw"]].isna().all().all()
