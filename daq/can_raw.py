"""The ``can_raw`` stream: every CAN frame as it was on the bus, and its MCAP codec.

A frame is every field python-can gives a ``can.Message``:

``arbitration_id`` (int), ``is_extended`` (0/1: 29-bit id), ``is_remote`` (0/1: RTR), ``is_error_frame``
(0/1), ``is_fd`` (0/1), ``bitrate_switch`` (0/1), ``error_state_indicator`` (0/1), ``dlc`` (int),
``data`` (array of byte values, up to 64; a plot panel graphs ``.data[2]``), ``channel`` (the
interface's channel as python-can gives it: a string such as ``"can0"``, an integer, or null),
``is_rx`` (0/1: direction, 0 = transmitted by the logging node), ``t_bus_ns`` (the interface's
timestamp, integer ns: ``round(timestamp * 1e9)``) and ``status`` (8 = error frame).

The CAN driver registers the codec (:func:`register`): :func:`cdpr.daq.mcap_writer.register_stream_codec`
for the ``can_raw`` stream, and the driver's batch type for the writer's batch path, which formats a
batch of frames at once with numpy (:func:`encode_can_frames`) instead of one reading at a time.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .mcap_writer import FrameRecords, StreamCodec, register_frame_batch_type
from .source import STATUS_BAD_FRAME, FieldDescription, Reading, StreamDescription

#: the fields of a frame, in the order they are written
FIELDS = (
    "arbitration_id",
    "is_extended",
    "is_remote",
    "is_error_frame",
    "is_fd",
    "bitrate_switch",
    "error_state_indicator",
    "dlc",
    "data",
    "channel",
    "is_rx",
    "t_bus_ns",
)

DESCRIPTION = StreamDescription(
    {
        "arbitration_id": FieldDescription("", "int64"),
        "is_extended": FieldDescription("", "int64"),
        "is_remote": FieldDescription("", "int64"),
        "is_error_frame": FieldDescription("", "int64"),
        "is_fd": FieldDescription("", "int64"),
        "bitrate_switch": FieldDescription("", "int64"),
        "error_state_indicator": FieldDescription("", "int64"),
        "dlc": FieldDescription("", "int64"),
        "data": FieldDescription("", "bytes"),
        "channel": FieldDescription("", "str"),
        "is_rx": FieldDescription("", "int64"),
        "t_bus_ns": FieldDescription("ns", "int64"),
    },
    0.0,
    "every CAN frame as it was on the bus (t_bus_ns: the interface's timestamp)",
)


def t_bus_ns(timestamp_s: float) -> int:
    """The integer ns of a python-can timestamp (float seconds)."""
    return int(round(timestamp_s * 1e9))


def _channel(ch: Any) -> Any:
    return ch if ch is None or isinstance(ch, int | str) else str(ch)


def frame_values(msg: Any) -> dict[str, Any]:
    """The ``can_raw`` values of a ``can.Message``."""
    return {
        "arbitration_id": int(msg.arbitration_id),
        "is_extended": int(bool(msg.is_extended_id)),
        "is_remote": int(bool(msg.is_remote_frame)),
        "is_error_frame": int(bool(msg.is_error_frame)),
        "is_fd": int(bool(msg.is_fd)),
        "bitrate_switch": int(bool(msg.bitrate_switch)),
        "error_state_indicator": int(bool(msg.error_state_indicator)),
        "dlc": int(msg.dlc),
        "data": bytes(msg.data),
        "channel": _channel(msg.channel),
        "is_rx": int(bool(msg.is_rx)),
        "t_bus_ns": t_bus_ns(msg.timestamp),
    }


def raw_reading(msg: Any, t_ns: int, stream: str = "can_raw") -> Reading:
    """A ``can_raw`` reading of one ``can.Message``."""
    return Reading(stream, t_ns, frame_values(msg), STATUS_BAD_FRAME if msg.is_error_frame else 0)


def schema(stream: str) -> dict[str, Any]:
    flag = {"type": "integer", "minimum": 0, "maximum": 1}
    return {
        "type": "object",
        "title": f"cdpr.{stream}",
        "description": "A CAN frame as it was on the bus; time is the message log_time (ns since "
        "the Unix epoch), t_bus_ns the interface's timestamp.",
        "properties": {
            "arbitration_id": {"type": "integer", "minimum": 0, "description": "CAN identifier"},
            "is_extended": {**flag, "description": "1 for a 29-bit identifier"},
            "is_remote": {**flag, "description": "1 for a remote (RTR) frame"},
            "is_error_frame": flag,
            "is_fd": {**flag, "description": "1 for a CAN FD frame"},
            "bitrate_switch": flag,
            "error_state_indicator": flag,
            "dlc": {"type": "integer", "minimum": 0, "maximum": 64},
            "data": {
                "type": "array",
                "items": {"type": "integer", "minimum": 0, "maximum": 255},
                "maxItems": 64,
            },
            "channel": {"type": ["string", "integer", "null"]},
            "is_rx": {**flag, "description": "0 when the logging node transmitted the frame"},
            "t_bus_ns": {"type": "integer", "description": "interface timestamp, ns"},
            "status": {"type": "integer", "description": "8 = error frame"},
        },
        "required": list(FIELDS),
        "additionalProperties": True,
    }


def encode(r: Reading) -> bytes:
    """The JSON body of one ``can_raw`` reading (fields in :data:`FIELDS` order; a reading without
    ``dlc`` gets its data length, without ``is_rx`` a received frame, without ``t_bus_ns`` its
    ``t_ns``; extra values are kept)."""
    v = r.values
    data = bytes(v.get("data", b""))
    out: dict[str, Any] = {k: int(v.get(k, 0)) for k in FIELDS[:7]}
    out["dlc"] = int(v.get("dlc", len(data)))
    out["data"] = list(data)
    out["channel"] = _channel(v.get("channel"))
    out["is_rx"] = int(v.get("is_rx", 1))
    out["t_bus_ns"] = int(v.get("t_bus_ns", r.t_ns))
    for k, x in v.items():
        if k not in out:
            out[k] = x
    out["status"] = r.status
    return json.dumps(out, separators=(",", ":"), default=_jsonable).encode()


def _jsonable(x: Any) -> Any:
    if isinstance(x, bytes | bytearray):
        return list(x)
    tolist = getattr(x, "tolist", None)
    if tolist is not None:
        return tolist()
    raise TypeError(f"cannot encode {type(x).__name__} as JSON")


# -------------------------------------------------------------------------------------------------
# the hot path: a batch of classic 8-byte data frames formatted at once with numpy into fixed-width
# JSON bodies (numbers right-aligned in space-padded fields: still plain JSON, the same values as
# :func:`encode`)


_byte3 = np.array([list(f"{b:>3d}".encode()) for b in range(256)], dtype=np.uint8)
_pow10 = 10 ** np.arange(18, -1, -1, dtype=np.int64)


def template(channel: Any) -> tuple[str, dict[str, int]]:
    """The fixed-width body of a classic 8-byte data frame on ``channel`` (``#`` where the numbers
    go, right-aligned) and the positions of its fields (the reader parses it back)."""
    ch = json.dumps(_channel(channel))
    tpl = (
        '{"arbitration_id":#########,"is_extended":#,"is_remote":0,"is_error_frame":0,"is_fd":0,'
        '"bitrate_switch":0,"error_state_indicator":0,"dlc":8,'
        '"data":[###,###,###,###,###,###,###,###],"channel":' + ch + ',"is_rx":#,'
        '"t_bus_ns":###################,"status":0}'
    )
    pos = {
        "id": tpl.index("#"),
        "ext": tpl.index('"is_extended":') + len('"is_extended":'),
        "data": tpl.index('"data":[') + len('"data":['),
        "rx": tpl.index('"is_rx":') + len('"is_rx":'),
        "t": tpl.index('"t_bus_ns":') + len('"t_bus_ns":'),
    }
    return tpl, pos


def _decimal(v: Any, width: int) -> Any:
    """Right-aligned decimal digits of non-negative integers ``v`` (n,) below 10**width, as ASCII
    (n, width) uint8, leading zeros as spaces."""
    x = v.astype(np.int64)
    digits = np.empty((width, len(x)), np.uint8)
    for c in range(width - 1, -1, -1):  # integer division by a scalar: vectorised by numpy
        q = x // 10
        digits[c] = x - q * 10
        x = q
    digits += 48
    chars = digits.T
    lead = v[:, None] < _pow10[-width:]
    lead[:, -1] = False
    chars[lead] = 32
    return chars


def encode_columns(
    ids: Any, flags: Any, data: Any, lens: Any, t_bus: Any, channel: Any, is_rx: Any
) -> FrameRecords:
    """Bodies of frames given as columns: ``flags`` bit 0 extended, 1 error, 2 remote, 3 FD,
    ``data`` (n, >= 8) uint8, ``lens`` data lengths, ``t_bus`` int64 ns, ``channel`` one value for
    the batch, ``is_rx`` (n,) 0/1; frames outside the fast layout have ``ok`` False."""
    ids = np.asarray(ids, np.int64)
    flags = np.asarray(flags, np.int64)
    t_bus = np.asarray(t_bus, np.int64)
    ok = (
        (np.asarray(lens) == 8)
        & ((flags & 0b1110) == 0)  # not error, remote or FD
        & (ids >= 0)
        & (ids < 1_000_000_000)
        & (t_bus >= 0)
    )
    tpl, pos = template(channel)
    k = int(ok.sum())
    bodies = np.empty((k, len(tpl)), np.uint8)
    bodies[:] = np.frombuffer(tpl.replace("#", " ").encode(), np.uint8)
    if k:
        sel = ok if k < len(ok) else slice(None)
        bodies[:, pos["id"] : pos["id"] + 9] = _decimal(ids[sel], 9)
        chars = _byte3[np.asarray(data)[sel, :8]]  # (k, 8, 3)
        for j in range(8):
            a = pos["data"] + 4 * j
            bodies[:, a : a + 3] = chars[:, j]
        bodies[:, pos["ext"]] = 48 + (flags[sel] & 1)
        bodies[:, pos["rx"]] = 48 + np.asarray(is_rx, np.int64)[sel]
        bodies[:, pos["t"] : pos["t"] + 19] = _decimal(t_bus[sel], 19)
    return FrameRecords(ok, bodies)


def encode_can_frames(messages: Sequence[Any]) -> FrameRecords:
    """JSON bodies of ``can.Message`` frames, formatted with numpy (see :func:`encode_columns`):
    classic 8-byte data frames on the first frame's channel qualify, the others are marked."""
    n = len(messages)
    ids = np.array([m.arbitration_id for m in messages], dtype=np.int64)
    ts = np.array([m.timestamp for m in messages], dtype=np.float64)
    flags = np.array(
        [
            m.is_extended_id | (m.is_error_frame << 1) | (m.is_remote_frame << 2) | (m.is_fd << 3)
            for m in messages
        ],
        dtype=np.int64,
    )
    datas = [bytes(m.data) for m in messages]
    lens = np.fromiter(map(len, datas), np.int64, n)
    dlc8 = np.fromiter((m.dlc == 8 for m in messages), bool, n)
    ch0 = _channel(messages[0].channel) if n else None
    same_ch = np.fromiter((_channel(m.channel) == ch0 for m in messages), bool, n)
    rx = np.fromiter((bool(m.is_rx) for m in messages), np.int64, n)
    t_bus = np.rint(ts * 1e9)
    fits = (lens == 8) & dlc8 & same_ch & (t_bus >= 0) & (t_bus < 9e18)
    data = np.zeros((n, 8), np.uint8)
    if fits.any():
        data[fits] = np.frombuffer(
            b"".join([d for d, f in zip(datas, fits.tolist(), strict=True) if f]), np.uint8
        ).reshape(-1, 8)
    lens = np.where(fits, lens, -1)
    t64 = np.where(fits, t_bus, 0).astype(np.int64)
    return encode_columns(ids, flags, data, lens, t64, ch0, rx)


