"""Camera calibration: intrinsics (ChArUco, chessboard or circle grid) and extrinsics to {O}.

Intrinsics (:func:`calibrate_intrinsics`): target corners per view (sub-pixel), views checked for
"no board", "too few corners" and blur (edge spread estimated at the corners), OpenCV's
``calibrateCameraExtended`` (pinhole + k1, k2, p1, p2 [, k3]), then iterative rejection of views whose
RMS exceeds ``reject_k`` times the median, parameter standard deviations, and a split-half
cross-validation (calibrate on every other view, measure the reprojection error of the held-out
views with their poses re-fitted by PnP at the other half's intrinsics, and compare the parameters).

Extrinsics: from a board placed at a known pose in {O} (:func:`extrinsics_from_board`) or from
fiducials at known positions in {O} (:func:`extrinsics_from_fiducials`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.analysis.errors import InputError

from . import cv
from .camera_model import CameraModel
from .markers import MarkerLayout
from .pose import camera_pose_from_points

F64 = NDArray[np.float64]


BOARD_TYPES = ("charuco", "chessboard", "circles")
"""Calibration target kinds (the board file's ``[board] type``)."""


@dataclass
class BoardSpec:
    """A calibration target of kind ``type``:

    - ``"charuco"``: ``squares_x`` x ``squares_y`` squares of ``square_m``, markers of ``marker_m``
      from ``dictionary``, ``legacy_pattern`` flag;
    - ``"chessboard"``: ``squares_x`` x ``squares_y`` squares of ``square_m`` (the inner corners,
      ``(squares_x - 1) x (squares_y - 1)``, are measured), ``detector`` ``"classic"`` or ``"sb"``;
    - ``"circles"``: ``circles_x`` x ``circles_y`` circles, centre spacing ``spacing_m``,
      ``asymmetric`` grid flag.

    Optionally its pose in {O} (for extrinsics; ChArUco only): ``R_O_B`` and ``position_O_m`` of
    the board origin (OpenCV board frame: origin at the top-left outer corner, x right, y down,
    z into the board)."""

    type: str = "charuco"
    squares_x: int = 12
    squares_y: int = 9
    square_m: float = 0.030
    marker_m: float = 0.022
    dictionary: str = "DICT_5X5_100"
    legacy_pattern: bool = False
    detector: str = "classic"
    circles_x: int = 4
    circles_y: int = 11
    spacing_m: float = 0.02
    asymmetric: bool = False
    R_O_B: F64 | None = None
    position_O_m: F64 | None = None

    def make(self) -> cv.CalibrationTarget:
        if self.type == "chessboard":
            return cv.ChessboardTarget(self.squares_x, self.squares_y, self.square_m, self.detector)
        if self.type == "circles":
            return cv.CircleGridTarget(
                self.circles_x, self.circles_y, self.spacing_m, self.asymmetric
            )
        if self.type != "charuco":
            raise InputError(f"board type: expected one of {BOARD_TYPES}, got {self.type!r}")
        return cv.CharucoBoard(
            self.squares_x,
            self.squares_y,
            self.square_m,
            self.marker_m,
            self.dictionary,
            self.legacy_pattern,
        )

    def description(self) -> dict[str, Any]:
        """The keys that define this target (for the camera file's provenance)."""
        keys = {
            "charuco": ("squares_x", "squares_y", "square_m", "marker_m", "dictionary"),
            "chessboard": ("squares_x", "squares_y", "square_m", "detector"),
            "circles": ("circles_x", "circles_y", "spacing_m", "asymmetric"),
        }[self.type]
        return {"type": self.type, **{k: getattr(self, k) for k in keys}}


@dataclass
class CalibrationSettings:
    """Acceptance limits: corners per view, views, blur (edge spread, px), rejection factor, k3."""

    min_corners: int = 12
    min_views: int = 8
    max_blur_px: float = 2.5
    reject_k: float = 3.0
    reject_floor_px: float = 0.3
    max_reject_rounds: int = 3
    fix_k3: bool = True
    zero_tangential: bool = False


@dataclass
class View:
    """Target corners (or circle centres) found in one image: name, corners (N, 2) px, ids (N,),
    blur estimate (px)."""

    name: str
    corners_px: F64
    ids: NDArray[np.int64]
    blur_px: float


def edge_spread_px(gray: NDArray[np.uint8], points_px: F64, half: int = 5) -> float:
    """Median blur estimate (Gaussian sigma of the edge spread, px) around the given corners:
    contrast / (sqrt(2 pi) * max gradient) in a window, the value a blurred step edge gives."""
    g = gray.astype(np.float64)
    gy, gx = np.gradient(g)
    mag = np.hypot(gx, gy)
    h, w = g.shape
    out = []
    for x, y in np.asarray(points_px).reshape(-1, 2):
        xi, yi = int(round(x)), int(round(y))
        if xi - half < 0 or yi - half < 0 or xi + half + 1 > w or yi + half + 1 > h:
            continue
        win = g[yi - half : yi + half + 1, xi - half : xi + half + 1]
        contrast = np.percentile(win, 95) - np.percentile(win, 5)
        m = mag[yi - half : yi + half + 1, xi - half : xi + half + 1].max()
        if contrast > 20 and m > 0:
            out.append(contrast / (np.sqrt(2 * np.pi) * m))
    return float(np.median(out)) if out else float("inf")


def detect_view(
    name: str, gray: NDArray[np.uint8], board: cv.CalibrationTarget, settings: CalibrationSettings
) -> tuple[View | None, str]:
    """Target corners of one image, or ``(None, reason)`` if the view is unusable."""
    corners, ids = board.detect(gray)
    if len(ids) == 0:
        return None, "no board found"
    if len(ids) < settings.min_corners:
        return None, f"only {len(ids)} {board.kind} corners (need {settings.min_corners})"
    # circle centres are not edges: the edge-spread blur check applies to corners only
    blur = float("nan") if board.kind == "circles" else edge_spread_px(gray, corners)
    if blur > settings.max_blur_px:
        return None, f"blurred (edge spread {blur:.2f} px > {settings.max_blur_px:g} px)"
    return View(name, corners, ids, blur), ""


@dataclass
class IntrinsicsResult:
    """Outcome of :func:`calibrate_intrinsics`."""

    camera: CameraModel
    rms_px: float
    per_view_rms_px: dict[str, float]
    std: dict[str, float]
    rejected: dict[str, str]
    views: list[View]
    split_half: dict[str, Any] = field(default_factory=dict)


_STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def _calibrate(
    views: list[View],
    board: cv.CalibrationTarget,
    size: tuple[int, int],
    fix_k3: bool,
    zero_tangential: bool = False,
) -> dict[str, Any]:
    obj_all = board.corners_board_m
    return cv.calibrate_camera(
        [obj_all[v.ids] for v in views],
        [v.corners_px for v in views],
        size,
        fix_k3=fix_k3,
        zero_tangential=zero_tangential,
    )


def _holdout_rms(views: list[View], board: cv.CalibrationTarget, K: F64, dist: F64) -> list[float]:
    obj_all = board.corners_board_m
    out = []
    for v in views:
        ok, r, t = cv.solve_pnp(obj_all[v.ids], v.corners_px, K, dist, "iterative")
        if not ok:
            out.append(float("nan"))
            continue
        r, t = cv.refine_pnp_lm(obj_all[v.ids], v.corners_px, K, dist, r, t)
        res = cv.project_points(obj_all[v.ids], r, t, K, dist) - v.corners_px
        out.append(float(np.sqrt(np.mean(np.sum(res**2, axis=1)))))
    return out


def calibrate_intrinsics(
    views: list[View],
    board: cv.CalibrationTarget,
    image_size_px: tuple[int, int],
    settings: CalibrationSettings | None = None,
    name: str = "camera",
) -> IntrinsicsResult:
    """Intrinsics from target views (see the module docstring); raises :class:`InputError` if
    fewer than ``min_views`` views are usable."""
    s = settings or CalibrationSettings()
    if len(views) < s.min_views:
        raise InputError(f"too few usable views: {len(views)} (need {s.min_views})")
    rejected: dict[str, str] = {}
    current = list(views)
    res = _calibrate(current, board, image_size_px, s.fix_k3, s.zero_tangential)
    for _ in range(s.max_reject_rounds):
        pv = res["per_view_rms_px"]
        limit = max(s.reject_k * float(np.median(pv)), s.reject_floor_px)
        bad = [i for i, e in enumerate(pv) if e > limit]
        if not bad or len(current) - len(bad) < s.min_views:
            break
        for i in bad:
            rejected[current[i].name] = f"outlier view (RMS {pv[i]:.3f} px > {limit:.3f} px)"
        current = [v for i, v in enumerate(current) if i not in set(bad)]
        res = _calibrate(current, board, image_size_px, s.fix_k3, s.zero_tangential)
    std = {n: float(x) for n, x in zip(_STD_NAMES, res["std_intrinsics"], strict=False)}
    per_view = {v.name: float(e) for v, e in zip(current, res["per_view_rms_px"], strict=True)}
    cam = CameraModel(res["K"], res["dist"], image_size_px, name=name)
    out = IntrinsicsResult(cam, res["rms_px"], per_view, std, rejected, current)
    out.split_half = split_half(current, board, image_size_px, s.fix_k3, s.zero_tangential)
    cam.calibration = {
        "method": f"{board.kind}, cv2.calibrateCameraExtended"
        + (", k3 fixed at 0" if s.fix_k3 else "")
        + (", p1 = p2 = 0" if s.zero_tangential else ""),
        "rms_px": out.rms_px,
        "n_views": len(current),
        "n_corners": int(sum(len(v.ids) for v in current)),
        "std": std,
        "per_view_rms_px": per_view,
        "rejected": rejected,
        "split_half": out.split_half,
    }
    return out


def split_half(
    views: list[View],
    board: cv.CalibrationTarget,
    size: tuple[int, int],
    fix_k3: bool,
    zero_tangential: bool = False,
) -> dict[str, Any]:
    """Calibrate on even and on odd views; held-out RMS of each half with the other's intrinsics."""
    if len(views) < 8:
        return {}
    halves = [views[0::2], views[1::2]]
    fits = [_calibrate(h, board, size, fix_k3, zero_tangential) for h in halves]
    out: dict[str, Any] = {}
    for a, b in ((0, 1), (1, 0)):
        K, dist = fits[a]["K"], fits[a]["dist"]
        out[f"heldout_rms_px_{'AB'[b]}"] = _holdout_rms(halves[b], board, K, dist)
        out[f"fit_rms_px_{'AB'[a]}"] = fits[a]["rms_px"]
    for i, n in enumerate(("fx", "fy", "cx", "cy")):
        va = [fits[0]["K"][0, 0], fits[0]["K"][1, 1], fits[0]["K"][0, 2], fits[0]["K"][1, 2]][i]
        vb = [fits[1]["K"][0, 0], fits[1]["K"][1, 1], fits[1]["K"][0, 2], fits[1]["K"][1, 2]][i]
        out[f"{n}_A"], out[f"{n}_B"] = float(va), float(vb)
    out["names_A"] = [v.name for v in halves[0]]
    out["names_B"] = [v.name for v in halves[1]]
    return out


@contextmanager
def _png_figure(path: str, nrows: int, ncols: int, size: tuple[float, float]) -> Iterator[Any]:
    """``plt.subplots(nrows, ncols)`` (figure, axes) at 100 dpi, saved as ``path`` when the block
    ends without an exception and closed in every case (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(nrows, ncols, figsize=size, dpi=100)
    try:
        yield fig, axes
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)


def coverage_figure(result: IntrinsicsResult, path: str) -> None:
    """PNG of every used corner over the image area, coloured by view (gaps show up as blank)."""
    W, H = result.camera.image_size_px
    with _png_figure(path, 1, 1, (6.4, 6.4 * H / W + 0.6)) as (fig, ax):
        import matplotlib.pyplot as plt

        cmap = plt.get_cmap("tab20")
        for i, v in enumerate(result.views):
            ax.plot(v.corners_px[:, 0], v.corners_px[:, 1], ".", ms=2, color=cmap(i % 20))
        ax.set_xlim(-0.5, W - 0.5)
        ax.set_ylim(H - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_title(f"corner coverage: {len(result.views)} views, RMS {result.rms_px:.3f} px")
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")


def crossval_figure(result: IntrinsicsResult, path: str) -> None:
    """PNG of the split-half cross-validation: held-out per-view RMS and the parameters of each half."""
    sh = result.split_half
    with _png_figure(path, 1, 2, (10, 4)) as (fig, axes):
        if not sh:
            axes[0].text(0.5, 0.5, "fewer than 8 views: no split-half test", ha="center")
        else:
            a, b = sh["heldout_rms_px_A"], sh["heldout_rms_px_B"]
            axes[0].bar(np.arange(len(a)), a, color="C0", label="half A, intrinsics of B")
            axes[0].bar(
                np.arange(len(b)) + len(a) + 1, b, color="C1", label="half B, intrinsics of A"
            )
            axes[0].axhline(
                result.rms_px,
                color="k",
                ls="--",
                lw=1,
                label=f"all-view fit RMS {result.rms_px:.3f}",
            )
            axes[0].set_ylabel("held-out RMS (px)")
            axes[0].set_xlabel("view")
            axes[0].legend(fontsize=8)
            names = ["fx", "fy", "cx", "cy"]
            diff = [sh[f"{n}_A"] - sh[f"{n}_B"] for n in names]
            # each half has sqrt(2) x the all-view std; their difference sqrt(2) x that again
            sd = [2.0 * result.std.get(n, np.nan) for n in names]
            axes[1].bar(names, diff, yerr=sd, capsize=4, color="C2")
            axes[1].axhline(0, color="k", lw=0.8)
            axes[1].set_ylabel("half A - half B (px)  [bars: +-1 sigma of the difference]")
        axes[0].set_title("split-half cross-validation")


# ------------------------------------------------------------------------------------ extrinsics
def extrinsics_from_board(
    camera: CameraModel,
    spec: BoardSpec,
    gray: NDArray[np.uint8],
    sigma_px: float = 0.1,
    min_corners: int = 12,
) -> CameraModel:
    """Camera pose in {O} from one image of a board placed at ``spec.R_O_B``, ``spec.position_O_m``."""
    if spec.R_O_B is None or spec.position_O_m is None:
        raise InputError("board: its pose in {O} ([pose_O]) is needed for extrinsics")
    board = spec.make()
    if not isinstance(board, cv.CharucoBoard):
        raise InputError(
            f"board: extrinsics need a ChArUco board (a {spec.type} has no marks that fix its "
            "orientation, so its corner order is ambiguous)"
        )
    corners, ids = board.detect(gray)
    if len(ids) < min_corners:
        raise InputError(f"board: only {len(ids)} ChArUco corners found (need {min_corners})")
    obj_O = board.corners_board_m[ids] @ np.asarray(spec.R_O_B).T + np.asarray(spec.position_O_m)
    return _extrinsics(camera, obj_O, corners, sigma_px, "ChArUco board at a known pose in {O}")


def extrinsics_from_fiducials(
    camera: CameraModel, layout: MarkerLayout, gray: NDArray[np.uint8], sigma_px: float = 0.05
) -> CameraModel:
    """Camera pose in {O} from fiducials whose positions are given in {O} (layout frame "O")."""
    from .detect import FiducialDetector

    if layout.kind != "fiducial" or layout.frame != "O":
        raise InputError("markers: expected a fiducial layout with frame = 'O' for extrinsics")
    ids, corners = FiducialDetector(layout, camera).detect(gray)
    if len(ids) < 2:
        raise InputError(f"markers: only {len(ids)} of the layout's markers found (need 2)")
    pos = {int(i): k for k, i in enumerate(layout.ids)}
    obj = layout.fiducial_corners_m[[pos[int(i)] for i in ids]].reshape(-1, 3)
    return _extrinsics(
        camera,
        obj,
        corners.reshape(-1, 2),
        sigma_px,
        f"{len(ids)} fiducials at known positions in {{O}}",
    )


def _extrinsics(
    camera: CameraModel, obj_O: ArrayLike, img: ArrayLike, sigma_px: float, method: str
) -> CameraModel:
    R_O_C, c_O, cov, rms, sigma_used = camera_pose_from_points(obj_O, img, camera, sigma_px)
    info = {
        "method": method,
        "rms_px": rms,
        "n_points": int(np.asarray(img).reshape(-1, 2).shape[0]),
        "std_position_O_m": np.sqrt(np.diag(cov)[:3]).tolist(),
        "std_rotation_O_rad": np.sqrt(np.diag(cov)[3:]).tolist(),
        "sigma_px_prior": sigma_px,
        "sigma_px_from_residuals": sigma_used,
    }
    return camera.with_extrinsics(R_O_C, c_O, info)
