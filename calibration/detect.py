"""Marker detection: fiducials with edge-based sub-pixel corners, IR blobs and their labelling.

Fiducials (:class:`FiducialDetector`): OpenCV's ArUco detector finds and decodes the markers (on the
full frame, or only in small windows around the corners predicted from the last pose when tracking);
every corner is then refined by fitting straight lines to the four outer edges of the black square:
sub-pixel edge points from the gradient centroid across the edge (unbiased for a symmetric blur,
unlike ``cornerSubPix`` on the L-shaped outer corners, which moves them inward by ~0.2 px), undistorted
to the normalised image plane, a total-least-squares line per side, corners at the intersections.

Point markers (:func:`detect_blobs`, :class:`PointMatcher`): threshold, connected components on a
4x downsampled copy (or windows around predicted positions), intensity-weighted centroids at full
resolution; correspondence to the layout by scored hypotheses (2-point similarity alignments of the
reference projection, refined by PnP, scored by robust reprojection cost), accepted only with a
margin over the runner-up labelling; then frame-to-frame tracking from the last pose.  Every frame
whose labelling is not unique is flagged ``FLAG_AMBIGUOUS``; labels are never guessed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.analysis.errors import InputError

from . import cv
from .camera_model import CameraModel
from .markers import MarkerLayout
from .pose import (
    FLAG_AMBIGUOUS,
    FLAG_FEW_POINTS,
    FLAG_HIGH_RESIDUAL,
    FLAG_NO_POSE,
    FLAG_OCCLUDED_MARK,
    FLAG_TRACK_RESET,
    PoseEstimate,
    estimate_pose,
    failed_pose,
)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def bilinear(gray: NDArray[np.uint8], x: F64, y: F64) -> F64:
    """Bilinear samples of ``gray`` at (x, y) px (pixel centres at integers), clamped at the border."""
    h, w = gray.shape
    x = np.clip(x, 0, w - 1.000001)
    y = np.clip(y, 0, h - 1.000001)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    g = gray
    a = g[y0, x0] * (1 - fx) + g[y0, x0 + 1] * fx
    b = g[y0 + 1, x0] * (1 - fx) + g[y0 + 1, x0 + 1] * fx
    return a * (1 - fy) + b * fy


# ------------------------------------------------------------------------------------ fiducials
MIN_EDGE_STEP_DN = 15.0
"""Least step (DN) from the white outside to the black border across an edge sample; a side needs
half its samples to pass (a pure-noise frame has strong gradients but no consistent step)."""


def refine_marker_corners(
    gray: NDArray[np.uint8],
    corners_px: ArrayLike,
    cells: int,
    camera: CameraModel,
    iterations: int = 1,
    samples_per_side: int = 16,
) -> tuple[F64, NDArray[np.bool_], F64]:
    """Refine (N, 4, 2) marker corners by line fits to the outer edges (see the module docstring).

    ``cells``: cells per side including the black border (e.g. 6 for a 4x4 dictionary).
    ``iterations``: at most this many passes, each sampling the edges around the last corners
    (from a detector's corners a fraction of a pixel off, the profile window is off the edge and
    each pass moves part of the way: a blurred small marker needs several); stops when no corner
    moves by 0.002 px.  Returns the refined corners, a mask of markers whose refinement succeeded
    (others keep their input), and per marker ``[RSS, dof, rho]`` (N, 3) of the edge samples
    about their four lines (px^2 across the edge; dof = samples used - 8; rho the correlation of
    neighbouring samples' residuals, clipped to [0, 0.9]): the edge-sample noise this frame
    shows, whose propagation to the corners is :func:`edge_fit_corner_covariance`.
    All markers and sides are processed at once (vectorised).
    """
    C0 = np.asarray(corners_px, np.float64).reshape(-1, 4, 2)
    N = len(C0)
    ok = np.ones(N, dtype=bool)
    noise = np.full((N, 3), np.nan)
    if N == 0:
        return C0.copy(), ok, noise
    C = C0.copy()
    T = samples_per_side
    ts = np.linspace(0.12, 0.88, T)
    u = np.linspace(-1.0, 1.0, 17)  # profile positions, in units of the half-width R
    for _ in range(iterations):
        a = C
        b = np.roll(C, -1, axis=1)
        L = np.linalg.norm(b - a, axis=2)  # (N, 4)
        d = (b - a) / np.maximum(L, 1e-9)[..., None]
        nrm = np.stack([-d[..., 1], d[..., 0]], axis=-1)
        R = np.clip(0.45 * L / cells, 1.5, 3.5)  # (N, 4)
        ss = R[..., None] * u  # (N, 4, Q)
        base = (
            a[:, :, None, :] + (ts[None, None, :, None] * L[..., None, None]) * d[:, :, None, :]
        )  # (N,4,T,2)
        P = (
            base[:, :, :, None, :] + ss[:, :, None, :, None] * nrm[:, :, None, None, :]
        )  # (N,4,T,Q,2)
        prof = bilinear(gray, P[..., 0], P[..., 1])
        g = np.clip(-np.diff(prof, axis=-1), 0.0, None)  # the falling edge only (white -> black)
        gmax = g.max(axis=-1, keepdims=True)
        wgt = np.clip(g - 0.25 * gmax, 0, None)
        sw = wgt.sum(axis=-1)
        smid = 0.5 * (ss[..., 1:] + ss[..., :-1])  # (N,4,Q-1)
        s_star = (wgt * smid[:, :, None, :]).sum(axis=-1) / np.maximum(sw, 1e-12)  # (N,4,T)
        # a real edge: white quiet zone outside (u < 0: the normal points into the marker), black
        # border inside, by at least MIN_EDGE_STEP_DN (noise has gradients, not a consistent step)
        step = prof[..., :3].mean(axis=-1) - prof[..., -3:].mean(axis=-1)  # (N,4,T)
        use = (sw > 0) & (gmax[..., 0] > 8.0) & (step > MIN_EDGE_STEP_DN)
        E = base + s_star[..., None] * nrm[:, :, None, :]  # (N,4,T,2)
        xn = cv.undistort_to_normalized(E.reshape(-1, 2), camera.K, camera.dist).reshape(N, 4, T, 2)
        wu = use.astype(np.float64)
        cnt = wu.sum(axis=-1)  # (N,4)
        mu = (xn * wu[..., None]).sum(axis=2) / np.maximum(cnt, 1)[..., None]
        dxn = (xn - mu[:, :, None, :]) * wu[..., None]
        S = np.einsum("nstp,nstq->nspq", dxn, dxn)
        _, vec = np.linalg.eigh(S)  # ascending eigenvalues: column 0 is the line normal
        n_line = vec[..., :, 0]  # (N,4,2)
        dist_line = np.einsum("nsp,nsp->ns", n_line, mu)
        # corner i = intersection of side i-1 and side i
        A = np.stack([np.roll(n_line, 1, axis=1), n_line], axis=2)  # (N,4,2,2)
        rhs = np.stack([np.roll(dist_line, 1, axis=1), dist_line], axis=2)  # (N,4,2)
        det = np.linalg.det(A)
        good = (cnt.min(axis=1) >= T // 2) & (L.min(axis=1) >= 8) & (np.abs(det).min(axis=1) > 1e-9)
        A = np.where(good[:, None, None, None], A, np.eye(2))
        X = np.linalg.solve(A, rhs[..., None])[..., 0]  # (N,4,2)
        pts = np.concatenate([X.reshape(-1, 2), np.ones((N * 4, 1))], axis=1)
        newC = cv.project_points(pts, np.zeros(3), np.zeros(3), camera.K, camera.dist).reshape(
            N, 4, 2
        )
        ok &= good
        # the samples' distances to their lines (normalised units -> px by the focal length)
        off = (np.einsum("nstp,nsp->nst", xn, n_line) - dist_line[..., None]) * wu
        pair = wu[..., 1:] * wu[..., :-1]
        c1 = np.sum(off[..., 1:] * off[..., :-1] * pair, axis=(1, 2)) / np.maximum(
            pair.sum(axis=(1, 2)), 1
        )
        c0 = np.sum(off**2, axis=(1, 2)) / np.maximum(cnt.sum(axis=1), 1)
        rho = np.clip(c1 / np.maximum(c0, 1e-30), 0.0, 0.9)
        noise = np.stack(
            [np.sum(off**2, axis=(1, 2)) * camera.K[0, 0] ** 2, cnt.sum(axis=1) - 8.0, rho],
            axis=1,
        )
        step = np.abs(np.where(ok[:, None, None], newC - C, 0.0)).max()
        C = np.where(ok[:, None, None], newC, C)
        if step < 0.002:  # converged
            break
    moved = np.abs(C - C0).reshape(N, -1).max(axis=1)
    ok &= np.all(np.isfinite(C.reshape(N, -1)), axis=1) & (moved < 3.0)
    noise[~ok] = np.nan
    return np.where(ok[:, None, None], C, C0), ok, noise


SATURATION_MAX_FRACTION = 0.10
"""A marker with more of its pixels at 254-255 than this is overexposed (its whites clipped)."""


def saturated_fraction(gray: NDArray[np.uint8], corners_px: ArrayLike) -> F64:
    """(N,) fraction of the pixels inside each marker's corner bounding box at 254 or 255.

    Clipped whites cut the bright half of every blurred edge, so the edge fit puts the edges
    toward the dark side: each marker looks larger and the pose comes nearer the camera (1.8 mm
    at gain 1.6 on the second renderer, with a reprojection RMS under the limit).  Above
    :data:`SATURATION_MAX_FRACTION` the pose is flagged ``saturated``."""
    C = np.asarray(corners_px, np.float64).reshape(-1, 4, 2)
    h, w = gray.shape
    out = np.zeros(len(C))
    for k, c in enumerate(C):
        x0, y0 = np.clip(np.floor(c.min(axis=0)).astype(int), 0, [w - 1, h - 1])
        x1, y1 = np.clip(np.ceil(c.max(axis=0)).astype(int) + 1, 1, [w, h])
        if x1 > x0 and y1 > y0:
            out[k] = float(np.mean(gray[y0:y1, x0:x1] >= 254))
    return out


def edge_fit_corner_covariance(corners_px: ArrayLike, samples_per_side: int = 16) -> F64:
    """(N, 8, 8) covariance of edge-fitted corners (x0, y0, .., x3, y3 of each marker, TL TR BR BL)
    per unit variance of one edge sample's position across its edge.

    Each side is a line fitted to ``samples_per_side`` points at ``t`` in [0.12, 0.88] of its
    length: its offset error ``d`` (variance 1/T) and angle error ``a`` (variance 1/(L^2 S), with
    ``S = sum (t - 0.5)^2``) move its ends, along its normal, by ``d -+ a L / 2``: variance
    ``1/T + 1/(4 S)`` at each end and covariance ``1/T - 1/(4 S)`` between them, whatever the side
    length L.  Corner k, the intersection of sides k-1 and k, moves by ``A_k^-1 [u_{k-1}^+, u_k^-]``
    with ``A_k`` the two sides' normals.  The angle term dominates (``1/(4S)`` ~ 0.29 against
    ``1/T`` = 0.06): corner errors are mostly a marker's edges turning, which moves its corners
    against each other and hardly the marker, so independent corner noise would overstate the
    pose's error (docs/vision.md).  All samples are assumed used."""
    C = np.asarray(corners_px, np.float64).reshape(-1, 4, 2)
    N = len(C)
    T = samples_per_side
    ts = np.linspace(0.12, 0.88, T)
    S = float(np.sum((ts - ts.mean()) ** 2))
    var_end, cov_ends = 1.0 / T + 0.25 / S, 1.0 / T - 0.25 / S
    d = np.roll(C, -1, axis=1) - C  # side i from corner i to corner i+1
    d /= np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-12)
    nrm = np.stack([-d[..., 1], d[..., 0]], axis=-1)  # (N, 4, 2)
    A = np.stack([np.roll(nrm, 1, axis=1), nrm], axis=2)  # corner k: rows n_{k-1}, n_k
    Ainv = np.linalg.inv(A)  # (N, 4, 2, 2)
    # u = [u_0^-, u_0^+, u_1^-, u_1^+, ..]: corner k uses u_{k-1}^+ (index 2k-1) and u_k^- (2k)
    G = np.zeros((N, 8, 8))
    for k in range(4):
        G[:, 2 * k : 2 * k + 2, (2 * k - 1) % 8] = Ainv[:, k, :, 0]
        G[:, 2 * k : 2 * k + 2, 2 * k] = Ainv[:, k, :, 1]
    Su = np.kron(np.eye(4), np.array([[var_end, cov_ends], [cov_ends, var_end]]))
    return np.einsum("nij,jk,nlk->nil", G, Su, G)


