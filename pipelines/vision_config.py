"""Loaders of the vision files: calibration board (TOML), marker layout (TOML), camera model (JSON).

The board file is checked by :class:`BoardFile` and the schema of its ``type`` (the schema library:
:mod:`cdpr.daq.schema`).  Every error is a :class:`~cdpr.analysis.errors.ConfigError` naming the
file, the key and the problem.  The camera, marker-layout and IR-detector (``--blobs``) loaders
are :mod:`cdpr.daq.vision_files`' (a camera source reads those files too), here for the commands.
"""

from __future__ import annotations

import os
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field

from cdpr.analysis.errors import ConfigError
from cdpr.calibration.intrinsics import BoardSpec, CalibrationSettings
from cdpr.calibration.markers import MarkerLayout
from cdpr.daq.schema import Euler_rad, Schema, Text, Vec3_m, parse
from cdpr.daq.vision_files import load_blob_settings, load_camera, load_marker_layout

from .config import load_toml

__all__ = [
    "BoardFile",
    "layout_toml",
    "load_blob_settings",
    "load_board",
    "load_camera",
    "load_marker_layout",
]

_Count = Annotated[int, Field(ge=3, le=1000)]
_Size_m = Annotated[float, Field(gt=0.0, le=10.0)]


class _CharucoBoard(Schema):
    type: Literal["charuco"] = "charuco"
    squares_x: _Count
    squares_y: _Count
    square_m: _Size_m
    marker_m: _Size_m
    dictionary: Text = "DICT_5X5_100"
    legacy_pattern: bool = False


class _Chessboard(Schema):
    type: Literal["chessboard"]
    squares_x: _Count
    squares_y: _Count
    square_m: _Size_m
    detector: Text = "classic"


class _CirclesBoard(Schema):
    type: Literal["circles"]
    circles_x: _Count
    circles_y: _Count
    spacing_m: _Size_m
    asymmetric: bool = False


_BOARDS: dict[str, type[Schema]] = {
    "charuco": _CharucoBoard,
    "chessboard": _Chessboard,
    "circles": _CirclesBoard,
}


class _CalibrationLimits(Schema):
    """``[calibration]``: the acceptance limits of :class:`CalibrationSettings`."""

    min_corners: Annotated[int, Field(ge=1, le=100_000)] = CalibrationSettings.min_corners
    min_views: Annotated[int, Field(ge=1, le=100_000)] = CalibrationSettings.min_views
    max_blur_px: Annotated[float, Field(gt=0.0, le=1e3)] = CalibrationSettings.max_blur_px
    reject_k: Annotated[float, Field(gt=0.0, le=1e3)] = CalibrationSettings.reject_k
    reject_floor_px: Annotated[float, Field(gt=0.0, le=1e3)] = CalibrationSettings.reject_floor_px
    max_reject_rounds: Annotated[int, Field(ge=1, le=100)] = CalibrationSettings.max_reject_rounds
    fix_k3: bool = CalibrationSettings.fix_k3
    zero_tangential: bool = CalibrationSettings.zero_tangential


class _BoardPose(Schema):
    """``[pose_O]``: the board frame in {O} (Z-Y-X angles)."""

    position_m: Vec3_m
    euler_rad: Euler_rad


class BoardFile(Schema):
    """A board file: ``[board]`` (checked by the schema of its ``type``), ``[calibration]``,
    ``[pose_O]``."""

    board: dict[str, Any]
    calibration: _CalibrationLimits = Field(default_factory=_CalibrationLimits)
    pose_O: _BoardPose | None = None


def load_board(path: str | os.PathLike[str]) -> tuple[BoardSpec, CalibrationSettings]:
    """A board file: ``[board]`` with ``type`` (``"charuco"``, the default, ``"chessboard"`` or
    ``"circles"``) and that kind's keys (ChArUco: squares_x, squares_y, square_m, marker_m,
    dictionary, legacy_pattern; chessboard: squares_x, squares_y, square_m, detector; circles:
    circles_x, circles_y, spacing_m, asymmetric), optional ``[calibration]`` limits and optional
    ``[pose_O]`` (position_m, euler_rad: Z-Y-X angles of the board frame in {O}) for extrinsics.
    An unknown table, key or type is an error naming the file and the key."""
    src = str(path)
    f = parse(BoardFile, load_toml(path), src)
    kind = f.board.get("type", "charuco")
    if not isinstance(kind, str) or kind not in _BOARDS:
        raise ConfigError(
            src, "board.type", f"expected one of {', '.join(map(repr, _BOARDS))}, got {kind!r}"
        )
    spec = BoardSpec(**parse(_BOARDS[kind], f.board, src, prefix="board").model_dump())
    if kind == "chessboard":
        from cdpr.calibration.cv import CHESSBOARD_DETECTORS

        if spec.detector not in CHESSBOARD_DETECTORS:
            raise ConfigError(
                src,
                "board.detector",
                f"expected one of {', '.join(map(repr, CHESSBOARD_DETECTORS))}, "
                f"got {spec.detector!r}",
            )
    if kind == "charuco":
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
    if f.pose_O is not None:
        from cdpr.analysis.rotations import rotation_from_euler

        if kind != "charuco":
            raise ConfigError(
                src,
                "pose_O",
                f"a {kind} has no marks that fix its orientation: use a ChArUco board",
            )
        spec.position_O_m = np.asarray(f.pose_O.position_m, np.float64)
        spec.R_O_B = rotation_from_euler(np.asarray(f.pose_O.euler_rad, np.float64))
    return spec, CalibrationSettings(**f.calibration.model_dump())


def layout_toml(layout: MarkerLayout, header: str = "") -> str:
    """A layout as TOML text (for the data samples and round trips)."""
    import tomli_w

    text = tomli_w.dumps(layout.to_mapping())
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + "\n" + text
    return text
