"""Column-block streams in the run writer: a high-rate flat numeric stream stored as column blocks
on ``/<stream>`` (:mod:`cdpr.daq.column_blocks`) and, unless its codec gives a block layout of its
own, a per-sample JSON view of it on ``/<stream>/view`` (the first sample of every
:data:`~cdpr.daq.column_blocks.VIEW_PERIOD_NS`, what Foxglove plots).

:func:`add_block_stream` registers the channels and gives the stream's state
(:class:`BlockStream`: its buffer of samples not yet written); :func:`emit_block` writes the
buffered samples as blocks and their view messages (the writer calls it when the buffer is full and
at every chunk close, so a block is on disk when its chunk is).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from . import column_blocks
from .mcap_chunks import ChunkedWriter
from .mcap_codecs import StreamCodec, encode_json, topic_of
from .source import StreamDescription


@dataclass
class BlockStream:
    """The writer's state of one column-block stream: the samples not yet written, its channel, the
    view's channel (None: no view), its last 20 ms bin and message count, and the integer fields (a
    missing value, NaN in the block, is left out of a view message rather than written as null)."""

    buf: column_blocks.BlockBuffer
    cid: int
    view_cid: int | None
    ints: set[str]
    last_bin: int = -1
    view_count: int = 0
    #: %-formats of the view's rows, by (column, is float) names
    formats: dict[tuple[tuple[str, bool], ...], str] = field(default_factory=dict)


def add_block_stream(
    writer: ChunkedWriter,
    stream: str,
    description: StreamDescription,
    codec: StreamCodec,
    meta: dict[str, str],
    chunk_size: int,
    layout: str | None = None,
) -> BlockStream:
    """Register a high-rate flat numeric stream: column blocks on ``/<stream>`` (channel metadata
    ``meta`` and the blocks') and the per-sample view on ``/<stream>/view``; with a ``layout`` (the
    codec's ``block_layout``: columns its module defines, written with
    :meth:`~cdpr.daq.mcap_writer.McapRunWriter.write_columns`), the blocks alone."""
    sid = writer.register_schema(
        column_blocks.BLOCK_SCHEMA_NAME,
        "jsonschema",
        json.dumps(column_blocks.block_schema(stream, description)).encode(),
    )
    block_meta = column_blocks.channel_metadata(description)
    if layout is not None:  # the per-sample fields as the layout's module reads them back
        fields = {k: [f.dtype, f.unit] for k, f in description.fields.items()}
        block_meta = {**block_meta, "layout": layout, "fields": json.dumps(fields)}
    cid = writer.register_channel(topic_of(stream), "json", sid, {**meta, **block_meta})
    if layout is not None:
        return BlockStream(
            column_blocks.BlockBuffer(column_blocks.MAX_BLOCK_SAMPLES), cid, None, set()
        )
    period = column_blocks.VIEW_PERIOD_NS
    vsid = writer.register_schema(
        codec.schema_name,
        "jsonschema",
        json.dumps(codec.schema, separators=(",", ":")).encode(),
    )
    vmeta = {**meta, "view_of": topic_of(stream), "view_period_ns": str(period)}
    vmeta["rate_hz"] = repr(min(float(description.rate_hz), 1e9 / period))
    vcid = writer.register_channel(topic_of(stream) + "/view", "json", vsid, vmeta)
    # a block holds at most about one chunk of samples (so chunk_size bounds a block too)
    ncols = len(description.fields) + 2
    return BlockStream(
        column_blocks.BlockBuffer(
            max(1, min(column_blocks.MAX_BLOCK_SAMPLES, chunk_size // (8 * ncols)))
        ),
        cid,
        vcid,
        column_blocks.int_fields(description),
    )


def emit_block(writer: ChunkedWriter, bs: BlockStream) -> None:
    """Write the buffered samples of a block stream as one block (split at
    :data:`~cdpr.daq.column_blocks.MAX_BLOCK_SAMPLES`) and their per-sample view messages."""
    import numpy as np

    buf = bs.buf
    got = buf.take()
    if got is None:
        return
    t_all, cols_all = got
    stored = {k: column_blocks.narrow(v) for k, v in cols_all.items()}  # the same values
    cid = bs.cid
    add = writer.add_message
    step = buf.max_samples
    for a in range(0, len(t_all), step):
        t = t_all[a : a + step]
        cols = {k: v[a : a + step] for k, v in stored.items()}
        body = column_blocks.encode_block(t, cols, buf.written, buf.values)
        add(cid, int(t[-1]), body, int(t[0]), buf.messages)
        buf.messages += 1
        buf.written += len(t)
    if bs.view_cid is None:
        return
    # the view: the first sample in each VIEW_PERIOD_NS bin of time
    bins = t_all // column_blocks.VIEW_PERIOD_NS
    pick = np.flatnonzero(np.diff(bins, prepend=bs.last_bin) != 0)
    bs.last_bin = int(bins[-1])
    if len(pick):
        _emit_view(writer, bs, t_all[pick], {k: v[pick] for k, v in cols_all.items()})


def _emit_view(writer: ChunkedWriter, bs: BlockStream, t: Any, cols: dict[str, Any]) -> None:
    """The view messages of samples at times ``t`` (``cols``: their values): rows of finite
    numbers through a %-format of the columns (``%r`` of a float is what JSON writes), the
    others as dicts (a NaN in an integer field left out: missing, not null)."""
    import numpy as np

    add = writer.add_message
    names = list(cols)
    floats = [n for n in names if cols[n].dtype.kind == "f"]
    finite = np.ones(len(t), bool)
    for n in floats:
        finite &= np.isfinite(cols[n])
    key = tuple((n, n in floats) for n in names)
    fmt = bs.formats.get(key)
    if fmt is None:
        quoted = [json.dumps(n).replace("%", "%%") for n, _ in key]
        fmt = bs.formats[key] = (
            "{"
            + ",".join(f"{q}:%r" if f else f"{q}:%d" for q, (_, f) in zip(quoted, key, strict=True))
            + "}"
        )
    rows = [cols[n].tolist() for n in names]
    ts = t.tolist()
    k = bs.view_count
    for j, (ti, ok, row) in enumerate(
        zip(ts, finite.tolist(), zip(*rows, strict=True), strict=True)
    ):
        if ok:
            body = (fmt % row).encode()
        else:
            body = encode_json(
                {
                    n: v
                    for n, v in zip(names, row, strict=True)
                    if not (n in bs.ints and v != v)  # NaN: missing, not null
                }
            )
        add(bs.view_cid, ti, body, ti, k + j)
    bs.view_count = k + len(ts)