def check_frame(
    gray: NDArray[Any], size_wh: tuple[int, int] | None = None, name: str = "frame"
) -> None:
    """Raise :class:`InputError` unless ``gray`` is a single-channel uint8 image (of ``size_wh``
    (width, height) px when given: a frame of another size than the calibrated camera's would give
    a pose far off, silently).  ``name`` (a file, or "frame 12") starts the message."""
    a = np.asarray(gray)
    if a.ndim != 2:
        raise InputError(
            f"{name}: expected a gray (H, W) image, got shape {a.shape} "
            "(convert colour frames to gray first: cdpr.calibration.cv.to_gray)"
        )
    if a.dtype != np.uint8:
        raise InputError(f"{name}: expected 8-bit pixels (uint8), got {a.dtype}")
    if size_wh is not None and (a.shape[1], a.shape[0]) != tuple(size_wh):
        raise InputError(
            f"{name}: {a.shape[1]}x{a.shape[0]} px, the camera model is "
            f"{size_wh[0]}x{size_wh[1]} px (wrong camera, or a resized or cropped frame)"
        )


@dataclass
class FiducialDetector:
    """ArUco/AprilTag detection for a fiducial layout, with edge refinement and ROI tracking.

    ``roi_margin``: window around a predicted marker, as a fraction of its size (plus 12 px).
    """

    layout: MarkerLayout
    camera: CameraModel
    roi_margin: float = 0.25
    edge_refine: bool = True
    redecode_every: int = 10
    track_max_move_cells: float = 0.35
    _det: cv.ArucoDetector = field(init=False)

    def __post_init__(self) -> None:
        self._det = cv.ArucoDetector(
            self.layout.dictionary,
            cv.ArucoDetectorSettings(refinement="none" if self.edge_refine else "subpix"),
        )
        # windows around predicted markers: one adaptive-threshold scale is enough (3x cheaper)
        self._det_win = cv.ArucoDetector(
            self.layout.dictionary,
            cv.ArucoDetectorSettings(
                refinement="none" if self.edge_refine else "subpix",
                adaptive_win_min=15,
                adaptive_win_max=15,
                adaptive_win_step=10,
                min_perimeter_rate=0.2,
            ),
        )
        self._known = set(int(i) for i in self.layout.ids)
        self._frames = 0
        self.edge_noise = np.zeros((0, 3))
        """Per marker of the last :meth:`detect`, ``[RSS px^2, dof, rho]`` of its edge samples
        about their lines (:func:`refine_marker_corners`; NaN when not edge-refined)."""
        self._cells = cv.dictionary_marker_cells(self.layout.dictionary) + 2

    def detect(self, gray: NDArray[np.uint8], predicted: F64 | None = None) -> tuple[I64, F64]:
        """Markers of the layout in ``gray``: ids (N,) and corners (N, 4, 2) px (and
        :attr:`edge_noise` of each).

        predicted: optional (M, 4, 2) corners of every layout marker (layout order) from the last
        pose(s).  Tracking then fits the edges directly around the predicted corners (no decoding)
        when every marker's edges are found within ``track_max_move_cells`` of the prediction; every
        ``redecode_every``-th frame, or when that fails, the markers are decoded again in windows
        around the prediction, and if any is missing, on the full frame.
        """
        check_frame(gray, self.camera.image_size_px)
        ids: I64
        corners: F64
        self._frames += 1
        if predicted is not None and self.edge_refine and self._frames % self.redecode_every:
            pred = np.asarray(predicted, np.float64).reshape(-1, 4, 2)
            if np.all(np.isfinite(pred)):
                c, ok, noise = refine_marker_corners(
                    gray, pred, self._cells, self.camera, iterations=2
                )
                size = np.linalg.norm(pred[:, 0] - pred[:, 2], axis=1) / np.sqrt(2)
                move = np.abs(c - pred).reshape(len(c), -1).max(axis=1)
                if ok.all() and np.all(move < self.track_max_move_cells * size / self._cells):
                    self.edge_noise = noise
                    return self.layout.ids.copy(), c
        if predicted is not None:
            ids, corners = self._detect_windows(gray, predicted)
            if len(ids) < len(self._known):
                ids, corners = self._full(gray)
        else:
            ids, corners = self._full(gray)
        self.edge_noise = np.full((len(ids), 3), np.nan)
        if self.edge_refine and len(ids):
            corners, _, self.edge_noise = refine_marker_corners(
                gray, corners, self._cells, self.camera, iterations=12
            )
        return ids, corners

    def _full(self, gray: NDArray[np.uint8]) -> tuple[I64, F64]:
        c, ids = self._det.detect(gray)
        keep = np.array([int(i) in self._known for i in ids], dtype=bool)
        c, ids = c[keep], ids[keep]
        ids, first = np.unique(ids, return_index=True)  # a duplicated id: keep one (rare)
        return ids, c[first]

    def _detect_windows(self, gray: NDArray[np.uint8], predicted: F64) -> tuple[I64, F64]:
        h, w = gray.shape
        out_ids, out_c = [], []
        for mid, pc in zip(self.layout.ids, np.asarray(predicted).reshape(-1, 4, 2), strict=True):
            if not np.all(np.isfinite(pc)):
                continue
            size = np.linalg.norm(pc[0] - pc[2])
            pad = self.roi_margin * size + 8
            x0 = int(max(np.floor(pc[:, 0].min() - pad), 0))
            x1 = int(min(np.ceil(pc[:, 0].max() + pad), w))
            y0 = int(max(np.floor(pc[:, 1].min() - pad), 0))
            y1 = int(min(np.ceil(pc[:, 1].max() + pad), h))
            if x1 - x0 < 16 or y1 - y0 < 16:
                continue
            c, ids = self._det_win.detect(np.ascontiguousarray(gray[y0:y1, x0:x1]))
            sel = ids == mid
            if sel.sum() == 1:
                out_ids.append(int(mid))
                out_c.append(c[sel][0] + [x0, y0])
        if not out_ids:
            return np.zeros(0, np.int64), np.zeros((0, 4, 2))
        return np.asarray(out_ids, np.int64), np.stack(out_c)


