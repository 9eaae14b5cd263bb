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


def _blur(img: NDArray[np.float64], sigma_px: float) -> NDArray[np.float64]:
    """Separable Gaussian blur (numpy), edges replicated."""
    r = int(np.ceil(4 * sigma_px))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_px) ** 2)
    k /= k.sum()
    p = np.pad(img, r, mode="edge")
    p = sum(k[i] * p[:, i : i + img.shape[1]] for i in range(2 * r + 1))
    return sum(k[i] * p[i : i + img.shape[0], :] for i in range(2 * r + 1))


def render_ir_disks(
    K: NDArray[np.float64],
    size_wh: tuple[int, int],
    centres_C_m: NDArray[np.float64],
    normals_C: NDArray[np.float64],
    radius_m: float,
    rng: np.random.Generator,
    ss: int = 4,
    blur_px: float = 0.8,
    noise_dn: float = 1.5,
    background_dn: float = 12.0,
    spot_dn: float | NDArray[np.float64] = 235.0,
    gradient: tuple[float, float] = (0.0, 0.0),
    background_ramp_dn: tuple[float, float] = (0.0, 0.0),
) -> NDArray[np.uint8]:
    """Gray IR frame of bright flat disks (centres (N, 3) and unit normals (N, 3) in the camera
    frame, m) on a dark background, through a distortion-free pinhole camera ``K``: every sample
    ray is intersected with each disk's plane, coverage per pixel, Gaussian optical blur, noise.

    The world's mess: ``spot_dn`` one level for every disk or one per disk (retro-reflectors seen
    at different angles and distances differ by tens of percent; levels above 255 clip, as a
    saturated sensor does); ``gradient`` (gx, gy) a smooth illumination field multiplying the
    scene, ``1 + gx (u - w/2) / w + gy (v - h/2) / h`` (uneven IR lighting: ``(0.3, 0)`` is 30 %
    brighter at the right edge than at the left); ``background_ramp_dn`` (rx, ry) an additive
    background ramp over the frame, DN from the centre to the right / bottom edge (stray light)."""
    w, h = size_wh
    n_disks = len(np.asarray(centres_C_m))
    spots = np.broadcast_to(np.asarray(spot_dn, np.float64), (n_disks,))
    scene = np.zeros((h, w))  # spot level above the background, per pixel (coverage-weighted)
    cover = np.zeros((h, w))
    Ki = np.linalg.inv(K)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    for c, n, spot in zip(np.asarray(centres_C_m), np.asarray(normals_C), spots, strict=True):
        u0, v0 = (K @ c)[:2] / c[2]
        rpx = K[0, 0] * radius_m / c[2] + 3
        x0, x1 = int(max(np.floor(u0 - rpx), 0)), int(min(np.ceil(u0 + rpx) + 1, w))
        y0, y1 = int(max(np.floor(v0 - rpx), 0)), int(min(np.ceil(v0 + rpx) + 1, h))
        if x1 <= x0 or y1 <= y0:
            continue
        u = np.arange(x0, x1)[None, :, None, None] + off[None, None, None, :]
        v = np.arange(y0, y1)[:, None, None, None] + off[None, None, :, None]
        u, v = np.broadcast_arrays(u, v)
        d = np.stack([u, v, np.ones_like(u)], axis=-1) @ Ki.T  # rays (.., 3)
        s = (n @ c) / (d @ n)
        X = d * s[..., None]
        inside = np.sum((X - c) ** 2, axis=-1) <= radius_m**2
        cov = inside.mean(axis=(2, 3))
        region = scene[y0:y1, x0:x1]
        nearer = cov > cover[y0:y1, x0:x1]
        region[nearer] = (spot - background_dn) * cov[nearer]
        cover[y0:y1, x0:x1] = np.maximum(cover[y0:y1, x0:x1], cov)
    vv, uu = np.mgrid[0:h, 0:w]
    field = 1.0 + gradient[0] * (uu - w / 2) / w + gradient[1] * (vv - h / 2) / h
    ramp = background_ramp_dn[0] * (uu - w / 2) / (w / 2) + background_ramp_dn[1] * (vv - h / 2) / (
        h / 2
    )
    img = (background_dn + scene) * field + ramp
    if blur_px > 0:
        img = _blur(img, blur_px)
    img = img + rng.normal(0.0, noise_dn, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_square_markers(
    K: NDArray[np.float64],
    size_wh: tuple[int, int],
    corners_C_m: NDArray[np.float64],
    bits: list[NDArray[np.uint8]],
    quiet_zone_cells: float,
    rng: np.random.Generator,
    ss: int = 4,
    blur_px: float = 0.8,
    noise_dn: float = 1.5,
    background_dn: float = 110.0,
    dark_dn: float = 25.0,
    light_dn: float = 225.0,
    gain: float = 1.0,
) -> NDArray[np.uint8]:
    """Gray frame of square fiducials through a distortion-free pinhole camera ``K``.

    ``corners_C_m`` (N, 4, 3): each marker's black-square corners in the camera frame, in the order
    TL, TR, BR, BL; ``bits[i]`` (n, n): its cells (0 black, else white, black border included),
    row 0 along TL->TR; a white quiet zone of ``quiet_zone_cells`` cells surrounds it.  Every one of
    the ``ss x ss`` sample rays per pixel is intersected with the marker's plane and coloured by the
    cell it hits (area coverage), then Gaussian optical blur, ``gain`` (exposure), clipping at 255
    (a gain above 255 / light_dn saturates the whites, as an overexposed sensor does), noise."""
    w, h = size_wh
    img = np.full((h, w), background_dn)
    Ki = np.linalg.inv(K)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    r = int(np.ceil(4 * blur_px)) + 1
    box = [w, h, 0, 0]  # region to blur: the markers' boxes
    for C, b in zip(np.asarray(corners_C_m, np.float64), bits, strict=True):
        n = b.shape[0]
        tl = C[0]
        side = np.linalg.norm(C[1] - C[0])
        cell = side / n
        eu = (C[1] - C[0]) / side
        ev = (C[3] - C[0]) / np.linalg.norm(C[3] - C[0])
        nrm = np.cross(eu, ev)
        q = quiet_zone_cells * cell
        outer = np.array([tl + a * eu + c * ev for a in (-q, side + q) for c in (-q, side + q)])
        uv = outer @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        x0, x1 = int(max(np.floor(uv[:, 0].min()) - 2, 0)), int(min(np.ceil(uv[:, 0].max()) + 3, w))
        y0, y1 = int(max(np.floor(uv[:, 1].min()) - 2, 0)), int(min(np.ceil(uv[:, 1].max()) + 3, h))
        if x1 <= x0 or y1 <= y0:
            continue
        box = [min(box[0], x0), min(box[1], y0), max(box[2], x1), max(box[3], y1)]
        u = np.arange(x0, x1)[None, :, None, None] + off[None, None, None, :]
        v = np.arange(y0, y1)[:, None, None, None] + off[None, None, :, None]
        # ray d = Ki (u, v, 1) meets the plane at s = n.tl / n.d; plane coordinates are then
        # s d.e - tl.e: every dot product with d is linear in (u, v)
        ln, la, lc = Ki.T @ nrm, Ki.T @ eu, Ki.T @ ev
        s_ = (nrm @ tl) / (ln[0] * u + ln[1] * v + ln[2])
        a = (s_ * (la[0] * u + la[1] * v + la[2]) - tl @ eu) / cell  # column, along TL->TR
        c = (s_ * (lc[0] * u + lc[1] * v + lc[2]) - tl @ ev) / cell  # row, along TL->BL
        inside_zone = (a >= -quiet_zone_cells) & (a < n + quiet_zone_cells)
        inside_zone &= (c >= -quiet_zone_cells) & (c < n + quiet_zone_cells)
        in_marker = (a >= 0) & (a < n) & (c >= 0) & (c < n)
        ia = np.clip(np.floor(a), 0, n - 1).astype(int)
        ic = np.clip(np.floor(c), 0, n - 1).astype(int)
        val = np.where(in_marker & (b[ic, ia] == 0), dark_dn, light_dn)
        patch = img[y0:y1, x0:x1][:, :, None, None]
        img[y0:y1, x0:x1] = np.where(inside_zone, val, patch).mean(axis=(2, 3))
    if blur_px > 0 and box[2] > box[0]:
        x0, y0 = max(box[0] - r, 0), max(box[1] - r, 0)
        x1, y1 = min(box[2] + r, w), min(box[3] + r, h)
        img[y0:y1, x0:x1] = _blur(img[y0:y1, x0:x1], blur_px)  # elsewhere: uniform background
    img = gain * img + rng.normal(0.0, noise_dn, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
