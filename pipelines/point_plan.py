"""The test points of a run: from its ``/events`` test-point events where it has them, else the
steady stretches detected in its signals (:func:`cdpr.analysis.balance.steady_points`), and the
per-point conditions the correction stages read (mean p, T, humidity, repeat groups).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cdpr.analysis.balance import (
    SteadyRule,
    interpolate_at,
    point_stats,
    points_from_events,
    steady_points,
)

from .run_arrays import RunData


@dataclass
class PointPlan:
    """The test points of a run: index ranges into the tension samples and what is known of each."""

    ranges: list[tuple[int, int]]
    labels: list[str]
    kind: list[str]
    source: str  # "events" | "detected"
    flags: list[str]
    targets: dict[str, list[Any]]
    motion: dict[str, list[Any]] = field(default_factory=dict)
    """An oscillation point's motion from its events (:data:`MOTION_FIELDS`; "" / NaN for a
    steady point)."""
    event_ns: list[tuple[int, int]] = field(default_factory=list)
    """Each point's start and end event times (points from events; empty when detected)."""


MOTION_FIELDS: tuple[str, ...] = (
    "motion_axis", "motion_amplitude", "motion_frequency_Hz", "motion_cycles",
    "motion_settling_cycles", "inertia_tare",
)  # fmt: skip
"""The fields of an oscillation point's ``test_point`` events (docs/dynamic_tests.md)."""


def plan_points(run: RunData, rule: SteadyRule) -> PointPlan:
    """Test points from the ``/events`` stream when the run has one, else detected steady points."""
    if run.events:
        opened: dict[str, tuple[int, dict[str, Any]]] = {}
        pts: list[tuple[int, int, dict[str, Any], str]] = []
        for t, b in run.events:
            label = str(b.get("point", ""))
            phase = b.get("phase")
            if phase == "start":
                for t0, b0 in opened.values():  # a point never ended closes here
                    pts.append((t0, t - 1, b0, "no_end_event"))
                opened = {label: (t, b)}
            elif phase == "end" and label in opened:
                t0, b0 = opened.pop(label)
                pts.append((t0, t, b0, ""))
        for t0, b0 in opened.values():
            pts.append((t0, int(run.t_ns[-1]), b0, "no_end_event"))
        pts.sort(key=lambda x: x[0])
        ranges = points_from_events(run.t_ns, [x[0] for x in pts], [x[1] for x in pts])
        targets = {
            k: [x[2].get(k, np.nan) for x in pts]
            for k in ("target_aoa_deg", "target_sideslip_deg", "target_airspeed_mps", "repeat_of")
        }
        motion = {
            k: [x[2].get(k, "" if k in ("motion_axis", "inertia_tare") else np.nan) for x in pts]
            for k in MOTION_FIELDS
        }
        return PointPlan(
            ranges,
            [str(x[2].get("point", "")) for x in pts],
            [str(x[2].get("kind", "wind_on")) for x in pts],
            "events",
            [x[3] for x in pts],
            targets,
            motion,
            [(int(x[0]), int(x[1])) for x in pts],
        )
    q = interpolate_at(run.t_ns, run.pose_t_ns[~run.pose_bad], run.poses[~run.pose_bad])
    v = run.tunnel[0] if run.tunnel is not None else None
    ranges = steady_points(run.t_ns, v, q, run.mask_bits == 0, rule)
    if v is None:
        kind = ["unknown"] * len(ranges)
    else:
        vm = np.array([np.nanmean(v[a:b]) for a, b in ranges])
        kind = ["tare" if x < rule.wind_off_mps else "wind_on" for x in vm]
    return PointPlan(
        ranges,
        [f"d{i:02d}" for i in range(len(ranges))],
        kind,
        "detected",
        [""] * len(ranges),
        {},
    )


def point_conditions(run: RunData, plan: PointPlan) -> dict[str, np.ndarray]:
    """Per-point inputs of the correction stages: ``temperature_K`` and ``static_pressure_Pa``
    (means over each point, NaN without them in the tunnel stream), ``relative_humidity`` (the
    mean over each point; NaN when any sample of the point has none) and ``repeat_group`` (the
    index of the point a point repeats, else its own)."""
    s = len(plan.ranges)
    out: dict[str, np.ndarray] = {}
    for k, key in enumerate(("static_pressure_Pa", "temperature_K")):
        if run.pressure_temperature is None:
            out[key] = np.full(s, np.nan)
        else:
            v = run.pressure_temperature[k]
            out[key] = point_stats(v, plan.ranges, run.mask_bits).mean[:, 0]
    rh = np.full(s, np.nan)
    if run.humidity is not None:
        for i, (a, b) in enumerate(plan.ranges):
            w = run.humidity[a:b]
            if w.size and np.isfinite(w).all():
                rh[i] = float(np.mean(w))
    out["relative_humidity"] = rh
    first = {lab: i for i, lab in reversed(list(enumerate(plan.labels)))}
    rep = plan.targets.get("repeat_of", [""] * s)
    out["repeat_group"] = np.array(
        [first.get(str(r), i) if isinstance(r, str) and r else i for i, r in enumerate(rep)],
        dtype=np.int64,
    )
    return out
