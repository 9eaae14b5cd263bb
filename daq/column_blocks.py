"""Column blocks: how run files store high-rate flat numeric streams (load cells at 1 kHz).

One JSON message per block of consecutive samples instead of one per sample, so an hour of 8 cells
at 1 kHz reads back at about a million samples per second (``np.frombuffer``) instead of being
parsed sample by sample.  A block message (schema ``cdpr.column_block``, JSON, valid against its
schema, so Foxglove and any MCAP reader open it) is::

    {"timestamp": {"sec", "nsec"},   # the block's last sample (also the message's log_time)
     "first_sample": 12000,         # index of the block's first sample in the stream (0-based)
     "count": 250,                  # samples in the block
     "columns": ["t_ns", "T_front_left_top_N", ..., "status"],
     "dtypes": ["<i8", "<f8", ..., "|u1"],   # little-endian int64 or float64 (NaN: missing);
                                             # an integer column whose values fit is stored
                                             # narrower: "|u1" (uint8) or "<i4" (int32)
     "values": {"channel": ["can0", 1, null]},  # optional: a column of indexes into a table
     "data": "<base64 of the columns' bytes, one column after the other>"}

``t_ns`` (the sample times, int64 ns since the Unix epoch) is always the first column.  The message's
``log_time`` is the block's *last* sample time and its ``publish_time`` the first, so a time window
``[a, b)`` needs the blocks from the first whose log_time is ``>= a`` to the first whose log_time is
``>= b``, inclusive (the run reader does that from the message indexes alone).  The channel's
metadata says ``storage = "column_blocks"`` and describes the per-sample fields (``fields``: name ->
[dtype, unit]).

Beside the blocks the writer keeps a per-sample JSON *view* (``/<stream>/view``, the stream's flat
schema: the first sample of every :data:`VIEW_PERIOD_NS` of time, at most 50 Hz), so a Foxglove plot
panel graphs the tensions; analysis never reads the view.

Which streams: a stream whose description is flat and numeric (scalar int/float fields) and whose
nominal rate is at least :data:`MIN_RATE_HZ` (``docs/recording.md`` has the measured bytes per
sample and read speeds of both layouts).

A ``values`` table names the values of a column that holds few distinct JSON values (a CAN channel
such as ``"can0"``, ``0`` or ``null``): the column holds indexes into the table.  A stream's table
only grows, so a later block's table starts with an earlier block's.  Raw CAN frames imported from a
log use ``|u1`` columns and a table (layout ``can_frames``, :mod:`cdpr.daq.can_raw`).
"""

from __future__ import annotations

import base64
import json
from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np

from cdpr.analysis.errors import InputError

__all__ = [
    "BLOCK_SCHEMA_NAME",
    "MAX_BLOCK_SAMPLES",
    "MIN_RATE_HZ",
    "STORAGE",
    "VIEW_PERIOD_NS",
    "BlockBuffer",
    "block_schema",
    "decode_blocks",
    "encode_block",
    "uses_blocks",
]

BLOCK_SCHEMA_NAME = "cdpr.column_block"
#: channel metadata ``storage`` of a block channel
STORAGE = "column_blocks"
#: streams at this nominal rate or above are stored as blocks
MIN_RATE_HZ = 200.0
#: the per-sample JSON view beside the blocks: the first sample of every 20 ms of time (<= 50 Hz)
VIEW_PERIOD_NS = 20_000_000
#: a block is closed at this many samples (and at every chunk close of the writer)
MAX_BLOCK_SAMPLES = 2048

_INT, _FLOAT, _U8, _I32 = "<i8", "<f8", "|u1", "<i4"
_DATA_KEY = b',"data":"'
_DTYPES = {d: np.dtype(d) for d in (_INT, _FLOAT, _U8, _I32)}
_INT_DTYPES = frozenset({"int64", "int32", "int", "uint8", "bool"})
_NUMERIC = _INT_DTYPES | {"float64", "float32", "float"}


def int_fields(description: Any) -> set[str]:
    """The integer fields of a block stream's description (stored as ``<i8``)."""
    return {name for name, f in description.fields.items() if f.dtype in _INT_DTYPES}


