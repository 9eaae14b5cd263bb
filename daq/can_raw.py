"""The ``can_raw`` stream: every CAN frame as it was on the bus, its layouts and its MCAP codec.

A frame is every field python-can gives a ``can.Message``:

``arbitration_id`` (int), ``is_extended`` (0/1: 29-bit id), ``is_remote`` (0/1: RTR), ``is_error_frame``
(0/1), ``is_fd`` (0/1), ``bitrate_switch`` (0/1), ``error_state_indicator`` (0/1), ``dlc`` (int),
``data`` (array of byte values, up to 64), ``channel`` (the interface's channel as python-can gives
it: a string such as ``"can0"``, an integer, or null), ``is_rx`` (0/1: direction, 0 = transmitted
by the logging node), ``t_bus_ns`` (the interface's timestamp, integer ns: ``round(timestamp *
1e9)``) and ``status`` (8 = a bad frame: an error frame, a frame no classic bus carries as logged,
or a load-cell frame the decoder could not use).

Every run cdpr writes (``record``, ``simulate``, a replay, ``import``) stores ``/can_raw`` as frame
blocks (:func:`frame_block`, channel metadata ``layout = "can_frames"``): the frames of a
:class:`CanFrameBatch` (the batch type of the CAN sources, from a live bus or a log) as columns.
One JSON message per frame (:func:`encode`) is what runs from before the blocks hold and what a
stream added without a description gets; every reader reads both.
"""

from __future__ import annotations

import bisect
import json
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from .can_frames import BRS, ERROR, ESI, EXTENDED, FD, ODD, REMOTE, RX, FrameColumns, concat_frames
from .mcap_writer import StreamCodec, register_frame_batch_type, register_stream_codec
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


def _channel(ch: Any) -> Any:
    return ch if ch is None or isinstance(ch, int | str) else str(ch)


def frame_values(frames: FrameColumns, i: int) -> dict[str, Any]:
    """The ``can_raw`` values of frame ``i``."""
    f = int(frames.flags[i])
    return {
        "arbitration_id": int(frames.arbitration_id[i]),
        "is_extended": int(bool(f & EXTENDED)),
        "is_remote": int(bool(f & REMOTE)),
        "is_error_frame": int(bool(f & ERROR)),
        "is_fd": int(bool(f & FD)),
        "bitrate_switch": int(bool(f & BRS)),
        "error_state_indicator": int(bool(f & ESI)),
        "dlc": int(frames.dlc[i]),
        "data": frames.data[i, : int(frames.length[i])].tobytes(),
        "channel": _channel(frames.channel[i]),
        "is_rx": int(bool(f & RX)),
        "t_bus_ns": int(round(float(frames.t_s[i]) * 1e9)),
    }


def frame_status(frames: FrameColumns, bad: Any = None) -> np.ndarray:
    """The ``status`` of frames: :data:`~cdpr.daq.source.STATUS_BAD_FRAME` for an error frame, an
    odd one (:data:`~cdpr.daq.can_frames.ODD`) and the ``bad`` ones (the load-cell frames the
    decoder could not use), else 0."""
    flagged = (frames.flags & (ERROR | ODD)) != 0
    if bad is not None:
        flagged = flagged | np.asarray(bad, bool)
    return np.where(flagged, STATUS_BAD_FRAME, 0).astype(np.int64)


def raw_reading(msg: Any, t_ns: int, stream: str = "can_raw") -> Reading:
    """A ``can_raw`` reading of one ``can.Message``."""
    frames = FrameColumns.from_messages([msg])
    return Reading(stream, t_ns, frame_values(frames, 0), int(frame_status(frames)[0]))


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
# runs written before the frame blocks: the recorder's batch path wrote classic 8-byte data frames
# as fixed-width JSON bodies (numbers right-aligned in space-padded fields: plain JSON); the reader
# (:mod:`cdpr.daq.run_reader`) parses those rows back by position with this template


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


