"""Log replay: any CAN log cdpr reads (:func:`cdpr.daq.canlog.read_log`: candump ``.log``, ``.asc``,
``.blf``, ``.trc``, ``.csv``, and whatever else python-can reads) as a CAN source, at the recorded
speed or as fast as possible, through the same frame columns and decoder as ``cdpr import``.

Settings of ``can_replay``:

path: the log file (format from the suffix).
speed: ``"recorded"`` (frames come out at their recorded spacing, scaled by ``time_scale``) or
  ``"max"`` (as fast as the reader asks, ``batch`` frames per read).
dbc, cables, offset_counts, gain_N_per_count: decode load-cell frames into ``tensions`` as the CAN
  driver does (``decode = false`` for raw frames only).
timestamps: ``"log"`` (default): ``t_ns`` is the frame's recorded time (:func:`log_times`: logs with
  relative times, e.g. ASC, are placed at the moment the replay opened); ``"host"``: the host time
  of the read that delivers the frames, spaced as recorded.

``exhausted`` turns True when the log has been delivered.  A log that turns out bad part-way (a
line or object its reader names) ends the replay there: the frames before it are delivered, the
error is logged and counted (``stats.bad``, ``stats.extra["log_error"]``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError

from . import can_raw
from .can_decoder import build_decoder
from .can_frames import FrameColumns, concat_frames, empty_frames
from .can_raw import CanFrameBatch
from .can_source import add_samples
from .canlog import read_log, readable
from .source import Source, StreamDescription

log = logging.getLogger(__name__)

#: timestamps below ~1973 (s) are relative to the start of the log
RELATIVE_LIMIT_S = 1.0e8


def log_times(t_s: np.ndarray, first_s: float, open_ns: int) -> np.ndarray:
    """The time (integer ns) a frame of a log is put at: its timestamp (``round(t * 1e9)``), or
    for a log with relative times (below :data:`RELATIVE_LIMIT_S`) ``open_ns`` plus its offset
    from the log's first frame ``first_s``."""
    t_bus = np.rint(t_s * 1e9).astype(np.int64)
    rel = t_s < RELATIVE_LIMIT_S
    if not rel.any():
        return t_bus
    return np.where(rel, open_ns + np.rint((t_s - first_s) * 1e9).astype(np.int64), t_bus)


class CanReplaySource(Source):
    """A CAN log as a source (see the module docstring for the settings)."""

    kind = "can_replay"
    accepts_origin = True

    def __init__(
        self,
        name: str,
        path: str,
        speed: str = "recorded",
        time_scale: float = 1.0,
        batch: int = 2000,
        dbc: str | None = None,
        decode: bool = True,
        cables: Sequence[str] | None = None,
        offset_counts: Any = None,
        gain_N_per_count: Any = None,
        rate_hz: float = 0.0,
        timestamps: str = "log",
        origin: str = "<config>",
    ) -> None:
        super().__init__(name)
        prefix = f"sources.{name}"
        self.origin = origin
        self.path = Path(path)
        if not self.path.is_file():
            raise ConfigError(origin, f"{prefix}.path", f"log file not found: {self.path}")
        if not readable(self.path):
            raise ConfigError(
                origin, f"{prefix}.path", f"cannot read log: unknown format {self.path.suffix!r}"
            )
        # speed, timestamps, time_scale > 0: checked by cdpr.daq.source_schema.CanReplaySettings
        self.speed = speed
        self.time_scale = float(time_scale)
        self.batch = int(batch)
        self.timestamps = timestamps
        self.rate_hz = float(rate_hz)
        self.decoder = None
        self.dbc_path = ""
        if decode:
            self.decoder, self.dbc_path = build_decoder(
                origin, prefix, dbc, cables, offset_counts, gain_N_per_count
            )
        self._blocks: Iterator[FrameColumns] | None = None
        self._buf = empty_frames()
        self._done = False
        self._log_t0: float | None = None
        self._wall_t0 = 0.0
        self._open_ns = 0

    @property
    def exhausted(self) -> bool:
        return self._done and not len(self._buf)

    def settings(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "path": str(self.path),
            "speed": self.speed,
            "time_scale": self.time_scale,
            "timestamps": self.timestamps,
        }
        if self.decoder is not None:
            out.update(
                dbc=self.dbc_path,
                cables=list(self.decoder.cables),
                **self.decoder.calibration.to_mapping(),
            )
        return out

    def describe(self) -> dict[str, StreamDescription]:
        out = {"can_raw": can_raw.DESCRIPTION}
        if self.decoder is not None:
            out["tensions"] = self.decoder.describe(self.rate_hz)
        return out

    def _open(self) -> None:
        self._blocks = read_log(self.path)
        self._buf = empty_frames()
        self._done = False
        self._log_t0 = None
        self._wall_t0 = time.monotonic()
        self._open_ns = time.time_ns()

    def _close(self) -> None:
        blocks, self._blocks = self._blocks, None
        close = getattr(blocks, "close", None)
        if close is not None:
            close()

    def _fill(self, want: int) -> None:
        """Read blocks of the log until ``want`` frames are buffered or it ends."""
        parts = [self._buf]
        have = len(self._buf)
        while have < want and not self._done and self._blocks is not None:
            try:
                cols = next(self._blocks)
            except StopIteration:
                self._done = True
                break
            except ConfigError as exc:  # a bad line part-way: keep what was read
                self.stats.bad += 1
                self.stats.extra["log_error"] = 1
                self._done = True
                log.warning("%s: log ends with an error: %s", self.name, exc)
                break
            parts.append(cols)
            have += len(cols)
        self._buf = concat_frames(parts)

    def _read(self, timeout_s: float) -> CanFrameBatch:  # type: ignore[override]
        self._fill(self.batch)
        buf = self._buf
        if not len(buf):
            out = CanFrameBatch()
            if self.decoder is not None:
                add_samples(out, self.decoder, self.decoder.flush(), self.stats, False)
            if not out.others:
                time.sleep(min(timeout_s, 0.01))
            return out
        if self._log_t0 is None:
            self._log_t0 = float(buf.t_s[0])
            self._wall_t0 = time.monotonic()
        n = min(self.batch, len(buf))
        if self.speed == "recorded":
            # the frames due by the end of this read; at least one (waiting for it, within the
            # timeout)
            due = self._wall_t0 + (buf.t_s[:n] - self._log_t0) / self.time_scale
            now = time.monotonic()
            wait = float(due[0]) - now
            if wait > 0:
                time.sleep(min(wait, timeout_s))
                now = time.monotonic()
                if float(due[0]) > now:
                    return CanFrameBatch()
            n = int(np.searchsorted(due, now, side="right"))
        frames = buf.take(slice(0, n))
        self._buf = buf.take(slice(n, None))
        if self.timestamps == "host":
            t_ns = time.time_ns() + np.rint(
                (frames.t_s - frames.t_s[-1]) / self.time_scale * 1e9
            ).astype(np.int64)
        else:
            t_ns = log_times(frames.t_s, self._log_t0, self._open_ns)
        out = CanFrameBatch(t_ns=t_ns, frames=frames)
        if self.decoder is not None:
            samples = self.decoder.decode_frames(frames, t_ns)
            add_samples(out, self.decoder, samples, self.stats, True)
            if self._done and not len(self._buf):
                add_samples(out, self.decoder, self.decoder.flush(n), self.stats, True)
        return out