# -------------------------------------------------------------------------------------------------
# frame blocks: the bulk layout (``cdpr import``): frames as column blocks
# (:mod:`cdpr.daq.column_blocks`, channel metadata ``layout = "can_frames"``)

#: the ``layout`` of a channel of frame blocks
BLOCK_LAYOUT = "can_frames"
#: the 0/1 fields of a frame, each a uint8 column of a frame block
FLAG_FIELDS = FIELDS[1:7]


def block_columns(
    arbitration_id: Any,
    flags: dict[str, Any],
    dlc: Any,
    data: Any,
    length: Any,
    channel_index: Any,
    is_rx: Any,
    t_bus: Any,
) -> dict[str, np.ndarray]:
    """The columns of frames in a frame block (the writer adds ``status``): ``arbitration_id``
    int64; each of :data:`FLAG_FIELDS` (``flags[name]``, n bools) uint8; ``dlc``, ``length`` (bytes
    of data) uint8; ``data_0`` ... ``data_<w-1>`` uint8 for the widest frame (w bytes; bytes past a
    frame's length 0); ``channel`` uint8 indexes into the block's ``values`` table; ``is_rx``
    uint8; ``t_bus_ns`` int64 (the interface's timestamp)."""
    length = np.asarray(length, np.int64)
    n = len(length)
    data = np.asarray(data, np.uint8).reshape(n, -1)
    w = int(length.max()) if n else 0
    cols: dict[str, np.ndarray] = {"arbitration_id": np.asarray(arbitration_id, np.int64)}
    for name in FLAG_FIELDS:
        cols[name] = np.asarray(flags[name], bool).view(np.uint8)
    cols["dlc"] = np.asarray(dlc, np.int64).astype(np.uint8)
    cols["length"] = length.astype(np.uint8)
    for j in range(w):
        cols[f"data_{j}"] = np.ascontiguousarray(data[:, j])
    cols["channel"] = np.asarray(channel_index, np.int64)  # stored narrow when it fits
    cols["is_rx"] = np.asarray(is_rx, bool).view(np.uint8)
    cols["t_bus_ns"] = np.asarray(t_bus, np.int64)
    return cols


