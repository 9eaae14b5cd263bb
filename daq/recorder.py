"""The recorder: sources -> bounded queues -> one writer thread -> an MCAP run file.

One acquisition thread per source calls :meth:`Source.read` in a loop and puts each batch of
readings on that source's bounded queue; a full queue drops the batch and counts it (``dropped``),
the acquisition never blocks on the disk.  One writer thread drains every queue into a
:class:`~cdpr.daq.mcap_io.McapRunWriter`, closes a chunk at least every ``flush_interval_s`` and
fsyncs, and once a second writes a ``/recorder`` message with the counters (so drops are known even
in a salvaged file).  :meth:`Recorder.stop` (also run by ``with Recorder(...)``, and by the CLI's
SIGINT/SIGTERM handlers) stops the sources, drains the queues, writes the ``run_end`` metadata and
finishes the file (summary and footer) on every exit path.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import traceback
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import InputError

from .faultwatch import DataWatch
from .health import HealthMonitor
from .mcap_io import McapRunWriter
from .mcap_writer import is_frame_batch
from .runs import iso_utc
from .source import FieldDescription, Reading, Source, StreamDescription, now_ns


@dataclass
class RecorderOptions:
    """Tuning of the recorder.

    queue_readings: capacity of each source's queue, in readings (a batch that does not fit is dropped).
    chunk_size: close an MCAP chunk when its uncompressed size exceeds this (bytes).
    flush_interval_s: ... or when it is older than this; every flush is fsynced.
    compression: ``"zstd"``, ``"lz4"`` or ``"none"``.
    stats_interval_s: period of the ``/recorder`` counter messages.
    read_timeout_s: timeout of each :meth:`Source.read` call (bounds the stop latency).
    startup_timeout_s: a source with no reading this long after the start is a failure: the recording
        stops (``failure`` names it) unless ``allow_degraded``, then it goes on with the others.
    stall_timeout_s: a periodic source (a stream with ``rate_hz > 0``) silent this long (at least 5
        sample periods) after it delivered is stalled: a fault event, an alarm while it lasts.
    allow_degraded: keep recording when a source never delivers (the fault is still reported).
    capture_logs: while recording, log records (INFO and above) of this logger (the drivers': bus
        errors, reopens, bad lines) become ``/event`` messages instead of console lines; ``None``: off.
    max_log_events_per_s: at most this many captured log records per second (the rest are counted).
    """

    queue_readings: int = 200_000
    chunk_size: int = 256 * 1024
    flush_interval_s: float = 0.25
    compression: str = "zstd"
    stats_interval_s: float = 1.0
    read_timeout_s: float = 0.05
    capture_logs: str | None = "cdpr.daq"
    max_log_events_per_s: int = 20
    startup_timeout_s: float = 5.0
    stall_timeout_s: float = 2.0
    allow_degraded: bool = False

    def __post_init__(self) -> None:
        if not self.startup_timeout_s > 0 or not self.stall_timeout_s > 0:
            raise InputError(
                "startup_timeout_s and stall_timeout_s must be > 0 s, got "
                f"{self.startup_timeout_s} and {self.stall_timeout_s}"
            )
        if self.queue_readings < 1:
            raise InputError(f"queue_readings must be >= 1, got {self.queue_readings}")
        if not 0 < self.flush_interval_s <= 1.0:
            raise InputError(
                f"flush_interval_s must be in (0, 1] s (crash safety), got {self.flush_interval_s}"
            )


@dataclass
class Attachment:
    """A file embedded in the run (rig, calibration, config)."""

    name: str
    data: bytes
    media_type: str = "text/plain"

    @classmethod
    def from_file(cls, path: str | os.PathLike[str], name: str | None = None) -> Attachment:
        p = Path(path)
        media = {".toml": "application/toml", ".json": "application/json", ".csv": "text/csv"}.get(
            p.suffix.lower(), "application/octet-stream"
        )
        if p.suffix.lower() in (".dbc", ".txt", ".log"):
            media = "text/plain"
        return cls(name or p.name, p.read_bytes(), media)


class _EventLogHandler(logging.Handler):
    """Turns log records into recorder events (rate-limited)."""

    def __init__(self, recorder: Recorder, per_s: int) -> None:
        super().__init__(logging.INFO)
        self.recorder = recorder
        self.per_s = per_s
        self.window = 0.0
        self.n = 0
        self.suppressed = 0

    def emit(self, record: logging.LogRecord) -> None:
        now = time.monotonic()
        if now - self.window >= 1.0:
            if self.suppressed:
                self.recorder.event(
                    f"{self.suppressed} log messages suppressed", level="warning", name="recorder"
                )
            self.window, self.n, self.suppressed = now, 0, 0
        self.n += 1
        if self.n > self.per_s:
            self.suppressed += 1
            return
        try:
            msg = record.getMessage()
        except Exception:  # a bad format string must not break the recording
            msg = str(record.msg)
        self.recorder.event(msg, level=record.levelname.lower(), name=record.name)


class _BoundedQueue:
    """Batches of readings, at most ``capacity`` readings; a batch that does not fit is dropped."""

    __slots__ = ("_dq", "_lock", "capacity", "pending", "accepted", "dropped", "peak")

    def __init__(self, capacity: int) -> None:
        self._dq: deque[list[Reading]] = deque()
        self._lock = threading.Lock()
        self.capacity = capacity
        self.pending = 0
        self.accepted = 0
        self.dropped = 0
        self.peak = 0

    def put(self, batch: list[Reading]) -> bool:
        n = len(batch)
        with self._lock:
            if self.pending + n > self.capacity:
                self.dropped += n
                return False
            self._dq.append(batch)
            self.pending += n
            self.accepted += n
            if self.pending > self.peak:
                self.peak = self.pending
        return True

    def take_all(self) -> list[list[Reading]]:
        with self._lock:
            if not self._dq:
                return []
            out = list(self._dq)
            self._dq.clear()
            self.pending = 0
        return out


_JOIN_FRAMES = 8192
_SMALL_DRAIN = 2048


def _joined(batches: list[Any]) -> list[Any]:
    """Consecutive CAN frame batches (:class:`~cdpr.daq.can_raw.CanFrameBatch`, one stream per
    source) joined into batches of about ``_JOIN_FRAMES`` frames: the writer formats a batch's
    frames in one go, faster for a few thousand frames than for a few hundred, and a bounded size
    keeps the memory of a large backlog's formatting small."""
    out: list[Any] = []
    group: list[Any] = []
    n = 0
    for b in batches:
        group.append(b)
        n += len(b)
        if n >= _JOIN_FRAMES:
            out.append(group[0].join(group) if len(group) > 1 else group[0])
            group, n = [], 0
    if group:
        out.append(group[0].join(group) if len(group) > 1 else group[0])
    return out


