"""Load-cell calibration (raw counts -> newtons) and the CAN frame budget check.

A load-cell channel reports raw ADC counts ``c``; its tension is ``T_N = (c - offset_counts) *
gain_N_per_count``.  :class:`Calibration` holds one offset and one gain per channel.

The frame budget: a classic CAN data frame with an 11-bit identifier and ``n`` data bytes takes
``44 + 8 n`` bits plus 3 bits of interframe space without stuffing (111 bits for 8 bytes) and, with
worst-case bit stuffing, ``44 + 8 n + floor((34 + 8 n - 1) / 4) + 3`` bits (135 bits for 8 bytes).
A 1 Mbit/s bus therefore carries about 7400 (worst case) to 9000 (no stuffing) 8-byte frames per
second.  :func:`check_frame_budget` refuses a configuration whose worst-case load exceeds the
allowed fraction of the bit rate, naming the configuration key at fault.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.systematic import LoadCellCalibrationSd, loadcell_sd_from_fit

FloatArray = NDArray[np.float64]

INT24_MIN = -(1 << 23)
INT24_MAX = (1 << 23) - 1


def can_frame_bits(data_bytes: int = 8, extended: bool = False, stuffing: bool = True) -> int:
    """Bits on the wire for one classic CAN data frame, including 3 bits of interframe space.

    data_bytes: 0..8; extended: 29-bit identifier (adds 20 bits); stuffing: worst-case bit stuffing.
    Standard id, 8 bytes: 111 bits without stuffing, 135 with worst-case stuffing.
    """
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"data_bytes: expected 0..8, got {data_bytes}")
    header = 64 if extended else 44  # SOF..EOF of a data frame with no data, excluding IFS
    stuffable = (54 if extended else 34) + 8 * data_bytes
    bits = header + 8 * data_bytes + 3
    if stuffing:
        bits += (stuffable - 1) // 4
    return bits


@dataclass(frozen=True)
class FrameBudget:
    """Result of a frame budget computation: frames/s, worst-case bits/s and the bus load fraction."""

    frames_per_s: float
    bits_per_s: float
    bitrate: int
    load: float
    max_load: float

    @property
    def fits(self) -> bool:
        return self.load <= self.max_load


def frame_budget(
    bitrate: int,
    rate_hz: float,
    frames_per_sample: int,
    data_bytes: int = 8,
    extended: bool = False,
    max_load: float = 0.9,
) -> FrameBudget:
    """Worst-case bus load of ``frames_per_sample`` frames of ``data_bytes`` bytes at ``rate_hz``."""
    frames = float(rate_hz) * frames_per_sample
    bits = frames * can_frame_bits(data_bytes, extended, stuffing=True)
    return FrameBudget(frames, bits, int(bitrate), bits / float(bitrate), float(max_load))


def check_frame_budget(
    origin: str,
    key_prefix: str,
    bitrate: int,
    rate_hz: float,
    frames_per_sample: int,
    data_bytes: int = 8,
    extended: bool = False,
    max_load: float = 0.9,
) -> FrameBudget:
    """Raise :class:`ConfigError` (naming ``<key_prefix>.rate_hz``) if the frames cannot fit the bus.

    Returns the :class:`FrameBudget` when they fit.  ``bitrate``, ``rate_hz`` (> 0) and
    ``max_load`` (in (0, 1]) come checked by a schema (:mod:`cdpr.daq.source_schema`, the
    schedule's).
    """
    b = frame_budget(bitrate, rate_hz, frames_per_sample, data_bytes, extended, max_load)
    if not b.fits:
        cap = max_load * bitrate / (can_frame_bits(data_bytes, extended) * frames_per_sample)
        raise ConfigError(
            origin,
            f"{key_prefix}.rate_hz",
            f"{rate_hz:g} Hz x {frames_per_sample} frames/sample = {b.frames_per_s:.6g} frames/s "
            f"needs {b.bits_per_s / 1e3:.6g} kbit/s worst case ({100 * b.load:.3g} % of "
            f"{bitrate / 1e3:.0f} kbit/s, limit {100 * max_load:.0f} %): at most {math.floor(cap)} Hz fits",
        )
    return b


@dataclass(frozen=True)
class Calibration:
    """Per-channel linear calibration: ``T_N = (counts - offset_counts) * gain_N_per_count``.

    offset_counts: (n,) zero-load reading, counts; gain_N_per_count: (n,) N per count (non-zero).
    """

    offset_counts: FloatArray
    gain_N_per_count: FloatArray

    def __post_init__(self) -> None:
        off = np.asarray(self.offset_counts, dtype=np.float64).reshape(-1)
        gain = np.asarray(self.gain_N_per_count, dtype=np.float64).reshape(-1)
        if off.shape != gain.shape:
            raise ValueError(f"offset {off.shape} and gain {gain.shape} must have the same length")
        object.__setattr__(self, "offset_counts", off)
        object.__setattr__(self, "gain_N_per_count", gain)

    @property
    def n_channels(self) -> int:
        return int(self.offset_counts.shape[0])

    def to_newtons(self, counts: Any) -> FloatArray:
        """Counts (..., n) -> tensions (..., n) in N."""
        return (np.asarray(counts, dtype=np.float64) - self.offset_counts) * self.gain_N_per_count

    def to_counts(self, tensions_N: Any) -> FloatArray:
        """Tensions (..., n) in N -> counts (..., n) as floats (not rounded or clipped)."""
        return np.asarray(tensions_N, dtype=np.float64) / self.gain_N_per_count + self.offset_counts

    def to_mapping(self) -> dict[str, list[float]]:
        return {
            "offset_counts": self.offset_counts.tolist(),
            "gain_N_per_count": self.gain_N_per_count.tolist(),
        }


RAW_MISSING_COUNTS = -(1 << 31)
"""The ``raw_<cable>_counts`` value recorded for a channel whose frame is missing (T is NaN)."""


def tensions_from_raw(calibration: Calibration, raw_counts: Any) -> FloatArray:
    """Tensions (..., n) in N from recorded ``raw_<cable>_counts`` (..., n): the recorder's
    :meth:`Calibration.to_newtons`, with NaN where a count is missing (NaN or
    :data:`RAW_MISSING_COUNTS`), as the recorder writes T for a missing frame."""
    c = np.array(raw_counts, dtype=np.float64)
    c[c == RAW_MISSING_COUNTS] = np.nan
    return calibration.to_newtons(c)


DEFAULT_GAIN_N_PER_COUNT = 5.0e-5
"""Default gain: 5e-5 N/count, i.e. +-419 N over the signed 24-bit range (assumption)."""


def calibration_from_settings(
    origin: str,
    key_prefix: str,
    n_channels: int,
    offset_counts: Sequence[float] | float | None = None,
    gain_N_per_count: Sequence[float] | float | None = None,
) -> Calibration:
    """Build a :class:`Calibration` for ``n_channels`` from settings values (scalar or one per
    channel); a wrong length or a zero/non-finite gain raises :class:`ConfigError` naming the key."""

    def vec(key: str, value: Any, default: float) -> FloatArray:
        if value is None:
            value = default
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ConfigError(
                origin, f"{key_prefix}.{key}", f"expected numbers, got {value!r}"
            ) from None
        if a.ndim == 0:
            a = np.full(n_channels, float(a))
        if a.shape != (n_channels,):
            raise ConfigError(
                origin, f"{key_prefix}.{key}", f"expected {n_channels} values, got {a.size}"
            )
        if not np.all(np.isfinite(a)):
            raise ConfigError(origin, f"{key_prefix}.{key}", "expected finite numbers")
        return a

    off = vec("offset_counts", offset_counts, 0.0)
    gain = vec("gain_N_per_count", gain_N_per_count, DEFAULT_GAIN_N_PER_COUNT)
    if np.any(gain == 0):
        raise ConfigError(origin, f"{key_prefix}.gain_N_per_count", "gain must be non-zero")
    return Calibration(off, gain)


# --------------------------------------------------------------------------------------------
# the load-cell calibration file: one format, written by `cdpr calibrate loadcells` (and the
# virtual rig), read by record, import, simulate and the campaign file
# --------------------------------------------------------------------------------------------
CALIBRATION_FILE_KIND = "loadcells"
_CAL_KEYS_REQUIRED = ("offset_counts", "gain_N_per_count")
#: the other keys of ``[calibration]``: its identity and the fit statistics `cdpr calibrate
#: loadcells` writes (kept in :attr:`LoadCellCalibrationFile.extra`); any other key is an error
_CAL_KEYS_OPTIONAL = (
    "kind", "id", "cables", "source", "created_utc", "software_version", "sd_offset_counts",
    "sd_gain_N_per_count", "corr_offset_gain", "residual_rms_N", "nonlinearity_pct", "n_points",
)  # fmt: skip


@dataclass(frozen=True)
class LoadCellCalibrationFile:
    """A load-cell calibration file: ``[calibration]`` with ``kind = "loadcells"``, ``id``,
    ``cables`` (names, optional), ``offset_counts`` and ``gain_N_per_count`` (one value or one per
    cable) and any fit statistics (``sd_*``, ``residual_rms_N``, ...: kept in ``extra``)."""

    path: str
    id: str
    cables: tuple[str, ...] | None
    offset_counts: Any
    gain_N_per_count: Any
    extra: Mapping[str, Any]

    def for_cables(self, cables: Sequence[str]) -> Calibration:
        """The calibration of ``cables`` in that order (matched by name when the file names its
        cables; a missing or extra cable is a :class:`ConfigError` naming the file)."""
        names = list(cables)
        off, gain = self.offset_counts, self.gain_N_per_count
        if self.cables is not None:
            if sorted(self.cables) != sorted(names):
                missing = [n for n in names if n not in self.cables]
                extra = [n for n in self.cables if n not in names]
                said = "; ".join(
                    filter(
                        None,
                        [
                            f"no calibration for {', '.join(missing)}" if missing else "",
                            f"calibrates unknown {', '.join(extra)}" if extra else "",
                        ],
                    )
                )
                raise ConfigError(
                    self.path,
                    "calibration.cables",
                    f"{said} (calibrates {list(self.cables)}, the rig has {names})",
                )
            order = [self.cables.index(n) for n in names]
            off = off if np.ndim(off) == 0 else [off[i] for i in order]
            gain = gain if np.ndim(gain) == 0 else [gain[i] for i in order]
        return calibration_from_settings(self.path, "calibration", len(names), off, gain)

    def settings(self, cables: Sequence[str]) -> dict[str, list[float]]:
        """``offset_counts`` / ``gain_N_per_count`` driver settings for ``cables``."""
        return self.for_cables(cables).to_mapping()

    def sd_for_cables(self, cables: Sequence[str]) -> LoadCellCalibrationSd | None:
        """The calibration's own uncertainty for ``cables`` in that order (the fit's parameter
        covariance, :func:`cdpr.analysis.systematic.loadcell_sd_from_fit`), or None when the file
        does not give it (no ``sd_offset_counts`` / ``sd_gain_N_per_count``: the reduction then
        flags ``loadcell_calibration_sd_not_given``).  Without ``corr_offset_gain`` the two σ are
        used with the bound of :func:`cdpr.analysis.systematic.loadcell_calibration_covariance`."""
        names = list(cables)
        cal = self.for_cables(names)  # checks the names
        sd = _calibration_sd(self.path, self.extra, len(self.cables or names))
        if sd is None:
            return None
        order = (
            list(range(len(names)))
            if self.cables is None
            else [self.cables.index(n) for n in names]
        )
        so, sg, corr, n = (None if v is None else v[order] for v in sd)
        assert so is not None and sg is not None and n is not None
        return loadcell_sd_from_fit(cal.gain_N_per_count, so, sg, corr, n)


def read_calibration_file(path: str | os.PathLike[str]) -> LoadCellCalibrationFile:
    """Read a load-cell calibration file (errors name the file and key)."""
    from .files import load_toml

    return parse_calibration_file(str(path), load_toml(str(path)))


def is_calibration_file(data: Mapping[str, Any]) -> bool:
    """True when a parsed TOML document is a load-cell calibration file (its ``[calibration]``
    says ``kind = "loadcells"``): how a run's attached calibrations are told apart."""
    cal = data.get("calibration")
    return isinstance(cal, Mapping) and cal.get("kind") == CALIBRATION_FILE_KIND


