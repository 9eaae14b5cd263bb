"""The min/max envelope the analysis plots are drawn from, against a plain loop over the bins."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.pipelines.plotting import minmax_envelope


def _loop_envelope(t: np.ndarray, y: np.ndarray, n_bins: int) -> tuple[list, list]:
    """Written separately: for each bin [i*n//b, (i+1)*n//b), its first time twice, the min and
    the max of the finite values (NaN when there is none)."""
    n = len(t)
    ts, ys = [], []
    for i in range(n_bins):
        a, b = i * n // n_bins, (i + 1) * n // n_bins
        ts += [t[a], t[a]]
        lo, hi = [], []
        for col in range(y.shape[1]):
            vals = [v for v in y[a:b, col] if v == v]
            lo.append(min(vals) if vals else float("nan"))
            hi.append(max(vals) if vals else float("nan"))
        ys += [lo, hi]
    return ts, ys


def test_envelope_matches_a_loop_and_keeps_spikes_and_gaps() -> None:
    rng = np.random.default_rng(5)
    n, m, bins = 10_007, 3, 97  # bins of unequal size
    t = np.arange(n) * 0.001
    y = rng.normal(100.0, 1.0, (n, m))
    y[1234, 1] = 250.0  # a one-sample spike
    y[5000:5300, 2] = np.nan  # a gap longer than a bin
    y[7000, 0] = np.nan  # one masked sample inside a bin
    td, yd = minmax_envelope(t, y, bins)
    et, ey = _loop_envelope(t, y, bins)
    assert td.shape == (2 * bins,) and yd.shape == (2 * bins, m)
    np.testing.assert_array_equal(td, et)
    np.testing.assert_array_equal(yd, np.array(ey))
    assert np.nanmax(yd[:, 1]) == 250.0
    assert np.isnan(yd[:, 2]).sum() >= 2  # the gap stays a gap
    assert np.isfinite(yd[:, 0]).all()


def test_short_series_unchanged_and_bad_input_said() -> None:
    t = np.arange(10)
    y = np.arange(10.0)
    td, yd = minmax_envelope(t, y, 5)
    assert td is t and yd.tolist() == y.tolist()
    with pytest.raises(ValueError, match="t has 10 samples, y 9"):
        minmax_envelope(t, y[:-1], 2)
    with pytest.raises(ValueError, match="n_bins"):
        minmax_envelope(t, y, 0)
