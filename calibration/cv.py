"""The one module that imports OpenCV (``cv2``): the adapters that normalise shapes and API changes,
and the OpenCV-backed calibration targets (``CharucoBoard``, ``ChessboardTarget``,
``CircleGridTarget``), ArUco detector and video I/O built on them.

Every other module calls these functions with plain numpy arrays:

- image points are ``(N, 2)`` float64 in pixels, OpenCV's convention (pixel centres at integer
  coordinates, the top-left pixel covers ``[-0.5, 0.5]^2``);
- object points are ``(N, 3)`` float64 in metres;
- ids are ``(N,)`` int64 (OpenCV 4.x returns ``(N, 1)``, 5.x ``(N,)``: both are flattened here);
- ArUco corners are ``(N, 4, 2)`` float64.

Tested range: ``opencv-python-headless >= 4.9, < 5`` (:data:`SUPPORTED`); OpenCV 5.0 split calib3d
and changed the aruco Python API.  :func:`check_version` raises if the installed version is outside.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.analysis.errors import ConfigError, InputError

F64 = NDArray[np.float64]

SUPPORTED: tuple[tuple[int, int], tuple[int, int]] = ((4, 9), (5, 0))
"""Tested OpenCV versions: ``SUPPORTED[0] <= (major, minor) < SUPPORTED[1]``."""

VERSION: str = cv2.__version__


def version_tuple() -> tuple[int, int, int]:
    """Installed OpenCV version as ``(major, minor, patch)``."""
    parts = [int("".join(ch for ch in p if ch.isdigit()) or 0) for p in VERSION.split(".")[:3]]
    while len(parts) < 3:
        parts.append(0)
    return parts[0], parts[1], parts[2]


def check_version() -> None:
    """Raise :class:`ConfigError` if the installed OpenCV is outside :data:`SUPPORTED`."""
    v = version_tuple()[:2]
    if not (SUPPORTED[0] <= v < SUPPORTED[1]):
        raise ConfigError(
            "opencv-python-headless",
            "version",
            f"installed {VERSION}, tested range >= {SUPPORTED[0]} and < {SUPPORTED[1]}",
        )


check_version()


def set_num_threads(n: int) -> None:
    """Limit OpenCV's internal thread pool (``1`` for single-core benchmarks)."""
    cv2.setNumThreads(int(n))


# ------------------------------------------------------------------------------------ geometry
def rodrigues(rvec: ArrayLike) -> F64:
    """Rotation matrix (3, 3) from a rotation vector (3,) in rad."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return np.asarray(R, dtype=np.float64)


def rotation_vector(R: ArrayLike) -> F64:
    """Rotation vector (3,) in rad from a rotation matrix (3, 3)."""
    r, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64).reshape(3, 3))
    return np.asarray(r, dtype=np.float64).reshape(3)


def _dist(dist: ArrayLike) -> NDArray[np.float64]:
    return np.asarray(dist, dtype=np.float64).reshape(-1, 1)


def project_points(
    object_points: ArrayLike, rvec: ArrayLike, tvec: ArrayLike, K: ArrayLike, dist: ArrayLike
) -> F64:
    """Project (N, 3) points given in the object frame to pixels (N, 2) with lens distortion."""
    obj = np.asarray(object_points, dtype=np.float64).reshape(-1, 1, 3)
    if obj.shape[0] == 0:
        return np.zeros((0, 2))
    return _project(obj, rvec, tvec, K, dist)[0]


def project_points_jacobian(
    object_points: ArrayLike, rvec: ArrayLike, tvec: ArrayLike, K: ArrayLike, dist: ArrayLike
) -> tuple[F64, F64]:
    """Projections (N, 2) and ``cv2.projectPoints``' Jacobian (2N, 6) w.r.t. ``[rvec, tvec]``."""
    obj = np.asarray(object_points, dtype=np.float64).reshape(-1, 1, 3)
    return _project(obj, rvec, tvec, K, dist)


def _project(
    obj: F64, rvec: ArrayLike, tvec: ArrayLike, K: ArrayLike, dist: ArrayLike
) -> tuple[F64, F64]:
    """``cv2.projectPoints`` of (N, 1, 3) points: pixels (N, 2) and the Jacobian (2N, 6) w.r.t.
    ``[rvec, tvec]``."""
    img, jac = cv2.projectPoints(
        obj,
        np.asarray(rvec, dtype=np.float64).reshape(3, 1),
        np.asarray(tvec, dtype=np.float64).reshape(3, 1),
        np.asarray(K, dtype=np.float64),
        _dist(dist),
    )
    return img.reshape(-1, 2).astype(np.float64), np.asarray(jac, np.float64)[:, :6]