# ------------------------------------------------------------------------------------ blobs
@dataclass
class BlobSettings:
    """IR-mark detection and its shape check (every field is a key of a camera source's
    ``[sources.<name>.blobs]`` table and of ``cdpr pose --blobs``: docs/vision.md)."""

    threshold_dn: float = 100.0
    """A blob is the pixels above this level (DN; the background must stay below it)."""
    min_area_px: float = 6.0
    """Blobs of fewer pixels above the threshold are noise."""
    max_area_px: float = 5000.0
    """Blobs of more pixels are not marks (a lamp, a reflection)."""
    coarse_factor: int = 4
    """Downsampling of the whole-frame search (1: none)."""
    window_px: int = 0
    """Half-size of the search window around predicted marks (0: 24 px)."""
    shape_check: bool = True
    """Compare each labelled blob with its mark's projected disk (:func:`check_blob_shapes`)."""
    notch_tolerance: float = 0.08
    """A straight band darker (or brighter) than the mark's own profile by more than this
    fraction of its peak makes the mark damaged (:func:`blob_profile`)."""
    notch_sigma: float = 6.0
    """... and only if that band's mean is this many standard errors from zero (pixel noise)."""
    notch_margin_px: float = 0.75
    """Pixels at least this far inside the projected outline enter the band search."""
    bias_tolerance_px: float = 0.06
    """Light that does not fit the mark's own image and moves its centroid by more than this
    (px) makes the mark damaged (:func:`blob_profile`: a band grazing the rim)."""
    rim_tolerance_px: float = 0.2
    """Largest deviation (px) of the blob's rim from the projected outline."""


