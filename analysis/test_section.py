"""The test section's geometry in {O}: a straight prism along x with a convex cross-section.

The flow fills the prism (closed section: between the walls; open jet: the jet, taken as the
nozzle's section carried downstream) and is still outside it.  The windage model loads only the
part of each cable inside; the wall corrections use the cross-section area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .errors import InputError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class SectionGeometry:
    """A prism ``x_start_m <= x <= x_end_m`` with the convex polygon ``polygon_yz_m`` (k, 2) in y-z.

    polygon_yz_m: vertices (y, z) in {O}, m, counter-clockwise, convex.
    """

    x_start_m: float
    x_end_m: float
    polygon_yz_m: FloatArray

    def __post_init__(self) -> None:
        poly = check_trailing(self.polygon_yz_m, "polygon_yz_m", (2,))
        if poly.ndim != 2 or poly.shape[0] < 3:
            raise InputError(f"polygon_yz_m: expected (k >= 3, 2) vertices, got {poly.shape}")
        if not self.x_end_m > self.x_start_m:
            raise InputError("x_end_m: expected > x_start_m")
        e = np.roll(poly, -1, axis=0) - poly
        cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
        if np.any(cross <= 0):
            raise InputError("polygon_yz_m: expected a convex polygon, counter-clockwise")
        poly = poly.copy()
        poly.setflags(write=False)
        object.__setattr__(self, "polygon_yz_m", poly)

    @property
    def area_m2(self) -> float:
        """Cross-section area (shoelace formula), m^2."""
        y, z = self.polygon_yz_m[:, 0], self.polygon_yz_m[:, 1]
        return float(0.5 * np.sum(y * np.roll(z, -1) - np.roll(y, -1) * z))

    def half_spaces(self) -> tuple[FloatArray, FloatArray]:
        """``(normals (k+2, 3), offsets (k+2,))``: the prism is ``normals @ x <= offsets``."""
        poly = self.polygon_yz_m
        e = np.roll(poly, -1, axis=0) - poly
        n_yz = np.stack([e[:, 1], -e[:, 0]], axis=1)  # outward for a CCW polygon
        n_yz /= np.linalg.norm(n_yz, axis=1, keepdims=True)
        normals = np.zeros((poly.shape[0] + 2, 3))
        normals[:-2, 1:] = n_yz
        normals[-2] = [-1.0, 0.0, 0.0]
        normals[-1] = [1.0, 0.0, 0.0]
        offsets = np.concatenate(
            [np.einsum("ij,ij->i", n_yz, poly), [-self.x_start_m, self.x_end_m]]
        )
        return normals, offsets


def regular_octagon(side_m: float, center_yz_m: ArrayLike = (0.0, 0.0)) -> FloatArray:
    """Vertices (8, 2) of a regular octagon with flat sides on top, bottom and the walls."""
    if not side_m > 0:
        raise InputError(f"side_m: expected > 0 m, got {side_m}")
    apothem = side_m * (1.0 + np.sqrt(2.0)) / 2.0
    angles = np.deg2rad(22.5 + 45.0 * np.arange(8))
    radius = apothem / np.cos(np.deg2rad(22.5))
    c = np.asarray(center_yz_m, dtype=np.float64)
    return np.stack([radius * np.cos(angles), radius * np.sin(angles)], axis=1) + c


def rectangle(width_m: float, height_m: float, center_yz_m: ArrayLike = (0.0, 0.0)) -> FloatArray:
    """Vertices (4, 2) of a width (y) x height (z) rectangle."""
    if not (width_m > 0 and height_m > 0):
        raise InputError("width_m, height_m: expected > 0 m")
    c = np.asarray(center_yz_m, dtype=np.float64)
    w, h = width_m / 2, height_m / 2
    return np.array([[w, -h], [w, h], [-w, h], [-w, -h]]) + c


def segment_inside(
    start_O_m: ArrayLike, end_O_m: ArrayLike, section: SectionGeometry
) -> tuple[FloatArray, FloatArray]:
    """Parameters ``(s_in, s_out)`` (..., each in [0, 1]) of the part of each segment inside.

    The segment is ``start + s (end - start)``; ``s_out <= s_in`` when it misses the prism
    (Cyrus-Beck clipping against the prism's half-spaces, vectorised).
    """
    a = check_trailing(start_O_m, "start_O_m", (3,))
    b = check_trailing(end_O_m, "end_O_m", (3,))
    normals, offsets = section.half_spaces()
    d = b - a
    num = offsets - a @ normals.T  # (..., planes): slack at s = 0
    den = d @ normals.T  # (..., planes)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = num / den
    lower = np.where(den < 0, s, -np.inf)
    upper = np.where(den > 0, s, np.inf)
    parallel_out = (den == 0) & (num < 0)
    s_in = np.clip(np.max(lower, axis=-1), 0.0, 1.0)
    s_out = np.clip(np.min(upper, axis=-1), 0.0, 1.0)
    s_out = np.where(np.any(parallel_out, axis=-1), s_in, s_out)
    return s_in, np.maximum(s_out, s_in)