def undistort_to_normalized(pixels: ArrayLike, K: ArrayLike, dist: ArrayLike) -> F64:
    """Normalised undistorted coordinates (N, 2) (``x/z, y/z`` in the camera frame) of pixels (N, 2).

    Fixed-point iteration of OpenCV's distortion model (the same scheme as ``cv2.undistortPoints``)
    vectorised in numpy, run to convergence (1e-13) instead of OpenCV's default 5 iterations, which
    leave errors of a few hundredths of a pixel at the image edge.
    """
    pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] == 0:
        return np.zeros((0, 2))
    Km = np.asarray(K, dtype=np.float64)
    d = np.zeros(8)
    dd = np.asarray(dist, dtype=np.float64).reshape(-1)
    if dd.size > 8:
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-13)
        out = cv2.undistortPointsIter(pts.reshape(-1, 1, 2), Km, _dist(dist), None, None, crit)
        return out.reshape(-1, 2).astype(np.float64)
    d[: dd.size] = dd
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    fx, fy, cx, cy, skew = Km[0, 0], Km[1, 1], Km[0, 2], Km[1, 2], Km[0, 1]
    yd = (pts[:, 1] - cy) / fy
    xd = (pts[:, 0] - cx - skew * yd) / fx
    x, y = xd.copy(), yd.copy()
    for _ in range(60):
        r2 = x * x + y * y
        icdist = (1 + ((k6 * r2 + k5) * r2 + k4) * r2) / (1 + ((k3 * r2 + k2) * r2 + k1) * r2)
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        xn = (xd - dx) * icdist
        yn = (yd - dy) * icdist
        step = max(np.abs(xn - x).max(), np.abs(yn - y).max())
        x, y = xn, yn
        if step < 1e-11:
            break
    return np.stack([x, y], axis=1)


PNP_METHODS = {
    "sqpnp": "SOLVEPNP_SQPNP",
    "iterative": "SOLVEPNP_ITERATIVE",
    "ippe": "SOLVEPNP_IPPE",
}


def solve_pnp(
    object_points: ArrayLike,
    image_points: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike,
    method: str = "sqpnp",
    rvec0: ArrayLike | None = None,
    tvec0: ArrayLike | None = None,
) -> tuple[bool, F64, F64]:
    """Pose of the object frame in the camera frame: ``(ok, rvec (3,), tvec (3,) m)``.

    ``method`` is ``"sqpnp"``, ``"iterative"`` or ``"ippe"`` (planar).  With ``rvec0``/``tvec0`` the
    iterative method starts from that guess.
    """
    obj = np.ascontiguousarray(np.asarray(object_points, dtype=np.float64).reshape(-1, 1, 3))
    img = np.ascontiguousarray(np.asarray(image_points, dtype=np.float64).reshape(-1, 1, 2))
    flag = getattr(cv2, PNP_METHODS[method])
    try:
        if rvec0 is not None and tvec0 is not None:
            r = np.asarray(rvec0, dtype=np.float64).reshape(3, 1).copy()
            t = np.asarray(tvec0, dtype=np.float64).reshape(3, 1).copy()
            ok, r, t = cv2.solvePnP(
                obj,
                img,
                np.asarray(K, np.float64),
                _dist(dist),
                r,
                t,
                True,
                cv2.SOLVEPNP_ITERATIVE,
            )
        else:
            ok, r, t = cv2.solvePnP(obj, img, np.asarray(K, np.float64), _dist(dist), flags=flag)
    except cv2.error:
        return False, np.zeros(3), np.zeros(3)
    return bool(ok), np.asarray(r, np.float64).reshape(3), np.asarray(t, np.float64).reshape(3)


