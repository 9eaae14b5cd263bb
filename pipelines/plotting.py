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
    **subplots_kw: Any,
) -> Iterator[tuple[Any, Any]]:
    """A figure and its (nrows, ncols) array of axes (never squeezed) to draw on in the block.

    On leaving the block the figure is laid out (``tight_layout``), rendered as PNG at ``dpi`` and
    written with :func:`~cdpr.pipelines.config.atomic_output`; it is closed in every case, and an
    exception in the block writes nothing.  ``size`` is the figure size in inches; ``subplots_kw``
    go to ``plt.subplots`` (``sharex``, ``height_ratios``, ...).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(nrows, ncols, figsize=size, squeeze=False, **subplots_kw)
    try:
        yield fig, axes
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=dpi)
    finally:
        plt.close(fig)
    with atomic_output(path, "wb") as fh:
        fh.write(buf.getvalue())