def uses_blocks(description: Any, any_rate: bool = False) -> bool:
    """True when a stream of this :class:`~cdpr.daq.source.StreamDescription` is stored as column
    blocks: nominal rate >= :data:`MIN_RATE_HZ` (unless ``any_rate``) and every field a numeric
    scalar."""
    if description is None or not description.fields:
        return False
    if not any_rate and not float(description.rate_hz) >= MIN_RATE_HZ:
        return False
    return all(
        getattr(f, "dtype", "float64") in _NUMERIC and not tuple(getattr(f, "shape", ()) or ())
        for f in description.fields.values()
    )


def block_schema(stream: str, description: Any) -> dict[str, Any]:
    """JSON schema of the block messages of ``stream`` (the per-sample fields in its description)."""
    fields = ", ".join(description.fields) if description is not None else ""
    return {
        "type": "object",
        "title": BLOCK_SCHEMA_NAME,
        "description": (
            f"Samples of {stream} in column blocks: 'data' is base64 of the columns' little-endian "
            f"bytes one after the other, names and dtypes in 'columns' and 'dtypes' (t_ns first). "
            f"Fields: {fields}, status. log_time: the block's last sample."
        ),
        "properties": {
            "timestamp": {
                "type": "object",
                "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
            },
            "first_sample": {"type": "integer", "minimum": 0},
            "count": {"type": "integer", "minimum": 1},
            "columns": {"type": "array", "items": {"type": "string"}},
            "dtypes": {
                "type": "array",
                "items": {"type": "string", "enum": [_INT, _FLOAT, _U8, _I32]},
            },
            "values": {
                "type": "object",
                "additionalProperties": {"type": "array"},
                "description": "per column: the table its values index (few distinct values)",
            },
            "data": {"type": "string", "contentEncoding": "base64"},
        },
        "required": ["first_sample", "count", "columns", "dtypes", "data"],
    }


def channel_metadata(description: Any) -> dict[str, str]:
    """The block channel's metadata: storage kind and the per-sample fields (name -> [dtype,
    unit])."""
    ints = int_fields(description)
    fields = {
        name: [_INT if name in ints else _FLOAT, f.unit] for name, f in description.fields.items()
    }
    fields["status"] = [_INT, ""]
    return {"storage": STORAGE, "fields": json.dumps(fields, separators=(",", ":"))}


def _column(values: Any) -> np.ndarray:
    """A block column: int64 when every value is an integer (or bool), else float64 (None: NaN)."""
    a = np.asarray(values)
    if a.dtype.kind in "USV":
        raise InputError(f"column block: expected numbers, got {a.dtype.kind!r} values")
    if a.dtype == np.uint8:  # bytes and flags: one byte a sample
        return a
    if a.dtype.kind in "iub":
        return a.astype(_INT)
    if a.dtype.kind == "f":
        return a.astype(_FLOAT)
    try:
        return np.asarray(values, dtype=_FLOAT)  # None -> NaN
    except (TypeError, ValueError):
        raise InputError(
            f"column block: expected numbers, got {type(next(iter(values))).__name__}"
        ) from None


def narrow(a: np.ndarray) -> np.ndarray:
    """An int64 column in the narrowest storage that holds its values exactly (uint8 for 0..255,
    int32, else int64); other columns as they are.  The reader gives int64 back."""
    if a.dtype != np.int64 or not len(a):
        return a
    lo, hi = int(a.min()), int(a.max())
    if lo >= 0 and hi <= 255:
        return a.astype(np.uint8)
    if lo >= -(2**31) and hi < 2**31:
        return a.astype(np.int32)
    return a


def encode_block(
    t_ns: np.ndarray,
    columns: Mapping[str, np.ndarray],
    first_sample: int,
    values: Mapping[str, Sequence[Any]] | None = None,
) -> bytes:
    """One block message body: ``t_ns`` (n,) int64 and the columns (n,) int64, float64, int32 or
    uint8;
    ``values``: the tables of the columns that hold indexes into one."""
    t_ns = np.ascontiguousarray(t_ns, dtype=_INT)
    n = len(t_ns)
    names = ["t_ns", *columns]
    arrays = [t_ns, *(np.ascontiguousarray(c) for c in columns.values())]
    for name, a in zip(names, arrays, strict=True):
        if a.shape != (n,) or a.dtype.str not in _DTYPES:
            raise InputError(
                f"column block: {name}: expected ({n},) int64/float64/int32/uint8, got {a.shape} "
                f"{a.dtype}"
            )
    sec, nsec = divmod(int(t_ns[-1]), 1_000_000_000)
    head = {
        "timestamp": {"sec": sec, "nsec": nsec},
        "first_sample": int(first_sample),
        "count": n,
        "columns": names,
        "dtypes": [a.dtype.str for a in arrays],
    }
    if values:
        head["values"] = {k: list(v) for k, v in values.items()}
    data = base64.b64encode(b"".join([memoryview(a).cast("B") for a in arrays]))
    return b"".join(
        [json.dumps(head, separators=(",", ":"))[:-1].encode(), b',"data":"', data, b'"}']
    )


