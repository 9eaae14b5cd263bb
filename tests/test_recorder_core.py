"""The recorder on real transports: a python-can virtual bus, bounded queues with drop counts, failing
drivers, duplicate stream names, the live view.  Files are checked with the independent reader."""

from __future__ import annotations

import io
import json
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from test_recorder_helpers import CountingSource, VirtualCanRaw, node_read

from cdpr.analysis.errors import InputError
from cdpr.daq.live import LiveView, tension_warnings
from cdpr.daq.mcap_io import read_run
from cdpr.daq.recorder import Attachment, Recorder, RecorderOptions
from cdpr.daq.source import (
    STATUS_SLACK,
    FieldDescription,
    Reading,
    Source,
    StreamDescription,
)


def _send_frames(channel: str, n: int, rate_hz: float) -> None:
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False, bitrate=1000000)
    try:
        t0 = time.perf_counter()
        for i in range(n):
            bus.send(
                can.Message(arbitration_id=0x181 + i % 4, data=i.to_bytes(4, "little") + b"\0" * 4)
            )
            due = t0 + (i + 1) / rate_hz
            d = due - time.perf_counter()
            if d > 0.0005:
                time.sleep(d)
    finally:
        bus.shutdown()


def test_every_frame_of_a_virtual_bus_is_recorded_in_order(tmp_path: Path) -> None:
    ch = f"rec-{uuid.uuid4().hex}"
    src = VirtualCanRaw("can0", ch)
    src.open()  # a virtual bus only delivers to buses open when the frame is sent
    p = tmp_path / "run.mcap"
    rec = Recorder(
        [src],
        p,
        metadata={"label": "vbus", "software_version": "test"},
        attachments=[Attachment("rig/r.toml", b"[rig]\n", "application/toml")],
        options=RecorderOptions(flush_interval_s=0.2),
    )
    rec.start()
    n = 6000
    _send_frames(ch, n, 4000.0)
    time.sleep(0.3)
    rec.stop()
    node = node_read(p)
    assert node["complete"] and node["error"] is None and node["bad_json"] == 0
    assert node["topics"]["/frames"] == n
    assert (
        node["schemas"]["/frames"] == "cdpr.frames" and node["schemas"]["/event"] == "foxglove.Log"
    )
    assert node["topics"]["/recorder"] >= 1
    assert [m["name"] for m in node["metadata"]] == ["run", "run_end"]
    assert node["attachments"][0]["name"] == "rig/r.toml"
    assert node["chunks"] >= 3  # chunks closed by time, not only at finish
    rc = read_run(p)
    seqs = [b["seq"] for _, b in rc.messages["/frames"]]
    assert seqs == list(range(n))
    assert rc.messages["/frames"][5][1]["data"] == [5, 0, 0, 0, 0, 0, 0, 0]
    end = rc.metadata["run_end"]
    assert end["dropped_total"] == "0" and json.loads(end["message_counts"])["frames"] == n
    last = rc.messages["/recorder"][-1][1]
    assert last["can0_read"] == n and last["can0_dropped"] == 0
    assert rc.metadata["run"]["sources"] == "can0"


def test_a_full_queue_drops_and_counts_exactly(tmp_path: Path) -> None:
    """A source far faster than a tiny queue: written + dropped == produced (the truth)."""
    src = CountingSource("fast", total=60_000, batch=1000)
    p = tmp_path / "drop.mcap"
    rec = Recorder([src], p, options=RecorderOptions(queue_readings=1500))
    rec.start()
    rec.wait(20.0)  # until the source is exhausted
    rec.stop()
    st = rec.status()
    node = node_read(p)
    written = node["topics"].get("/count", 0)
    assert rec.dropped > 0
    assert written + rec.dropped == src.produced == 60_000
    assert st.sources["fast"].dropped == rec.dropped
    rc = read_run(p)
    assert json.loads(rc.metadata["run_end"]["sources"])["fast"]["dropped"] == rec.dropped
    ids = [b["i"] for _, b in rc.messages["/count"]]
    assert ids == sorted(ids) and len(set(ids)) == written  # whole batches dropped, no duplicates