def refine_pnp_lm(
    object_points: ArrayLike,
    image_points: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike,
    rvec: ArrayLike,
    tvec: ArrayLike,
    iterations: int = 30,
) -> tuple[F64, F64]:
    """Levenberg-Marquardt refinement of a pose (``cv2.solvePnPRefineLM``): ``(rvec, tvec)``."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3, 1).copy()
    t = np.asarray(tvec, dtype=np.float64).reshape(3, 1).copy()
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(iterations), 1e-12)
    r, t = cv2.solvePnPRefineLM(
        np.asarray(object_points, dtype=np.float64).reshape(-1, 1, 3),
        np.asarray(image_points, dtype=np.float64).reshape(-1, 1, 2),
        np.asarray(K, np.float64),
        _dist(dist),
        r,
        t,
        crit,
    )
    return np.asarray(r, np.float64).reshape(3), np.asarray(t, np.float64).reshape(3)


def solve_pnp_planar_all(
    object_points: ArrayLike, image_points: ArrayLike, K: ArrayLike, dist: ArrayLike
) -> list[tuple[F64, F64]]:
    """Both IPPE solutions for coplanar points (the two poses a planar target's image allows:
    ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE)``), best reprojection first: ``(rvec, tvec)``."""
    obj = np.ascontiguousarray(np.asarray(object_points, dtype=np.float64).reshape(-1, 1, 3))
    img = np.ascontiguousarray(np.asarray(image_points, dtype=np.float64).reshape(-1, 1, 2))
    try:
        n, rs, ts, _ = cv2.solvePnPGeneric(
            obj, img, np.asarray(K, np.float64), _dist(dist), flags=cv2.SOLVEPNP_IPPE
        )
    except cv2.error:
        return []
    return [
        (np.asarray(r, np.float64).reshape(3), np.asarray(t, np.float64).reshape(3))
        for r, t in zip(rs[:n], ts[:n], strict=True)
    ]


# ------------------------------------------------------------------------------------ images
def to_gray(image: NDArray[Any]) -> NDArray[np.uint8]:
    """A single-channel uint8 image from a gray or BGR image."""
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    return np.asarray(image)


def remap(
    src: NDArray[Any],
    map_x: NDArray[np.float32],
    map_y: NDArray[np.float32],
    nearest: bool = True,
    border_value: float = 0.0,
) -> NDArray[Any]:
    """Sample ``src`` at ``(map_x, map_y)`` (pixel-centre convention); outside -> ``border_value``."""
    return cv2.remap(
        src,
        np.ascontiguousarray(map_x, dtype=np.float32),
        np.ascontiguousarray(map_y, dtype=np.float32),
        cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(border_value),
    )


def warp_perspective(
    src: NDArray[Any], H: ArrayLike, size_wh: tuple[int, int], border_value: float = 0.0
) -> NDArray[Any]:
    """``dst(x) = src(H^-1 x)`` (bilinear), pixel-centre convention, outside -> ``border_value``."""
    return cv2.warpPerspective(
        src,
        np.asarray(H, np.float64),
        (int(size_wh[0]), int(size_wh[1])),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(border_value),
    )


def gaussian_blur(image: NDArray[Any], sigma_px: float) -> NDArray[Any]:
    """Gaussian blur with standard deviation ``sigma_px`` (kernel +-4 sigma); identity for 0."""
    if sigma_px <= 0:
        return image
    k = 2 * int(np.ceil(4 * sigma_px)) + 1
    return cv2.GaussianBlur(image, (k, k), sigmaX=sigma_px, sigmaY=sigma_px)


def downsample_area(image: NDArray[Any], factor: int) -> NDArray[Any]:
    """Average ``factor x factor`` blocks (exact box filter); shape must be divisible by factor."""
    if factor == 1:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def threshold(gray: NDArray[np.uint8], level: float) -> NDArray[np.uint8]:
    """Binary image (0/255): pixels strictly above ``level``."""
    _, b = cv2.threshold(gray, float(level), 255, cv2.THRESH_BINARY)
    return b


def connected_components(binary: NDArray[np.uint8]) -> tuple[int, NDArray[np.int32], NDArray[Any]]:
    """8-connected components: ``(n_labels incl. background, labels, stats)``.

    ``stats`` is (n, 5) int: ``x, y, width, height, area`` per label (label 0 is the background).
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8, ltype=cv2.CV_32S)
    return int(n), labels, stats