def _centroid(
    gray: NDArray[np.uint8], x0: int, y0: int, x1: int, y1: int, thr: float
) -> tuple[float, float, float, float] | None:
    """Intensity-weighted centroid of the blob in a window: weights ``I - background`` on the blob
    pixels (above ``thr``) dilated by 2 px; background = median of the window border."""
    win = gray[y0:y1, x0:x1].astype(np.float64)
    if win.size == 0:
        return None
    border = np.concatenate([win[0], win[-1], win[:, 0], win[:, -1]])
    bg = float(np.median(border))
    if bg > thr:  # the surroundings are as bright as the blob (a grey or washed-out frame)
        return None
    mask = win > thr
    area = float(mask.sum())
    if area == 0:
        return None
    # dilate the mask by 2 px (cheap shifts)
    m = mask.copy()
    for _ in range(2):
        d = m.copy()
        d[1:] |= m[:-1]
        d[:-1] |= m[1:]
        d[:, 1:] |= m[:, :-1]
        d[:, :-1] |= m[:, 1:]
        m = d
    wgt = np.where(m, np.clip(win - bg, 0, None), 0.0)
    s = wgt.sum()
    if s <= 0:
        return None
    ys, xs = np.mgrid[y0:y1, x0:x1]
    return float((wgt * xs).sum() / s), float((wgt * ys).sum() / s), area, float(win.max())


def detect_blobs(
    gray: NDArray[np.uint8], settings: BlobSettings | None = None, predicted: F64 | None = None
) -> F64:
    """Bright blobs: (N, 3) ``[x_px, y_px, area_px]`` (intensity-weighted centroids).

    predicted: optional (M, 2) positions to search around (windows of ``window_px``), else the whole
    frame is scanned on a ``coarse_factor`` downsampled copy and each blob measured at full size.
    """
    s = settings or BlobSettings()
    check_frame(gray)
    h, w = gray.shape
    windows: list[tuple[int, int, int, int]] = []
    if predicted is not None:
        hw = s.window_px or 24
        for x, y in np.asarray(predicted).reshape(-1, 2):
            if np.isfinite(x) and np.isfinite(y):
                windows.append(
                    (
                        int(max(x - hw, 0)),
                        int(max(y - hw, 0)),
                        int(min(x + hw + 1, w)),
                        int(min(y + hw + 1, h)),
                    )
                )
    else:
        f = max(int(s.coarse_factor), 1)
        small = cv.downsample_area(gray[: h - h % f, : w - w % f], f) if f > 1 else gray
        # a blob's mean over f x f cells is lower: use half the threshold above the background
        n, _, stats = cv.connected_components(cv.threshold(small, s.threshold_dn * 0.5))
        for k in range(1, n):
            x, y, bw, bh, _area = stats[k]
            windows.append(
                (
                    max(x * f - 3, 0),
                    max(y * f - 3, 0),
                    min((x + bw) * f + 3, w),
                    min((y + bh) * f + 3, h),
                )
            )
    out = []
    for x0, y0, x1, y1 in windows:
        sub = gray[y0:y1, x0:x1]
        if sub.size == 0:
            continue
        n, labels, stats = cv.connected_components(
            cv.threshold(np.ascontiguousarray(sub), s.threshold_dn)
        )
        for k in range(1, n):
            bx, by, bw, bh, area = stats[k]
            # a blob touching the image border is cut: its centroid is biased, it is not measured
            if x0 + bx == 0 or y0 + by == 0 or x0 + bx + bw == w or y0 + by + bh == h:
                continue
            # a blob cut by a search window (not by the image border): search the whole frame
            if predicted is not None and (
                bx == 0 or by == 0 or bx + bw == x1 - x0 or by + bh == y1 - y0
            ):
                return detect_blobs(gray, s, None)
            if area < s.min_area_px or area > s.max_area_px:
                continue
            pad = 3
            c = _centroid(
                gray,
                max(x0 + bx - pad, 0),
                max(y0 + by - pad, 0),
                min(x0 + bx + bw + pad, w),
                min(y0 + by + bh + pad, h),
                s.threshold_dn,
            )
            if c is not None:
                out.append((c[0], c[1], c[2]))
    if not out:
        return np.zeros((0, 3))
    b = np.asarray(out)
    # windows may overlap: merge duplicates closer than 1 px
    keep = np.ones(len(b), bool)
    for i in range(len(b)):
        if keep[i]:
            dup = np.linalg.norm(b[i + 1 :, :2] - b[i, :2], axis=1) < 1.0
            keep[i + 1 :][dup] = False
    return b[keep]


# ------------------------------------------------------------------------------------ blob shape
def projected_disks_px(
    layout: MarkerLayout, camera: CameraModel, rvec: F64, tvec: F64, n: int = 64
) -> tuple[F64, F64, F64]:
    """Image of each IR disk of ``layout`` at the pose (rvec, tvec) of {P} in {C}: its area (px^2,
    the projected outline as a polygon), the projected centre, and the projected outline (``n``
    points of the rim, lens distortion included); (M,), (M, 2), (M, n, 2)."""
    ang = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    areas, outlines = [], []
    centres = cv.project_points(layout.point_centers_m, rvec, tvec, camera.K, camera.dist)
    for p in layout.points:
        nrm = np.asarray(p.normal, np.float64)
        nrm = nrm / np.linalg.norm(nrm)
        a = np.cross(nrm, [1.0, 0.0, 0.0])
        if np.linalg.norm(a) < 1e-6:
            a = np.cross(nrm, [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(nrm, a)
        ring = p.center_m + p.radius_m * (np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b)
        uv = cv.project_points(ring, rvec, tvec, camera.K, camera.dist)
        x, y = uv[:, 0], uv[:, 1]
        areas.append(0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))))
        outlines.append(uv)
    return np.asarray(areas), centres, np.asarray(outlines)


def blob_edge_residual(gray: NDArray[np.uint8], centre_px: F64, outline_px: F64) -> float:
    """Largest distance (px) between the blob's rim and the expected outline.

    Along the ray from ``centre_px`` through each outline point, the outermost crossing of the half
    level (between the local background and the blob's peak; bilinear samples every 0.1 px),
    refined to the centroid of the falling gradient within 1.5 px, is compared with the outline's
    distance; a shift of the blob and a uniform growth (the blur) are fitted out (least squares).
    Returns the largest absolute residual (mean over 7 neighbouring rays).  A band across the rim
    pulls a stretch of it inward (a grazing cable that hardly changes the flux); an intact disk
    gives 0.03-0.15 px (bilinear samples of a 0.7-0.8 px blur, measured on both test renderers)."""
    c = np.asarray(centre_px, np.float64)
    d = outline_px - c
    rho = np.linalg.norm(d, axis=1)
    u = d / rho[:, None]
    # from 3 px inside the rim (a ray dark there is cut: r = 0) to 4 px outside, every 0.1 px
    t = np.arange(max(float(rho.min()) - 3.0, 0.0), float(rho.max()) + 4.0, 0.1)
    xs = c[0] + u[:, :1] * t[None, :]
    ys = c[1] + u[:, 1:] * t[None, :]
    prof = bilinear(gray, xs, ys)  # (n, T)
    bg = float(np.median(prof[:, -1]))
    level = bg + 0.5 * (float(prof.max()) - bg)
    above = prof >= level
    grad = np.clip(-np.diff(prof, axis=1), 0.0, None)  # falling edge strength between samples
    tm = 0.5 * (t[1:] + t[:-1])
    T = len(t)
    any_hit = above.any(axis=1)
    j = T - 1 - np.argmax(above[:, ::-1], axis=1)  # outermost sample at or above the level
    valid = any_hit & (j + 1 < T)  # else nothing bright (r = 0) or bright to the end (r = 0)
    # gradient centroid within +-1.5 px of the outermost half-level crossing (less biased by the
    # sample phase than the crossing itself)
    near = np.abs(tm[None, :] - t[j][:, None]) <= 1.5
    g = np.where(near, grad, 0.0)
    gs = g.sum(axis=1)
    r = np.where(gs > 0, (g * tm[None, :]).sum(axis=1) / np.where(gs > 0, gs, 1.0), t[j])
    r = np.where(valid, r, 0.0)
    A = np.column_stack([np.ones(len(rho)), u])
    coef, *_ = np.linalg.lstsq(A, r - rho, rcond=None)
    res = r - rho - A @ coef
    # mean over 7 neighbouring rays: a cut spans several, pixel-phase errors of the samples do not
    k = 3
    smooth = np.mean([np.roll(res, j) for j in range(-k, k + 1)], axis=0)
    return float(np.max(np.abs(smooth)))


