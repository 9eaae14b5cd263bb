"""The settings of every acquisition driver on the schema library: one model per ``kind``, one
discriminated union (:data:`SourceSettings`), one check (:func:`check_source`) used by both a daq
config's ``[sources.<name>]`` tables and :func:`cdpr.daq.source.create_source`.

Each model refuses unknown keys and checks types and ranges (a rate > 0, a CAN bit rate of the
standard set, ports and paths non-empty strings, timeouts > 0); an error names the file and the
key (``sources.cells.bitrate``) through the one formatter :func:`cdpr.daq.schema.config_error`.
What relates a setting to a file or to other settings stays with the driver: a DBC's channels
against ``cables`` (and calibration lengths), the CAN frame budget, the serial line budget, a
file or folder that must exist, exactly one of a camera's ``device``, ``video``, ``folder``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, TypeAdapter, ValidationError
from pydantic_core import PydanticCustomError

from cdpr.analysis.errors import ConfigError

from .schema import Schema, Text, config_error, plain
from .vision_files import BlobDetection

CAN_BITRATES = (
    10_000,
    20_000,
    50_000,
    100_000,
    125_000,
    250_000,
    500_000,
    750_000,
    800_000,
    1_000_000,
)
"""Classic CAN bit rates (bit/s) the adapters we know set (CiA 301 and the slcan ``S0``..``S8``)."""
MAX_RATE_HZ = 1e6
MIN_RATE_HZ = 1e-6
"""A rate below one sample in 11 days is a typo (and 1e-320 Hz would overflow the frame budget)."""
MAX_TIMEOUT_S = 3600.0


def _positive_finite(value: Any) -> Any:
    """A rate: a number (not a string, not a bool), finite and > 0 (one message for each)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PydanticCustomError("number_type", "Input should be a number")
    if not (math.isfinite(value) and value > 0):
        raise PydanticCustomError("finite_positive", "Input should be a finite number > 0")
    return value


Rate_hz = Annotated[float, BeforeValidator(_positive_finite), Field(ge=MIN_RATE_HZ, le=MAX_RATE_HZ)]
Timeout_s = Annotated[float, Field(gt=0.0, le=MAX_TIMEOUT_S)]
Path = Annotated[str, Field(min_length=1, max_length=4096)]
Port = Annotated[str, Field(min_length=1, max_length=4096)]
Name = Annotated[str, Field(min_length=1, max_length=200)]
Cables = Annotated[list[Name], Field(min_length=1, max_length=1000)]
Count = Annotated[float, Field(ge=-1e12, le=1e12)]
Counts = Count | Annotated[list[Count], Field(min_length=1, max_length=1000)]
"""One value for every channel, or one per channel (the length is checked against the cables)."""
Baudrate = Annotated[int, Field(gt=0, le=100_000_000)]
Backoff_s = Annotated[list[Timeout_s], Field(min_length=2, max_length=2)]
"""(first, max) delay between attempts to reopen a lost device, s."""


class _LoadCellCalibration(Schema):
    cables: Cables | None = None
    offset_counts: Counts | None = None
    gain_N_per_count: Counts | None = None
    calibration_file: Path | None = None
    """A calibration file written by ``cdpr calibrate loadcells`` (daq config only)."""


class CanLoadCellSettings(_LoadCellCalibration):
    """``can_loadcell``: load cells on a python-can bus (:class:`cdpr.daq.can_source.CanLoadCellSource`)."""

    kind: Literal["can_loadcell"]
    interface: Name
    channel: Annotated[str, Field(min_length=1, max_length=4096)] | Annotated[int, Field(ge=0)]
    bitrate: Literal[CAN_BITRATES]  # type: ignore[valid-type]
    rate_hz: Rate_hz = 200.0
    dbc: Path | None = None
    max_bus_load: Annotated[float, Field(gt=0.0, le=1.0)] = 0.9
    bus_options: dict[Name, Text | int | float | bool] = Field(default_factory=dict)
    raw: bool = True
    decode: bool = True
    reopen_backoff_s: Backoff_s = Field(default_factory=lambda: [0.1, 5.0])
    error_frame_limit: Annotated[int, Field(ge=1, le=1_000_000_000)] = 1000


class SerialLoadCellSettings(_LoadCellCalibration):
    """``serial_loadcell``: ``$LC`` lines on a serial port
    (:class:`cdpr.daq.serial_source.SerialLoadCellSource`)."""

    kind: Literal["serial_loadcell"]
    port: Port
    baudrate: Baudrate = 115200
    rate_hz: Rate_hz = 100.0
    reopen_backoff_s: Backoff_s = Field(default_factory=lambda: [0.05, 2.0])


class SerialTunnelSettings(Schema):
    """``serial_tunnel``: ``$TUN`` lines on a serial port (:class:`cdpr.daq.tunnel.SerialTunnelSource`)."""

    kind: Literal["serial_tunnel"]
    port: Port
    baudrate: Baudrate = 115200
    rate_hz: Rate_hz = 10.0
    reopen_backoff_s: Backoff_s = Field(default_factory=lambda: [0.05, 2.0])
    test_points: bool = False