def corner_subpix(
    gray: NDArray[np.uint8], corners: ArrayLike, half_window: int = 4, iterations: int = 40
) -> F64:
    """Refine (N, 2) corner estimates to sub-pixel positions (``cv2.cornerSubPix``)."""
    c = np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2).copy()
    if c.shape[0] == 0:
        return np.zeros((0, 2))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-4)
    cv2.cornerSubPix(gray, c, (half_window, half_window), (-1, -1), crit)
    return c.reshape(-1, 2).astype(np.float64)


def encode_image(image: NDArray[Any], fmt: str = "jpeg", quality: int = 90) -> bytes:
    """JPEG or PNG bytes of an image."""
    fmt = fmt.lower()
    if fmt in ("jpeg", "jpg"):
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    elif fmt == "png":
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    else:
        raise InputError(f"image format: expected 'jpeg' or 'png', got {fmt!r}")
    if not ok:
        raise InputError(f"could not encode a {image.shape} image as {fmt}")
    return bytes(buf.tobytes())


def decode_image(data: bytes, gray: bool = True) -> NDArray[np.uint8] | None:
    """Decode JPEG/PNG bytes; ``None`` if the bytes are not an image."""
    arr = np.frombuffer(data, dtype=np.uint8)
    img = cv2.imdecode(arr, cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    return img


def read_image(path: str | os.PathLike[str], gray: bool = True) -> NDArray[np.uint8] | None:
    """Read an image file (any format OpenCV reads); ``None`` if it cannot be read."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError:
        return None
    if data.size == 0:
        return None
    return cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)


def write_image(path: str | os.PathLike[str], image: NDArray[Any]) -> None:
    """Write an image; the format follows the file extension."""
    ext = os.path.splitext(str(path))[1] or ".png"
    ok, buf = cv2.imencode(ext, image)
    if not ok:
        raise InputError(f"could not encode an image as {ext}")
    with open(path, "wb") as fh:
        fh.write(buf.tobytes())


IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


# ------------------------------------------------------------------------------------ video
class VideoCapture:
    """``cv2.VideoCapture`` on a device index or a video file, with the few calls we need."""

    def __init__(self, target: int | str) -> None:
        self._cap = cv2.VideoCapture(target)
        self.target = target

    def is_opened(self) -> bool:
        return bool(self._cap.isOpened())

    def read(self) -> NDArray[np.uint8] | None:
        """Next frame or ``None`` at the end of the stream / on a read failure."""
        ok, frame = self._cap.read()
        return frame if ok else None

    def grab(self) -> bool:
        return bool(self._cap.grab())

    def position_ms(self) -> float:
        """Timestamp of the last frame read, ms from the start (files) or the driver's clock."""
        return float(self._cap.get(cv2.CAP_PROP_POS_MSEC))

    def frame_index(self) -> int:
        return int(self._cap.get(cv2.CAP_PROP_POS_FRAMES))

    def fps(self) -> float:
        return float(self._cap.get(cv2.CAP_PROP_FPS))

    def frame_count(self) -> int:
        return int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))

    def release(self) -> None:
        self._cap.release()


class VideoWriter:
    """Write gray frames to a video file (MJPG in .avi by default; used by tests and demos)."""

    def __init__(
        self, path: str, size_wh: tuple[int, int], fps: float, fourcc: str = "MJPG"
    ) -> None:
        self._w = cv2.VideoWriter(
            str(path), cv2.VideoWriter_fourcc(*fourcc), float(fps), tuple(size_wh), True
        )
        if not self._w.isOpened():
            raise InputError(f"cannot open a video writer for {path} ({fourcc})")

    def write(self, gray: NDArray[np.uint8]) -> None:
        self._w.write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR) if gray.ndim == 2 else gray)

    def release(self) -> None:
        self._w.release()


# ------------------------------------------------------------------------------------ ArUco
DICTIONARY_FILE_EXTENSIONS = (".yml", ".yaml", ".json", ".xml")

_DICT_CACHE: dict[str, Any] = {}
"""Dictionaries read from files, by path (a cache, not state: the file is read once)."""