def blob_parts(gray: NDArray[np.uint8], xy_px: ArrayLike, radius_px: float, thr: float) -> int:
    """Number of connected parts above ``thr`` in the window of half-size ``radius_px + 4`` around
    ``xy_px`` (a cable across a disk splits it in two); 0 if the window leaves the image."""
    h, w = gray.shape
    x, y = np.asarray(xy_px, np.float64)
    hw = int(np.ceil(radius_px)) + 4
    xi, yi = int(round(x)), int(round(y))
    x0, y0, x1, y1 = xi - hw, yi - hw, xi + hw + 1, yi + hw + 1
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return 0
    n, _, _ = cv.connected_components(cv.threshold(np.ascontiguousarray(gray[y0:y1, x0:x1]), thr))
    return int(n - 1)


NOTCH_ANGLES = 24
"""Directions (over 180 degrees, 7.5 degrees apart) of the lines :func:`blob_profile` averages
along."""
PROFILE_KNOT_PX = 0.5
"""Knot spacing (px) of the mark's own radial profile in :func:`blob_profile`."""
NOTCH_MIN_PIXELS = 3
"""Least number of pixels on a line for its mean to count."""


def _fit_profile(k: I64, g0: F64, g1: F64, X: F64, y: F64, nk: int) -> F64:
    """Least squares of ``y ~ c[k] g0 + c[k+1] g1 + X c[nk:]`` (a piecewise-linear profile on
    ``nk`` knots, the pixel at weights ``g0``, ``g1`` between knots ``k`` and ``k + 1``, plus the
    columns of ``X`` (n, q)) through its normal equations summed per knot (the profile's block is
    tridiagonal); a knot without pixels stays 0."""
    q = X.shape[1]
    H = np.zeros((nk + q, nk + q))
    d = np.arange(nk)
    H[d, d] = np.bincount(k, g0 * g0, nk) + np.bincount(k + 1, g1 * g1, nk) + 1e-9
    off = np.bincount(k, g0 * g1, nk)[: nk - 1]
    H[d[:-1], d[:-1] + 1] = off
    H[d[:-1] + 1, d[:-1]] = off
    for j in range(q):
        col = np.bincount(k, g0 * X[:, j], nk) + np.bincount(k + 1, g1 * X[:, j], nk)
        H[:nk, nk + j] = col
        H[nk + j, :nk] = col
    H[nk:, nk:] = X.T @ X
    b = np.concatenate([np.bincount(k, g0 * y, nk) + np.bincount(k + 1, g1 * y, nk), X.T @ y])
    return np.linalg.solve(H, b)


@dataclass
class BlobProfile:
    """Result of :func:`blob_profile` for one blob.

    ``notch``: the largest mean residual along a line relative to the mark's own peak (signed:
    < 0 a dark band, > 0 a bright streak; 0 when no line is significant); ``bias_px``: how far
    the light that does not fit the mark's own image moves its intensity-weighted centroid (px:
    what a damaged blob does to the pose); ``shift_px`` (2,): the intact image's offset from the
    projected centre; ``peak_dn``: the mark's plateau above the background; ``noise_dn``: the
    pixel noise from the residuals."""

    notch: float
    bias_px: float
    shift_px: F64
    peak_dn: float
    noise_dn: float


