"""An independent reader of column-block messages (docs/recording.md, "Column blocks"), written from
the documented layout with the standard library only (json, base64, struct), for tests that read run
files with the ``mcap`` package's own reader instead of ``open_run``."""

from __future__ import annotations

import base64
import json
import struct
from typing import Any

_FMT = {"<i8": "q", "<f8": "d", "|u1": "B", "<i4": "i"}
_FLAGS = ("is_extended", "is_remote", "is_error_frame", "is_fd", "bitrate_switch",
          "error_state_indicator")  # fmt: skip


def block_rows(body: bytes) -> list[dict[str, Any]]:
    """The samples of one block message body as dicts (``t_ns`` and every column)."""
    doc = json.loads(body)
    n = doc["count"]
    raw = base64.b64decode(doc["data"])
    cols: dict[str, tuple[Any, ...]] = {}
    pos = 0
    for name, dt in zip(doc["columns"], doc["dtypes"], strict=True):
        fmt = "<" + _FMT[dt] * n
        cols[name] = struct.unpack_from(fmt, raw, pos)
        pos += struct.calcsize(fmt)
    assert pos == len(raw), "block data length"
    for name, table in doc.get("values", {}).items():  # indexes into a table of values
        cols[name] = tuple(table[i] for i in cols[name])
    return [{k: v[i] for k, v in cols.items()} for i in range(n)]


def frame_row(row: dict[str, Any]) -> dict[str, Any]:
    """A row of a ``can_frames`` block as the per-frame JSON body has it (``data`` the first
    ``length`` of ``data_0`` ... as a list)."""
    out = {"arbitration_id": row["arbitration_id"], **{k: row[k] for k in _FLAGS}}
    out["dlc"] = row["dlc"]
    out["data"] = [row[f"data_{j}"] for j in range(row["length"])]
    out |= {"channel": row["channel"], "is_rx": row["is_rx"], "t_bus_ns": row["t_bus_ns"]}
    out["status"] = row["status"]
    return out


def _rows(channel: Any, body: bytes) -> list[dict[str, Any]]:
    rows = block_rows(body)
    if channel.metadata.get("layout") == "can_frames":
        return [{"t_ns": r["t_ns"], **frame_row(r)} for r in rows]
    return rows


def is_block_channel(channel: Any) -> bool:
    return channel.metadata.get("storage") == "column_blocks"


def samples(reader: Any, topic: str) -> list[dict[str, Any]]:
    """Every sample of ``topic`` read with an ``mcap`` reader (``make_reader(fh)``): the rows of its
    column blocks, or its per-sample JSON messages (``t_ns`` from the log time)."""
    out: list[dict[str, Any]] = []
    for _, channel, msg in reader.iter_messages([topic], log_time_order=True):
        if is_block_channel(channel):
            out += _rows(channel, msg.data)
        else:
            out.append({"t_ns": msg.log_time, **json.loads(msg.data)})
    return out


def messages(reader: Any) -> dict[str, list[tuple[int, dict[str, Any]]]]:
    """topic -> [(t_ns, values)] of every message of every topic, a column block's rows one by
    one."""
    out: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    for _, channel, msg in reader.iter_messages(log_time_order=True):
        rows = out.setdefault(channel.topic, [])
        if is_block_channel(channel):
            rows += [(r.pop("t_ns"), r) for r in _rows(channel, msg.data)]
        else:
            rows.append((msg.log_time, json.loads(msg.data)))
    return out
