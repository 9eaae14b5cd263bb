"""Test-side drawing of a cable across an IR mark (issue 11): a dark straight band of width 1-3 px
through one blob, drawn on an already rendered frame with numpy only (analytic anti-aliased
coverage of the band, then the same Gaussian blur as the second renderer), so that the detector
under test never sees how the band was made."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from vision_grid_renderer import _blur


def draw_cable(
    img: NDArray[np.uint8],
    centre_px: tuple[float, float],
    angle_rad: float,
    offset_px: float,
    width_px: float,
    level_dn: float = 12.0,
    half_len_px: int = 30,
    blur_px: float = 0.7,
) -> NDArray[np.uint8]:
    """Copy of ``img`` with a band of ``width_px`` at ``angle_rad`` whose centre line passes
    ``offset_px`` from ``centre_px``; band pixels tend to ``level_dn`` (the cable is as dark as the
    background) in proportion to their coverage."""
    h, w = img.shape
    cx, cy = centre_px
    x0, x1 = max(int(cx) - half_len_px, 0), min(int(cx) + half_len_px + 1, w)
    y0, y1 = max(int(cy) - half_len_px, 0), min(int(cy) + half_len_px + 1, h)
    ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    nx, ny = -np.sin(angle_rad), np.cos(angle_rad)  # unit normal of the band
    d = np.abs((xs - cx) * nx + (ys - cy) * ny - offset_px)
    cover = np.clip(width_px / 2 + 0.5 - d, 0.0, 1.0)
    if blur_px > 0:
        cover = _blur(cover, blur_px)
    out = img.astype(np.float64)
    sub = out[y0:y1, x0:x1]
    out[y0:y1, x0:x1] = sub * (1 - cover) + level_dn * cover
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