def blob_profile(
    gray: NDArray[np.uint8],
    centre_px: ArrayLike,
    outline_px: F64,
    margin_px: float = 0.75,
    min_sigma: float = 6.0,
) -> BlobProfile:
    """Damage to a blob found from its *shape*, whatever its brightness (see :func:`check_blob_shapes`).

    Every pixel up to 3 px outside the projected ``outline_px`` (around ``centre_px``) gets its
    signed distance ``e`` to the outline along the ray from the centre.  The mark's own image is
    fitted as a radial profile of ``e`` (piecewise linear, knots every :data:`PROFILE_KNOT_PX`:
    any blur, any brightness, clipped tops included), plus a plane (a smooth illumination
    gradient), then plus a shift of the profile (its slope along the ray times the ray's
    direction: where the intact image is), by least squares with pixels beyond 3 robust sigma
    left out, twice per stage (a band's pixels do not bend the profile).  What does not fit:

    - *notch*: the residuals of the pixels at least ``margin_px`` inside the outline, averaged
      along lines 1 px wide in :data:`NOTCH_ANGLES` directions (a cable is a straight dark band:
      its line's mean is a large fraction of the peak, while noise averages out); a line counts
      when its mean is ``min_sigma`` standard errors from zero (noise from the residuals' MAD);
    - *bias*: the first moment of all residuals over the fitted mark's light: how far the missing
      (or added) light moves the centroid from the intact image's centre (a band grazing the rim
      hardly darkens the plateau but pulls the centroid by a tenth of a pixel).

    NaN fields if the window leaves the image or the mark has no plateau."""
    nan = BlobProfile(float("nan"), float("nan"), np.full(2, np.nan), float("nan"), float("nan"))
    h, w = gray.shape
    c0 = np.asarray(centre_px, np.float64)
    d = outline_px - c0
    rho = np.linalg.norm(d, axis=1)
    R = int(np.ceil(rho.max())) + 4
    xi, yi = int(round(c0[0])), int(round(c0[1]))
    if xi - R < 0 or yi - R < 0 or xi + R + 1 > w or yi + R + 1 > h:
        return nan
    I_all = gray[yi - R : yi + R + 1, xi - R : xi + R + 1].astype(np.float64).ravel()
    g = np.arange(-R, R + 1, dtype=np.float64)
    px = np.tile(g + xi, 2 * R + 1)  # pixel coordinates of the window
    py = np.repeat(g + yi, 2 * R + 1)
    # the outline's radius in each direction (periodic linear interpolation over the rays)
    ang = np.arctan2(d[:, 1], d[:, 0])
    order = np.argsort(ang)
    a_ext = np.concatenate([ang[order] - 2 * np.pi, ang[order], ang[order] + 2 * np.pi])
    r_ext = np.tile(rho[order], 3)
    shift = np.zeros(2)
    use_all = np.ones(len(I_all), dtype=bool)
    for it in range(3):
        # the outline moved by the shift found so far (where the intact image is)
        dx_all, dy_all = px - c0[0] - shift[0], py - c0[1] - shift[1]
        dist_all = np.hypot(dx_all, dy_all)
        e_all = dist_all - np.interp(np.arctan2(dy_all, dx_all), a_ext, r_ext)
        outside = e_all > 3.0
        if outside.sum() < 8:
            return nan
        bg = float(np.median(I_all[outside]))
        sel = ~outside
        I, dx, dy, e, dist = I_all[sel], dx_all[sel], dy_all[sel], e_all[sel], dist_all[sel]
        use = use_all[sel]
        u = (e - e.min()) / PROFILE_KNOT_PX
        k = np.floor(u).astype(np.int64)
        f = u - k
        g0, g1 = 1.0 - f, f  # the pixel's weights on knots k and k + 1 (linear interpolation)
        nk = int(k.max()) + 2
        X = np.column_stack([dx, dy])
        for _ in range(2):
            coef = _fit_profile(k[use], g0[use], g1[use], X[use], I[use], nk)
            res = I - (coef[k] * g0 + coef[k + 1] * g1 + X @ coef[nk:])
            noise = max(1.4826 * float(np.median(np.abs(res[use]))), 0.5)
            use = np.abs(res) <= 3.0 * noise
        use_all[:] = True
        use_all[sel] = use
        # the profile shifted by s changes a pixel by -slope(e) (u . s): fit s to the residuals
        slope = (coef[1:nk] - coef[: nk - 1]) / PROFILE_KNOT_PX
        rd = np.maximum(dist, 1e-9)
        G = np.column_stack([-slope[k] * dx / rd, -slope[k] * dy / rd])
        step = np.linalg.lstsq(G[use], res[use], rcond=None)[0]
        if np.hypot(*step) < 0.05 or it == 2:  # small: applied to the residuals (linear)
            res = res - G @ step
            shift += step
            dx, dy = dx - step[0], dy - step[1]
            break
        shift += np.clip(step, -1.0, 1.0)  # a pose off by more: the profile refitted there
    light = float(np.sum(I - res - bg))  # the fitted mark's light above the background
    if light <= 0:
        return nan
    bias = np.array([res @ dx, res @ dy]) / light
    inner = e <= -margin_px
    if inner.sum() < NOTCH_MIN_PIXELS:
        return nan
    peak = float(np.median(I[inner] - X[inner] @ coef[nk:])) - bg
    if peak <= 0:
        return nan
    r = res[inner]
    th = np.arange(NOTCH_ANGLES) * np.pi / NOTCH_ANGLES
    P = np.floor(np.outer(-np.sin(th), dx[inner]) + np.outer(np.cos(th), dy[inner]) + 0.5)
    P = (P - P.min()).astype(np.int64)
    m = int(P.max()) + 1
    idx = (np.arange(NOTCH_ANGLES)[:, None] * m + P).ravel()
    cnt = np.bincount(idx, minlength=NOTCH_ANGLES * m)
    tot = np.bincount(idx, weights=np.tile(r, NOTCH_ANGLES), minlength=NOTCH_ANGLES * m)
    ok = cnt >= NOTCH_MIN_PIXELS
    mean = np.where(ok, tot / np.maximum(cnt, 1), 0.0)
    sig = ok & (np.abs(mean) * np.sqrt(cnt) >= min_sigma * noise)
    notch = float(mean[sig][np.argmax(np.abs(mean[sig]))] / peak) if sig.any() else 0.0
    return BlobProfile(notch, float(np.hypot(*bias)), shift.copy(), peak, noise)


@dataclass
class BlobShapeCheck:
    """Result of :func:`check_blob_shapes`, per layout mark: the notch depth (relative to the
    mark's own peak, :func:`blob_notch`) and the rim residual (px; nan when not measured), the
    number of parts, the score (the worst test over its tolerance: > 1 damaged, inf split, nan
    not measured); and the marks whose blob is damaged (worst first) or lost."""

    notch_depth: F64
    bias_px: F64
    rim_residual_px: F64
    parts: I64
    score: F64
    damaged: I64
    lost: I64


def check_blob_shapes(
    gray: NDArray[np.uint8],
    layout: MarkerLayout,
    camera: CameraModel,
    rvec: F64,
    tvec: F64,
    labels: I64,
    settings: BlobSettings | None = None,
) -> BlobShapeCheck:
    """Compare each labelled blob with the mark's expected image at the estimated pose.

    The projected disk of the mark's known radius gives its outline.  Three tests of the blob's
    shape, each against the mark itself (never against the other marks: retro-reflective marks
    differ by tens of percent in brightness, and the lighting varies over the frame); any failing
    makes the mark *damaged*: (1) no straight band darker (or brighter) than the mark's own
    profile by ``notch_tolerance`` of its peak (:func:`blob_notch`: a cable across the disk);
    (2) the blob is in one part (a cable across the middle splits it); (3) its rim follows the
    projected outline (:func:`blob_edge_residual`) within ``rim_tolerance_px`` (a band grazing
    the rim).  A mark whose disk faces the camera and lies inside the image (with a margin) but
    has no label is *lost*."""
    s = settings or BlobSettings()
    M = len(layout.points)
    _, centres, outlines = projected_disks_px(layout, camera, rvec, tvec)
    radii = np.max(np.linalg.norm(outlines - centres[:, None, :], axis=2), axis=1)
    notch = np.full(M, np.nan)
    bias = np.full(M, np.nan)
    rim = np.full(M, np.nan)
    parts = np.zeros(M, np.int64)
    for m in range(M):
        if labels[m] >= 0:
            parts[m] = blob_parts(gray, centres[m], radii[m], s.threshold_dn)
            if parts[m]:
                prof = blob_profile(gray, centres[m], outlines[m], s.notch_margin_px, s.notch_sigma)
                notch[m], bias[m] = prof.notch, prof.bias_px
                rim[m] = blob_edge_residual(gray, centres[m], outlines[m])
    with np.errstate(invalid="ignore"):
        score = np.fmax(np.abs(notch) / s.notch_tolerance, rim / s.rim_tolerance_px)
        score = np.fmax(score, bias / s.bias_tolerance_px)
    score[parts > 1] = np.inf
    damaged = np.flatnonzero((score > 1.0) & (labels >= 0))
    damaged = damaged[np.argsort(-score[damaged], kind="stable")]
    R = cv.rodrigues(rvec)
    pc = layout.point_centers_m @ R.T + tvec
    facing = np.einsum("ij,ij->i", layout.point_normals @ R.T, pc) < 0
    h, w = gray.shape
    inside = (
        (centres[:, 0] - radii - 4 >= 0)
        & (centres[:, 1] - radii - 4 >= 0)
        & (centres[:, 0] + radii + 4 < w)
        & (centres[:, 1] + radii + 4 < h)
    )
    lost = np.flatnonzero((labels < 0) & facing & inside)
    return BlobShapeCheck(
        notch, bias, rim, parts, score, damaged.astype(np.int64), lost.astype(np.int64)
    )