# -------------------------------------------------------------------------------------------------
# frame blocks: the bulk layout (``cdpr import``): frames as column blocks
# (:mod:`cdpr.daq.column_blocks`, channel metadata ``layout = "can_frames"``)

#: the ``layout`` of a channel of frame blocks
BLOCK_LAYOUT = "can_frames"
#: the 0/1 fields of a frame, each a uint8 column of a frame block
FLAG_FIELDS = FIELDS[1:7]


def frame_block(
    frames: FrameColumns, t_ns: Any, bad: Any = None
) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, dict[str, list[Any]]]:
    """``(t_ns, columns, status, values)`` of frames for a frame block
    (:meth:`~cdpr.daq.mcap_writer.McapRunWriter.write_columns`): ``arbitration_id`` int64; each of
    :data:`FLAG_FIELDS` uint8; ``dlc``, ``length`` (bytes of data) uint8; ``data_0`` ...
    ``data_<w-1>`` uint8 for the widest frame (w bytes; bytes past a frame's length 0);
    ``channel`` indexes into ``values["channel"]`` (the distinct channels as python-can gives them:
    a name, a number or None); ``is_rx`` uint8; ``t_bus_ns`` int64 (the interface's timestamp);
    ``status`` (:func:`frame_status`)."""
    fl = frames.flags
    length = frames.length.astype(np.int64)
    n = len(length)
    w = int(length.max()) if n else 0
    cols: dict[str, np.ndarray] = {"arbitration_id": frames.arbitration_id.astype(np.int64)}
    for name, bit in zip(FLAG_FIELDS, (EXTENDED, REMOTE, ERROR, FD, BRS, ESI), strict=True):
        cols[name] = ((fl & bit) != 0).view(np.uint8)
    cols["dlc"] = frames.dlc.astype(np.uint8)
    cols["length"] = length.astype(np.uint8)
    for j in range(w):
        cols[f"data_{j}"] = np.ascontiguousarray(frames.data[:, j])
    codes, table = _channel_codes(frames.channel)
    cols["channel"] = codes  # stored narrow when it fits
    cols["is_rx"] = ((fl & RX) != 0).view(np.uint8)
    cols["t_bus_ns"] = frames.t_bus_ns
    return np.asarray(t_ns, np.int64), cols, frame_status(frames, bad), {"channel": table}


def _channel_codes(channel: np.ndarray) -> tuple[np.ndarray, list[Any]]:
    """Indexes (n,) into a table of the distinct channels of a block of frames."""
    n = len(channel)
    if n == 0:
        return np.zeros(0, np.int64), []
    ch0 = channel[0]
    if ch0 is not None and bool(np.all(channel == ch0)):  # one channel (the usual log)
        return np.zeros(n, np.int64), [_channel(ch0)]
    import pandas as pd

    codes, uniq = pd.factorize(channel, use_na_sentinel=False)
    return codes.astype(np.int64), [
        None if u is None or u != u else _channel(u) for u in uniq.tolist()
    ]


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
        col = cols[f"data_{j}"]
        if col.dtype.kind == "f":  # blocks of narrower frames lack the column: NaN, past length
            col = np.nan_to_num(col, nan=0.0)
        rows[:, j] = col
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


