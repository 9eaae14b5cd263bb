"""Acquisition config files (``tunnel.toml``): the run, the recorder and the sources.

Layout (example: ``data_samples/tunnel.toml``; every relative path is relative to the config file)::

    [run]
    label = "tp01"                      # test-point label (run name: <date>_<time>_<label>)
    rig = "flat_optimum.toml"           # rig file: recorded (name, sha256) and attached
    calibrations = ["loadcell.dbc"]     # files attached to the run; ids = name@sha256[:12]
    operator = "A. N. Other"
    notes = "wind-off tare then 17.27 m/s"

    [recorder]
    out = "runs"                        # default output folder (``--out`` wins)
    chunk_size_kib = 256                # close a chunk above this size ...
    flush_interval_s = 0.25             # ... or after this long (<= 1 s), then fsync
    compression = "zstd"                # zstd | lz4 | none
    queue_readings = 200000             # per-source queue capacity (readings)
    startup_timeout_s = 5.0             # a source silent this long after the start fails the run
    stall_timeout_s = 2.0               # a periodic source silent this long is a fault (stalled)
    nice = -10                          # process priority asked for (-20..19; refused: an event)

    [sources.loadcells]                 # one table per source; "kind" picks the driver
    kind = "can_loadcell"
    interface = "virtual"
    ...                                 # the driver's own settings (docs/daq_drivers.md)

Every error is a :class:`~cdpr.analysis.errors.ConfigError` naming the file, the key and the problem.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field

from cdpr.analysis.errors import ConfigError
from cdpr.daq.schema import Schema, Text, parse
from cdpr.daq.source_schema import check_source, driver_settings

from .config import file_sha256, load_toml

#: Source settings that name files: resolved relative to the config file.
PATH_KEYS = (
    "dbc",
    "calibration",
    "calibration_file",
    "file",
    "path",
    "log",
    "rig",
    "schedule",
    "camera",
    "layout",
    "video",
)
#: Source settings that name folders (an image folder of a ``camera`` source): resolved likewise.
DIR_KEYS = ("folder",)

_Path = Annotated[str, Field(min_length=1, max_length=4096)]
_Timeout_s = Annotated[float, Field(gt=0.0, le=3600.0)]


class RunSection(Schema):
    """``[run]``: label, rig file, calibration files, operator, notes."""

    label: Text = "run"
    rig: _Path | None = None
    calibrations: Annotated[list[_Path], Field(max_length=1000)] = Field(default_factory=list)
    operator: Text = ""
    notes: Text = ""


class RecorderSection(Schema):
    """``[recorder]``: output, chunking, compression, queue, startup and stall timeouts, nice."""

    out: _Path | None = None
    chunk_size_kib: Annotated[int, Field(ge=1, le=64 * 1024)] = 256
    flush_interval_s: Annotated[float, Field(gt=0.0, le=1.0)] = 0.25
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    queue_readings: Annotated[int, Field(ge=1, le=100_000_000)] = 200_000
    startup_timeout_s: _Timeout_s = 5.0
    stall_timeout_s: _Timeout_s = 2.0
    nice: Annotated[int, Field(ge=-20, le=19)] = -10


class DaqFile(Schema):
    """A daq config: ``[run]`` and ``[recorder]`` checked here; each ``[sources.<name>]`` table
    by the schema of its ``kind`` (:func:`cdpr.daq.source_schema.check_source`), after ``[run]``
    (whose files are resolved first)."""

    run: RunSection = Field(default_factory=RunSection)
    recorder: RecorderSection = Field(default_factory=RecorderSection)
    sources: dict[str, Any] = Field(default_factory=dict)


@dataclass
class SourceConfig:
    """One ``[sources.<name>]`` table: the driver ``kind`` and its settings."""

    name: str
    kind: str
    settings: dict[str, Any]


@dataclass
class DaqConfig:
    """A loaded acquisition config."""

    path: Path
    label: str = "run"
    rig: Path | None = None
    calibrations: list[Path] = field(default_factory=list)
    operator: str = ""
    notes: str = ""
    out: Path | None = None
    chunk_size: int = 256 * 1024
    flush_interval_s: float = 0.25
    compression: str = "zstd"
    queue_readings: int = 200_000
    startup_timeout_s: float = 5.0
    stall_timeout_s: float = 2.0
    nice: int | None = -10
    sources: list[SourceConfig] = field(default_factory=list)
    raw: dict[str, Any] = field(default_factory=dict)

    def calibration_ids(self) -> dict[str, str]:
        """``file name -> name@sha256[:12]`` of each calibration file."""
        return {p.name: f"{p.name}@{file_sha256(p)[:12]}" for p in self.calibrations}


def _resolve(base: Path, value: str, origin: str, key: str, must_exist: bool = True) -> Path:
    p = Path(value)
    if not p.is_absolute():
        p = base / p
    if must_exist and not p.is_file():
        raise ConfigError(origin, key, f"file not found: {p}")
    return p


def load_daq_config(path: str | os.PathLike[str]) -> DaqConfig:
    """Load and validate ``tunnel.toml`` (layout in the module docstring).

    Each source table is checked by the schema of its ``kind`` (unknown keys, types, ranges);
    what relates settings to files (a DBC's channels, the frame budget) is checked by the driver
    when the sources are built (:func:`build_sources`), before any device is opened.
    """
    p = Path(path)
    origin = str(p)
    data = load_toml(p)
    base = p.parent
    cfg = DaqConfig(path=p, raw=data)
    f = parse(DaqFile, data, origin)
    run, rec = f.run, f.recorder
    cfg.label, cfg.operator, cfg.notes = run.label, run.operator, run.notes
    if run.rig is not None:
        cfg.rig = _resolve(base, run.rig, origin, "run.rig")
    cfg.calibrations = [
        _resolve(base, c, origin, f"run.calibrations[{i}]") for i, c in enumerate(run.calibrations)
    ]
    if rec.out is not None:
        cfg.out = Path(rec.out) if Path(rec.out).is_absolute() else base / rec.out
    cfg.chunk_size = rec.chunk_size_kib * 1024
    cfg.flush_interval_s = rec.flush_interval_s
    cfg.compression = rec.compression
    cfg.queue_readings = rec.queue_readings
    cfg.startup_timeout_s = rec.startup_timeout_s
    cfg.stall_timeout_s = rec.stall_timeout_s
    cfg.nice = rec.nice

    if not f.sources:
        raise ConfigError(origin, "sources", "expected at least one [sources.<name>] table")
    for name, table in f.sources.items():
        prefix = f"sources.{name}"
        model = check_source(table, name, origin)  # keys, types, ranges: the kind's schema
        settings = driver_settings(model)
        for k in PATH_KEYS:
            if k in settings and isinstance(settings[k], str):
                settings[k] = str(_resolve(base, settings[k], origin, f"{prefix}.{k}"))
        for k in DIR_KEYS:
            if k in settings and isinstance(settings[k], str):
                d = Path(settings[k]) if Path(settings[k]).is_absolute() else base / settings[k]
                if not d.is_dir():
                    raise ConfigError(origin, f"{prefix}.{k}", f"folder not found: {d}")
                settings[k] = str(d)
        if "calibration_file" in settings:
            _apply_calibration_file(settings, origin, prefix)
            cal_path = Path(settings.pop("calibration_file"))
            if cal_path not in cfg.calibrations:
                cfg.calibrations.append(cal_path)  # attached to the run, its id recorded
        cfg.sources.append(SourceConfig(name, model.kind, settings))
    return cfg


def _apply_calibration_file(settings: dict[str, Any], origin: str, prefix: str) -> None:
    """Take ``offset_counts`` and ``gain_N_per_count`` from a load-cell calibration file (written by
    ``cdpr calibrate loadcells``) named by ``calibration_file``; its cables must match the
    source's ``cables`` when both are given."""
    path = settings["calibration_file"]
    both = [k for k in ("offset_counts", "gain_N_per_count") if k in settings]
    if both:
        raise ConfigError(
            origin, f"{prefix}.{both[0]}", "given both inline and by calibration_file"
        )
    from cdpr.daq.loadcell import read_calibration_file

    cal = read_calibration_file(path)
    cables = settings.get("cables")
    if cables is not None and cal.cables is not None and list(cal.cables) != list(cables):
        raise ConfigError(
            origin,
            f"{prefix}.calibration_file",
            f"its cables {list(cal.cables)} differ from {prefix}.cables {list(cables)}",
        )
    settings["offset_counts"] = cal.offset_counts
    settings["gain_N_per_count"] = cal.gain_N_per_count


def build_sources(cfg: DaqConfig) -> list[Any]:
    """The drivers of ``cfg`` (not opened); a bad setting raises :class:`ConfigError`."""
    import cdpr.daq.drivers  # noqa: F401  - registers the drivers
    from cdpr.daq.source import create_source

    out = []
    for sc in cfg.sources:
        out.append(create_source(sc.kind, sc.name, sc.settings, origin=str(cfg.path)))
    return out