# ------------------------------------------------------------------------------------ labelling
@dataclass
class MatchResult:
    """Labelling of blobs: ``labels[m]`` = index of the blob seen as layout marker m, or -1;
    ``margin`` = cost gap to the runner-up labelling (chi-square units; inf if none); the pose."""

    labels: I64
    margin: float
    pose: PoseEstimate
    flags: int
    hypotheses: int = 0


@dataclass
class PointMatcher:
    """Label blobs with the markers of a ``"points"`` layout and estimate the pose.

    reference: ``(position_O_m, R_O_P)`` the nominal pose (the rig's reference pose) used for
    acquisition; sigma_px: centroid noise (px, per coordinate); gate_px: association radius after
    the pose fit; margin_min: required cost gap (chi-square units) over the runner-up labelling;
    max_angle_deg / scale_range: the span of image-plane rotations and scales tried at acquisition.
    """

    layout: MarkerLayout
    camera: CameraModel
    reference: tuple[F64, F64]
    sigma_px: float = 0.05
    gate_px: float = 3.0
    margin_min: float = 25.0
    min_markers: int = 5
    max_angle_deg: float = 60.0
    scale_range: tuple[float, float] = (0.6, 1.6)
    track_gate_px: float = 30.0
    _last: tuple[F64, F64] | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        self.P = self.layout.point_centers_m
        self.normals = self.layout.point_normals
        R_C_P, t = self.camera.pose_C_P(*self.reference)
        self._ref = (cv.rotation_vector(R_C_P), t)
        self._ref_px = cv.project_points(self.P, *self._ref, self.camera.K, self.camera.dist)
        self._ref_h = np.column_stack([self._ref_px, np.ones(len(self._ref_px))])

    def reset(self) -> None:
        """Forget the last pose (next frame is acquired from scratch)."""
        self._last = None

    # -- scoring -------------------------------------------------------------------------------
    def _nearest_blobs(self, rvec: F64, tvec: F64, blobs: F64) -> tuple[I64, F64, F64]:
        """Project the markers with the pose; per marker (M): blob indices by distance (M, N), the
        distance to the nearest blob and to the second nearest (inf with one blob), px."""
        proj = cv.project_points(self.P, rvec, tvec, self.camera.K, self.camera.dist)
        d = np.linalg.norm(proj[:, None, :] - blobs[None, :, :2], axis=2)  # (M, N)
        order = np.argsort(d, axis=1)
        nearest = d[np.arange(len(self.P)), order[:, 0]]
        second = (
            d[np.arange(len(self.P)), order[:, 1]]
            if d.shape[1] > 1
            else np.full(len(self.P), np.inf)
        )
        return order, nearest, second

    def _associate(self, rvec: F64, tvec: F64, blobs: F64) -> tuple[I64, float, float]:
        """Labels by nearest blob within the gate; cost (chi-square units) and crowding margin."""
        order, nearest, second = self._nearest_blobs(rvec, tvec, blobs)
        labels = np.full(len(self.P), -1, np.int64)
        within = nearest < self.gate_px
        labels[within] = order[within, 0]
        # a blob claimed by two markers is not a valid labelling: drop both
        vals, counts = np.unique(labels[labels >= 0], return_counts=True)
        for v in vals[counts > 1]:
            labels[labels == v] = -1
        chi_gate = (self.gate_px / self.sigma_px) ** 2 / 2
        cost = float(np.sum(np.where(labels >= 0, (nearest / self.sigma_px) ** 2 / 2, chi_gate)))
        crowd = float(np.min(np.where(within, second - nearest, np.inf))) if within.any() else 0.0
        return labels, cost, crowd

    def _fit(
        self, labels: I64, blobs: F64, guess: tuple[F64, F64] | None
    ) -> tuple[F64, F64] | None:
        sel = labels >= 0
        if sel.sum() < 4:
            return None
        obj, img = self.P[sel], blobs[labels[sel], :2]
        if guess is None:
            ok, r, t = cv.solve_pnp(obj, img, self.camera.K, self.camera.dist, "sqpnp")
            if not ok:
                return None
        else:
            r, t = guess
        r, t = cv.refine_pnp_lm(obj, img, self.camera.K, self.camera.dist, r, t)
        if t[2] <= 0:
            return None
        # visibility: labelled disks must face the camera
        R = cv.rodrigues(r)
        pc = self.P[sel] @ R.T + t
        if np.any(np.einsum("ij,ij->i", self.normals[sel] @ R.T, pc) >= 0):
            return None
        return r, t

    def _finalize(self, labels: I64, blobs: F64, margin: float, flags: int, nh: int) -> MatchResult:
        sel = labels >= 0
        if sel.sum() < 4:
            labels = np.full_like(labels, -1)  # no pose, no labels: never a guess
            return MatchResult(
                labels,
                margin,
                failed_pose(FLAG_FEW_POINTS),
                flags | FLAG_FEW_POINTS | FLAG_NO_POSE,
                nh,
            )
        pose = estimate_pose(
            self.P[sel],
            blobs[labels[sel], :2],
            self.camera,
            self.sigma_px,
            max_rms_px=max(4 * self.sigma_px * np.sqrt(2), 0.3),
        )
        flags |= pose.flags
        if pose.n_points < self.min_markers:  # counted after outlier rejection
            flags |= FLAG_FEW_POINTS
        if margin < self.margin_min:
            flags |= FLAG_AMBIGUOUS
        pose.flags = flags
        if not (flags & (FLAG_AMBIGUOUS | FLAG_NO_POSE | FLAG_HIGH_RESIDUAL)):
            self._last = (pose.rvec_C, pose.tvec_C_m)
        else:
            self._last = None
        return MatchResult(labels, margin, pose, flags, nh)

    # -- public --------------------------------------------------------------------------------
    def match(self, blobs: ArrayLike) -> MatchResult:
        """Label (N, >=2) blob positions (px) and estimate the pose; tracks from the last frame."""
        b = np.asarray(blobs, np.float64).reshape(
            -1, np.asarray(blobs).shape[-1] if np.size(blobs) else 3
        )
        if len(b) < 4:
            self._last = None
            return MatchResult(
                np.full(len(self.P), -1, np.int64),
                0.0,
                failed_pose(FLAG_FEW_POINTS),
                FLAG_FEW_POINTS | FLAG_NO_POSE,
            )
        if self._last is not None:
            res = self._track(b)
            if res is not None:
                return res
            flags = FLAG_TRACK_RESET
        else:
            flags = 0
        return self._acquire(b, flags)

    def drop_marks(self, res: MatchResult, blobs: ArrayLike, marks: ArrayLike) -> MatchResult:
        """The pose of ``res`` again without the layout marks ``marks`` (their blobs judged damaged
        by :func:`check_blob_shapes`), flagged ``FLAG_OCCLUDED_MARK`` (and ``few_points`` if
        fewer than ``min_markers`` remain)."""
        b = np.asarray(blobs, np.float64)
        labels = res.labels.copy()
        labels[np.asarray(marks, np.int64)] = -1
        keep = res.flags & (FLAG_TRACK_RESET | FLAG_AMBIGUOUS)
        out = self._finalize(labels, b, res.margin, keep | FLAG_OCCLUDED_MARK, res.hypotheses)
        out.flags |= FLAG_OCCLUDED_MARK
        out.pose.flags |= out.flags
        return out

    def _track(self, b: F64) -> MatchResult | None:
        r, t = self._last  # type: ignore[misc]
        order, near, sec = self._nearest_blobs(r, t, b)
        labels = np.where(near < self.track_gate_px, order[:, 0], -1)
        # unambiguous: the runner-up blob of each marker is much farther than the nearest
        if np.any((labels >= 0) & (sec < 2 * near + 4 * self.gate_px)):
            return None
        if (
            len(np.unique(labels[labels >= 0])) != (labels >= 0).sum()
            or (labels >= 0).sum() < self.min_markers
        ):
            return None
        fit = self._fit(labels, b, (r, t))
        if fit is None:
            return None
        labels2, cost, crowd = self._associate(*fit, b)
        if not np.array_equal(labels2, labels):
            return None
        margin = (crowd / self.sigma_px) ** 2 / 2
        return self._finalize(labels, b, margin, 0, 1)

    def _robust(self, lab: I64, b: F64) -> tuple[float, I64] | None:
        """PnP on a candidate labelling, re-association, and - if some pairs do not fit - the same
        with each pair left out in turn (one wrong pair among >= 5); best cost wins."""
        best: tuple[float, I64] | None = None
        trials = [lab]
        for attempt in range(2):
            for cand in trials:
                fit = self._fit(cand, b, None)
                if fit is None:
                    continue
                labels, cost, _ = self._associate(*fit, b)
                if (labels >= 0).sum() >= 4:
                    fit2 = self._fit(labels, b, fit)
                    if fit2 is not None:
                        labels, cost, _ = self._associate(*fit2, b)
                if best is None or cost < best[0]:
                    best = (cost, labels)
            if attempt == 0:
                if best is not None and (best[1] >= 0).sum() >= (lab >= 0).sum():
                    break
                idx = np.flatnonzero(lab >= 0)
                if len(idx) < 5:
                    break
                trials = []
                for j in idx:
                    t = lab.copy()
                    t[j] = -1
                    trials.append(t)
        return best

    def _affine_relabel(self, lab: I64, b: F64, gate: float) -> I64:
        """Re-associate with the affine map (least squares) of the reference projection that best
        fits the current pairs (absorbs the out-of-plane tilt a similarity cannot), twice."""
        for _ in range(2):
            sel = lab >= 0
            if sel.sum() < 3:
                return lab
            A = self._ref_h[sel]
            try:
                X = np.linalg.solve(A.T @ A, A.T @ b[lab[sel], :2])
            except np.linalg.LinAlgError:
                return lab
            pred = self._ref_h @ X
            d = np.linalg.norm(pred[:, None, :] - b[None, :, :2], axis=2)
            nn = d.argmin(axis=1)
            dn = d.min(axis=1)
            new = np.where(dn < gate, nn, -1)
            counts = np.bincount(new[new >= 0], minlength=len(b))
            if counts.size and counts.max() > 1:
                for v in np.flatnonzero(counts > 1):
                    claim = np.flatnonzero(new == v)
                    new[claim[claim != claim[np.argmin(dn[claim])]]] = -1
            if np.array_equal(new, lab):
                return new
            lab = new
        return lab

    def _acquire(self, b: F64, flags: int) -> MatchResult:
        Q = self._ref_px[:, 0] + 1j * self._ref_px[:, 1]
        B = b[:, 0] + 1j * b[:, 1]
        M, N = len(Q), len(B)
        ma, mb = np.array([(i, j) for i in range(M) for j in range(M) if i != j]).T
        ba, bb = np.array([(i, j) for i in range(N) for j in range(N) if i != j]).T
        s = (B[bb][None, :] - B[ba][None, :]) / (Q[mb][:, None] - Q[ma][:, None])  # (PM, PB)
        ok = (np.abs(s) > self.scale_range[0]) & (np.abs(s) < self.scale_range[1])
        ok &= np.abs(np.angle(s)) < np.deg2rad(self.max_angle_deg)
        pi, pj = np.nonzero(ok)
        if len(pi) == 0:
            self._last = None
            return MatchResult(
                np.full(M, -1, np.int64), 0.0, failed_pose(), flags | FLAG_NO_POSE, 0
            )
        ss = s[pi, pj]
        tt = B[ba[pj]] - ss * Q[ma[pi]]
        T = ss[:, None] * Q[None, :] + tt[:, None]  # (H, M)
        d = np.abs(T[:, :, None] - B[None, None, :])  # (H, M, N)
        extent = np.abs(Q - Q.mean()).max()
        gate0 = 0.15 * extent + 10
        nn = d.argmin(axis=2)
        dn = d.min(axis=2)
        lab = np.where(dn < gate0, nn, -1)
        srt = np.sort(lab, axis=1)
        # distinct blobs claimed (a blob claimed twice counts once)
        count = (srt[:, 0] >= 0).astype(np.int64) + (
            (srt[:, 1:] != srt[:, :-1]) & (srt[:, 1:] >= 0)
        ).sum(axis=1)
        score = count - 1e-3 * np.minimum(dn, gate0).sum(axis=1) / gate0
        cand = np.argsort(-score)
        seen: set[bytes] = set()
        seen_pre: set[bytes] = set()
        results: list[tuple[float, I64]] = []
        for h in cand[:1500]:
            if count[h] < 3:
                break
            lab_h = lab[h].copy()
            # a blob claimed by several markers goes to the nearest one
            counts = np.bincount(lab_h[lab_h >= 0], minlength=N)
            if counts.max() > 1:
                for v in np.flatnonzero(counts > 1):
                    claim = np.flatnonzero(lab_h == v)
                    lab_h[claim[claim != claim[np.argmin(dn[h, claim])]]] = -1
            if (lab_h >= 0).sum() < 3:
                continue
            pre = lab_h.tobytes()
            if pre in seen_pre:
                continue
            seen_pre.add(pre)
            lab_h = self._affine_relabel(lab_h, b, 0.06 * extent + 8)
            if (lab_h >= 0).sum() < 4:
                continue
            key = lab_h.tobytes()
            if key in seen:
                continue
            seen.add(key)
            res = self._robust(lab_h, b)
            if res is None:
                continue
            cost, labels = res
            results.append((cost, labels))
            if len(seen) >= 25:
                break
            # enough alternatives seen once a labelling explains its blobs at the noise level
            good = [c for c, lab_ in results if c <= 9.0 * len(self.P)]
            if good and len(results) >= 6:
                break
        if not results:
            self._last = None
            return MatchResult(
                np.full(M, -1, np.int64), 0.0, failed_pose(), flags | FLAG_NO_POSE, len(seen)
            )
        results.sort(key=lambda x: x[0])
        best_cost, best = results[0]
        runner = next((c for c, lab_ in results[1:] if not np.array_equal(lab_, best)), np.inf)
        return self._finalize(best, b, float(runner - best_cost), flags, len(seen))
