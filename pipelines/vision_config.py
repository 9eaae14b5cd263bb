"""Loaders of the vision files: ChArUco board (TOML), marker layout (TOML), camera model (JSON).

Every error is a :class:`~cdpr.analysis.errors.ConfigError` naming the file, the key and the problem.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError
from cdpr.calibration.camera_model import CameraModel, camera_from_mapping
from cdpr.calibration.intrinsics import BoardSpec, CalibrationSettings
from cdpr.calibration.markers import MarkerLayout, layout_from_mapping

from .config import load_json, load_toml


def _number(
    src: str, table: dict[str, Any], key: str, prefix: str, kind: type, positive: bool = True
) -> Any:
    if key not in table:
        raise ConfigError(src, prefix + key, "missing")
    v = table[key]
    if (
        isinstance(v, bool)
        or not isinstance(v, int | float)
        or (kind is int and not isinstance(v, int))
    ):
        raise ConfigError(
            src, prefix + key, f"expected {'an integer' if kind is int else 'a number'}, got {v!r}"
        )
    if positive and not v > 0:
        raise ConfigError(src, prefix + key, f"expected a positive value, got {v!r}")
    return kind(v)


_BOARD_KEYS = {
    "charuco": ("squares_x", "squares_y", "square_m", "marker_m", "dictionary", "legacy_pattern"),
    "chessboard": ("squares_x", "squares_y", "square_m", "detector"),
    "circles": ("circles_x", "circles_y", "spacing_m", "asymmetric"),
}
_BOARD_TABLES = ("board", "calibration", "pose_O")
_CALIBRATION_KEYS = (
    "min_corners",
    "min_views",
    "max_blur_px",
    "reject_k",
    "reject_floor_px",
    "max_reject_rounds",
    "fix_k3",
    "zero_tangential",
)


def _no_unknown_keys(src: str, table: dict[str, Any], known: tuple[str, ...], prefix: str) -> None:
    for key in table:
        if key not in known:
            raise ConfigError(
                src, prefix + key, f"unknown key (expected one of {', '.join(known)})"
            )


def _bool(src: str, table: dict[str, Any], key: str, prefix: str, default: bool) -> bool:
    v = table.get(key, default)
    if not isinstance(v, bool):
        raise ConfigError(src, prefix + key, f"expected true or false, got {v!r}")
    return v


def load_board(path: str | os.PathLike[str]) -> tuple[BoardSpec, CalibrationSettings]:
    """A board file: ``[board]`` with ``type`` (``"charuco"``, the default, ``"chessboard"`` or
    ``"circles"``) and that kind's keys (ChArUco: squares_x, squares_y, square_m, marker_m,
    dictionary, legacy_pattern; chessboard: squares_x, squares_y, square_m, detector; circles:
    circles_x, circles_y, spacing_m, asymmetric), optional ``[calibration]`` limits and optional
    ``[pose_O]`` (position_m, euler_rad: Z-Y-X angles of the board frame in {O}) for extrinsics.
    An unknown table, key or type is an error naming the file and the key."""
    src = str(path)
    data = load_toml(path)
    _no_unknown_keys(src, data, _BOARD_TABLES, "")
    b = data.get("board")
    if not isinstance(b, dict):
        raise ConfigError(src, "board", "missing [board] table")
    kind = b.get("type", "charuco")
    if kind not in _BOARD_KEYS:
        raise ConfigError(
            src, "board.type", f"expected one of {', '.join(map(repr, _BOARD_KEYS))}, got {kind!r}"
        )
    _no_unknown_keys(src, b, ("type", *_BOARD_KEYS[kind]), "board.")
    if kind == "circles":
        spec = BoardSpec(
            type=kind,
            circles_x=_number(src, b, "circles_x", "board.", int),
            circles_y=_number(src, b, "circles_y", "board.", int),
            spacing_m=_number(src, b, "spacing_m", "board.", float),
            asymmetric=_bool(src, b, "asymmetric", "board.", False),
        )
        if spec.circles_x < 3 or spec.circles_y < 3:
            raise ConfigError(src, "board.circles_x", "expected at least 3 x 3 circles")
    else:
        spec = BoardSpec(
            type=kind,
            squares_x=_number(src, b, "squares_x", "board.", int),
            squares_y=_number(src, b, "squares_y", "board.", int),
            square_m=_number(src, b, "square_m", "board.", float),
        )
        if spec.squares_x < 3 or spec.squares_y < 3:
            raise ConfigError(src, "board.squares_x", "expected at least 3 x 3 squares")
    if kind == "chessboard":
        from cdpr.calibration.cv import CHESSBOARD_DETECTORS

        spec.detector = str(b.get("detector", "classic"))
        if spec.detector not in CHESSBOARD_DETECTORS:
            raise ConfigError(
                src,
                "board.detector",
                f"expected one of {', '.join(map(repr, CHESSBOARD_DETECTORS))}, "
                f"got {b['detector']!r}",
            )
    if kind == "charuco":
        spec.marker_m = _number(src, b, "marker_m", "board.", float)
        spec.dictionary = str(b.get("dictionary", "DICT_5X5_100"))
        spec.legacy_pattern = _bool(src, b, "legacy_pattern", "board.", False)
        if spec.marker_m >= spec.square_m:
            raise ConfigError(
                src, "board.marker_m", f"must be smaller than square_m ({spec.square_m})"
            )
        if not spec.dictionary.startswith("DICT_"):
            raise ConfigError(
                src,
                "board.dictionary",
                f"expected a name like 'DICT_5X5_100', got {spec.dictionary!r}",
            )
    try:
        spec.make()
    except Exception as exc:  # noqa: BLE001 - OpenCV raises its own error type for bad boards
        raise ConfigError(src, "board", f"OpenCV cannot build this board: {exc}") from None
    c = data.get("calibration", {})
    if not isinstance(c, dict):
        raise ConfigError(src, "calibration", "expected a table")
    _no_unknown_keys(src, c, _CALIBRATION_KEYS, "calibration.")
    s = CalibrationSettings()
    for key, num in (
        ("min_corners", int),
        ("min_views", int),
        ("max_blur_px", float),
        ("reject_k", float),
        ("reject_floor_px", float),
        ("max_reject_rounds", int),
    ):
        if key in c:
            setattr(s, key, _number(src, c, key, "calibration.", num))
    for key in ("fix_k3", "zero_tangential"):
        if key in c:
            if not isinstance(c[key], bool):
                raise ConfigError(
                    src, f"calibration.{key}", f"expected true or false, got {c[key]!r}"
                )
            setattr(s, key, c[key])
    pose = data.get("pose_O")
    if pose is not None:
        from cdpr.analysis.rotations import rotation_from_euler

        if not isinstance(pose, dict):
            raise ConfigError(src, "pose_O", "expected a table")
        if kind != "charuco":
            raise ConfigError(
                src,
                "pose_O",
                f"a {kind} has no marks that fix its orientation: use a ChArUco board",
            )
        _no_unknown_keys(src, pose, ("position_m", "euler_rad"), "pose_O.")
        for key in ("position_m", "euler_rad"):
            v = pose.get(key) if isinstance(pose, dict) else None
            try:
                a = np.asarray(v, dtype=np.float64)
            except (TypeError, ValueError):
                a = np.zeros(0)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise ConfigError(src, f"pose_O.{key}", f"expected 3 finite numbers, got {v!r}")
        spec.position_O_m = np.asarray(pose["position_m"], np.float64)
        spec.R_O_B = rotation_from_euler(np.asarray(pose["euler_rad"], np.float64))
    return spec, s


def load_marker_layout(path: str | os.PathLike[str]) -> MarkerLayout:
    """A marker layout file (format in :mod:`cdpr.calibration.markers`)."""
    layout = layout_from_mapping(load_toml(path), source=str(path))
    if layout.kind == "fiducial":
        from cdpr.calibration import cv

        try:
            cv.aruco_dictionary(layout.dictionary)
        except ConfigError:  # a custom dictionary file: its own file and key
            raise
        except Exception as exc:  # noqa: BLE001
            raise ConfigError(str(path), "dictionary", str(exc)) from None
    return layout


def load_camera(path: str | os.PathLike[str]) -> CameraModel:
    """A camera model JSON file (format in :mod:`cdpr.calibration.camera_model`)."""
    p = Path(path)
    data = load_json(p)
    return camera_from_mapping(data, source=str(p))


def layout_toml(layout: MarkerLayout, header: str = "") -> str:
    """A layout as TOML text (for the data samples and round trips)."""
    import tomli_w

    text = tomli_w.dumps(layout.to_mapping())
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + "\n" + text
    return text
