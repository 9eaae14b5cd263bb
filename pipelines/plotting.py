"""PNG figures written whole or not at all (matplotlib, Agg backend, imported lazily)."""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from .config import atomic_output


@contextmanager
def png_figure(
    path: str | os.PathLike[str],
    nrows: int = 1,
    ncols: int = 1,
    size: tuple[float, float] = (6.4, 4.4),
    dpi: int = 110,
    tight: bool = True,
    **subplots_kw: Any,
) -> Iterator[tuple[Any, Any]]:
    """A figure and its (nrows, ncols) array of axes (never squeezed) to draw on in the block.

    On leaving the block the figure is laid out (``tight_layout``), rendered as PNG at ``dpi`` and
    written with :func:`~cdpr.pipelines.config.atomic_output`; it is closed in every case, and an
    exception in the block writes nothing.  ``size`` is the figure size in inches; ``subplots_kw``
    go to ``plt.subplots`` (``sharex``, ``height_ratios``, ...).  ``tight=False`` skips
    ``tight_layout`` (the block lays the figure out itself: cheaper for a grid of many panels).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(nrows, ncols, figsize=size, squeeze=False, **subplots_kw)
    try:
        yield fig, axes
        if tight:
            fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=dpi)
    finally:
        plt.close(fig)
    with atomic_output(path, "wb") as fh:
        fh.write(buf.getvalue())


def minmax_bins(y: Any, n_bins: int) -> tuple[Any, Any, Any]:
    """The one binning of the decimated plots: ``n_bins`` bins of equal sample count over ``y``
    (n, ...) (n >= n_bins; bin k starts at ``k n // n_bins``), each bin's minimum and maximum per
    column with NaN ignored (a bin of NaN only stays NaN).  Returns ``(starts (b,), lo, hi)``.
    Vectorised: one ``fmin/fmax.reduceat``."""
    import warnings

    import numpy as np

    n = len(y)
    starts = (np.arange(n_bins, dtype=np.int64) * n) // n_bins
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN bins
        lo = np.fmin.reduceat(y, starts, axis=0)
        hi = np.fmax.reduceat(y, starts, axis=0)
    return starts, lo, hi


def minmax_envelope(t: Any, y: Any, n_bins: int = 2000) -> tuple[Any, Any]:
    """Decimate samples for a line plot: the min/max envelope over ``n_bins`` bins of equal sample
    count.

    ``t`` (n,) sample times, ``y`` (n,) or (n, m) values.  Returns ``(t_d, y_d)`` with two points
    per bin, both at the bin's first time: the bin's minimum then its maximum (per column, NaN
    ignored; a bin of NaN only stays NaN, so a gap stays a gap).  Drawn as a line, this covers
    exactly the pixels the full series would at a width of up to ``n_bins`` pixels (every spike
    stays visible), from ``2 * n_bins`` points instead of ``n``.  Series of at most ``2 * n_bins``
    samples come back unchanged.  Vectorised: one ``fmin/fmax.reduceat`` per call.
    """
    import numpy as np

    t = np.asarray(t)
    y = np.asarray(y, dtype=np.float64)
    if n_bins < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    if y.shape[0] != t.shape[0]:
        raise ValueError(f"t has {t.shape[0]} samples, y {y.shape[0]}")
    n = len(t)
    if n <= 2 * n_bins:
        return t, y
    starts, lo, hi = minmax_bins(y, n_bins)
    t_d = np.repeat(t[starts], 2)
    y_d = np.empty((2 * n_bins, *y.shape[1:]))
    y_d[0::2] = lo
    y_d[1::2] = hi
    return t_d, y_d
