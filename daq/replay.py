"""Log replay: any CAN log python-can reads (candump ``.log``, ``.asc``, ``.blf``, ``.csv``, ``.trc``,
...) as a CAN source, at the recorded speed or as fast as possible.

Settings of ``can_replay``:

path: the log file (format from the suffix, as ``can.LogReader`` decides).
speed: ``"recorded"`` (frames come out at their recorded spacing, scaled by ``time_scale``) or
  ``"max"`` (as fast as the reader asks, ``batch`` frames per read).
dbc, cables, offset_counts, gain_N_per_count: decode load-cell frames into ``tensions`` as the CAN
  driver does (``decode = false`` for raw frames only).
timestamps: ``"log"`` (default): ``t_ns`` is the frame's recorded time (logs with relative times,
  e.g. ASC, are placed at the moment the replay opened); ``"host"``: the host time of the replay.

``exhausted`` turns True when the log has been delivered.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import can

from cdpr.analysis.errors import ConfigError

from .can_source import CAN_RAW_DESCRIPTION, build_decoder, raw_reading
from .source import Reading, Source, StreamDescription

_RELATIVE_LIMIT_S = 1.0e8  # timestamps below ~1973 are relative to the start of the log


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
        self._it: Iterator[can.Message] | None = None
        self._reader: Any = None
        self._next: can.Message | None = None
        self._done = False
        self._log_t0: float | None = None
        self._wall_t0 = 0.0
        self._open_ns = 0

    @property
    def exhausted(self) -> bool:
        return self._done

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
        out = {"can_raw": CAN_RAW_DESCRIPTION}
        if self.decoder is not None:
            out["tensions"] = self.decoder.describe(self.rate_hz)
        return out

    def _open(self) -> None:
        try:
            self._reader = can.LogReader(str(self.path))
            self._it = iter(self._reader)
        except (ValueError, OSError) as exc:
            raise ConfigError(
                self.origin, f"sources.{self.name}.path", f"cannot read log: {exc}"
            ) from None
        self._done = False
        self._next = None
        self._log_t0 = None
        self._wall_t0 = time.monotonic()
        self._open_ns = time.time_ns()

    def _close(self) -> None:
        r, self._reader = self._reader, None
        self._it = None
        if r is not None and hasattr(r, "stop"):
            r.stop()

    def _pull(self) -> can.Message | None:
        if self._next is not None:
            m, self._next = self._next, None
            return m
        if self._it is None:
            return None
        try:
            return next(self._it)
        except StopIteration:
            self._done = True
            return None
        except Exception as exc:  # a corrupt tail: keep what was read
            self.stats.bad += 1
            self.stats.extra["log_error"] = 1
            self._done = True
            self._it = None
            import logging

            logging.getLogger(__name__).warning("%s: log ends with an error: %s", self.name, exc)
            return None

    def _t_ns(self, msg: can.Message) -> int:
        if self.timestamps == "host":
            return time.time_ns()
        ts = msg.timestamp
        if ts < _RELATIVE_LIMIT_S:
            t0 = self._log_t0 or 0.0
            return self._open_ns + int(round((ts - t0) * 1e9))
        return int(round(ts * 1e9))

    def _read(self, timeout_s: float) -> list[Reading]:
        out: list[Reading] = []
        if self._done and self._next is None:
            if self.decoder is not None:
                out.extend(self.decoder.flush())
            if not out:
                time.sleep(min(timeout_s, 0.01))
            return out
        deadline = time.monotonic() + timeout_s
        n = 0
        while n < self.batch:
            msg = self._pull()
            if msg is None:
                break
            if self._log_t0 is None:
                self._log_t0 = msg.timestamp
                self._wall_t0 = time.monotonic()
            if self.speed == "recorded":
                due = self._wall_t0 + (msg.timestamp - self._log_t0) / self.time_scale
                wait = due - time.monotonic()
                if wait > 0:
                    if out or time.monotonic() + wait > deadline:
                        self._next = msg
                        if not out:
                            time.sleep(max(0.0, min(wait, deadline - time.monotonic())))
                        break
                    time.sleep(wait)
            t_ns = self._t_ns(msg)
            out.append(raw_reading(msg, t_ns))
            if self.decoder is not None:
                lost0 = self.decoder.lost
                out.extend(self.decoder.decode(msg, t_ns))
                self.stats.lost += self.decoder.lost - lost0
            n += 1
        if self._done and self.decoder is not None:
            out.extend(self.decoder.flush())
        return out
