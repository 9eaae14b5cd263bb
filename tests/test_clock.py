"""The sampling instants from reception times and the sample counter: bursts of latency, lost
samples and a clock drift between the sensor and the host, against the instants they were made
from."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis.clock import sample_clock
from cdpr.analysis.errors import InputError


def _stream(rng: np.random.Generator, n: int, ppm: float, burst_ms: float):
    k = np.arange(n)
    k = k[rng.random(n) > 0.002]  # a few samples lost: the counter still counts them
    period = 1e6 * (1.0 + ppm * 1e-6)  # 1 kHz on the sensor's crystal, host's ns
    true = 1_790_000_000_000_000_000 + np.rint(k * period).astype(np.int64)
    latency = rng.exponential(0.2e6, k.size)  # USB/CAN adapter jitter, ~0.2 ms
    bursts = rng.random(k.size) < 0.02  # the host busy: tens of ms late, in runs
    latency = latency + np.where(bursts, rng.exponential(burst_ms * 1e6, k.size), 0.0)
    return k, true, true + latency.astype(np.int64)


@pytest.mark.parametrize("ppm", [0.0, 40.0])
def test_bursts_lost_samples_and_drift_leave_the_instants(ppm: float) -> None:
    rng = np.random.default_rng(int(ppm))
    k, true, rx = _stream(rng, 200_000, ppm, burst_ms=30.0)
    c = sample_clock(rx, k, segment_s=60.0)
    err = c.t_ns - true
    assert np.abs(err).max() < 0.05e6  # 50 us, where the reception times were up to ~0.2 s late
    assert np.abs(rx - true).max() > 50e6
    assert c.period_ns == pytest.approx(1e6 * (1 + ppm * 1e-6), rel=1e-6)
    assert np.all(np.diff(c.t_ns) > 0) and np.all(c.latency_ns > -1e3)


def test_an_hour_is_fast_and_bad_counters_are_refused() -> None:
    import time

    rng = np.random.default_rng(1)
    k, true, rx = _stream(rng, 3_600_000, 25.0, burst_ms=20.0)
    t0 = time.process_time()
    c = sample_clock(rx, k)
    assert time.process_time() - t0 < 20.0  # about 1 s idle; vectorised over samples
    assert c.segments == 60 and np.abs(c.t_ns - true).max() < 0.05e6
    with pytest.raises(InputError, match="increasing"):
        sample_clock(rx[:10], np.array([0, 1, 2, 2, 3, 4, 5, 6, 7, 8]))
    with pytest.raises(InputError, match="counter"):
        sample_clock(rx[:10], k[:9])


def test_sample_clock_sees_through_late_bursts() -> None:
    """1 kHz samples received with 0.2 ms of latency, in bursts up to 40 ms late (a loaded
    host), with a counter: the clock is the sample times plus the smallest latency."""
    rng = np.random.default_rng(0)
    n = 200_000
    true = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 1_000_000
    late = rng.exponential(50_000, n).astype(np.int64) + 200_000
    for s in rng.integers(0, n - 60, 40):  # bursts: 40 samples delivered together
        late[s : s + 40] = true[s + 40] - true[s : s + 40] + 200_000
    clock = sample_clock(true + late, np.arange(n) + 12345).t_ns
    err = clock - true - 200_000
    assert np.abs(err).max() < 20_000  # 20 us