def _dictionary_from_file(path: str) -> Any:
    """A custom dictionary from an OpenCV FileStorage file (``nmarkers``, ``markersize``,
    ``maxCorrectionBits``, ``marker_0`` ... as bit strings), the format OpenCV's
    ``Dictionary::writeDictionary`` writes and its ArUco tutorials read."""
    if path in _DICT_CACHE:
        return _DICT_CACHE[path]
    if not os.path.isfile(path):
        raise ConfigError(path, "", "dictionary file not found")
    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise ConfigError(path, "", f"not an OpenCV FileStorage file: {exc.err}") from None
    try:
        for key in ("nmarkers", "markersize"):
            if fs.getNode(key).empty():
                raise ConfigError(path, key, "missing")
        n, size = int(fs.getNode("nmarkers").real()), int(fs.getNode("markersize").real())
        for i in range(n):
            bits = fs.getNode(f"marker_{i}").string()
            if len(bits) != size * size or set(bits) - {"0", "1"}:
                raise ConfigError(
                    path, f"marker_{i}", f"expected {size * size} bits of 0/1, got {bits!r}"
                )
        d = cv2.aruco.Dictionary()
        if not d.readDictionary(fs.root()):
            raise ConfigError(path, "", "OpenCV cannot read this dictionary")
    finally:
        fs.release()
    _DICT_CACHE[path] = d
    return d


def aruco_dictionary(name: str) -> Any:
    """A predefined ArUco/AprilTag dictionary by name (``"DICT_4X4_50"``, ``"DICT_APRILTAG_36h11"``),
    or a custom one from a file path ending in .yml, .yaml, .json or .xml."""
    if name.lower().endswith(DICTIONARY_FILE_EXTENSIONS):
        return _dictionary_from_file(name)
    key = name if name.startswith("DICT_") else f"DICT_{name}"
    if not hasattr(cv2.aruco, key):
        names = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise InputError(f"dictionary: expected one of {names}, got {name!r}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))


def marker_bits_image(dictionary: str, marker_id: int, border_bits: int = 1) -> NDArray[np.uint8]:
    """The marker as an image with one pixel per cell (black border included), 0/255 uint8."""
    d = aruco_dictionary(dictionary)
    n = int(d.markerSize) + 2 * border_bits
    return cv2.aruco.generateImageMarker(d, int(marker_id), n, borderBits=border_bits)


def dictionary_marker_cells(dictionary: str) -> int:
    """Cells per marker side without the border."""
    return int(aruco_dictionary(dictionary).markerSize)


@dataclass
class ArucoDetectorSettings:
    """Detector settings: corner refinement ``"subpix"``, ``"contour"``, ``"apriltag"`` or ``"none"``,
    sub-pixel window half-size in px, and the minimal marker perimeter as a fraction of the image."""

    refinement: str = "subpix"
    subpix_half_window: int = 4
    subpix_iterations: int = 60
    subpix_min_accuracy: float = 0.005
    min_perimeter_rate: float = 0.03
    adaptive_win_min: int = 3
    adaptive_win_max: int = 23
    adaptive_win_step: int = 10


_REFINE = {
    "subpix": "CORNER_REFINE_SUBPIX",
    "contour": "CORNER_REFINE_CONTOUR",
    "apriltag": "CORNER_REFINE_APRILTAG",
    "none": "CORNER_REFINE_NONE",
}


class ArucoDetector:
    """``cv2.aruco.ArucoDetector`` with normalised outputs.

    ``settings=None`` keeps OpenCV's defaults (the benchmark's peer).
    """

    def __init__(self, dictionary: str, settings: ArucoDetectorSettings | None = None) -> None:
        params = cv2.aruco.DetectorParameters()
        if settings is not None:
            params.cornerRefinementMethod = getattr(cv2.aruco, _REFINE[settings.refinement])
            params.cornerRefinementWinSize = int(settings.subpix_half_window)
            params.cornerRefinementMaxIterations = int(settings.subpix_iterations)
            params.cornerRefinementMinAccuracy = float(settings.subpix_min_accuracy)
            if hasattr(params, "relativeCornerRefinmentWinSize"):
                params.relativeCornerRefinmentWinSize = 1.0  # use the absolute window
            params.minMarkerPerimeterRate = float(settings.min_perimeter_rate)
            params.adaptiveThreshWinSizeMin = settings.adaptive_win_min
            params.adaptiveThreshWinSizeMax = settings.adaptive_win_max
            params.adaptiveThreshWinSizeStep = settings.adaptive_win_step
        self.dictionary = dictionary
        self.settings = settings
        self._det = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params)

    def detect(self, gray: NDArray[np.uint8]) -> tuple[F64, NDArray[np.int64]]:
        """Markers in a gray image: corners (N, 4, 2) px (OpenCV order: top-left, top-right,
        bottom-right, bottom-left of the marker as printed) and ids (N,)."""
        corners, ids, _ = self._det.detectMarkers(gray)
        if ids is None or len(corners) == 0:
            return np.zeros((0, 4, 2)), np.zeros(0, dtype=np.int64)
        c = np.stack([np.asarray(x, dtype=np.float64).reshape(4, 2) for x in corners])
        return c, np.asarray(ids, dtype=np.int64).reshape(-1)


