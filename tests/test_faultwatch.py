"""The data-fault detector on tension samples made here (a separate generator: counts = a slow ramp
plus Gaussian noise per cable) with known faults at known samples: a stuck cell, a noise burst,
status flags, a short flag inside one batch; clean data raises nothing.  Batches of 2 samples, as a
busy CAN read gives them."""

from __future__ import annotations

import numpy as np

from cdpr.daq.faultwatch import DataWatch
from cdpr.daq.source import STATUS_BAD_FRAME, Reading

CABLES = ["a", "b", "c"]
RATE_HZ = 200.0


def _samples(n: int, seed: int, sd_counts: float = 800.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ramp = np.linspace(0, 5000, n)[:, None] + np.array([2.0e6, 2.1e6, 2.2e6])
    return np.round(ramp + rng.normal(0, sd_counts, (n, len(CABLES)))).astype(np.int64)


def _feed(counts: np.ndarray, status: np.ndarray | None = None, batch: int = 2) -> list[dict]:
    events: list[dict] = []
    w = DataWatch(lambda msg, level, **kw: events.append({"message": msg, "level": level, **kw}))
    st = np.zeros_like(counts) if status is None else status
    rs = [
        Reading(
            "tensions",
            int(k * 1e9 / RATE_HZ),
            {
                **{f"T_{c}_N": float(counts[k, j]) * 5e-5 for j, c in enumerate(CABLES)},
                **{f"raw_{c}_counts": int(counts[k, j]) for j, c in enumerate(CABLES)},
                **{f"status_{c}": int(st[k, j]) for j, c in enumerate(CABLES)},
            },
        )
        for k in range(len(counts))
    ]
    for i in range(0, len(rs), batch):
        w.feed(rs[i : i + batch])
    return events


def _kinds(events: list[dict]) -> list[tuple[str, str, int]]:
    return [(e["fault"], e.get("cable", ""), int(e["t_start_ns"] * RATE_HZ / 1e9)) for e in events]


def test_clean_data_raises_nothing() -> None:
    for seed in range(3):
        assert _feed(_samples(1500, seed)) == []


def test_a_stuck_cell_and_its_end() -> None:
    c = _samples(1000, 1)
    c[400:600, 1] = c[399, 1]  # cable b repeats its last counts for 1 s
    ev = _kinds(_feed(c))
    assert ev == [("stuck", "b", 400), ("stuck_end", "b", 400)]


def test_a_noise_burst_on_one_cable() -> None:
    c = _samples(1200, 2)
    rng = np.random.default_rng(9)
    c[500:700, 2] += np.round(rng.normal(0, 800 * 20, 200)).astype(np.int64)
    ev = [e for e in _feed(c) if e["fault"] == "noise_burst"]
    assert len(ev) == 1 and ev[0]["cable"] == "c"
    assert 500 <= ev[0]["t_start_ns"] * RATE_HZ / 1e9 <= 530  # within 0.15 s of its start


def test_status_flags_even_a_single_flagged_sample() -> None:
    c = _samples(600, 3)
    st = np.zeros_like(c)
    st[100:300, 0] = 2  # slack
    st[401, 2] = 1  # one saturated sample, inside one batch of two
    ev = _kinds(_feed(c, st))
    assert ("slack", "a", 100) in ev and ("slack_end", "a", 100) in ev
    assert ("saturated", "c", 401) in ev and ("saturated_end", "c", 401) in ev
    assert not [k for k in ev if k[0].startswith(("stuck", "noise"))]  # flags are no noise


def test_camera_poses_flagged_bad_are_markers_lost() -> None:
    events: list[dict] = []
    w = DataWatch(lambda msg, level, **kw: events.append({"message": msg, **kw}))
    for k in range(30):
        bad = 10 <= k < 20
        w.feed([Reading("pose", k * 100_000_000, {"n_points": 0 if bad else 12},
                        STATUS_BAD_FRAME if bad else 0)])  # fmt: skip
    assert [(e["fault"], e["t_start_ns"]) for e in events] == [
        ("markers_lost", 1_000_000_000),
        ("markers_lost_end", 1_000_000_000),
    ]