def frame_block_of_readings(
    readings: Sequence[Reading],
) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, dict[str, Any]]:
    """:func:`frame_block` of ``can_raw`` readings (a source that gives readings, not batches;
    their own status kept)."""
    n = len(readings)
    v = [r.values for r in readings]
    datas = [bytes(x.get("data", b"")) for x in v]
    w = max([8, *map(len, datas)])
    flags = np.array(
        [sum(bit * bool(x.get(name, 0)) for name, bit in _FLAG_BITS) | RX * bool(x.get("is_rx", 1))
         for x in v], np.uint8,
    )  # fmt: skip
    ch = np.empty(n, object)
    ch[:] = [x.get("channel") for x in v]
    frames = FrameColumns(
        np.array([x.get("t_bus_ns", r.t_ns) * 1e-9 for x, r in zip(v, readings, strict=True)]),
        np.array([x.get("arbitration_id", 0) for x in v], np.int64),
        flags,
        np.array([x.get("dlc", len(d)) for x, d in zip(v, datas, strict=True)], np.int64),
        np.frombuffer(b"".join(d.ljust(w, b"\0") for d in datas), np.uint8).reshape(n, w).copy(),
        np.array(list(map(len, datas)), np.int64),
        ch,
        np.zeros(n, np.int64),
    )
    t, cols, _, values = frame_block(frames, [r.t_ns for r in readings])
    cols["t_bus_ns"] = np.array([x.get("t_bus_ns", r.t_ns) for x, r in zip(v, readings, strict=True)],
                                np.int64)  # exact, not through a float  # fmt: skip
    return t, cols, np.array([r.status for r in readings], np.int64), values


_FLAG_BITS = tuple(zip(FLAG_FIELDS, (EXTENDED, REMOTE, ERROR, FD, BRS, ESI), strict=True))


def codec(stream: str, description: StreamDescription | None) -> Any:
    """The ``can_raw`` stream codec (registered by :func:`register`): frame blocks (``layout``
    :data:`BLOCK_LAYOUT`) for a stream added with the frame description (every run cdpr writes;
    frame batches and single readings alike), else one JSON message per reading (:func:`encode`:
    a stream added without a description, or with other fields)."""
    frames = description is not None and set(description.fields) == set(FIELDS)
    return StreamCodec(
        f"cdpr.{stream}",
        schema(stream),
        encode,
        block_layout=BLOCK_LAYOUT if frames else None,
        block_rows=frame_block_of_readings if frames else None,
    )


def register(register_codec: Callable[..., None]) -> None:
    """Register the codec for ``can_raw`` streams and :class:`CanFrameBatch` for the writer's
    batch path (done when this module is imported)."""
    register_codec("can_raw", codec)
    register_frame_batch_type(CanFrameBatch)