def simple_blob_detect(gray: NDArray[np.uint8], bright: bool = True) -> F64:
    """``cv2.SimpleBlobDetector`` with default parameters (bright blobs if ``bright``): (N, 2) px."""
    params = cv2.SimpleBlobDetector_Params()
    if bright:
        params.blobColor = 255
    kps = cv2.SimpleBlobDetector_create(params).detect(gray)
    return np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2)


# ------------------------------------------------------------------------------------ ChArUco
class CharucoBoard:
    """A ChArUco board: ``squares_x`` x ``squares_y`` squares of ``square_m``, markers of
    ``marker_m``; chessboard corner ids follow OpenCV (row-major, from the top-left inner corner)."""

    kind = "charuco"

    def __init__(
        self,
        squares_x: int,
        squares_y: int,
        square_m: float,
        marker_m: float,
        dictionary: str,
        legacy_pattern: bool = False,
    ) -> None:
        self.squares_x, self.squares_y = int(squares_x), int(squares_y)
        self.square_m, self.marker_m = float(square_m), float(marker_m)
        self.dictionary = dictionary
        self.board = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y),
            self.square_m,
            self.marker_m,
            aruco_dictionary(dictionary),
        )
        self.board.setLegacyPattern(bool(legacy_pattern))
        params = cv2.aruco.CharucoParameters()
        dparams = cv2.aruco.DetectorParameters()
        dparams.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        self._det = cv2.aruco.CharucoDetector(self.board, params, dparams)

    @property
    def corners_board_m(self) -> F64:
        """Chessboard corners (N, 3) in the board frame (m): x right, y down, z into the board."""
        return np.asarray(self.board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def image(self, px_per_square: int, margin_px: int = 0) -> NDArray[np.uint8]:
        """The board drawn with ``px_per_square`` pixels per square (plus a white margin)."""
        w = self.squares_x * px_per_square + 2 * margin_px
        h = self.squares_y * px_per_square + 2 * margin_px
        return self.board.generateImage((w, h), marginSize=margin_px, borderBits=1)

    def detect(
        self, gray: NDArray[np.uint8], refine: str | int = "adaptive"
    ) -> tuple[F64, NDArray[np.int64]]:
        """ChArUco corners (N, 2) px and their ids (N,).

        ``refine``: ``"adaptive"`` (default) refines ``CharucoDetector``'s corners once more with
        ``cornerSubPix`` in a half-window of 0.3 x the shortest distance between neighbouring
        corners in the image (2 to 11 px); ``"none"`` keeps ``CharucoDetector``'s corners; an
        integer is a fixed half-window.  Measured on rendered views (docs/vision.md): the
        detector's own corners carry a bias that puts fx 0.1 % (5 sigma) low; the adaptive window
        removes it and gives the lowest corner error at every blur tried, where a fixed 9 x 9
        window (half 4) is worse than none once the blur exceeds ~1 px."""
        cc, ci, _, _ = self._det.detectBoard(gray)
        if ci is None or len(ci) == 0:
            return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
        pts = np.asarray(cc, dtype=np.float64).reshape(-1, 2)
        ids = np.asarray(ci, dtype=np.int64).reshape(-1)
        if refine == "adaptive":
            if len(ids) >= 2:
                # the white margin between a corner and the nearest marker, in squares
                margin = (self.square_m - self.marker_m) / (2.0 * self.square_m)
                pts = corner_subpix(gray, pts, _spacing_half_window(pts, ADAPTIVE_K * margin))
        elif isinstance(refine, int) and not isinstance(refine, bool):
            pts = corner_subpix(gray, pts, refine)
        elif refine != "none":
            raise InputError(
                f"refine: expected 'adaptive', 'none' or a half-window, got {refine!r}"
            )
        return pts, ids


ADAPTIVE_K = 0.8


def _spacing_half_window(points_px: F64, fraction: float) -> int:
    """``fraction`` of the shortest distance between two of the points, within [2, 11] px: a
    ``cornerSubPix`` half-window that never reaches the neighbouring corner."""
    d = np.linalg.norm(points_px[:, None, :] - points_px[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return int(np.clip(round(fraction * float(d.min())), 2, 11))


CHESSBOARD_DETECTORS = ("classic", "sb")
"""``"classic"``: ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` with a window sized from the
corner spacing (the default: the lowest RMS on OpenCV's sample photos, docs/vision.md); ``"sb"``:
``cv2.findChessboardCornersSB`` (sector-based, sub-pixel by itself; more robust to blur)."""


class ChessboardTarget:
    """A plain chessboard of ``squares_x`` x ``squares_y`` squares of ``square_m``: the
    ``(squares_x - 1) x (squares_y - 1)`` inner corners, ids row-major from the first corner OpenCV
    reports (a chessboard has no id marks: the order may turn by 180 degrees between views, which
    intrinsics do not mind, but a known board pose in {O} cannot be used with it)."""

    kind = "chessboard"

    def __init__(
        self,
        squares_x: int,
        squares_y: int,
        square_m: float,
        detector: str = "classic",
        subpix_fraction: float = 0.3,
    ) -> None:
        if detector not in CHESSBOARD_DETECTORS:
            raise InputError(f"chessboard detector: expected one of {CHESSBOARD_DETECTORS}")
        self.squares_x, self.squares_y = int(squares_x), int(squares_y)
        self.square_m = float(square_m)
        self.detector = detector
        self.subpix_fraction = float(subpix_fraction)
        self.pattern = (self.squares_x - 1, self.squares_y - 1)

    @property
    def corners_board_m(self) -> F64:
        """Inner corners (N, 3) in the board frame (m), row-major: x right, y down, z = 0."""
        nx, ny = self.pattern
        jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
        xy = np.stack([jj.ravel(), ii.ravel()], axis=1) * self.square_m
        return np.hstack([xy, np.zeros((nx * ny, 1))]).astype(np.float64)

    def subpix_half_window(self, corners_px: F64) -> int:
        """``cornerSubPix`` half-window for the classic detector: ``subpix_fraction`` of the
        shortest distance between neighbouring corners, within [2, 11] px, so the window never
        reaches the next corner (OpenCV's tutorial uses a fixed 11: on left02.jpg, 22 px squares,
        that view's RMS is 1.22 px instead of 0.16 px; docs/vision.md)."""
        return _spacing_half_window(corners_px, self.subpix_fraction)

    def detect(self, gray: NDArray[np.uint8]) -> tuple[F64, NDArray[np.int64]]:
        """All inner corners (N, 2) px and ids ``0..N-1``, or empty arrays if the whole pattern is
        not found (OpenCV's chessboard detectors find all corners or none)."""
        if self.detector == "sb":
            flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            ok, c = cv2.findChessboardCornersSB(gray, self.pattern, flags=flags)
        else:
            flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
            ok, c = cv2.findChessboardCorners(gray, self.pattern, flags=flags)
            if ok:
                c = np.asarray(c, dtype=np.float64).reshape(-1, 2)
                c = corner_subpix(gray, c, self.subpix_half_window(c), 30)
        if not ok or c is None:
            return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
        pts = np.asarray(c, dtype=np.float64).reshape(-1, 2)
        return pts, np.arange(pts.shape[0], dtype=np.int64)


class CircleGridTarget:
    """A grid of ``circles_x`` x ``circles_y`` dark circles on white, centre spacing ``spacing_m``
    (``asymmetric``: OpenCV's asymmetric grid, whose ``spacing_m`` is OpenCV's ``squareSize``: rows
    ``spacing_m`` apart, circles of one row ``2 spacing_m`` apart, odd rows shifted by
    ``spacing_m``); ids row-major as ``cv2.findCirclesGrid`` orders the centres."""

    kind = "circles"

    def __init__(
        self, circles_x: int, circles_y: int, spacing_m: float, asymmetric: bool = False
    ) -> None:
        self.circles_x, self.circles_y = int(circles_x), int(circles_y)
        self.spacing_m = float(spacing_m)
        self.asymmetric = bool(asymmetric)

    @property
    def corners_board_m(self) -> F64:
        """Circle centres (N, 3) in the board frame (m), in ``findCirclesGrid``'s order."""
        nx, ny = self.circles_x, self.circles_y
        jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
        if self.asymmetric:
            x = (2 * jj + ii % 2) * self.spacing_m
        else:
            x = jj * self.spacing_m
        y = ii * self.spacing_m
        return np.stack([x.ravel(), y.ravel(), np.zeros(nx * ny)], axis=1).astype(np.float64)

    def detect(self, gray: NDArray[np.uint8]) -> tuple[F64, NDArray[np.int64]]:
        """All circle centres (N, 2) px and ids ``0..N-1``, or empty arrays if not all are found."""
        flags = cv2.CALIB_CB_ASYMMETRIC_GRID if self.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
        ok, c = cv2.findCirclesGrid(gray, (self.circles_x, self.circles_y), flags=flags)
        if not ok or c is None:
            return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
        pts = np.asarray(c, dtype=np.float64).reshape(-1, 2)
        return pts, np.arange(pts.shape[0], dtype=np.int64)


CalibrationTarget = CharucoBoard | ChessboardTarget | CircleGridTarget
"""Anything with ``kind``, ``corners_board_m`` (N, 3) and ``detect(gray) -> (corners (n, 2), ids)``."""


# ------------------------------------------------------------------------------------ calibration
def calibrate_camera(
    object_points: list[F64],
    image_points: list[F64],
    image_size_wh: tuple[int, int],
    K0: ArrayLike | None = None,
    fix_k3: bool = True,
    rational: bool = False,
    zero_tangential: bool = False,
) -> dict[str, Any]:
    """``cv2.calibrateCameraExtended``: per-view lists of (N, 3) and (N, 2) points.

    Returns ``rms_px``, ``K`` (3, 3), ``dist`` (5,) or (8,), ``rvecs``/``tvecs`` (V, 3),
    ``std_intrinsics`` (OpenCV order fx, fy, cx, cy, k1, k2, p1, p2, k3, ...) and
    ``per_view_rms_px`` (V,).
    """
    flags = 0
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if rational:
        flags |= cv2.CALIB_RATIONAL_MODEL
    if zero_tangential:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    K = None
    if K0 is not None:
        K = np.asarray(K0, dtype=np.float64).copy()
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    obj = [np.asarray(o, np.float32).reshape(-1, 1, 3) for o in object_points]
    img = [np.asarray(i, np.float32).reshape(-1, 1, 2) for i in image_points]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs, std_in, _std_ex, per_view = cv2.calibrateCameraExtended(
        obj, img, tuple(int(v) for v in image_size_wh), K, None, flags=flags, criteria=crit
    )
    n_dist = 8 if rational else 5
    return {
        "rms_px": float(rms),
        "K": np.asarray(K, np.float64),
        "dist": np.asarray(dist, np.float64).reshape(-1)[:n_dist],
        "rvecs": np.asarray([np.asarray(r).reshape(3) for r in rvecs]),
        "tvecs": np.asarray([np.asarray(t).reshape(3) for t in tvecs]),
        "std_intrinsics": np.asarray(std_in, np.float64).reshape(-1),
        "per_view_rms_px": np.asarray(per_view, np.float64).reshape(-1),
    }


def write_filestorage_yaml(path: str | os.PathLike[str], entries: dict[str, Any]) -> None:
    """Write an OpenCV FileStorage YAML file (matrices as ``!!opencv-matrix``, scalars, strings)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    try:
        for k, v in entries.items():
            if isinstance(v, np.ndarray):
                fs.write(k, np.asarray(v, np.float64))
            elif isinstance(v, bool):
                fs.write(k, int(v))
            elif isinstance(v, int | float | str):
                fs.write(k, v)
    finally:
        fs.release()


def read_filestorage_yaml(path: str | os.PathLike[str], keys: list[str]) -> dict[str, Any]:
    """Read entries back from an OpenCV FileStorage file (matrices as arrays, else real/string)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    out: dict[str, Any] = {}
    try:
        for k in keys:
            node = fs.getNode(k)
            if node.empty():
                continue
            if node.isString():
                out[k] = node.string()
            elif node.isMap() or node.isSeq():
                out[k] = np.asarray(node.mat(), np.float64)
            else:
                out[k] = node.real()
    finally:
        fs.release()
    return out