def block_columns_of(fields: Sequence[str]) -> set[str]:
    """The frame-block columns that give the per-frame ``fields`` (``data``: every ``data_<j>``
    and ``length``)."""
    out = {f for f in fields if f != "data"}
    if "data" in fields:
        out |= {"length", *(f"data_{j}" for j in range(64))}
    return out


def frames_from_blocks(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The per-frame columns (the fields of :data:`FIELDS` and ``status``, as the per-frame JSON
    layout reads back: 0/1 and counts int64, ``data`` bytes, ``channel`` as recorded) of decoded
    frame blocks (:func:`cdpr.daq.column_blocks.decode_blocks`; with some columns only: the
    fields they give)."""
    out: dict[str, np.ndarray] = {"t_ns": cols["t_ns"]}
    for name in (*FIELDS, "status"):
        if name == "data":
            if "length" in cols:
                out["data"] = _frame_bytes(cols)
        elif name == "channel":
            if "channel" in cols:
                out["channel"] = cols["channel"]
        elif name in cols:
            out[name] = cols[name].astype(np.int64)
    return out


def _frame_bytes(cols: dict[str, np.ndarray]) -> np.ndarray:
    """``bytes`` per frame: the first ``length`` of ``data_0``, ``data_1``, ..."""
    n = len(cols["t_ns"])
    length = cols["length"].astype(np.int64)
    w = 0
    while f"data_{w}" in cols:
        w += 1
    if np.any(length > w):
        raise ValueError(f"a frame's length {int(length.max())} is past its {w} data columns")
    rows = np.zeros((n, w), np.uint8)
    for j in range(w):
        rows[:, j] = cols[f"data_{j}"]
    flat = rows.tobytes()
    data = np.empty(n, object)
    data[:] = [flat[i * w : i * w + k] for i, k in enumerate(length.tolist())]
    return data


def frame_rows(cols: dict[str, np.ndarray]) -> list[tuple[int, dict[str, Any]]]:
    """(t_ns, values) per frame of decoded frame blocks, the values as the per-frame JSON body
    has them (``data`` a list of byte values; :func:`encode`)."""
    f = frames_from_blocks(cols)
    t = f.pop("t_ns").tolist()
    lists = {k: (v.tolist() if k != "data" else [list(d) for d in v]) for k, v in f.items()}
    names = [*FIELDS, "status"]
    return [(t[i], {k: lists[k][i] for k in names}) for i in range(len(t))]


def codec(stream: str, description: StreamDescription | None) -> Any:
    """The ``can_raw`` stream codec (registered by the CAN driver): per-frame JSON messages, or
    frame blocks (``layout`` :data:`BLOCK_LAYOUT`) for a stream added with ``blocks=True``."""
    return StreamCodec(
        f"cdpr.{stream}", schema(stream), encode, encode_can_frames, block_layout=BLOCK_LAYOUT
    )


def register(batch_type: type, register_codec: Callable[..., None]) -> None:
    """Register the codec for ``can_raw`` streams and ``batch_type`` (the driver's batch of
    frames) for the writer's batch path."""
    register_codec("can_raw", codec)
    register_frame_batch_type(batch_type)
