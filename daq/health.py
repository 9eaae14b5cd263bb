"""Source health during a recording: a source that never delivers, stalls, ends early or counts
errors is a fault, recorded as an ``/event``, shown as an alarm and summed up at the end.

:class:`HealthMonitor` is driven by the recorder: :meth:`HealthMonitor.delivered` from each
acquisition thread when a batch arrives (one float store), :meth:`HealthMonitor.check` about ten
times a second from the recorder's monitor thread.  Every fault becomes one ``/event`` with
``name = "fault"`` and the fields ``source`` and ``fault`` (``no_data``, ``stalled``, ``ended``,
``errors``, ``lost``, ``bad``, ``dropped``, ``reopened``), level ``error`` (``warning`` for a
source that comes back).  The monotonic clock is used throughout, so a host clock jump cannot
fake or hide a stall.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

#: counters of :class:`~cdpr.daq.recorder.SourceCounters` whose growth is a fault, with their words
COUNTER_FAULTS = {
    "errors": "driver/bus errors",
    "lost": "samples lost (counter gaps)",
    "bad": "bad frames/lines",
    "dropped": "readings dropped (queue full)",
    "reopened": "reopens",
}
#: driver counters (``Source.stats.extra``) reported as their own fault kinds
EXTRA_FAULTS = {
    "error_frames": "CAN error frames",
    "bus_off": "CAN bus-off",
    "pauses": "pause(s) longer than a counter wrap",
}


@dataclass
class _Track:
    periodic: bool
    period_s: float
    first: float | None = None
    last: float = 0.0
    stalled_since: float | None = None
    startup_flagged: bool = False
    ended_at: float | None = None
    counts: dict[str, int] = field(default_factory=dict)


class HealthMonitor:
    """Watches the sources of one recording.

    rates_hz: per source, the nominal rates of its streams (0 for event-driven streams); a source
        with a positive rate is periodic and may stall.
    emit: ``emit(message, level, **fields)`` records an event (the recorder's ``event``).
    """

    def __init__(
        self,
        rates_hz: Mapping[str, list[float]],
        emit: Callable[..., None],
        *,
        startup_timeout_s: float,
        stall_timeout_s: float,
    ) -> None:
        self.startup_timeout_s = float(startup_timeout_s)
        self.stall_timeout_s = float(stall_timeout_s)
        self._emit = emit
        self._tracks: dict[str, _Track] = {}
        for name, rates in rates_hz.items():
            pos = [r for r in rates if r > 0]
            self._tracks[name] = _Track(bool(pos), 1.0 / max(pos) if pos else 0.0)
        self.faults: list[str] = []
        self.fault_kinds: dict[str, set[str]] = {n: set() for n in rates_hz}
        self.never_delivered: list[str] = []
        self._t0 = time.monotonic()
        self.clock_jump_s = 0.1
        self._clock_offset_ns = time.time_ns() - time.monotonic_ns()
        self.clock_jumps: list[float] = []

    def start(self) -> None:
        """The recording starts now (the startup timeout counts from here)."""
        self._t0 = time.monotonic()

    def delivered(self, source: str) -> None:
        """``source`` delivered a non-empty batch (called from its acquisition thread)."""
        t = self._tracks[source]
        t.last = time.monotonic()
        if t.first is None:
            t.first = t.last

    def ended(self, source: str) -> None:
        """``source``'s acquisition thread ended on its own (end of data, not a stop)."""
        self._tracks[source].ended_at = time.monotonic()

    def _fault(self, source: str, kind: str, message: str, level: str = "error") -> None:
        self.faults.append(message)
        self.fault_kinds[source].add(kind)
        self._emit(message, level, name="fault", source=source, fault=kind)

    def stall_limit_s(self, source: str) -> float:
        """Silence after which ``source`` counts as stalled: the timeout, at least 5 periods."""
        return max(self.stall_timeout_s, 5.0 * self._tracks[source].period_s)

    def check(self, counters: Mapping[str, Any], stopping: bool, others_running: bool) -> list[str]:
        """Look at every source now; returns the sources that never delivered within the startup
        timeout and were flagged in this call.

        counters: per source, an object with the :data:`COUNTER_FAULTS` attributes,
        ``last_error`` and ``extra`` (driver counters, :data:`EXTRA_FAULTS`).
        stopping: a stop was requested (silence is then expected).
        others_running: some acquisition thread is still alive (an ended source is then early).
        """
        now = time.monotonic()
        self._check_clock()
        new_dead: list[str] = []
        for name, t in self._tracks.items():
            c = counters[name]
            for key, words in COUNTER_FAULTS.items():
                v = int(getattr(c, key))
                old = t.counts.get(key, 0)
                if v > old:
                    t.counts[key] = v
                    extra = (
                        f"; last error: {c.last_error}" if key == "errors" and c.last_error else ""
                    )
                    self._fault(name, key, f"source {name}: {v - old} {words} (total {v}){extra}")
            for key, words in EXTRA_FAULTS.items():
                v = int(getattr(c, "extra", {}).get(key, 0))
                old = t.counts.get(key, 0)
                if v > old:
                    t.counts[key] = v
                    more = ""
                    if key == "pauses":
                        # durations of the new pauses: whole counter wraps may hide inside them
                        new_s = list(getattr(c, "extra", {}).get("pause_s", ()))[old:v]
                        if new_s:  # the driver keeps the first 1000 durations
                            more = "; no sample for " + ", ".join(f"{d:.2f} s" for d in new_s)
                        more += " (samples lost in whole counter wraps cannot be counted)"
                    self._fault(name, key, f"source {name}: {v - old} {words} (total {v}){more}")
            if stopping:
                if t.first is None and not t.startup_flagged:  # a run shorter than the timeout
                    t.startup_flagged = True
                    self.never_delivered.append(name)
                    why = f" (last error: {c.last_error})" if c.last_error else ""
                    self._fault(
                        name, "no_data", f"source {name}: delivered nothing during the run{why}"
                    )
                continue
            if t.ended_at is not None:
                # another source still running a second later: this one ended early
                late = now - t.ended_at > 1.0
                if late and others_running and "ended" not in self.fault_kinds[name]:
                    self._fault(
                        name,
                        "ended",
                        f"source {name}: ended after {t.ended_at - self._t0:.1f} s while the run "
                        "went on",
                    )
                continue
            if t.first is None:
                if not t.startup_flagged and now - self._t0 >= self.startup_timeout_s:
                    t.startup_flagged = True
                    why = f" (last error: {c.last_error})" if c.last_error else ""
                    self.never_delivered.append(name)
                    new_dead.append(name)
                    self._fault(
                        name,
                        "no_data",
                        f"source {name}: delivered nothing within {self.startup_timeout_s:g} s{why}",
                    )
                continue
            if not t.periodic:
                continue
            silent = now - t.last
            if t.stalled_since is None and silent >= self.stall_limit_s(name):
                t.stalled_since = t.last
                self._fault(name, "stalled", f"source {name}: no data for {silent:.1f} s")
            elif t.stalled_since is not None and silent < self.stall_limit_s(name):
                gap = t.last - t.stalled_since
                t.stalled_since = None
                self._emit(
                    f"source {name}: data again after {gap:.1f} s",
                    "warning",
                    name="fault",
                    source=name,
                    fault="recovered",
                )
        return new_dead

    def _check_clock(self) -> None:
        """A step of the host clock (NTP, an operator, a VM resumed) against the monotonic clock:
        the readings' host timestamps jump with it, so it is a fault of the whole run."""
        offset = time.time_ns() - time.monotonic_ns()
        step_s = (offset - self._clock_offset_ns) / 1e9
        if abs(step_s) >= self.clock_jump_s:
            self._clock_offset_ns = offset
            self.clock_jumps.append(step_s)
            self.faults.append(f"host clock jumped by {step_s:+.3f} s")
            self._emit(
                f"host clock jumped by {step_s:+.3f} s: host timestamps before and after differ "
                "by that much more than the time that passed",
                "error",
                name="fault",
                source="host",
                fault="clock_jump",
                step_s=step_s,
            )

    def alarms(self) -> list[str]:
        """What is wrong right now (for the live view)."""
        now = time.monotonic()
        out = []
        for name, t in self._tracks.items():
            if t.first is None and t.startup_flagged:
                out.append(f"{name}: no data since the start")
            elif t.stalled_since is not None:
                out.append(f"{name}: no data for {now - t.stalled_since:.1f} s")
            elif t.ended_at is not None and "ended" in self.fault_kinds[name]:
                out.append(f"{name}: ended")
        return out

    def summary(self) -> list[str]:
        """One line per faulty source: its fault kinds and counters (empty: a clean run)."""
        out = []
        if self.clock_jumps:
            steps = ", ".join(f"{s:+.3f} s" for s in self.clock_jumps)
            out.append(f"host clock: jumped {len(self.clock_jumps)}x ({steps})")
        for name, kinds in self.fault_kinds.items():
            if not kinds:
                continue
            t = self._tracks[name]
            parts = []
            if "no_data" in kinds:
                parts.append("delivered nothing")
            if "stalled" in kinds:
                n = sum(1 for f in self.faults if f.startswith(f"source {name}: no data for"))
                parts.append(f"stalled {n}x")
            if "ended" in kinds:
                parts.append("ended early")
            for key, words in {**COUNTER_FAULTS, **EXTRA_FAULTS}.items():
                if t.counts.get(key):
                    parts.append(f"{t.counts[key]} {words}")
            out.append(f"source {name}: " + ", ".join(parts))
        return out