class FlakySource(Source):
    """Fails on its 2nd and 3rd read, then works: the recorder must log and carry on."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.calls = 0
        self.opens = 0

    def describe(self) -> dict[str, StreamDescription]:
        return {"flaky": StreamDescription({"k": FieldDescription("", "int64")}, 0.0)}

    def _open(self) -> None:
        self.opens += 1

    def _close(self) -> None:
        pass

    def _read(self, timeout_s: float) -> list[Reading]:
        self.calls += 1
        if self.calls in (2, 3):
            raise OSError("device unplugged")
        time.sleep(0.01)
        return [Reading("flaky", time.time_ns(), {"k": self.calls})] if self.calls < 30 else []


def test_a_failing_driver_is_logged_and_the_recording_goes_on(tmp_path: Path) -> None:
    src = FlakySource("flaky")
    p = tmp_path / "flaky.mcap"
    with Recorder([src], p) as rec:
        time.sleep(2.0)  # backoff 0.2 s + 0.4 s, then 26 reads of 10 ms
    assert rec.status().sources["flaky"].errors == 2
    rc = read_run(p)
    ev = [b for _, b in rc.messages["/event"] if b["name"] != "fault"]
    assert sum("device unplugged" in b["message"] for b in ev) == 2
    assert [b["level"] for b in ev if "unplugged" in b["message"]] == [4, 4]
    # the two errors are also faults: events naming the source, and the run's summary
    faults = [b for _, b in rc.messages["/event"] if b["name"] == "fault"]
    assert sum(b["fault"] == "errors" for b in faults) >= 1
    assert all(b["source"] == "flaky" for b in faults)
    assert rc.metadata["run_end"]["faults"] == '["source flaky: 2 driver/bus errors"]'
    assert [b["k"] for _, b in rc.messages["/flaky"]] == [1, *range(4, 30)]
    assert src.opens >= 2  # closed and reopened after the error


def test_same_stream_from_two_sources_gets_two_topics(tmp_path: Path) -> None:
    a, b = CountingSource("bus_a", 50, 10, "can_raw"), CountingSource("bus_b", 70, 10, "can_raw")
    p = tmp_path / "two.mcap"
    rec = Recorder([a, b], p)
    rec.start()
    rec.wait(10.0)
    rec.stop()
    node = node_read(p)
    assert node["topics"]["/bus_a/can_raw"] == 50 and node["topics"]["/bus_b/can_raw"] == 70
    assert "/can_raw" not in node["topics"]


def test_bad_options_and_existing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="flush_interval_s"):
        RecorderOptions(flush_interval_s=5.0)
    p = tmp_path / "x.mcap"
    p.write_bytes(b"keep")
    with pytest.raises(InputError, match="never overwritten"):
        Recorder([CountingSource("c", 1)], p).start()
    assert p.read_bytes() == b"keep"


def test_live_view_refreshes_at_least_twice_a_second_and_warns(tmp_path: Path) -> None:
    from rich.console import Console

    class Tensions(CountingSource):
        def _read(self, timeout_s: float) -> list[Reading]:
            time.sleep(0.01)
            self.produced += 1
            return [
                Reading(
                    "tensions",
                    time.time_ns(),
                    {"T_c1_N": 10.0, "T_c2_N": 150.0, "T_c3_N": 320.0},
                    STATUS_SLACK,
                )
            ]

    buf = io.StringIO()
    console = Console(file=buf, force_terminal=True, width=160)
    rec = Recorder([Tensions("lc", 10**9)], tmp_path / "live.mcap")
    rec.start()
    lv = LiveView(rec, refresh_hz=4.0, t_min_N=[35.0] * 3, t_max_N=[300.0] * 3, console=console)
    with lv:
        time.sleep(1.6)
    rec.stop()
    assert lv.frames >= 1 + 2 * 1  # >= 2 Hz over >= 1 s, plus the first and last frames
    out = buf.getvalue()
    assert "tensions" in out and "c1 slack" in out and "c3 saturated" in out
    assert "c2" not in tension_warnings({"T_c2_N": 150.0}, [35.0], [300.0])


def test_stop_is_prompt_and_idempotent(tmp_path: Path) -> None:
    ch = f"rec-{uuid.uuid4().hex}"
    src = VirtualCanRaw("can0", ch)
    rec = Recorder([src], tmp_path / "s.mcap")
    rec.start()
    t = threading.Timer(0.3, rec.request_stop, args=("test",))
    t.start()
    t0 = time.monotonic()
    rec.wait()
    path = rec.stop()
    assert time.monotonic() - t0 < 2.0
    assert rec.stop() == path
    assert node_read(path)["complete"]
    assert read_run(path).metadata["run_end"]["stop_reason"] == "test"


def test_driver_log_records_become_events_rate_limited(tmp_path: Path, capfd) -> None:
    import logging

    log = logging.getLogger("cdpr.daq.test_driver")

    class Chatty(CountingSource):
        def _read(self, timeout_s: float) -> list[Reading]:
            if self.produced == 0:
                for i in range(30):
                    log.warning("bus error %d", i)
            return super()._read(timeout_s)

    rec = Recorder([Chatty("chatty", 10, 10)], tmp_path / "log.mcap")
    rec.start()
    rec.wait(5.0)
    rec.stop()
    assert logging.getLogger("cdpr.daq").handlers == []  # removed again
    events = [b for _, b in read_run(tmp_path / "log.mcap").messages["/event"]]
    logged = [e for e in events if e["message"].startswith("bus error")]
    assert [e["message"] for e in logged] == [f"bus error {i}" for i in range(20)]
    assert all(e["level"] == 3 and e["name"] == "cdpr.daq.test_driver" for e in logged)
    assert "bus error" not in capfd.readouterr().err  # recorded, not printed


def test_a_source_that_cannot_describe_itself_leaves_no_file(tmp_path: Path) -> None:
    class Broken(CountingSource):
        def describe(self) -> dict[str, StreamDescription]:
            raise InputError("sources.broken: no DBC")

    p = tmp_path / "none.mcap"
    with pytest.raises(InputError, match="no DBC"):
        Recorder([Broken("broken", 1)], p).start()
    assert not p.exists()