def decode_blocks(
    bodies: Sequence[bytes], where: str = "", columns: Collection[str] | None = None
) -> dict[str, np.ndarray]:
    """Columns (``t_ns`` first) of block message bodies, concatenated in the given order (an
    indexed column as its values, an object array); a column some blocks lack is NaN there (and
    float64), or 0 for a uint8 column.  ``columns``: only these (and ``t_ns``).  Bad blocks raise
    InputError naming ``where``."""
    if not bodies:
        return {"t_ns": np.empty(0, np.int64)}
    # the writer puts "data" last: the header is parsed as JSON, the base64 decoded straight from
    # the body's bytes (a JSON parser would scan every character of it); other layouts go through
    # json.loads whole
    heads: list[dict[str, Any]] = []
    datas: list[Any] = []
    for body in bodies:
        k = body.rfind(_DATA_KEY)
        try:
            if k > 0 and body.endswith(b'"}'):
                heads.append(json.loads(body[:k] + b"}"))
                datas.append(memoryview(body)[k + len(_DATA_KEY) : -2])
            else:
                h = json.loads(body)
                heads.append(h)
                datas.append(h.get("data") if isinstance(h, dict) else None)
        except ValueError as exc:
            raise InputError(f"{where}: a column block is not valid JSON ({exc})") from None
    parts: list[dict[str, np.ndarray]] = []
    tables: dict[str, dict[Any, Any]] = {}
    for h, data in zip(heads, datas, strict=True):
        try:
            n = int(h["count"])
            raw = base64.b64decode(data, validate=True)
            cols: dict[str, np.ndarray] = {}
            pos = 0
            for name, dt in zip(h["columns"], h["dtypes"], strict=True):
                d = _DTYPES[dt]
                a = np.frombuffer(raw, d, n, pos)
                # integers read back int64 whatever their storage (no uint8 arithmetic downstream)
                cols[name] = a.astype(np.int64) if d.kind in "iu" and d.itemsize < 8 else a
                pos += n * d.itemsize
            if pos != len(raw) or "t_ns" not in cols:
                raise ValueError("data length does not match count x columns")
            if columns is not None:  # copies: the block's bytes are not kept alive
                cols = {k: v.copy() for k, v in cols.items() if k == "t_ns" or k in columns}
            for name, table in (h.get("values") or {}).items():
                if name not in cols:
                    continue
                cols[name] = _looked_up(cols[name], table, tables.setdefault(name, {}))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise InputError(f"{where}: a column block is malformed ({exc})") from None
        parts.append(cols)
    return concat(parts)


