"""Schemas of the vision files a camera source reads: the camera model (JSON), the marker
layout (TOML) and the IR-mark detector's settings (a camera source's ``blobs`` table, or
``cdpr pose --blobs FILE``: :class:`BlobDetection`).

The camera file's keys, types, shapes and ranges are :class:`CameraFile`'s (the schema library:
:mod:`cdpr.daq.schema`); :func:`cdpr.calibration.camera_model.camera_from_mapping` then checks what
relates the numbers (a camera matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, a rotation, 4, 5
or 8 distortion terms); likewise :class:`LayoutFile` and
:func:`cdpr.calibration.markers.layout_from_mapping` (unique ids and labels, axes not parallel).
Errors name the file and the key (``extrinsics.R_O_C[2][1]``, ``point[3].radius_m``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, model_validator

from cdpr.analysis.errors import ConfigError
from cdpr.calibration.camera_model import CameraModel, camera_from_mapping
from cdpr.calibration.detect import BlobSettings
from cdpr.calibration.markers import MarkerLayout, layout_from_mapping

from .files import load_json, load_toml
from .schema import Schema, Text, Vec3_m, parse, rule_error

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


_Size_m = Annotated[float, Field(gt=0.0, le=10.0)]


class _Marker(Schema):
    id: Annotated[int, Field(ge=0, le=1_000_000)]
    center_m: Vec3_m
    normal: Vec3_m
    x_axis: Vec3_m
    size_m: _Size_m


class _Point(Schema):
    label: Annotated[str, Field(min_length=1, max_length=200)]
    center_m: Vec3_m
    normal: Vec3_m = Field(default_factory=lambda: [0.0, 0.0, 1.0])
    radius_m: _Size_m


class LayoutFile(Schema):
    """A marker layout TOML file (layout: :mod:`cdpr.calibration.markers`): a fiducial layout has
    ``dictionary``, ``quiet_zone_cells`` and ``[[marker]]`` tables, a points layout ``[[point]]``
    tables (the other kind's keys are refused by ``layout_from_mapping``)."""

    kind: Literal["fiducial", "points"]
    frame: Literal["P", "O"] = "P"
    name: Text = ""
    dictionary: Text | None = None
    quiet_zone_cells: Annotated[float, Field(ge=0.0, le=100.0)] | None = None
    marker: Annotated[list[_Marker], Field(max_length=10_000)] | None = None
    point: Annotated[list[_Point], Field(max_length=10_000)] | None = None


def load_marker_layout(path: str | os.PathLike[str]) -> MarkerLayout:
    """A marker layout file, checked by :class:`LayoutFile`, then by
    :func:`cdpr.calibration.markers.layout_from_mapping` (ids and labels unique, axes not
    parallel, enough markers) and, for fiducials, OpenCV's reading of the dictionary."""
    src = str(path)
    f = parse(LayoutFile, load_toml(path), src)
    layout = layout_from_mapping(f.model_dump(exclude_none=True), source=src)
    if layout.kind == "fiducial":
        from cdpr.calibration import cv

        try:
            cv.aruco_dictionary(layout.dictionary)
        except ConfigError:  # a custom dictionary file: its own file and key
            raise
        except Exception as exc:  # noqa: BLE001 - OpenCV raises its own error type
            raise ConfigError(src, "dictionary", str(exc)) from None
    return layout


_Px = Annotated[float, Field(gt=0.0, le=100.0)]


class BlobDetection(Schema):
    """The IR-mark detector's settings (:class:`cdpr.calibration.detect.BlobSettings`, whose
    defaults these are): a camera source's ``[sources.<name>.blobs]`` table, or the ``[blobs]``
    table of a ``cdpr pose --blobs`` file.  Meanings and defaults: docs/vision.md."""

    threshold_dn: Annotated[float, Field(gt=0.0, lt=255.0)] = BlobSettings.threshold_dn
    min_area_px: Annotated[float, Field(ge=1.0, le=1e8)] = BlobSettings.min_area_px
    max_area_px: Annotated[float, Field(ge=1.0, le=1e8)] = BlobSettings.max_area_px
    coarse_factor: Annotated[int, Field(ge=1, le=64)] = BlobSettings.coarse_factor
    window_px: Annotated[int, Field(ge=0, le=MAX_PIXELS)] = BlobSettings.window_px
    shape_check: bool = BlobSettings.shape_check
    notch_tolerance: Annotated[float, Field(gt=0.0, le=1.0)] = BlobSettings.notch_tolerance
    notch_sigma: Annotated[float, Field(gt=0.0, le=1e3)] = BlobSettings.notch_sigma
    notch_margin_px: Annotated[float, Field(ge=0.0, le=100.0)] = BlobSettings.notch_margin_px
    bias_tolerance_px: _Px = BlobSettings.bias_tolerance_px
    rim_tolerance_px: _Px = BlobSettings.rim_tolerance_px

    @model_validator(mode="after")
    def _areas(self) -> BlobDetection:
        if self.min_area_px > self.max_area_px:
            raise rule_error(f"expected <= max_area_px ({self.max_area_px:g})", "min_area_px")
        return self

    def settings(self) -> BlobSettings:
        return BlobSettings(**self.model_dump())


class BlobsFile(Schema):
    """A ``cdpr pose --blobs`` file: one ``[blobs]`` table (:class:`BlobDetection`)."""

    blobs: BlobDetection = Field(default_factory=BlobDetection)


def load_blob_settings(path: str | os.PathLike[str]) -> BlobSettings:
    """The IR-mark detector's settings from a TOML file's ``[blobs]`` table (keys and ranges of
    :class:`BlobDetection`; an unknown table or key is an error naming the file and the key)."""
    return parse(BlobsFile, load_toml(path), str(path)).blobs.settings()
