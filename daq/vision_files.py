"""Schemas of the vision files a camera source reads: the camera model (JSON).

The camera file's keys, types, shapes and ranges are :class:`CameraFile`'s (the schema library:
:mod:`cdpr.daq.schema`); :func:`cdpr.calibration.camera_model.camera_from_mapping` then checks what
relates the numbers (a camera matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, a rotation, 4, 5
or 8 distortion terms).  Errors name the file and the key (``extrinsics.R_O_C[2][1]``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field

from cdpr.calibration.camera_model import CameraModel, camera_from_mapping

from .files import load_json
from .schema import Schema, Text, Vec3_m, parse

MAX_PIXELS = 100_000
"""Largest image side (px)."""
MAX_FOCAL_PX = 1e7
"""Largest camera-matrix entry (px)."""

_Entry_px = Annotated[float, Field(ge=-MAX_FOCAL_PX, le=MAX_FOCAL_PX)]
_Row3 = Annotated[list[_Entry_px], Field(min_length=3, max_length=3)]
_Unit = Annotated[float, Field(ge=-1.0, le=1.0)]
_Rot3 = Annotated[
    list[Annotated[list[_Unit], Field(min_length=3, max_length=3)]],
    Field(min_length=3, max_length=3),
]


class _Extrinsics(Schema):
    """``extrinsics``: the camera pose in {O}; any other key is free information (``method``,
    ``looks_at_O_m``, the extrinsic calibration's residuals) kept with the model."""

    model_config = ConfigDict(extra="allow")

    R_O_C: _Rot3 = Field(
        default_factory=lambda: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    )
    position_O_m: Vec3_m = Field(default_factory=lambda: [0.0, 0.0, 0.0])


class CameraFile(Schema):
    """A camera model JSON file (layout: :mod:`cdpr.calibration.camera_model`)."""

    id: Text | None = None
    name: Text = "camera"
    model: Literal["opencv-pinhole"] = "opencv-pinhole"
    pixel_convention: Text | None = None
    image_size_px: Annotated[
        list[Annotated[int, Field(ge=1, le=MAX_PIXELS)]], Field(min_length=2, max_length=2)
    ]
    camera_matrix: Annotated[list[_Row3], Field(min_length=3, max_length=3)]
    dist_coeffs: Annotated[list[Annotated[float, Field(ge=-1e6, le=1e6)]], Field(max_length=8)]
    extrinsics: _Extrinsics = Field(default_factory=_Extrinsics)
    calibration: dict[str, Any] = Field(default_factory=dict)


def camera_from_file_mapping(data: Any, source: str) -> CameraModel:
    """A :class:`CameraModel` from a parsed camera file, checked by :class:`CameraFile`."""
    f = parse(CameraFile, data, source)
    return camera_from_mapping(f.model_dump(), source)


def load_camera(path: str | os.PathLike[str]) -> CameraModel:
    """A camera model JSON file (format in :mod:`cdpr.calibration.camera_model`)."""
    return camera_from_file_mapping(load_json(path), str(Path(path)))