def concat(parts: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The columns of consecutive parts (each with ``t_ns``) one after the other; a column a part
    lacks is 0 there when it is uint8 where present (bytes past a frame's length), else NaN."""
    if len(parts) == 1:
        return dict(parts[0])
    names: list[str] = []
    for p in parts:
        names += [c for c in p if c not in names]
    out: dict[str, np.ndarray] = {}
    for name in names:
        if all(name in p for p in parts):
            out[name] = np.concatenate([p[name] for p in parts])
            continue
        u8 = all(p[name].dtype == np.uint8 for p in parts if name in p)
        fill = (lambda n: np.zeros(n, np.uint8)) if u8 else (lambda n: np.full(n, np.nan))
        out[name] = np.concatenate(
            [
                (p[name] if u8 else p[name].astype(_FLOAT)) if name in p else fill(len(p["t_ns"]))
                for p in parts
            ]
        )
    return out


def _key(v: Any) -> tuple[str, Any]:
    return (type(v).__name__, v)  # 1 and "1" (and True) are different values


def _looked_up(idx: np.ndarray, table: Sequence[Any], seen: dict[Any, Any]) -> np.ndarray:
    """The values (object array) at indexes ``idx`` of a block's ``table``."""
    if not isinstance(table, list) or any(isinstance(v, dict | list) for v in table):
        raise ValueError("a values table is a list of scalars")
    if len(idx) and int(idx.max()) >= len(table):
        raise ValueError("an index past its values table")
    objs = np.empty(len(table), object)
    objs[:] = [seen.setdefault(_key(v), v) for v in table]
    return objs[idx.astype(np.intp)]


class BlockBuffer:
    """The samples of one block stream not yet written: readings (one at a time, the recorder) and
    column arrays (bulk writers, ``cdpr import``) in arrival order."""

    def __init__(self, max_samples: int = MAX_BLOCK_SAMPLES) -> None:
        #: the writer closes a block at this many samples
        self.max_samples = int(max_samples)
        #: samples written out in blocks so far, and block messages
        self.written = 0
        self.messages = 0
        self._pieces: list[tuple[np.ndarray, dict[str, Any]]] = []
        self._t: list[int] = []
        self._rows: list[dict[str, Any]] = []
        self.n = 0
        #: the values tables of the stream's indexed columns (they only grow)
        self.values: dict[str, list[Any]] = {}
        self._where: dict[str, dict[tuple[str, Any], int]] = {}

    def __len__(self) -> int:
        return self.n

    def add_reading(self, t_ns: int, values: Mapping[str, Any], status: int) -> None:
        row = dict(values)
        row["status"] = status
        self._t.append(t_ns)
        self._rows.append(row)
        self.n += 1

    def add_columns(
        self,
        t_ns: np.ndarray,
        columns: Mapping[str, Any],
        status: Any,
        values: Mapping[str, Sequence[Any]] | None = None,
    ) -> None:
        """Samples as columns; ``values``: for an indexed column, the table its indexes point
        into (mapped here onto the stream's table)."""
        t_ns = np.asarray(t_ns, np.int64)
        cols = {k: _column(v) for k, v in columns.items()}
        for k, table in (values or {}).items():
            cols[k] = self._indexes(k, table, cols[k])
        cols["status"] = np.broadcast_to(np.asarray(status, np.int64), t_ns.shape).astype(_INT)
        for k, v in cols.items():
            if v.shape != t_ns.shape:
                raise InputError(f"column block: {k}: expected {t_ns.shape} values, got {v.shape}")
        self._close_rows()
        self._pieces.append((t_ns, cols))
        self.n += len(t_ns)

    def _indexes(self, name: str, table: Sequence[Any], idx: np.ndarray) -> np.ndarray:
        """Indexes ``idx`` into ``table`` as indexes into the stream's table of ``name``."""
        where = self._where.setdefault(name, {})
        glob = self.values.setdefault(name, [])
        m = np.empty(len(table), np.int64)
        for i, v in enumerate(table):
            if isinstance(v, dict | list):
                raise InputError(f"column block: {name}: a table value must be a scalar, got {v!r}")
            m[i] = where.setdefault(_key(v), len(glob))
            if m[i] == len(glob):
                glob.append(v)
        if len(idx) and (idx.min() < 0 or idx.max() >= len(table)):
            raise InputError(f"column block: {name}: an index past its table of {len(table)}")
        return m[idx.astype(np.intp)]  # int64: stored narrow by the writer (narrow)

    def _close_rows(self) -> None:
        if not self._rows:
            return
        names = list(dict.fromkeys(k for r in self._rows for k in r))  # every key, first seen
        cols = {k: _column([r.get(k) for r in self._rows]) for k in names}
        self._pieces.append((np.asarray(self._t, np.int64), cols))
        self._t, self._rows = [], []

    def take(self) -> tuple[np.ndarray, dict[str, np.ndarray]] | None:
        """Everything buffered as (t_ns, columns), or None when empty; the buffer is emptied."""
        self._close_rows()
        if not self._pieces:
            return None
        pieces, self._pieces, self.n = self._pieces, [], 0
        if len(pieces) == 1:
            return pieces[0]
        t = np.concatenate([p[0] for p in pieces])
        cols = concat([{"t_ns": tt, **c} for tt, c in pieces])
        del cols["t_ns"]
        return t, cols
