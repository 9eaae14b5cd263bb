"""Virtual camera: renders fiducials, IR spots or ChArUco boards through a camera model.

Each planar patch (a marker with its white quiet zone, an IR disk, a calibration board) is rendered by
ray casting: every pixel is split into ``k x k`` sub-samples placed at jittered positions inside
their sub-cells (stratified sampling: the area coverage of an edge is estimated without bias, the
estimate's spread shows up as a little extra noise); each sub-sample's pixel position is undistorted
to a ray through the camera model, the ray is intersected with the patch plane, and the patch's
texture (nearest texel, exact cell edges) or its analytic shape is sampled there.  The sub-samples
are averaged per pixel, the image is blurred with a Gaussian optical PSF, Gaussian read noise is
added, and the result is quantised to uint8.

Half-pixel convention (OpenCV's): pixel ``(i, j)`` (column i, row j) covers ``[i-0.5, i+0.5] x
[j-0.5, j+0.5]``; so a point projected by ``cv2.projectPoints`` at ``(u, v)`` is the true image
position that the detectors should find.

Undistortion of the sub-sample positions: exact (iterative) at the pixel corners of each patch's
region, bilinearly interpolated inside each pixel (the error of that is < 1e-5 px for any real lens).
Not modelled: occlusion between markers, shading, the model body (uniform background), rolling shutter.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import cv
from .camera_model import CameraModel
from .markers import MarkerLayout

F64 = NDArray[np.float64]


@dataclass
class RenderSettings:
    """How frames look: sub-samples per pixel side, optical blur (px), read noise (DN), levels (DN).

    ``dark_dn``/``light_dn``: printed black/white of fiducials; ``background_dn``: the scene behind
    the markers; ``spot_dn``: IR disk brightness on the ``background_dn`` of an IR scene.
    """

    supersample: int = 3
    blur_sigma_px: float = 0.7
    noise_sigma_dn: float = 1.0
    background_dn: float = 110.0
    dark_dn: float = 25.0
    light_dn: float = 225.0
    spot_dn: float = 235.0
    ir_background_dn: float = 12.0
    jitter: bool = True
    illumination_gradient: tuple[float, float] = (0.0, 0.0)
    """(gx, gy): a smooth illumination field multiplying the whole scene,
    ``1 + gx (u - W/2) / W + gy (v - H/2) / H`` (uneven lighting; (0, 0): even)."""


_MAP_CACHE: dict[
    tuple[str, int], tuple[NDArray[np.float32], NDArray[np.float32], F64, tuple[int, int]]
] = {}
"""Per-camera resampling maps of :meth:`VirtualCamera.render_board` (a cache, not state)."""

# Shader: (x_m, y_m) in the patch plane -> (value_DN, inside 0/1)
Shader = Callable[[F64, F64], tuple[F64, F64]]


@dataclass
class _Patch:
    origin_C: F64  # a point of the plane, camera frame (m)
    ex_C: F64  # in-plane unit x axis
    ey_C: F64  # in-plane unit y axis
    normal_C: F64  # visible-side normal
    outline_m: F64  # (K, 2) plane coordinates bounding the patch (for the region of interest)
    shader: Shader


class VirtualCamera:
    """Render frames seen by ``camera`` (a :class:`CameraModel`, extrinsics used for {O} poses)."""

    def __init__(self, camera: CameraModel, settings: RenderSettings | None = None) -> None:
        self.camera = camera
        self.settings = settings or RenderSettings()

    # -- public ------------------------------------------------------------------------------
    def render_fiducials(
        self,
        layout: MarkerLayout,
        position_O_m: ArrayLike,
        R_O_P: ArrayLike,
        rng: np.random.Generator | None = None,
    ) -> NDArray[np.uint8]:
        """Frame (H, W) uint8 of a fiducial layout in {P} at platform pose (position_O_m, R_O_P)."""
        R_C_F, t_C_F = self._layout_pose(layout, position_O_m, R_O_P)
        s = self.settings
        patches = [self._fiducial_patch(layout, f, R_C_F, t_C_F) for f in layout.fiducials]
        return self._render(patches, s.background_dn, rng)

    def render_points(
        self,
        layout: MarkerLayout,
        position_O_m: ArrayLike,
        R_O_P: ArrayLike,
        rng: np.random.Generator | None = None,
        spurious_C: ArrayLike | None = None,
        spot_dn: ArrayLike | None = None,
    ) -> NDArray[np.uint8]:
        """Frame of IR disks (a ``"points"`` layout) at the platform pose.

        ``spurious_C``: optional (K, 4) extra disks ``[x, y, z, radius]`` in the camera frame
        (reflections, facing the camera) for robustness tests.  ``spot_dn``: optional level of
        each disk (M,), DN (retro-reflective marks differ by tens of percent with the angle and
        distance they are seen at; above 255 the sensor clips); default ``settings.spot_dn``.
        """
        R_C_F, t_C_F = self._layout_pose(layout, position_O_m, R_O_P)
        levels = np.broadcast_to(
            np.asarray(self.settings.spot_dn if spot_dn is None else spot_dn, np.float64),
            (len(layout.points),),
        )
        patches = [
            self._disk_patch(R_C_F @ p.center_m + t_C_F, R_C_F @ p.normal, p.radius_m, level)
            for p, level in zip(layout.points, levels, strict=True)
        ]
        if spurious_C is not None:
            for x, y, z, r in np.asarray(spurious_C, np.float64).reshape(-1, 4):
                c = np.array([x, y, z])
                patches.append(
                    self._disk_patch(c, -c / np.linalg.norm(c), r, self.settings.spot_dn)
                )
        return self._render(patches, self.settings.ir_background_dn, rng)

    def render_board(
        self,
        board: cv.CharucoBoard,
        R_C_B: ArrayLike,
        t_C_B: ArrayLike,
        rng: np.random.Generator | None = None,
        supersample: int = 2,
    ) -> NDArray[np.uint8]:
        """Frame of a ChArUco board at pose (R_C_B, t_C_B) in the camera frame (board frame as
        OpenCV's: x right, y down along the printed board, z into the board).

        Faster path than the ray caster (a board fills much of the frame): the board texture is
        warped by its exact homography into an ideal (distortion-free) image at ``supersample``
        times the resolution, which is resampled through the lens distortion by a cached per-camera
        map (exact iterative undistortion of every sub-sample), then area-averaged; blur and noise as
        for the other scenes.  Bilinear interpolation blurs edges symmetrically (no shift).
        """
        s = self.settings
        rng = rng if rng is not None else np.random.default_rng()
        R = np.asarray(R_C_B, np.float64)
        t = np.asarray(t_C_B, np.float64)
        k = max(int(supersample), 1)
        map_x, map_y, Ki, ideal_wh = self._ideal_maps(k)
        tpsq = 160
        margin_px = tpsq // 2
        img = board.image(tpsq, margin_px=margin_px)
        tex = np.where(img > 127, s.light_dn, s.dark_dn).astype(np.float32)
        texel = board.square_m / tpsq
        A = np.array(
            [
                [texel, 0, 0.5 * texel - margin_px * texel],
                [0, texel, 0.5 * texel - margin_px * texel],
                [0, 0, 1],
            ]
        )
        Hm = Ki @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
        ideal = cv.warp_perspective(tex, Hm, ideal_wh, border_value=s.background_dn)
        hi = cv.remap(ideal, map_x, map_y, nearest=False, border_value=s.background_dn)
        canvas = cv.downsample_area(hi, k).astype(np.float32)
        if s.blur_sigma_px > 0:
            canvas = cv.gaussian_blur(canvas, s.blur_sigma_px)
        if s.noise_sigma_dn > 0:
            canvas += np.float32(s.noise_sigma_dn) * rng.standard_normal(
                canvas.shape, dtype=np.float32
            )
        return np.clip(np.rint(canvas), 0, 255).astype(np.uint8)

    def _ideal_maps(
        self, k: int
    ) -> tuple[NDArray[np.float32], NDArray[np.float32], F64, tuple[int, int]]:
        key = (self.camera.id, k)
        if key in _MAP_CACHE:
            return _MAP_CACHE[key]
        cam = self.camera
        W, H = cam.image_size_px
        xs = (np.arange(W * k) + 0.5) / k - 0.5
        ys = (np.arange(H * k) + 0.5) / k - 0.5
        XX, YY = np.meshgrid(xs, ys)
        xn = cv.undistort_to_normalized(np.stack([XX.ravel(), YY.ravel()], 1), cam.K, cam.dist)
        pad = int(0.2 * max(W, H) * k)
        fx, fy = cam.K[0, 0] * k, cam.K[1, 1] * k
        cx = (cam.K[0, 2] + 0.5) * k - 0.5 + pad
        cy = (cam.K[1, 2] + 0.5) * k - 0.5 + pad
        Ki = np.array([[fx, cam.K[0, 1] * k, cx], [0, fy, cy], [0, 0, 1]])
        u = (fx * xn[:, 0] + Ki[0, 1] * xn[:, 1] + cx).reshape(H * k, W * k).astype(np.float32)
        v = (fy * xn[:, 1] + cy).reshape(H * k, W * k).astype(np.float32)
        out = (u, v, Ki, (W * k + 2 * pad, H * k + 2 * pad))
        _MAP_CACHE.clear()  # one camera at a time (the maps are large)
        _MAP_CACHE[key] = out
        return out

    # -- truth ---------------------------------------------------------------------------------
    def project_layout(
        self, layout: MarkerLayout, position_O_m: ArrayLike, R_O_P: ArrayLike
    ) -> F64:
        """True image positions: fiducial corners (N, 4, 2) or point centres (N, 2), px."""
        R_C_F, t_C_F = self._layout_pose(layout, position_O_m, R_O_P)
        rvec = cv.rotation_vector(R_C_F)
        cam = self.camera
        if layout.kind == "fiducial":
            pts = layout.fiducial_corners_m.reshape(-1, 3)
            return cv.project_points(pts, rvec, t_C_F, cam.K, cam.dist).reshape(-1, 4, 2)
        return cv.project_points(layout.point_centers_m, rvec, t_C_F, cam.K, cam.dist)

    # -- internals ---------------------------------------------------------------------------
    def _layout_pose(
        self, layout: MarkerLayout, position_O_m: ArrayLike, R_O_P: ArrayLike
    ) -> tuple[F64, F64]:
        if layout.frame == "O":
            return self.camera.R_C_O, -self.camera.R_C_O @ self.camera.position_O_m
        return self.camera.pose_C_P(position_O_m, R_O_P)

    def _fiducial_patch(self, layout: MarkerLayout, f, R_C_F: F64, t_C_F: F64) -> _Patch:  # type: ignore[no-untyped-def]
        s = self.settings
        bits = cv.marker_bits_image(layout.dictionary, f.id)
        n = bits.shape[0]
        q = int(round(layout.quiet_zone_cells))
        tex = np.pad(
            np.where(bits > 127, s.light_dn, s.dark_dn), q, constant_values=s.light_dn
        ).astype(np.float32)
        cell = f.size_m / n
        half = f.size_m / 2 + q * cell
        m = tex.shape[0]

        def shader(x: F64, y: F64) -> tuple[F64, F64]:
            u = np.floor((x + half) / cell).astype(np.int64)
            v = np.floor((half - y) / cell).astype(np.int64)  # texture rows go down, marker y up
            inside = (u >= 0) & (u < m) & (v >= 0) & (v < m)
            return tex[np.clip(v, 0, m - 1), np.clip(u, 0, m - 1)], inside.astype(np.float32)

        R = R_C_F @ f.R_F_M
        outline = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
        return _Patch(R_C_F @ f.center_m + t_C_F, R[:, 0], R[:, 1], R[:, 2], outline, shader)

    def _disk_patch(self, center_C: F64, normal_C: F64, radius_m: float, level: float) -> _Patch:
        n = normal_C / np.linalg.norm(normal_C)
        a = np.cross(n, [1.0, 0.0, 0.0])
        if np.linalg.norm(a) < 1e-6:
            a = np.cross(n, [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        r2 = radius_m**2

        def shader(x: F64, y: F64) -> tuple[F64, F64]:
            inside = (x * x + y * y <= r2).astype(np.float32)
            return np.full_like(x, level, dtype=np.float32), inside

        ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        outline = 1.1 * radius_m * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        return _Patch(center_C, a, b, n, outline, shader)

    def _render(
        self, patches: list[_Patch], background: float, rng: np.random.Generator | None
    ) -> NDArray[np.uint8]:
        s = self.settings
        rng = rng if rng is not None else np.random.default_rng()
        W, H = self.camera.image_size_px
        canvas = np.full((H, W), background, dtype=np.float32)
        rois = [r for p in patches if (r := self._draw(canvas, p, rng)) is not None]
        gx, gy = s.illumination_gradient
        if gx or gy:
            u = (np.arange(W, dtype=np.float32) - W / 2) / W
            v = (np.arange(H, dtype=np.float32) - H / 2) / H
            canvas *= np.float32(1.0) + np.float32(gx) * u[None, :] + np.float32(gy) * v[:, None]
        if s.blur_sigma_px > 0:
            # the background is uniform: blurring each drawn region (grown by the kernel radius) is
            # the same as blurring the whole frame, and much cheaper
            rad = int(np.ceil(4 * s.blur_sigma_px)) + 1
            for x0, y0, x1, y1 in _merge_rois(rois, rad, W, H):
                canvas[y0:y1, x0:x1] = cv.gaussian_blur(
                    np.ascontiguousarray(canvas[y0:y1, x0:x1]), s.blur_sigma_px
                )
        if s.noise_sigma_dn > 0:
            canvas += np.float32(s.noise_sigma_dn) * rng.standard_normal(
                canvas.shape, dtype=np.float32
            )
        return np.clip(np.rint(canvas), 0, 255).astype(np.uint8)

    def _draw(
        self, canvas: NDArray[np.float32], p: _Patch, rng: np.random.Generator
    ) -> tuple[int, int, int, int] | None:
        cam = self.camera
        W, H = cam.image_size_px
        if p.normal_C @ p.origin_C >= 0:  # seen from behind
            return None
        outline_C = p.origin_C + p.outline_m[:, :1] * p.ex_C + p.outline_m[:, 1:] * p.ey_C
        if np.any(outline_C[:, 2] <= 1e-6):
            return None
        uv = cv.project_points(outline_C, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        pad = 3.0 * self.settings.blur_sigma_px + 2
        x0 = max(int(np.floor(uv[:, 0].min() - pad)), 0)
        x1 = min(int(np.ceil(uv[:, 0].max() + pad)), W - 1)
        y0 = max(int(np.floor(uv[:, 1].min() - pad)), 0)
        y1 = min(int(np.ceil(uv[:, 1].max() + pad)), H - 1)
        if x1 < x0 or y1 < y0:
            return None
        w, h = x1 - x0 + 1, y1 - y0 + 1
        # exact undistortion at the pixel corners of the region
        gx = np.arange(w + 1) + x0 - 0.5
        gy = np.arange(h + 1) + y0 - 0.5
        GX, GY = np.meshgrid(gx, gy)
        nodes = cv.undistort_to_normalized(np.stack([GX.ravel(), GY.ravel()], 1), cam.K, cam.dist)
        nodes = nodes.reshape(h + 1, w + 1, 2)
        # exact plane coordinates at the nodes (ray-plane intersection)
        nrm = np.cross(p.ex_C, p.ey_C)
        denom = nodes[..., 0] * nrm[0] + nodes[..., 1] * nrm[1] + nrm[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = (nrm @ p.origin_C) / denom
        if not np.all(np.isfinite(depth) & (depth > 0)):
            return None  # the plane is seen edge-on or crosses the camera: not rendered
        dx = nodes[..., 0] * depth - p.origin_C[0]
        dy = nodes[..., 1] * depth - p.origin_C[1]
        dz = depth - p.origin_C[2]
        XM = (dx * p.ex_C[0] + dy * p.ex_C[1] + dz * p.ex_C[2]).ravel()
        YM = (dx * p.ey_C[0] + dy * p.ey_C[1] + dz * p.ey_C[2]).ravel()
        # pixels whose four corners see the same value are uniform (features are several pixels
        # wide); only the others (dilated by one pixel) are supersampled
        f32 = np.float32
        XM = XM.astype(f32)
        YM = YM.astype(f32)
        nval, nin = p.shader(XM, YM)
        nval = np.where(nin > 0, nval, f32(-1.0)).reshape(h + 1, w + 1)
        c00, c01, c10, c11 = nval[:-1, :-1], nval[:-1, 1:], nval[1:, :-1], nval[1:, 1:]
        mixed = (c00 != c01) | (c00 != c10) | (c00 != c11)
        grow = mixed.copy()
        grow[1:] |= mixed[:-1]
        grow[:-1] |= mixed[1:]
        grow[:, 1:] |= mixed[:, :-1]
        grow[:, :-1] |= mixed[:, 1:]
        cov = (c00 >= 0).astype(np.float64)
        acc = np.where(c00 >= 0, c00, 0.0).astype(np.float64)
        py, px = np.nonzero(grow)
        if len(py):
            k = max(int(self.settings.supersample), 1)
            base = ((np.arange(k) + 0.5) / k).astype(f32)
            shape = (len(py), k, k)
            FX = np.broadcast_to(base[None, None, :], shape)
            FY = np.broadcast_to(base[None, :, None], shape)
            if self.settings.jitter:
                FX = FX + (rng.random(shape, dtype=f32) - f32(0.5)) / f32(k)
                FY = FY + (rng.random(shape, dtype=f32) - f32(0.5)) / f32(k)
            i00 = (py * (w + 1) + px)[:, None, None]
            i01, i10, i11 = i00 + 1, i00 + (w + 1), i00 + (w + 2)
            gx, gy = f32(1.0) - FX, f32(1.0) - FY
            w00, w01, w10, w11 = gx * gy, FX * gy, gx * FY, FX * FY
            xm = XM[i00] * w00 + XM[i01] * w01 + XM[i10] * w10 + XM[i11] * w11
            ym = YM[i00] * w00 + YM[i01] * w01 + YM[i10] * w10 + YM[i11] * w11
            val, inside = p.shader(xm, ym)
            val = np.where(inside > 0, val, f32(0.0))
            cov[py, px] = inside.mean(axis=(1, 2), dtype=np.float64)
            acc[py, px] = val.mean(axis=(1, 2), dtype=np.float64)
        region = canvas[y0 : y1 + 1, x0 : x1 + 1]
        region *= (1.0 - cov).astype(np.float32)
        region += acc.astype(np.float32)
        return x0, y0, x1 + 1, y1 + 1


def _merge_rois(
    rois: list[tuple[int, int, int, int]], pad: int, W: int, H: int
) -> list[tuple[int, int, int, int]]:
    """Grow each region by ``pad`` (clipped to the image) and merge overlapping ones."""
    boxes = [
        (max(a - pad, 0), max(b - pad, 0), min(c + pad, W), min(d + pad, H)) for a, b, c, d in rois
    ]
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return boxes


# ------------------------------------------------------------------------------------------------
def random_board_poses(
    camera: CameraModel,
    board: cv.CharucoBoard,
    n: int,
    rng: np.random.Generator,
    distance_m: tuple[float, float] = (0.55, 0.85),
    max_tilt_deg: float = 40.0,
) -> list[tuple[F64, F64]]:
    """``n`` board poses ``(R_C_B, t_C_B)`` that keep the whole board inside the image (5 % margin),
    tilted up to ``max_tilt_deg`` about random in-plane axes, placed so the views cover the image."""
    from cdpr.analysis.rotations import rotation_from_euler

    W, H = camera.image_size_px
    bw, bh = board.squares_x * board.square_m, board.squares_y * board.square_m
    corners_B = np.array([[0, 0, 0], [bw, 0, 0], [bw, bh, 0], [0, bh, 0]], dtype=np.float64)
    out: list[tuple[F64, F64]] = []
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > 200 * n:
            raise RuntimeError("could not place the board inside the image")
        tilt = np.deg2rad(max_tilt_deg) * (2 * rng.random(2) - 1)
        roll = rng.uniform(-np.pi / 6, np.pi / 6)
        R = rotation_from_euler([tilt[0], tilt[1], roll])
        z = rng.uniform(*distance_m)
        # aim the board centre at a random point of the image
        target = np.array([rng.uniform(0.2, 0.8) * W, rng.uniform(0.2, 0.8) * H])
        xn = cv.undistort_to_normalized(target[None], camera.K, camera.dist)[0]
        centre_C = np.array([xn[0] * z, xn[1] * z, z])
        t = centre_C - R @ np.array([bw / 2, bh / 2, 0.0])
        corners_C = corners_B @ R.T + t
        if np.any(corners_C[:, 2] < 0.1):
            continue
        uv = cv.project_points(corners_C, np.zeros(3), np.zeros(3), camera.K, camera.dist)
        if (
            uv[:, 0].min() < 0.05 * W
            or uv[:, 0].max() > 0.95 * W
            or uv[:, 1].min() < 0.05 * H
            or uv[:, 1].max() > 0.95 * H
        ):
            continue
        out.append((R, t))
    return out