def parse_calibration_file(p: str, data: Mapping[str, Any]) -> LoadCellCalibrationFile:
    """A load-cell calibration file's parsed TOML (``p`` names it in errors)."""
    other = sorted(set(data) - {"calibration"})
    if other:
        raise ConfigError(
            p, other[0], "unknown key: a load-cell calibration file has one [calibration] table"
        )
    cal = data.get("calibration")
    if not isinstance(cal, Mapping):
        raise ConfigError(
            p,
            "calibration",
            "missing [calibration] table (write the file with `cdpr calibrate loadcells`)",
        )
    unknown = sorted(set(cal) - {*_CAL_KEYS_REQUIRED, *_CAL_KEYS_OPTIONAL})
    if unknown:
        raise ConfigError(
            p,
            f"calibration.{unknown[0]}",
            "unknown key (a load-cell calibration has "
            + ", ".join((*_CAL_KEYS_REQUIRED, *_CAL_KEYS_OPTIONAL))
            + ")",
        )
    kind = cal.get("kind", CALIBRATION_FILE_KIND)
    if kind != CALIBRATION_FILE_KIND:
        raise ConfigError(
            p, "calibration.kind", f"expected {CALIBRATION_FILE_KIND!r}, got {kind!r}"
        )
    for k in _CAL_KEYS_REQUIRED:
        if k not in cal:
            raise ConfigError(p, f"calibration.{k}", "missing")
    cables = cal.get("cables")
    if cables is not None:
        if not isinstance(cables, list) or not all(isinstance(c, str) for c in cables):
            raise ConfigError(p, "calibration.cables", "expected a list of cable names")
        if len(set(cables)) != len(cables):
            raise ConfigError(p, "calibration.cables", "a cable is named twice")
        cables = tuple(cables)
    n = len(cables) if cables is not None else None
    for k in _CAL_KEYS_REQUIRED:
        v = cal[k]
        if isinstance(v, list) and n is not None and len(v) != n:
            raise ConfigError(
                p, f"calibration.{k}", f"expected {n} values (one per cable), got {len(v)}"
            )
    if n is not None:  # validate values now, not at first use
        calibration_from_settings(
            p, "calibration", n, cal["offset_counts"], cal["gain_N_per_count"]
        )
        _calibration_sd(p, cal, n)
    extra = {k: v for k, v in cal.items() if k not in (*_CAL_KEYS_REQUIRED, "cables", "id", "kind")}
    return LoadCellCalibrationFile(
        p,
        str(cal.get("id", Path(p).name)),
        cables,
        cal["offset_counts"],
        cal["gain_N_per_count"],
        extra,
    )


