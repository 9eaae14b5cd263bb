"""A CAN log into a run: its frames as ``/can_raw`` frame blocks and the load-cell samples the decoder
makes of them as ``/tensions`` column blocks, a block of frames at a time (bounded memory), through
the same path as the live driver and replay: :func:`cdpr.daq.canlog.read_log` (one reader per
format) -> :meth:`cdpr.daq.can_decoder.LoadCellDecoder.decode_frames` -> the writer's
``write_columns``."""

from __future__ import annotations

import os
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError

from .can_decoder import LoadCellDecoder, Samples
from .can_frames import ODD, FrameColumns
from .can_raw import frame_block
from .canlog import read_log
from .replay import log_times
from .source import STATUS_GAP


@dataclass
class CanLogStats:
    """What an import of a CAN log met: frames, samples written, partial samples dropped where
    the log starts or ends mid-sample, odd frames (read as python-can reads them, flagged), bad
    load-cell frames, lost samples (counter gaps), partial samples kept, pauses."""

    frames: int = 0
    samples: int = 0
    partial_samples_dropped: int = 0
    odd_frames: int = 0
    bad_frames: int = 0
    lost: int = 0
    partial_samples: int = 0
    pauses: int = 0
    pause_s: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def import_can_log(
    writer: Any,
    path: str | os.PathLike[str],
    decoder: LoadCellDecoder | None,
    start_ns: int,
    progress: Callable[[int], None] | None = None,
) -> tuple[int, CanLogStats]:
    """Write the frames of the CAN log ``path`` (``can_raw``) and, with a decoder, its samples
    (``tensions``; both streams added to ``writer`` before).  A frame is put at its log time
    (:func:`cdpr.daq.replay.log_times`: a log with relative times at ``start_ns`` plus its offset
    from the first frame).  A partial sample at the very start or end of the log (cut mid-sample)
    is dropped and counted; partial samples inside the log are kept, flagged (``STATUS_GAP``).
    Returns the first frame's time and the counts; a log without a frame is a ConfigError."""
    stats = CanLogStats()
    first_ns: int | None = None
    log_t0 = 0.0
    for frames in _ahead(read_log(path, progress=progress)):
        if first_ns is None:
            log_t0 = float(frames.t_s[0])
        t_ns = log_times(frames.t_s, log_t0, start_ns)
        if first_ns is None:
            first_ns = int(t_ns[0])
        bad = None
        if decoder is not None:
            samples = decoder.decode_frames(frames, t_ns)
            bad = samples.bad
            _write_samples(writer, samples, stats, at_end=False)
        writer.write_columns("can_raw", *frame_block(frames, t_ns, bad))
        stats.frames += len(frames)
        stats.odd_frames += int(np.count_nonzero(frames.flags & ODD))
    if first_ns is None:
        raise ConfigError(str(path), "", "no CAN frames in the log")
    if decoder is not None:
        _write_samples(writer, decoder.flush(), stats, at_end=True)
        stats.bad_frames = decoder.bad
        stats.lost = decoder.lost
        stats.partial_samples = decoder.partial - stats.partial_samples_dropped
        stats.pauses = decoder.n_pauses
        stats.pause_s = [round(d * 1e-9, 3) for _, d in decoder.pauses]
    return first_ns, stats


def _ahead(blocks: Iterator[FrameColumns], depth: int = 2) -> Iterator[FrameColumns]:
    """The blocks of ``blocks``, read in a thread up to ``depth`` blocks ahead (the parser's numpy
    work overlaps the decoding and writing of the block before; bounded memory); an error of the
    reader is raised here, where the block would have come."""
    q: queue.Queue[Any] = queue.Queue(depth)
    stop = threading.Event()
    end = object()

    def put(item: Any) -> bool:
        while not stop.is_set():  # the consumer may have stopped: never block for good
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def run() -> None:
        try:
            for b in blocks:
                if not put(b):
                    return
            put(end)
        except BaseException as exc:  # handed to the consumer
            put(exc)

    t = threading.Thread(target=run, name="canlog-reader", daemon=True)
    t.start()
    try:
        while True:
            item = q.get()
            if item is end:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        t.join()
        close = getattr(blocks, "close", None)
        if close is not None:
            close()


def _write_samples(writer: Any, samples: Samples, stats: CanLogStats, at_end: bool) -> None:
    """Write decoded samples; a partial one where the log starts (before any sample was written)
    or ends (``at_end``) is dropped and counted."""
    gap = (samples.status & STATUS_GAP) != 0
    drop = gap.copy() if at_end else np.zeros(len(samples), bool)
    if stats.samples == 0 and len(samples):
        lead = int(np.argmin(gap)) if not gap.all() else len(samples)
        drop[:lead] = True
    if drop.any():
        stats.partial_samples_dropped += int(drop.sum())
        samples = samples.take(~drop)
    if len(samples):
        writer.write_columns("tensions", samples.t_ns, samples.columns, samples.status)
        stats.samples += len(samples)


class Progress:
    """A progress bar on stderr (bytes of the log read) for imports that take more than ~2 s."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.total = max(1, Path(path).stat().st_size)
        self.t0 = time.monotonic()
        self.shown = False

    def update(self, done_bytes: int) -> None:
        import sys

        dt = time.monotonic() - self.t0
        if dt < 2.0:
            return
        self.shown = True
        frac = min(1.0, done_bytes / self.total)
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\rimport [{bar:<30s}] {100 * frac:5.1f}% {dt:6.1f} s")
        sys.stderr.flush()

    def done(self) -> None:
        import sys

        if self.shown:
            sys.stderr.write("\n")
            sys.stderr.flush()
