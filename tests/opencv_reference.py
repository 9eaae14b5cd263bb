"""OpenCV's own calibration of chessboard photos, exactly as its calibration tutorial does it
(``findChessboardCorners`` with default flags, ``cornerSubPix`` with an 11 x 11 window and the
tutorial's stop criteria, ``calibrateCameraExtended`` with default flags): the independent reference
for the tests on real photographs.  This is the one file besides ``calibration/cv.py`` that imports
``cv2`` (``test_vision_cv.py`` allows it): a reference must not go through the code under test."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np


def tutorial_calibration(
    files: list[Path], pattern: tuple[int, int], keep: list[int] | None = None
) -> dict[str, Any]:
    """fx, fy, cx, cy with their standard deviations, RMS and per-view RMS (px) of OpenCV's
    tutorial pipeline on ``files`` (``keep``: indices of the files to use, default all)."""
    objp = np.zeros((pattern[0] * pattern[1], 3), np.float32)
    objp[:, :2] = np.mgrid[0 : pattern[0], 0 : pattern[1]].T.reshape(-1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    obj, img, size = [], [], None
    for k, f in enumerate(files):
        if keep is not None and k not in keep:
            continue
        gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ok, corners = cv2.findChessboardCorners(gray, pattern, None)
        assert ok, f"OpenCV finds no {pattern} chessboard in {f}"
        corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), crit)
        obj.append(objp)
        img.append(corners)
        size = gray.shape[::-1]
    return _calibrate(obj, img, size)


def _calibrate(obj: list[Any], img: list[Any], size: Any) -> dict[str, Any]:
    """``calibrateCameraExtended`` with default flags: fx, fy, cx, cy, their standard deviations,
    RMS, per-view RMS (px) and the distortion."""
    rms, K, dist, _, _, std, _, per_view = cv2.calibrateCameraExtended(obj, img, size, None, None)
    std = std.ravel()
    return {
        "rms_px": float(rms),
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "std": {"fx": float(std[0]), "fy": float(std[1]), "cx": float(std[2]), "cy": float(std[3])},
        "per_view_rms_px": per_view.ravel().astype(float).tolist(),
        "dist": dist.ravel().tolist(),
    }


REFINEMENTS = {
    "none": "CORNER_REFINE_NONE",
    "subpix": "CORNER_REFINE_SUBPIX",
    "contour": "CORNER_REFINE_CONTOUR",
    "apriltag": "CORNER_REFINE_APRILTAG",
}
"""OpenCV's ArUco corner refinements (``none`` is ``ArucoDetector``'s default)."""


def ippe_square_poses(
    gray: np.ndarray,
    dictionary: str,
    length_m: float,
    K: np.ndarray,
    dist: np.ndarray,
    refinement: str = "none",
) -> dict[int, dict[str, Any]]:
    """OpenCV's single-marker pose as its ArUco tutorial computes it: ``ArucoDetector`` (default
    parameters, ``refinement`` one of :data:`REFINEMENTS`), then ``solvePnPGeneric`` with
    ``SOLVEPNP_IPPE_SQUARE`` on the four corners ``(-L/2, L/2, 0), (L/2, L/2, 0), (L/2, -L/2, 0),
    (-L/2, -L/2, 0)``.  Per marker id: ``rvecs``, ``tvecs`` (both solutions, OpenCV's order:
    the lower reprojection error first), ``errors_px`` (their RMS) and ``corners_px`` (4, 2)."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = getattr(cv2.aruco, REFINEMENTS[refinement])
    det = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params
    )
    corners, ids, _ = det.detectMarkers(gray)
    h = length_m / 2
    obj = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], np.float64)
    out: dict[int, dict[str, Any]] = {}
    for c, i in zip(corners, np.ravel(ids) if ids is not None else [], strict=False):
        _, rv, tv, err = cv2.solvePnPGeneric(
            obj, c.reshape(4, 2).astype(np.float64), K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        out[int(i)] = {
            "rvecs": [np.ravel(r) for r in rv],
            "tvecs": [np.ravel(t) for t in tv],
            "errors_px": np.ravel(err).tolist(),
            "corners_px": c.reshape(4, 2).astype(np.float64),
        }
    return out


def charuco_calibration(
    files: list[Path],
    squares_xy: tuple[int, int],
    square_m: float,
    marker_m: float,
    dictionary: str,
) -> dict[str, Any]:
    """OpenCV's own ChArUco calibration of ``files``, as its calibrate_camera_charuco sample does
    it: ``CharucoDetector`` (default parameters) ``detectBoard``, ``matchImagePoints``, then
    ``calibrateCameraExtended`` with default flags (k1 k2 p1 p2 k3).  Keys as
    :func:`tutorial_calibration`, plus ``n_corners`` per view."""
    board = cv2.aruco.CharucoBoard(
        squares_xy,
        square_m,
        marker_m,
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)),
    )
    det = cv2.aruco.CharucoDetector(board)
    obj, img, n, size = [], [], [], None
    for f in files:
        gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        corners, ids, _, _ = det.detectBoard(gray)
        assert ids is not None and len(ids) >= 6, f"OpenCV finds no ChArUco board in {f}"
        o, i = board.matchImagePoints(corners, ids)
        obj.append(o)
        img.append(i)
        n.append(len(ids))
        size = gray.shape[::-1]
    return {**_calibrate(obj, img, size), "n_corners": n}