class CanFrameBatch(Sequence[Reading]):
    """The readings of one read of a CAN source: the frames (``can.Message`` objects as a live bus
    gives them, ``messages``, or columns read from a log, ``frames``), their times ``t_ns``
    (integer ns since the Unix epoch: host reception, or log time), and the other readings
    (decoded ``tensions``) with the number of frames they came after (``others``: ``(k,
    reading)``).

    It is a sequence of :class:`Reading` like any source's batch: indexing or iterating turns a
    frame into its ``can_raw`` reading (:func:`frame_values`) only when it is looked at.  The
    writer does not look: it writes the frames as a frame block (:meth:`frame_block`), which
    saves building a ``Reading`` and a dict per frame on a busy bus.  ``bad``: the frames the
    load-cell decoder could not use (flagged in ``/can_raw``).
    """

    __slots__ = ("stream", "messages", "t_ns", "others", "bad", "_frames", "_pos")

    def __init__(
        self,
        stream: str = "can_raw",
        messages: list[Any] | None = None,
        t_ns: Any = None,
        others: list[tuple[int, Reading]] | None = None,
        frames: FrameColumns | None = None,
        bad: Any = None,
    ) -> None:
        self.stream = stream
        self.messages: list[Any] = [] if messages is None else messages
        self.t_ns: Any = [] if t_ns is None else t_ns
        self.others: list[tuple[int, Reading]] = [] if others is None else others
        self.bad = bad
        self._frames = frames
        self._pos: list[int] | None = None

    @property
    def n_frames(self) -> int:
        return len(self.messages) if self.messages else len(self.t_ns)

    def frames(self) -> FrameColumns:
        """The frames as columns (made once from the messages of a live bus)."""
        if self._frames is None or len(self._frames) != self.n_frames:
            self._frames = FrameColumns.from_messages(self.messages)
        return self._frames

    def frame_block(self) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, dict[str, Any]]:
        """The frames as a frame block (:func:`frame_block`)."""
        return frame_block(self.frames(), self.t_ns, self.bad)

    def add_frame(self, msg: Any, t_ns: int) -> None:
        self.messages.append(msg)
        self.t_ns.append(t_ns)

    def add_reading(self, reading: Reading) -> None:
        self.others.append((self.n_frames, reading))
        self._pos = None

    def frame_reading(self, i: int) -> Reading:
        """The ``can_raw`` reading of frame ``i``."""
        frames = self.frames()
        bad = None if self.bad is None else self.bad[i : i + 1]
        status = int(frame_status(frames.take(slice(i, i + 1)), bad)[0])
        return Reading(self.stream, int(self.t_ns[i]), frame_values(frames, i), status)

    def renamed(self, renames: Mapping[str, str]) -> CanFrameBatch:
        """The same batch with streams renamed (``{"can_raw": "bus_a/can_raw", ...}``)."""
        others = [
            (
                k,
                Reading(renames[r.stream], r.t_ns, r.values, r.status)
                if r.stream in renames
                else r,
            )
            for k, r in self.others
        ]
        return CanFrameBatch(
            renames.get(self.stream, self.stream), self.messages, self.t_ns, others,
            self._frames, self.bad,
        )  # fmt: skip

    @classmethod
    def join(cls, batches: Sequence[CanFrameBatch]) -> CanFrameBatch:
        """One batch of consecutive batches of the same stream (in order)."""
        others: list[tuple[int, Reading]] = []
        k = 0
        for b in batches:
            others.extend((k + i, r) for i, r in b.others)
            k += b.n_frames
        bads = [b.bad for b in batches]
        bad = None
        if any(x is not None for x in bads):
            bad = np.concatenate(
                [np.zeros(b.n_frames, bool) if x is None else np.asarray(x, bool)
                 for b, x in zip(batches, bads, strict=True)]
            )  # fmt: skip
        t_ns = np.concatenate([np.asarray(b.t_ns, np.int64) for b in batches]) if batches else []
        if all(len(b.messages) == b.n_frames for b in batches):  # a live bus: messages
            msgs = [m for b in batches for m in b.messages]
            cached = [b._frames for b in batches]  # the columns made for decoding, if all have
            frames = concat_frames(cached) if all(f is not None for f in cached) else None  # type: ignore[arg-type]
            return cls(batches[0].stream, msgs, list(t_ns), others, frames, bad)
        frames = concat_frames([b.frames() for b in batches])
        return cls(batches[0].stream, [], t_ns, others, frames, bad)

    def latest(self) -> dict[str, Reading]:
        """The last reading of every stream in the batch."""
        out: dict[str, Reading] = {}
        if self.n_frames:
            out[self.stream] = self.frame_reading(self.n_frames - 1)
        for _, r in self.others:
            out[r.stream] = r
        return out

    def __len__(self) -> int:
        return self.n_frames + len(self.others)

    def _positions(self) -> list[int]:
        # position of every other reading in the combined order
        if self._pos is None:
            self._pos = [k + j for j, (k, _) in enumerate(self.others)]
        return self._pos

    def _one(self, i: int) -> Reading:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError("batch index out of range")
        if not self.others:
            return self.frame_reading(i)
        pos = self._positions()
        j = bisect.bisect_left(pos, i)
        if j < len(pos) and pos[j] == i:
            return self.others[j][1]
        return self.frame_reading(i - j)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return [self._one(k) for k in range(*i.indices(len(self)))]
        return self._one(i)

    def __iter__(self) -> Iterator[Reading]:
        others = self.others
        j = 0
        for i in range(self.n_frames):
            while j < len(others) and others[j][0] <= i:
                yield others[j][1]
                j += 1
            yield self.frame_reading(i)
        for _, r in others[j:]:
            yield r

    def __repr__(self) -> str:
        return (
            f"CanFrameBatch({self.stream!r}, {self.n_frames} frames, "
            f"{len(self.others)} other readings)"
        )


register(register_stream_codec)
