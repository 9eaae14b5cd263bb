"""Helpers (no tests) shared by the recorder/storage/CLI tests: the independent MCAP reader and sources.

The independent reader is the TypeScript reference implementation (npm ``@mcap/core``) run by node
from ``tools/mcap-check`` (installed by ``make install``).  It is a different implementation from the
python ``mcap`` package the recorder uses.
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

from cdpr.daq.source import FieldDescription, Reading, Source, StreamDescription

ROOT = Path(__file__).resolve().parents[1]
MCAP_CHECK = ROOT / "tools" / "mcap-check" / "mcap_check.js"


def node_read(path: str | Path) -> dict[str, Any]:
    """Summary of an MCAP file by @mcap/core: topics (message counts), samples (per column-block
    topic), schemas, metadata, attachments, chunks, complete (valid footer), statistics, error."""
    res = subprocess.run(
        ["node", "--single-threaded", str(MCAP_CHECK), str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["bad_blocks"] == 0, out  # every column block decodes, its times rise
    if out["complete"]:  # the summary's chunk and message indexes agree with the data section
        assert out["indexed"] is not None and out["indexed"]["topics"] == out["topics"], out
        assert out["indexed"]["chunk_indexes"] == out["chunks"], out
    return out


class VirtualCanRaw(Source):
    """A minimal raw-frame source on a python-can virtual bus (test-side, independent of the
    project's CAN driver): one ``frames`` reading per frame with the id, the data bytes and a
    counter taken from byte 0..3 of the payload."""

    def __init__(self, name: str, channel: str, stream: str = "frames") -> None:
        super().__init__(name)
        self.channel = channel
        self.stream = stream
        self.bus: Any = None

    def describe(self) -> dict[str, StreamDescription]:
        return {
            self.stream: StreamDescription(
                {
                    "arbitration_id": FieldDescription("", "int64"),
                    "data": FieldDescription("", "bytes"),
                    "seq": FieldDescription("", "int64"),
                },
                1000.0,
                "test frames",
            )
        }

    def _open(self) -> None:
        import can

        self.bus = can.Bus(
            interface="virtual", channel=self.channel, receive_own_messages=False, bitrate=1000000
        )

    def _close(self) -> None:
        self.bus.shutdown()

    def _read(self, timeout_s: float) -> list[Reading]:
        out: list[Reading] = []
        m = self.bus.recv(timeout_s)
        while m is not None:
            out.append(
                Reading(
                    self.stream,
                    time.time_ns(),
                    {
                        "arbitration_id": m.arbitration_id,
                        "data": bytes(m.data),
                        "seq": int.from_bytes(bytes(m.data[:4]), "little"),
                    },
                )
            )
            if len(out) >= 500:
                break
            m = self.bus.recv(0)
        return out


class CountingSource(Source):
    """Produces ``batch`` readings of stream ``stream`` per read as fast as it is called, numbered
    0, 1, 2, ... (the truth: ``produced``); stops after ``total``."""

    def __init__(self, name: str, total: int, batch: int = 100, stream: str = "count") -> None:
        super().__init__(name)
        self.total = total
        self.batch = batch
        self.stream = stream
        self.produced = 0

    def describe(self) -> dict[str, StreamDescription]:
        return {self.stream: StreamDescription({"i": FieldDescription("", "int64")}, 0.0, "")}

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    @property
    def exhausted(self) -> bool:
        return self.produced >= self.total

    def _read(self, timeout_s: float) -> list[Reading]:
        k = min(self.batch, self.total - self.produced)
        now = time.time_ns()
        out = [Reading(self.stream, now + j, {"i": self.produced + j}) for j in range(k)]
        self.produced += k
        return out
