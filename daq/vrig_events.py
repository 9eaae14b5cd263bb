"""The virtual rig's test-point events as a source: ``/events`` readings at schedule times.

:class:`TestPointEventSource` takes the event list of
:meth:`cdpr.daq.virtual_rig.VirtualRig.test_point_events` (``t_rel_ns`` from the schedule start) and
a clock giving the rig's host start time and time scale; once the rig has started, it emits each
event when its host time ``t0_ns + t_rel_ns / speed`` has passed, stamped with that time, as a
``Reading("events", ...)`` (foxglove.Log on topic ``/events``, ``name == "test_point"``).  After
the last event it idles until the run stops (never "ended early").

When the schedule sends its test points on the tunnel link (``test_points_on_link``), those
``$TPT`` lines are the run's ``test_point`` events, and ``cdpr simulate`` builds this source with
``stream="events_schedule"`` and ``event_name=SCHEDULE_EVENT_NAME``: the schedule's own events are
kept (topic ``/events_schedule``), never a second set of ``test_point`` events.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from .source import FieldDescription, Reading, Source, StreamDescription, now_ns

SCHEDULE_EVENT_NAME = "test_point_schedule"
"""``name`` of the schedule's test-point events when the tunnel link carries the points."""

EVENT_FIELDS = {
    "message": FieldDescription("", "str"),
    "name": FieldDescription("", "str"),
    "point": FieldDescription("", "str"),
    "phase": FieldDescription("", "str"),
    "kind": FieldDescription("", "str"),
    "target_aoa_deg": FieldDescription("deg"),
    "target_sideslip_deg": FieldDescription("deg"),
    "target_airspeed_mps": FieldDescription("m/s"),
    "repeat_of": FieldDescription("", "str"),
    "motion_axis": FieldDescription("", "str"),
    "motion_amplitude": FieldDescription("rad or m"),
    "motion_frequency_Hz": FieldDescription("Hz"),
    "motion_cycles": FieldDescription("", "int64"),
    "motion_settling_cycles": FieldDescription("", "int64"),
    "inertia_tare": FieldDescription("", "str"),
}
"""The fields of a ``test_point`` event; the ``motion_*`` fields and ``inertia_tare`` on an
oscillation point's events only (:func:`oscillation_event_fields`)."""

MOTION_EVENT_FIELDS = (
    "motion_axis",
    "motion_amplitude",
    "motion_frequency_Hz",
    "motion_cycles",
    "motion_settling_cycles",
    "inertia_tare",
)
"""The event fields of an oscillation point's motion (issue 22's shared names): the axis, the
amplitude in SI (rad or m), the frequency, the cycles analysed and the settling cycles before
them, the label of the inertia tare that serves it ("" if none)."""


def oscillation_event_fields(point: Any) -> dict[str, Any]:
    """The :data:`MOTION_EVENT_FIELDS` of an oscillation point or segment (any object with those
    attributes), as plain Python values."""
    cast = {"str": str, "int64": int, "float64": float}
    return {k: cast[EVENT_FIELDS[k].dtype](getattr(point, k)) for k in MOTION_EVENT_FIELDS}


class TestPointEventSource(Source):
    """Test-point events of a virtual-rig run (see the module docstring).

    events: dicts with ``t_rel_ns`` and the event fields; clock: returns ``(t0_ns, speed)`` of the
    running rig, ``t0_ns`` None before it starts.
    """

    __test__ = False
    kind = "test_point_events"

    def __init__(
        self,
        name: str,
        events: Sequence[Mapping[str, Any]],
        clock: Callable[[], tuple[int | None, float]],
        stream: str = "events",
        event_name: str | None = None,
    ) -> None:
        super().__init__(name)
        self._events = sorted(events, key=lambda e: int(e["t_rel_ns"]))
        self.stream = stream
        self.event_name = event_name
        self._clock = clock
        self._next = 0

    def describe(self) -> dict[str, StreamDescription]:
        what = "test-point events" if self.event_name is None else "the schedule's test points"
        return {self.stream: StreamDescription(dict(EVENT_FIELDS), 0.0, what)}

    def settings(self) -> dict[str, Any]:
        out: dict[str, Any] = {"n_events": len(self._events)}
        if self.event_name is not None:
            out.update(stream=self.stream, event_name=self.event_name)
        return out

    @property
    def done(self) -> bool:
        """Every event has gone out.  The source then idles until the run stops: it is not
        ``exhausted`` (the recorder's word for a source whose data ended early, a fault), since an
        event source has nothing to say between events and after the last one."""
        return self._next >= len(self._events)

    def _open(self) -> None:
        self._next = 0

    def _close(self) -> None:
        pass

    def _read(self, timeout_s: float) -> list[Reading]:
        t0, speed = self._clock()
        if t0 is None or self.done:
            time.sleep(timeout_s)
            return []
        out: list[Reading] = []
        deadline = now_ns() + int(timeout_s * 1e9)
        while not self.done:
            ev = self._events[self._next]
            t_ns = t0 + int(round(int(ev["t_rel_ns"]) / speed))
            now = now_ns()
            if t_ns > now:
                if out:
                    break
                if t_ns > deadline:
                    time.sleep(max(0, deadline - now) * 1e-9)
                    break
                time.sleep((t_ns - now) * 1e-9)
            values = {k: v for k, v in ev.items() if k != "t_rel_ns"}
            if self.event_name is not None:
                values["name"] = self.event_name
            out.append(Reading(self.stream, t_ns, values))
            self._next += 1
        return out
