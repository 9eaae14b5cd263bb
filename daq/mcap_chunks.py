"""The low-level MCAP writer of run files: :class:`ChunkedWriter`.

MCAP records are written through the ``mcap`` package's record classes, except messages, which are
packed here straight into the open chunk (the python writer's per-message objects took about 3/4 of
the writer's time), one at a time (:meth:`ChunkedWriter.add_message`) or a batch of equal-length
bodies as numpy arrays (:meth:`ChunkedWriter.add_messages`).  Chunks are compressed (zstd level
:data:`ZSTD_LEVEL`, lz4 or none) and written with their message indexes, optionally by one
background thread while the caller goes on; :meth:`ChunkedWriter.finish` writes the summary
section and the footer.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from typing import Any

_MAGIC = b"\x89MCAP0\r\n"
#: zstd level of the chunks: 1 (fastest) compressed the benchmark's CAN frames both faster (1.5x) and
#: smaller than the library default 3
ZSTD_LEVEL = 1
_MSG = struct.Struct("<BQHIQQ")  # opcode 0x05, record length, channel, sequence, log/publish time
_OP_MESSAGE = 0x05
_OP_MESSAGE_INDEX = 0x07


class ChunkedWriter:
    """An MCAP writer (spec v0): header, schemas and channels outside chunks (so every salvaged
    chunk stays decodable), messages in chunks with message indexes, metadata, attachments, and a
    summary section (schemas, channels, statistics, chunk/attachment/metadata indexes, summary
    offsets) written by :meth:`finish`, like the ``mcap`` package's writer."""

    def __init__(
        self, fh: Any, chunk_size: int, compression: str, background: bool = False
    ) -> None:
        from mcap.data_stream import RecordBuilder

        self._fh = fh
        # background: chunks are compressed and written by one thread, in order, while the caller
        # goes on (zstd releases the GIL); every other write waits for them first (drain)
        self._pool: Any = None
        self._pending: list[Any] = []
        if background:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(1, thread_name_prefix="mcap-chunks")
        self._rb = RecordBuilder()
        self._chunk_size = chunk_size
        self._compression = compression
        if compression == "zstd":
            import zstandard

            self._compress: Callable[[bytes], bytes] | None = zstandard.ZstdCompressor(
                level=ZSTD_LEVEL
            ).compress
        elif compression == "lz4":
            import lz4.frame

            self._compress = lz4.frame.compress
        else:
            self._compress = None
        self._schemas: dict[int, Any] = {}
        self._channels: dict[int, Any] = {}
        self._parts: list[bytes] = []
        self._chunk_len = 0
        # channel id -> segments of (log_time, offset) pairs: flat int lists or (k, 2) arrays
        self._chunk_index: dict[int, list[Any]] = {}
        self._chunk_indexes: list[Any] = []
        self._attachment_indexes: list[Any] = []
        self._metadata_indexes: list[Any] = []
        self.channel_message_counts: dict[int, int] = {}
        self.message_count = 0
        self.t_start = 0
        self.t_end = 0
        self.chunk_count = 0

    #: chunks waiting for the background thread at most (bounded memory)
    MAX_PENDING = 32

    def drain(self, keep: int = 0) -> None:
        """Wait until at most ``keep`` chunks are still being written by the background thread (an
        error there is raised here)."""
        while len(self._pending) > keep:
            self._pending.pop(0).result()

    def shutdown(self) -> None:
        """Stop the background thread (after the chunks it has)."""
        if self._pool is not None:
            try:
                self.drain()
            finally:
                self._pool.shutdown()
                self._pool = None

    def _emit(self) -> int:
        """Write the record builder's bytes to the file; returns their length."""
        data = self._rb.end()
        self._fh.write(data)
        return len(data)

    def start(self, profile: str, library: str) -> None:
        from mcap.records import Header

        self._fh.write(_MAGIC)
        Header(profile=profile, library=library).write(self._rb)
        self._emit()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        from mcap.records import Schema

        self.drain()
        sid = len(self._schemas) + 1
        s = Schema(id=sid, data=data, encoding=encoding, name=name)
        self._schemas[sid] = s
        s.write(self._rb)
        self._emit()
        return sid

    def register_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> int:
        from mcap.records import Channel

        self.drain()
        cid = len(self._channels) + 1
        c = Channel(
            id=cid,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=dict(metadata),
        )
        self._channels[cid] = c
        self.channel_message_counts[cid] = 0
        c.write(self._rb)
        self._emit()
        return cid

    def add_message(self, cid: int, t_ns: int, data: bytes, publish_ns: int, seq: int) -> None:
        n = len(data)
        off = self._chunk_len
        parts = self._parts
        parts.append(_MSG.pack(_OP_MESSAGE, 22 + n, cid, seq & 0xFFFFFFFF, t_ns, publish_ns))
        parts.append(data)
        self._chunk_len = off + 31 + n
        idx = self._chunk_index.get(cid)
        if idx is None:
            idx = self._chunk_index[cid] = [[]]
        last = idx[-1]
        if type(last) is not list:
            last = []
            idx.append(last)
        last += (t_ns, off)  # flat (log_time, offset) pairs
        if self._chunk_len > self._chunk_size:
            self.close_chunk()

    def add_messages(self, cid: int, t_ns: Any, bodies: Any, seq0: int) -> None:
        """Messages of one channel with bodies of equal length, at once: ``t_ns`` (n,) int64 log
        (and publish) times, ``bodies`` (n, L) uint8, sequence numbers ``seq0, seq0 + 1, ...``.
        The chunk is closed as soon as it outgrows ``chunk_size``, as with :meth:`add_message`."""
        import numpy as np

        n, body_len = bodies.shape
        rec_len = 31 + body_len
        recs = np.empty((n, rec_len), np.uint8)
        head = np.frombuffer(_MSG.pack(_OP_MESSAGE, 22 + body_len, cid, 0, 0, 0), np.uint8)
        recs[:, :31] = head
        seq = (np.arange(seq0, seq0 + n, dtype=np.int64) & 0xFFFFFFFF).astype("<u4")
        recs[:, 11:15] = seq.view(np.uint8).reshape(n, 4)
        t8 = np.ascontiguousarray(t_ns, dtype="<i8").view(np.uint8).reshape(n, 8)
        recs[:, 15:23] = t8
        recs[:, 23:31] = t8
        recs[:, 31:] = bodies
        t64 = np.asarray(t_ns, dtype=np.int64)
        a = 0
        while a < n:
            room = self._chunk_size - self._chunk_len
            b = min(n, a + max(1, room // rec_len + 1))  # just past chunk_size, like add_message
            off = self._chunk_len
            self._parts.append(recs[a:b].tobytes())
            pairs = np.empty((b - a, 2), np.int64)
            pairs[:, 0] = t64[a:b]
            pairs[:, 1] = off + rec_len * np.arange(b - a, dtype=np.int64)
            idx = self._chunk_index.get(cid)
            if idx is None:
                idx = self._chunk_index[cid] = []
            idx.append(pairs)
            self._chunk_len = off + rec_len * (b - a)
            a = b
            if self._chunk_len > self._chunk_size:
                self.close_chunk()

    def close_chunk(self) -> None:
        """Compress and write the open chunk and its message indexes (no-op when empty; with the
        background thread: hand it over, waiting while :data:`MAX_PENDING` are queued)."""
        if not self._parts:
            return
        import numpy as np

        raw = b"".join(self._parts)
        n = 0
        t0 = t1 = None
        pairs_of: dict[int, Any] = {}
        for cid, segments in self._chunk_index.items():
            # (log_time, offset) pairs in the order written: flat lists (one message at a time)
            # and (k, 2) arrays (batches)
            pairs = np.concatenate(
                [
                    np.asarray(sg, dtype=np.int64).reshape(-1, 2)
                    for sg in segments
                    if len(sg)  # type: ignore[arg-type]
                ]
            )
            pairs_of[cid] = pairs
            k = len(pairs)
            n += k
            self.channel_message_counts[cid] += k
            lo, hi = int(pairs[:, 0].min()), int(pairs[:, 0].max())
            t0 = lo if t0 is None or lo < t0 else t0
            t1 = hi if t1 is None or hi > t1 else t1
        t0, t1 = int(t0 or 0), int(t1 or 0)
        if self.message_count == 0:
            self.t_start, self.t_end = t0, t1
        else:
            self.t_start = min(self.t_start, t0)
            self.t_end = max(self.t_end, t1)
        self.message_count += n
        self.chunk_count += 1
        self._parts = []
        self._chunk_len = 0
        self._chunk_index = {}
        if self._pool is None:
            self._write_chunk(raw, pairs_of, t0, t1)
        else:
            self.drain(self.MAX_PENDING - 1)
            self._pending.append(self._pool.submit(self._write_chunk, raw, pairs_of, t0, t1))

    def _write_chunk(self, raw: bytes, pairs_of: dict[int, Any], t0: int, t1: int) -> None:
        """Compress and write one chunk (records ``raw``, message start and end times ``t0``,
        ``t1``) and its message indexes (``pairs_of``: channel -> (k, 2) log times and offsets)."""
        import zlib

        from mcap.data_stream import RecordBuilder
        from mcap.records import Chunk, ChunkIndex

        comp = self._compress(raw) if self._compress is not None else raw
        chunk = Chunk(
            compression=self._compression if self._compress is not None else "",
            data=comp,
            message_start_time=t0,
            message_end_time=t1,
            uncompressed_crc=zlib.crc32(raw),
            uncompressed_size=len(raw),
        )
        start = self._fh.tell()
        rb = RecordBuilder()  # its own builder: this may run in the background thread
        chunk.write(rb)
        data = rb.end()
        self._fh.write(data)
        length = len(data)
        offsets: dict[int, int] = {}
        pos = start + length
        index_parts = []
        for cid, pairs in pairs_of.items():
            # MessageIndex record, packed here: opcode 0x04, length, channel id, byte length of the
            # (log_time, offset) pairs, the pairs (the mcap class writes them one call at a time)
            body = pairs.astype("<u8").tobytes()
            offsets[cid] = pos
            rec = struct.pack("<BQHI", _OP_MESSAGE_INDEX, 6 + len(body), cid, len(body)) + body
            index_parts.append(rec)
            pos += len(rec)
        index = b"".join(index_parts)
        self._fh.write(index)
        index_len = len(index)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=t0,
                message_end_time=t1,
                chunk_start_offset=start,
                chunk_length=length,
                message_index_offsets=offsets,
                message_index_length=index_len,
                compression=chunk.compression,
                compressed_size=len(comp),
                uncompressed_size=len(raw),
            )
        )

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        from mcap.records import Metadata, MetadataIndex

        self.drain()
        offset = self._fh.tell()
        Metadata(name=name, metadata=data).write(self._rb)
        length = self._emit()
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_attachment(
        self, create_time: int, log_time: int, name: str, media_type: str, data: bytes
    ) -> None:
        from mcap.records import Attachment as McapAttachment
        from mcap.records import AttachmentIndex

        self.drain()
        offset = self._fh.tell()
        McapAttachment(
            create_time=create_time, log_time=log_time, name=name, media_type=media_type, data=data
        ).write(self._rb)
        length = self._emit()
        self._attachment_indexes.append(
            AttachmentIndex(
                offset=offset,
                length=length,
                create_time=create_time,
                log_time=log_time,
                data_size=len(data),
                name=name,
                media_type=media_type,
            )
        )

    def finish(self) -> None:
        """Close the open chunk, write DataEnd, the summary section, the footer and the magic."""
        import zlib

        from mcap.data_stream import RecordBuilder
        from mcap.opcode import Opcode
        from mcap.records import DataEnd, Footer, Statistics, SummaryOffset

        self.close_chunk()
        self.shutdown()
        DataEnd(data_section_crc=0).write(self._rb)
        self._emit()
        summary_start = self._fh.tell()
        sb = RecordBuilder()
        offsets: list[Any] = []

        def group(opcode: int, records: Iterable[Any]) -> None:
            g0 = sb.count
            for r in records:
                r.write(sb)
            offsets.append(
                SummaryOffset(
                    group_opcode=opcode, group_start=summary_start + g0, group_length=sb.count - g0
                )
            )

        group(Opcode.SCHEMA, self._schemas.values())
        group(Opcode.CHANNEL, self._channels.values())
        stats = Statistics(
            attachment_count=len(self._attachment_indexes),
            channel_count=len(self._channels),
            channel_message_counts={k: v for k, v in self.channel_message_counts.items() if v},
            chunk_count=self.chunk_count,
            message_count=self.message_count,
            message_end_time=self.t_end,
            message_start_time=self.t_start,
            metadata_count=len(self._metadata_indexes),
            schema_count=len(self._schemas),
        )
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, self._attachment_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + sb.count
        for o in offsets:
            o.write(sb)
        summary = sb.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(
            struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc
        )
        self._fh.write(summary)
        Footer(
            summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc
        ).write(self._rb)
        self._emit()
        self._fh.write(_MAGIC)