@dataclass
class SourceCounters:
    """What the recorder counted for one source (for the live view and the ``/recorder`` stream)."""

    name: str
    read: int = 0
    dropped: int = 0
    queued: int = 0
    errors: int = 0
    lost: int = 0
    bad: int = 0
    reopened: int = 0
    last_error: str = ""
    extra: dict[str, int] = field(default_factory=dict)


@dataclass
class RecorderStatus:
    """A snapshot of the recorder's state."""

    running: bool
    elapsed_s: float
    counts: dict[str, int]
    latest: dict[str, Reading]
    sources: dict[str, SourceCounters]
    flushes: int
    error: str | None = None
    stop_reason: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    alarms: list[str] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)
    failure: str | None = None


class Recorder:
    """Record ``sources`` into a new MCAP file at ``path``.

    Parameters
    ----------
    sources:
        Drivers (not yet opened; the recorder opens and closes them in their threads).
    path:
        The run file to create (must not exist).
    metadata:
        The ``run`` metadata record (see :func:`cdpr.daq.runs.run_metadata`), written first.
    attachments:
        Files embedded in the run (rig, calibrations, config).
    extra_streams:
        Streams to declare besides the sources' own (name -> description).
    """

    def __init__(
        self,
        sources: Sequence[Source],
        path: str | os.PathLike[str],
        *,
        metadata: Mapping[str, str] | None = None,
        attachments: Sequence[Attachment] = (),
        options: RecorderOptions | None = None,
        extra_streams: Mapping[str, StreamDescription] | None = None,
    ) -> None:
        names = [s.name for s in sources]
        if len(set(names)) != len(names):
            raise InputError(f"source names must be unique, got {names}")
        self.sources = list(sources)
        self.path = Path(path)
        self.options = options or RecorderOptions()
        self._metadata = dict(metadata or {})
        self._attachments = list(attachments)
        self._extra_streams = dict(extra_streams or {})
        self._queues = {s.name: _BoundedQueue(self.options.queue_readings) for s in self.sources}
        self._events: deque[Reading] = deque()
        self._counters = {s.name: SourceCounters(s.name) for s in self.sources}
        self._latest: dict[str, Reading] = {}
        self._stop = threading.Event()
        self._acq_done = threading.Event()
        self._threads: list[threading.Thread] = []
        self._writer_thread: threading.Thread | None = None
        self._writer: McapRunWriter | None = None
        self._error: str | None = None
        self._start_ns = 0
        self._t0 = 0.0
        self._stop_reason = ""
        self._stopped = False
        self._lock = threading.Lock()
        self._renames: dict[str, dict[str, str]] = {}
        self._log_handler: _EventLogHandler | None = None
        self._acq_errors = {s.name: 0 for s in self.sources}
        self._health: HealthMonitor | None = None
        self._monitor_thread: threading.Thread | None = None
        self.failure: str | None = None
        self._watch = DataWatch(self.event)
        self._os_error: OSError | None = None

    # lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        """Create the file, write metadata and attachments, declare the streams, start threads."""
        o = self.options
        self._writer = McapRunWriter(
            self.path,
            chunk_size=o.chunk_size,
            flush_interval_s=o.flush_interval_s,
            compression=o.compression,
        )
        try:
            self._start_ns = now_ns()
            self._t0 = time.monotonic()
            md = dict(self._metadata)
            md.setdefault("start_time_ns", str(self._start_ns))
            md.setdefault("start_time_utc", iso_utc(self._start_ns))
            md["sources"] = ",".join(s.name for s in self.sources)
            self._writer.add_metadata("run", md)
            for att in self._attachments:
                self._writer.add_attachment(att.name, att.data, att.media_type)
            self._writer.add_stream("event", StreamDescription({}, 0.0, "Run events."))
            self._writer.add_stream("recorder", self._recorder_description())
            described = {s.name: dict(s.describe()) for s in self.sources}
            seen: dict[str, int] = {}
            for d in described.values():
                for stream in d:
                    seen[stream] = seen.get(stream, 0) + 1
            for s in self.sources:
                # a stream name two sources share becomes <source>/<stream> (topic /<source>/<stream>)
                ren = {k: f"{s.name}/{k}" for k in described[s.name] if seen[k] > 1}
                self._renames[s.name] = ren
                for stream, desc in described[s.name].items():
                    self._writer.add_stream(ren.get(stream, stream), desc)
            for stream, desc in self._extra_streams.items():
                self._writer.add_stream(stream, desc)
            self._health = HealthMonitor(
                {n: [d.rate_hz for d in described[n].values()] for n in described},
                self.event,
                startup_timeout_s=o.startup_timeout_s,
                stall_timeout_s=o.stall_timeout_s,
            )
            self._writer.flush()
        except BaseException:
            # nothing recorded yet: leave no half-written run behind
            self._writer.finish()
            self.path.unlink(missing_ok=True)
            raise
        if o.capture_logs:
            self._log_handler = _EventLogHandler(self, o.max_log_events_per_s)
            logging.getLogger(o.capture_logs).addHandler(self._log_handler)
        self._writer_thread = threading.Thread(
            target=self._write_loop, name="recorder-writer", daemon=True
        )
        self._writer_thread.start()
        for s in self.sources:
            t = threading.Thread(target=self._acquire, args=(s,), name=f"acq-{s.name}", daemon=True)
            self._threads.append(t)
            t.start()
        self._health.start()
        self._monitor_thread = threading.Thread(
            target=self._monitor, name="recorder-health", daemon=True
        )
        self._monitor_thread.start()
        self.event("recording started", level="info")

    def request_stop(self, reason: str = "requested") -> None:
        """Ask the recorder to stop (safe from a signal handler: only sets a flag)."""
        if not self._stop.is_set():
            self._stop_reason = reason
            self._stop.set()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    def wait(self, duration_s: float | None = None, poll_s: float = 0.1) -> None:
        """Block until ``duration_s`` has elapsed, a stop is requested, or every source ended."""
        end = None if duration_s is None else time.monotonic() + duration_s
        while not self._stop.is_set():
            if end is not None and time.monotonic() >= end:
                self.request_stop("duration reached")
                break
            if self._threads and not any(t.is_alive() for t in self._threads):
                self.request_stop("all sources ended")
                break
            if self._writer_thread is not None and not self._writer_thread.is_alive():
                self.request_stop("writer failed")
                break
            self._stop.wait(
                poll_s if end is None else max(0.0, min(poll_s, end - time.monotonic()))
            )

    def stop(self, reason: str | None = None) -> Path:
        """Stop the sources, drain the queues and finish the file; idempotent.  Returns the path.

        Raises the writer thread's error (after the file is finished) if it failed.
        """
        with self._lock:
            if self._stopped:
                return self.path
            self._stopped = True
        self.request_stop(reason or "stopped")
        for t in self._threads:
            t.join(timeout=10.0)
        if self._monitor_thread is not None:
            self._monitor_thread.join(timeout=5.0)
        if self._health is not None:  # the counters' last changes (errors while stopping)
            self._health.check(self._refresh_counters(), stopping=True, others_running=False)
        if self._log_handler is not None:
            logging.getLogger(self.options.capture_logs).removeHandler(self._log_handler)
        self._acq_done.set()
        if self._writer_thread is not None:
            self._writer_thread.join(timeout=60.0)
        w = self._writer
        if w is not None and not w.finished:
            try:
                # the writer thread is gone: drain what is left here, then finish
                if self._writer_thread is None or not self._writer_thread.is_alive():
                    if self._error is None:
                        self._drain(w)
                        self._write_stats(w)
                    stop_ns = now_ns()
                    w.add_metadata("run_end", self._end_metadata(stop_ns))
            finally:
                w.finish()
        if self._error is not None:
            errno_ = self._os_error.errno if self._os_error is not None else None
            raise OSError(
                errno_,
                f"{self._error}: recording stopped; what was written is kept "
                f"(salvage it with `cdpr recover {self.path}`)",
                str(self.path),
            )
        return self.path

    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop("context exit" if exc[0] is None else f"exception {exc[0].__name__}")  # type: ignore[union-attr]

    # events and status -----------------------------------------------------------------------
    def event(self, message: str, level: str = "info", **extra: Any) -> None:
        """Record an event (``/event``, foxglove.Log) with the current time; never dropped."""
        self._events.append(
            Reading("event", now_ns(), {"message": message, "level": level, **extra})
        )

    def declares(self, stream: str) -> bool:
        """Whether ``stream`` is one of the ``extra_streams`` (events may go on it)."""
        return stream in self._extra_streams

    def stream_event(self, stream: str, message: str, level: str = "info", **extra: Any) -> None:
        """Record an event on ``stream`` (declared in ``extra_streams``; e.g. the live view's
        ``test_point`` events on ``/events``, the topic ``cdpr analyze`` reads) with the current
        time; never dropped."""
        if stream != "event" and stream not in self._extra_streams:
            raise InputError(f"stream_event: {stream!r} is not declared in extra_streams")
        self._events.append(
            Reading(stream, now_ns(), {"message": message, "level": level, **extra})
        )

    def _refresh_counters(self) -> dict[str, SourceCounters]:
        for s in self.sources:
            c = self._counters[s.name]
            q = self._queues[s.name]
            c.read, c.dropped, c.queued = q.accepted + q.dropped, q.dropped, q.pending
            c.lost, c.bad, c.reopened = s.stats.lost, s.stats.bad, s.stats.reopened
            c.errors = self._acq_errors[s.name] + s.stats.errors
            c.extra = dict(s.stats.extra)
        return self._counters

    def status(self) -> RecorderStatus:
        """Counters, latest reading per stream, elapsed time, alarms and faults (a snapshot)."""
        w = self._writer
        self._refresh_counters()
        h = self._health
        return RecorderStatus(
            running=not self._stop.is_set(),
            elapsed_s=time.monotonic() - self._t0 if self._t0 else 0.0,
            counts=dict(w.counts) if w else {},
            latest=dict(self._latest),
            sources={
                k: SourceCounters(**{**vars(v), "extra": dict(v.extra)})
                for k, v in self._counters.items()
            },
            flushes=w.flushes if w else 0,
            error=self._error,
            stop_reason=self._stop_reason,
            extra={"queue_peak": {k: q.peak for k, q in self._queues.items()}},
            alarms=h.alarms() if h is not None and not self._stop.is_set() else [],
            faults=h.summary() if h is not None else [],
            failure=self.failure,
        )

    def recent_tensions(self) -> tuple[list[str], Any, Any]:
        """Cables, times (k,) ns and tensions (k, m) N of the latest samples (about 2 s at 200 Hz)
        of the first tensions stream, for the live view's steadiness and wrench estimate."""
        return self._watch.recent_tensions()

    def backlog(self, source: str) -> int:
        """Readings of ``source`` waiting in its queue."""
        return self._queues[source].pending

    @property
    def dropped(self) -> int:
        """Readings dropped because a queue was full, all sources."""
        return sum(q.dropped for q in self._queues.values())

    # threads ---------------------------------------------------------------------------------
    def _acquire(self, src: Source) -> None:
        q = self._queues[src.name]
        c = self._counters[src.name]
        timeout = self.options.read_timeout_s
        backoff = 0.2
        ren = self._renames.get(src.name, {})
        name = src.name
        assert self._health is not None
        delivered = self._health.delivered
        try:
            while not self._stop.is_set():
                try:
                    batch = src.read(timeout)
                    backoff = 0.2
                except Exception as exc:  # a driver failure never kills the recording
                    self._acq_errors[src.name] += 1
                    c.last_error = f"{type(exc).__name__}: {exc}"
                    self.event(f"source {src.name}: {c.last_error}", level="error")
                    try:
                        src.close()
                    except Exception:
                        pass
                    self._stop.wait(backoff)
                    backoff = min(2 * backoff, 5.0)
                    continue
                if batch:
                    delivered(name)
                    if ren and is_frame_batch(batch):
                        batch = batch.renamed(ren)  # a CAN frame batch (can_raw.CanFrameBatch)
                    elif ren:
                        batch = [
                            Reading(ren[r.stream], r.t_ns, r.values, r.status)
                            if r.stream in ren
                            else r
                            for r in batch
                        ]
                    q.put(batch)
                elif getattr(src, "exhausted", False):
                    self.event(f"source {src.name}: end of data", level="info")
                    self._health.ended(name)
                    break
        finally:
            try:
                src.close()
            except Exception as exc:
                c.last_error = f"close: {type(exc).__name__}: {exc}"

    def _drain(self, w: McapRunWriter) -> int:
        n = 0
        latest = self._latest
        while self._events:
            r = self._events.popleft()
            w.write(r)
            latest[r.stream] = r
            n += 1
        write_many = w.write_many
        for q in self._queues.values():
            batches = q.take_all()
            if len(batches) > 1 and all(is_frame_batch(b) for b in batches):
                batches = _joined(batches)
            watch = self._watch.feed
            for batch in batches:
                n += write_many(batch)
                watch(batch)
                latest_of = getattr(batch, "latest", None)
                if latest_of is not None:  # a CAN frame batch knows its latest readings
                    latest.update(latest_of())
                    continue
                # the latest reading of every stream in the batch (walk back a little)
                seen: set[str] = set()
                for r in reversed(batch[-64:]):
                    if r.stream not in seen:
                        seen.add(r.stream)
                        latest[r.stream] = r
        return n

    def _write_loop(self) -> None:
        w = self._writer
        assert w is not None
        stats_every = self.options.stats_interval_s
        next_stats = time.monotonic() + stats_every
        try:
            while True:
                n = self._drain(w)
                now = time.monotonic()
                if now >= next_stats:
                    self._write_stats(w)
                    next_stats = now + stats_every
                w.maybe_flush()
                if n == 0:
                    if self._acq_done.is_set():
                        break
                    time.sleep(0.005)
                elif n < _SMALL_DRAIN:
                    # let a busy source's readings gather a little (10 ms, well inside the flush
                    # interval): batches of a few thousand frames cost less per frame to write
                    time.sleep(0.01)
            self._drain(w)
            self._write_stats(w)
            w.add_metadata("run_end", self._end_metadata(now_ns()))
            w.finish()
        except BaseException as exc:
            if isinstance(exc, OSError):  # a full disk, a file size limit, an I/O error
                self._error = exc.strerror or str(exc)
                self._os_error = exc
            else:  # a bug: the traceback matters
                self._error = f"{type(exc).__name__}: {exc}"
                traceback.print_exc()
            self._stop.set()
            try:
                w.finish()
            except BaseException:
                pass

    def _monitor(self) -> None:
        """Source health ten times a second until the stop: faults become events; a source that
        never delivered stops the recording unless ``allow_degraded``."""
        h = self._health
        assert h is not None
        while not self._stop.wait(0.1):
            alive = sum(t.is_alive() for t in self._threads)
            dead = h.check(self._refresh_counters(), stopping=False, others_running=alive > 0)
            if dead and not self.options.allow_degraded and self.failure is None:
                c = self._counters[dead[0]]
                why = f" (last error: {c.last_error})" if c.last_error else ""
                self.failure = (
                    f"source {dead[0]!r} delivered nothing within "
                    f"{self.options.startup_timeout_s:g} s{why}"
                )
                self.request_stop("failed: " + self.failure)

    # helpers ---------------------------------------------------------------------------------
    def _recorder_description(self) -> StreamDescription:
        f: dict[str, FieldDescription] = {}
        for s in self.sources:
            for k in ("read", "dropped", "queued", "errors", "lost", "bad", "reopened"):
                f[f"{s.name}_{k}"] = FieldDescription("", "int64")
        return StreamDescription(
            f,
            1.0 / self.options.stats_interval_s,
            "Recorder counters per source (cumulative): readings read, dropped (queue full), "
            "queued, driver errors, samples lost (counter gaps), bad frames/lines, reopens.",
        )

    def _write_stats(self, w: McapRunWriter) -> None:
        st = self.status()
        values: dict[str, int] = {}
        for name, c in st.sources.items():
            values.update(
                {
                    f"{name}_read": c.read,
                    f"{name}_dropped": c.dropped,
                    f"{name}_queued": c.queued,
                    f"{name}_errors": c.errors,
                    f"{name}_lost": c.lost,
                    f"{name}_bad": c.bad,
                    f"{name}_reopened": c.reopened,
                }
            )
        w.write(Reading("recorder", now_ns(), values, 1 if self.dropped else 0))

    def _end_metadata(self, stop_ns: int) -> dict[str, Any]:
        st = self.status()
        return {
            "stop_time_ns": str(stop_ns),
            "stop_time_utc": iso_utc(stop_ns),
            "duration_s": f"{(stop_ns - self._start_ns) / 1e9:.6f}",
            "stop_reason": self._stop_reason,
            "message_counts": st.counts,
            "sources": {k: vars(v) for k, v in st.sources.items()},
            "dropped_total": str(self.dropped),
            "queue_peak": st.extra["queue_peak"],
            "faults": st.faults,
            "failure": st.failure or "",
        }
