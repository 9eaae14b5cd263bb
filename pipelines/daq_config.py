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

    [sources.loadcells]                 # one table per source; "kind" picks the driver
    kind = "can_loadcell"
    interface = "virtual"
    ...                                 # the driver's own settings (docs/daq_drivers.md)

Every error is a :class:`~cdpr.analysis.errors.ConfigError` naming the file, the key and the problem.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import ConfigError

from .config import file_sha256, load_toml

#: Source settings that name files: resolved relative to the config file.
PATH_KEYS = ("dbc", "calibration", "calibration_file", "file", "path", "log", "rig", "schedule")

_RUN_KEYS = {"label", "rig", "calibrations", "operator", "notes"}
_REC_KEYS = {"out", "chunk_size_kib", "flush_interval_s", "compression", "queue_readings"}


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
    sources: list[SourceConfig] = field(default_factory=list)
    raw: dict[str, Any] = field(default_factory=dict)

    def calibration_ids(self) -> dict[str, str]:
        """``file name -> name@sha256[:12]`` of each calibration file."""
        return {p.name: f"{p.name}@{file_sha256(p)[:12]}" for p in self.calibrations}


def _resolve(base: Path, value: Any, origin: str, key: str, must_exist: bool = True) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigError(origin, key, f"expected a file path (string), got {value!r}")
    p = Path(value)
    if not p.is_absolute():
        p = base / p
    if must_exist and not p.is_file():
        raise ConfigError(origin, key, f"file not found: {p}")
    return p


def _typed(
    table: Mapping[str, Any], key: str, types: tuple[type, ...], origin: str, prefix: str
) -> Any:
    v = table[key]
    if isinstance(v, bool) and bool not in types:
        raise ConfigError(origin, f"{prefix}.{key}", f"expected {types[0].__name__}, got {v!r}")
    if not isinstance(v, types):
        raise ConfigError(origin, f"{prefix}.{key}", f"expected {types[0].__name__}, got {v!r}")
    return v


def _section(data: Mapping[str, Any], name: str, known: set[str], origin: str) -> dict[str, Any]:
    """The optional table ``[name]`` (empty if absent); a non-table or an unknown key raises."""
    table = data.get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(origin, name, "expected a table")
    bad = set(table) - known
    if bad:
        raise ConfigError(
            origin, f"{name}.{sorted(bad)[0]}", f"unknown key (known: {sorted(known)})"
        )
    return table


def load_daq_config(path: str | os.PathLike[str]) -> DaqConfig:
    """Load and validate ``tunnel.toml`` (layout in the module docstring).

    Source settings are checked by the drivers when they are built
    (:func:`build_sources`), so that the driver names the bad key.
    """
    p = Path(path)
    origin = str(p)
    data = load_toml(p)
    base = p.parent
    cfg = DaqConfig(path=p, raw=data)
    unknown = set(data) - {"run", "recorder", "sources"}
    if unknown:
        raise ConfigError(
            origin, sorted(unknown)[0], "unknown section (expected run, recorder, sources)"
        )

    run = _section(data, "run", _RUN_KEYS, origin)
    if "label" in run:
        cfg.label = _typed(run, "label", (str,), origin, "run")
    if "rig" in run:
        cfg.rig = _resolve(base, run["rig"], origin, "run.rig")
    if "calibrations" in run:
        cals = run["calibrations"]
        if not isinstance(cals, list):
            raise ConfigError(origin, "run.calibrations", "expected a list of file paths")
        cfg.calibrations = [
            _resolve(base, c, origin, f"run.calibrations[{i}]") for i, c in enumerate(cals)
        ]
    for k in ("operator", "notes"):
        if k in run:
            setattr(cfg, k, _typed(run, k, (str,), origin, "run"))

    rec = _section(data, "recorder", _REC_KEYS, origin)
    if "out" in rec:
        o = _typed(rec, "out", (str,), origin, "recorder")
        cfg.out = Path(o) if Path(o).is_absolute() else base / o
    if "chunk_size_kib" in rec:
        v = _typed(rec, "chunk_size_kib", (int,), origin, "recorder")
        if not 1 <= v <= 64 * 1024:
            raise ConfigError(origin, "recorder.chunk_size_kib", f"expected 1..65536, got {v}")
        cfg.chunk_size = v * 1024
    if "flush_interval_s" in rec:
        v = _typed(rec, "flush_interval_s", (int, float), origin, "recorder")
        if not 0 < v <= 1.0:
            raise ConfigError(
                origin, "recorder.flush_interval_s", f"expected a value in (0, 1] s, got {v}"
            )
        cfg.flush_interval_s = float(v)
    if "compression" in rec:
        v = _typed(rec, "compression", (str,), origin, "recorder")
        if v not in ("zstd", "lz4", "none"):
            raise ConfigError(
                origin, "recorder.compression", f"expected zstd, lz4 or none, got {v!r}"
            )
        cfg.compression = v
    if "queue_readings" in rec:
        v = _typed(rec, "queue_readings", (int,), origin, "recorder")
        if v < 1:
            raise ConfigError(origin, "recorder.queue_readings", f"expected >= 1, got {v}")
        cfg.queue_readings = v

    sources = data.get("sources", {})
    if not isinstance(sources, dict) or not sources:
        raise ConfigError(origin, "sources", "expected at least one [sources.<name>] table")
    for name, table in sources.items():
        prefix = f"sources.{name}"
        if not isinstance(table, dict):
            raise ConfigError(origin, prefix, "expected a table")
        if "kind" not in table or not isinstance(table["kind"], str):
            raise ConfigError(origin, f"{prefix}.kind", "missing driver name (string)")
        settings = {k: v for k, v in table.items() if k != "kind"}
        for k in PATH_KEYS:
            if k in settings and isinstance(settings[k], str):
                settings[k] = str(_resolve(base, settings[k], origin, f"{prefix}.{k}"))
        if "calibration_file" in settings:
            _apply_calibration_file(settings, origin, prefix)
            cal_path = Path(settings.pop("calibration_file"))
            if cal_path not in cfg.calibrations:
                cfg.calibrations.append(cal_path)  # attached to the run, its id recorded
        cfg.sources.append(SourceConfig(name, table["kind"], settings))
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
