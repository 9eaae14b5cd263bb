"""The virtual rig's test-point events as a source: ``/events`` readings at schedule times.

:class:`TestPointEventSource` takes the event list of
:meth:`cdpr.daq.virtual_rig.VirtualRig.test_point_events` (``t_rel_ns`` from the schedule start) and
a clock giving the rig's host start time and time scale; once the rig has started, it emits each
event when its host time ``t0_ns + t_rel_ns / speed`` has passed, stamped with that time, as a
``Reading("events", ...)`` (foxglove.Log on topic ``/events``, ``name == "test_point"``).  It is
exhausted once every event has gone out.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from .source import FieldDescription, Reading, Source, StreamDescription, now_ns

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
}


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
    ) -> None:
        super().__init__(name)
        self._events = sorted(events, key=lambda e: int(e["t_rel_ns"]))
        self._clock = clock
        self._next = 0

    def describe(self) -> dict[str, StreamDescription]:
        return {"events": StreamDescription(dict(EVENT_FIELDS), 0.0, "test-point events")}

    def settings(self) -> dict[str, Any]:
        return {"n_events": len(self._events)}

    @property
    def exhausted(self) -> bool:
        return self._next >= len(self._events)

    def _open(self) -> None:
        self._next = 0

    def _close(self) -> None:
        pass

    def _read(self, timeout_s: float) -> list[Reading]:
        t0, speed = self._clock()
        if t0 is None or self.exhausted:
            time.sleep(timeout_s)
            return []
        out: list[Reading] = []
        deadline = now_ns() + int(timeout_s * 1e9)
        while not self.exhausted:
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
            out.append(Reading("events", t_ns, values))
            self._next += 1
        return out