CALIBRATION_SD_KEYS: tuple[str, ...] = (
    "sd_offset_counts",
    "sd_gain_N_per_count",
    "corr_offset_gain",
    "n_points",
)
"""The fit statistics of ``[calibration]`` that give the calibration's parameter covariance (one
value or one per cable): the two σ are needed together, ``n_points`` with them (the degrees of
freedom ``n_points - 2``), ``corr_offset_gain`` is optional (older files lack it)."""


def _calibration_sd(
    path: str, cal: Mapping[str, Any], n: int
) -> tuple[FloatArray | None, ...] | None:
    """The values of :data:`CALIBRATION_SD_KEYS` as arrays (n,) each for the file's n cables
    (``corr_offset_gain`` None when not given), None when the file gives no σ; a bad value is a
    :class:`ConfigError` naming the file and key."""
    if "sd_offset_counts" not in cal and "sd_gain_N_per_count" not in cal:
        return None
    out: list[FloatArray | None] = []
    for key in CALIBRATION_SD_KEYS:
        if key not in cal:
            if key == "corr_offset_gain":
                out.append(None)
                continue
            raise ConfigError(
                path, f"calibration.{key}", "missing (the fit's σ need sd_offset_counts, "
                "sd_gain_N_per_count and n_points together)",
            )  # fmt: skip
        v = cal[key]
        vals = v if isinstance(v, list) else [v]
        if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in vals):
            raise ConfigError(path, f"calibration.{key}", f"expected numbers, got {v!r}")
        a = np.asarray(vals, dtype=np.float64)
        if a.size == 1:
            a = np.full(n, a[0])
        if a.size != n:
            raise ConfigError(
                path, f"calibration.{key}", f"expected {n} values (one per cable), got {a.size}"
            )
        lo, hi, what = {
            "corr_offset_gain": (-1.0, 1.0, "a correlation in [-1, 1]"),
            "n_points": (3.0, math.inf, "at least 3 calibration points"),
        }.get(key, (0.0, math.inf, "a standard deviation >= 0"))
        bad = np.flatnonzero(~np.isfinite(a) | (a < lo) | (a > hi))
        if bad.size:
            raise ConfigError(
                path, f"calibration.{key}[{bad[0]}]", f"expected {what}, got {a[bad[0]]:g}"
            )
        out.append(a)
    return tuple(out)


def calibration_file_text(
    cables: Sequence[str],
    calibration: Calibration,
    cal_id: str,
    extra: Mapping[str, Any] | None = None,
) -> str:
    """The TOML text of a load-cell calibration file (the one format; see
    :func:`read_calibration_file`)."""
    from .files import toml_inline_arrays

    if len(cables) != calibration.n_channels:
        raise ValueError(f"{len(cables)} cables for {calibration.n_channels} channels")
    body: dict[str, Any] = {"id": cal_id, "kind": CALIBRATION_FILE_KIND, **dict(extra or {})}
    body["cables"] = list(cables)
    body.update(calibration.to_mapping())
    return (
        "# Load-cell calibration: T_N = (counts - offset_counts) * gain_N_per_count\n"
        + toml_inline_arrays({"calibration": body})
    )