class TunnelPoint(Schema):
    """A test point's tunnel conditions (config, command line or ``set_point``)."""

    airspeed_mps: Annotated[float, Field(ge=0.0, le=1e3)]
    static_pressure_Pa: Annotated[float, Field(gt=0.0, le=1e8)] = 101325.0
    temperature_K: Annotated[float, Field(gt=0.0, le=1e4)] = 293.15


class ManualTunnelSettings(TunnelPoint):
    """``manual_tunnel``: conditions typed in per test point (:class:`cdpr.daq.tunnel.ManualTunnelSource`)."""

    kind: Literal["manual_tunnel"]
    rate_hz: Rate_hz = 1.0
    label: Text = ""


class CanReplaySettings(_LoadCellCalibration):
    """``can_replay``: a CAN log as a source (:class:`cdpr.daq.replay.CanReplaySource`)."""

    kind: Literal["can_replay"]
    path: Path
    speed: Literal["recorded", "max"] = "recorded"
    time_scale: Annotated[float, Field(gt=0.0, le=1e6)] = 1.0
    batch: Annotated[int, Field(ge=1, le=10_000_000)] = 2000
    dbc: Path | None = None
    decode: bool = True
    rate_hz: Annotated[float, Field(ge=0.0, le=MAX_RATE_HZ)] = 0.0
    timestamps: Literal["log", "host"] = "log"


class CameraSettings(Schema):
    """``camera``: poses from a device, a video or an image folder
    (:class:`cdpr.daq.camera_source.CameraSource`)."""

    kind: Literal["camera"]
    camera: Path
    layout: Path
    device: Annotated[int, Field(ge=0, le=1000)] | None = None
    video: Path | None = None
    folder: Path | None = None
    fps: Annotated[float, Field(ge=0.0, le=MAX_RATE_HZ)] = 0.0
    realtime: bool = True
    image_every: Annotated[int, Field(ge=0, le=1_000_000_000)] = 0
    image_rate_hz: Annotated[float, Field(ge=0.0, le=MAX_RATE_HZ)] = 0.0
    image_format: Literal["jpeg", "png"] = "jpeg"
    jpeg_quality: Annotated[int, Field(ge=0, le=100)] = 85
    sigma_px: Annotated[float, Field(gt=0.0, le=1e3)] | None = None
    track: bool = True
    blobs: BlobDetection = Field(default_factory=BlobDetection)
    """IR marks: the detector's settings (``[sources.<name>.blobs]``; docs/vision.md)."""


SourceSettings = Annotated[
    CanLoadCellSettings
    | SerialLoadCellSettings
    | SerialTunnelSettings
    | ManualTunnelSettings
    | CanReplaySettings
    | CameraSettings,
    Field(discriminator="kind"),
]
"""A ``[sources.<name>]`` table: the model of its ``kind``."""

_SOURCES: TypeAdapter[Any] = TypeAdapter(SourceSettings)
SOURCE_KINDS = tuple(
    m.model_fields["kind"].annotation.__args__[0]  # type: ignore[union-attr]
    for m in (
        CanLoadCellSettings,
        SerialLoadCellSettings,
        SerialTunnelSettings,
        ManualTunnelSettings,
        CanReplaySettings,
        CameraSettings,
    )
)
"""The kinds that have a schema (every driver :mod:`cdpr.daq.drivers` registers)."""


def check_source(table: Mapping[str, Any], name: str, origin: str) -> Any:
    """The model of one source table (``kind`` and the driver's settings), or a
    :class:`ConfigError` naming ``origin`` and ``sources.<name>.<key>``."""
    prefix = f"sources.{name}"
    if not isinstance(table, Mapping):
        raise ConfigError(origin, prefix, "expected a table")
    kind = table.get("kind")
    if not isinstance(kind, str):
        raise ConfigError(origin, f"{prefix}.kind", "missing driver name (string)")
    if kind not in SOURCE_KINDS:
        raise ConfigError(
            origin, f"{prefix}.kind", f"unknown driver {kind!r} (known: {sorted(SOURCE_KINDS)})"
        )
    try:
        return _SOURCES.validate_python(plain(dict(table)))
    except ValidationError as exc:
        # a tagged union puts the tag first in each location: the key a user reads has none
        errors = [{**e, "loc": tuple(e["loc"])[1:]} for e in exc.errors(include_url=False)]
        raise config_error(exc, origin, prefix, errors) from None
    except RecursionError:
        raise ConfigError(origin, prefix, "nested too deeply") from None


def driver_settings(model: Any) -> dict[str, Any]:
    """The keyword arguments of a validated source: the keys the table gave (the driver's own
    defaults for the rest), without ``kind``."""
    out: dict[str, Any] = model.model_dump(exclude_unset=True, exclude={"kind"})
    return out
