"""A second, independent renderer for the vision tests: planar targets (circle grids) seen through
a pinhole camera without distortion, written with numpy only (no ``calibration/render.py``, no
OpenCV).  Each pixel is split into ``ss x ss`` samples; every sample's ray is intersected with the
target plane (inverse homography) and coloured dark inside a circle, white outside: the pixel is
the mean (area coverage, so edges are anti-aliased), then Gaussian noise is added."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def rotation_xyz(rx: float, ry: float, rz: float) -> NDArray[np.float64]:
    """R = Rz @ Ry @ Rx (rad)."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def render_circle_grid(
    K: NDArray[np.float64],
    size_wh: tuple[int, int],
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    n_xy: tuple[int, int],
    spacing_m: float,
    radius_m: float,
    rng: np.random.Generator,
    ss: int = 3,
    noise_dn: float = 2.0,
    dark_dn: float = 30.0,
    light_dn: float = 220.0,
) -> NDArray[np.uint8]:
    """Gray image of a symmetric grid of ``n_xy`` dark disks (centres at ``(i, j) * spacing_m``,
    z = 0 in the target frame) on a white card one spacing wider than the grid, on a mid-grey
    background; a target point x_t is at ``R x_t + t`` in the camera frame."""
    w, h = size_wh
    H = K @ np.column_stack([R[:, 0], R[:, 1], t])  # target plane (x, y, 1) -> pixel
    Hi = np.linalg.inv(H)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    u = np.arange(w)[None, :, None, None] + off[None, None, None, :]
    v = np.arange(h)[:, None, None, None] + off[None, None, :, None]
    Z = Hi[2, 0] * u + Hi[2, 1] * v + Hi[2, 2]
    x = (Hi[0, 0] * u + Hi[0, 1] * v + Hi[0, 2]) / Z
    y = (Hi[1, 0] * u + Hi[1, 1] * v + Hi[1, 2]) / Z
    nx, ny = n_xy
    card = (x >= -spacing_m) & (x <= nx * spacing_m) & (y >= -spacing_m) & (y <= ny * spacing_m)
    # the nearest centre of a regular grid is the rounded coordinate
    i = np.clip(np.rint(x / spacing_m), 0, nx - 1)
    j = np.clip(np.rint(y / spacing_m), 0, ny - 1)
    inside = (x - i * spacing_m) ** 2 + (y - j * spacing_m) ** 2 <= radius_m**2
    value = np.where(card, np.where(inside, dark_dn, light_dn), 120.0).mean(axis=(2, 3))
    value = value + rng.normal(0.0, noise_dn, value.shape)
    return np.clip(np.rint(value), 0, 255).astype(np.uint8)
