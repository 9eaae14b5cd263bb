"""The virtual rig's schedule: segments (pose, wind, test-point kind and targets), faults, the
sensor model and the rates, read from a schedule TOML file (format: docs/daq_drivers.md) or built
from a test matrix (:func:`cdpr.pipelines.campaign.schedule_from_matrix`).

One job: parse and validate.  The physics twin is :class:`cdpr.daq.virtual_rig.VirtualRig`, the
transports :class:`cdpr.daq.virtual_rig.RigRun`; both take a :class:`Schedule`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import Rig

from .aero_model import AeroModel, aero_from_mapping
from .files import load_toml
from .loadcell import check_frame_budget

FAULT_KINDS = (
    "dropout",
    "slack",
    "saturate",
    "stuck",
    "noise_burst",
    "sensor_fault",
    "port_vanish",
)


# --------------------------------------------------------------------------------------------
# schedule
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Segment:
    """One constant test condition: pose of P in {O}, wind speed, duration.

    Values ramp linearly from the previous segment's over ``transition_s`` (quasi-static: the
    inertia of the slow move is neglected).  ``tare``: a wind-off tare segment (wind must be 0).
    """

    label: str
    duration_s: float
    wind_mps: float
    position_O_m: tuple[float, float, float]
    euler_rad: tuple[float, float, float]
    transition_s: float = 0.0
    tare: bool = False
    kind: str = ""
    target_aoa_deg: float = 0.0
    target_sideslip_deg: float = 0.0
    repeat_of: str = ""

    @property
    def is_test_point(self) -> bool:
        """A segment from a test matrix (it has a kind): the rig emits its test-point events."""
        return self.kind != ""


@dataclass(frozen=True)
class Fault:
    """A fault on demand, active over ``[start_s, start_s + duration_s)`` of schedule time.

    kind: one of :data:`FAULT_KINDS`; cable: channel index (0-based) for per-cable faults;
    factor: noise multiplier of ``noise_burst``; value_N: tension a slack cable reads.
    """

    kind: str
    start_s: float
    duration_s: float
    cable: int = -1
    factor: float = 50.0
    value_N: float = 0.3


@dataclass(frozen=True)
class SensorModel:
    """Noise, drift, quantisation (through the calibration), latency and flags of the load cells.

    noise_sd_N: white noise, N; drift_N_per_s: linear drift scale, each channel drifts at
    ``drift_N_per_s * d_i`` with ``d_i`` uniform in [-1, 1] from the seed; latency_s: delay from
    measurement to transmission; slack_threshold_N: below this the slack bit is set;
    offset_counts / gain_N_per_count: the amplifier's true calibration (also what the driver is
    told, unless ``driver_gain_error`` scales the gain the driver is told).
    """

    noise_sd_N: float = 0.05
    drift_N_per_s: float = 0.002
    latency_s: float = 0.002
    slack_threshold_N: float = 2.0
    offset_counts: tuple[float, ...] | None = None
    gain_N_per_count: float | tuple[float, ...] = 5.0e-5
    tunnel_airspeed_sd_mps: float = 0.05
    tunnel_pressure_sd_Pa: float = 2.0
    tunnel_temperature_sd_K: float = 0.02


@dataclass(frozen=True)
class Schedule:
    """A virtual-rig run: segments, faults, rates and models (see the TOML format in the docs)."""

    name: str
    segments: tuple[Segment, ...]
    rate_hz: float = 200.0
    tunnel_rate_hz: float = 10.0
    method: str = "exact"
    seed: int = 0
    bitrate: int = 1_000_000
    faults: tuple[Fault, ...] = ()
    sensor: SensorModel = field(default_factory=SensorModel)
    aero: AeroModel = field(default_factory=AeroModel)
    source: str = "<memory>"

    @property
    def duration_s(self) -> float:
        return float(sum(s.duration_s for s in self.segments))


_SCHED_KEYS = {"name", "rate_hz", "tunnel_rate_hz", "method", "seed", "bitrate"}
_SEG_KEYS = {
    "label",
    "duration_s",
    "wind_mps",
    "position_O_m",
    "euler_rad",
    "euler_deg",
    "transition_s",
    "tare",
    "kind",
    "target_aoa_deg",
    "target_sideslip_deg",
    "repeat_of",
}
POINT_KINDS = ("wind_on", "tare", "zero", "windage")
_FAULT_KEYS = {"kind", "start_s", "duration_s", "cable", "factor", "value_N"}
_TOP = {"schedule", "segments", "faults", "sensor", "aero"}


def _f(source: str, key: str, v: Any, lo: float | None = None, strict: bool = False) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ConfigError(source, key, f"expected a number, got {v!r}") from None
    if not math.isfinite(x):
        raise ConfigError(source, key, "expected a finite number")
    if lo is not None and (x < lo or (strict and x == lo)):
        raise ConfigError(source, key, f"must be {'>' if strict else '>='} {lo:g}, got {x:g}")
    return x


def _vec3(source: str, key: str, v: Any) -> tuple[float, float, float]:
    if not isinstance(v, list | tuple) or len(v) != 3:
        raise ConfigError(source, key, f"expected 3 numbers, got {v!r}")
    a, b, c = (_f(source, key, x) for x in v)
    return (a, b, c)


def _table(source: str, key: str, value: Any, allowed: Collection[str]) -> Mapping[str, Any]:
    """``value`` as a table whose keys are all in ``allowed`` (else ConfigError at ``key``)."""
    if not isinstance(value, Mapping):
        raise ConfigError(source, key, "expected a table")
    for k in value:
        if k not in allowed:
            raise ConfigError(source, f"{key}.{k}", f"unknown key (allowed: {sorted(allowed)})")
    return value


def schedule_from_mapping(data: Mapping[str, Any], source: str, rig: Rig) -> Schedule:
    """Build and validate a :class:`Schedule` from a parsed schedule file (TOML mapping).

    ``rig`` gives the default pose (its reference pose) and the cable names faults may use.
    Errors are :class:`ConfigError` naming ``source`` and the key (``segments[2].wind_mps``).
    """
    unknown = sorted(set(data) - _TOP)
    if unknown:
        raise ConfigError(source, unknown[0], f"unknown key (allowed: {sorted(_TOP)})")
    sch = _table(source, "schedule", data.get("schedule", {}), _SCHED_KEYS)
    rate = _f(source, "schedule.rate_hz", sch.get("rate_hz", 200.0), 0.0, True)
    t_rate = _f(source, "schedule.tunnel_rate_hz", sch.get("tunnel_rate_hz", 10.0), 0.0, True)
    method = str(sch.get("method", "exact"))
    from cdpr.analysis.tension import METHODS

    if method not in METHODS:
        raise ConfigError(
            source,
            "schedule.method",
            f"unknown tension method {method!r} (known: {sorted(METHODS)})",
        )
    segs_raw = data.get("segments")
    if not isinstance(segs_raw, list) or not segs_raw:
        raise ConfigError(source, "segments", "expected a non-empty array of [[segments]] tables")
    segs = []
    rp, re_ = rig.reference_position_O_m, rig.reference_euler_rad
    ref_p = (float(rp[0]), float(rp[1]), float(rp[2]))
    ref_e = (float(re_[0]), float(re_[1]), float(re_[2]))
    prev_p, prev_e = ref_p, ref_e
    for i, s_raw in enumerate(segs_raw):
        k = f"segments[{i}]"
        s = _table(source, k, s_raw, _SEG_KEYS)
        if "duration_s" not in s:
            raise ConfigError(source, f"{k}.duration_s", "missing")
        dur = _f(source, f"{k}.duration_s", s["duration_s"], 0.0, True)
        wind = _f(source, f"{k}.wind_mps", s.get("wind_mps", 0.0), 0.0)
        kind = s.get("kind", "")
        if kind != "" and kind not in POINT_KINDS:
            raise ConfigError(
                source, f"{k}.kind", f"expected one of {list(POINT_KINDS)}, got {kind!r}"
            )
        tare = bool(s.get("tare", False)) or kind in ("tare", "zero")
        if kind in ("wind_on", "windage") and wind == 0:
            raise ConfigError(source, f"{k}.wind_mps", f"a {kind} point needs wind > 0")
        if tare and wind != 0:
            raise ConfigError(source, f"{k}.wind_mps", "a tare segment is wind-off: must be 0")
        pos = (
            _vec3(source, f"{k}.position_O_m", s["position_O_m"]) if "position_O_m" in s else prev_p
        )
        if "euler_rad" in s and "euler_deg" in s:
            raise ConfigError(source, f"{k}.euler_deg", "give euler_rad or euler_deg, not both")
        if "euler_rad" in s:
            eul = _vec3(source, f"{k}.euler_rad", s["euler_rad"])
        elif "euler_deg" in s:
            d = _vec3(source, f"{k}.euler_deg", s["euler_deg"])
            eul = (math.radians(d[0]), math.radians(d[1]), math.radians(d[2]))
        else:
            eul = prev_e
        trans = _f(source, f"{k}.transition_s", s.get("transition_s", 0.0), 0.0)
        if trans > dur:
            raise ConfigError(source, f"{k}.transition_s", f"longer than the segment ({dur:g} s)")
        repeat_of = s.get("repeat_of", "")
        if not isinstance(repeat_of, str):
            raise ConfigError(source, f"{k}.repeat_of", f"expected a label, got {repeat_of!r}")
        segs.append(
            Segment(
                str(s.get("label", f"seg{i}")),
                dur,
                wind,
                pos,
                eul,
                trans,
                tare,
                kind,
                _f(source, f"{k}.target_aoa_deg", s.get("target_aoa_deg", 0.0)),
                _f(source, f"{k}.target_sideslip_deg", s.get("target_sideslip_deg", 0.0)),
                repeat_of,
            )
        )
        prev_p, prev_e = pos, eul
    total = sum(s.duration_s for s in segs)
    faults = []
    f_raw = data.get("faults", [])
    if not isinstance(f_raw, list):
        raise ConfigError(source, "faults", "expected an array of [[faults]] tables")
    for i, fr_raw in enumerate(f_raw):
        k = f"faults[{i}]"
        fr = _table(source, k, fr_raw, _FAULT_KEYS)
        kind = fr.get("kind")
        if kind not in FAULT_KINDS:
            raise ConfigError(
                source, f"{k}.kind", f"expected one of {list(FAULT_KINDS)}, got {kind!r}"
            )
        start = _f(source, f"{k}.start_s", fr.get("start_s", 0.0), 0.0)
        dur = _f(source, f"{k}.duration_s", fr.get("duration_s", 0.0), 0.0, True)
        if start >= total:
            raise ConfigError(
                source, f"{k}.start_s", f"after the end of the schedule ({total:g} s)"
            )
        cable = -1
        if kind in ("slack", "saturate", "stuck", "sensor_fault"):
            if "cable" not in fr:
                raise ConfigError(
                    source, f"{k}.cable", f"a {kind} fault needs a cable (name or index)"
                )
            c = fr["cable"]
            if isinstance(c, str):
                if c not in rig.cable_names:
                    raise ConfigError(
                        source,
                        f"{k}.cable",
                        f"unknown cable {c!r} (rig has {list(rig.cable_names)})",
                    )
                cable = rig.cable_names.index(c)
            elif isinstance(c, int) and 0 <= c < rig.n_cables:
                cable = c
            else:
                raise ConfigError(
                    source, f"{k}.cable", f"expected a cable name or 0..{rig.n_cables - 1}"
                )
        faults.append(
            Fault(
                kind,
                start,
                dur,
                cable,
                _f(source, f"{k}.factor", fr.get("factor", 50.0), 0.0),
                _f(source, f"{k}.value_N", fr.get("value_N", 0.3)),
            )
        )
    sens_raw = data.get("sensor", {})
    if not isinstance(sens_raw, Mapping):
        raise ConfigError(source, "sensor", "expected a table")
    sens_fields = SensorModel.__dataclass_fields__
    kw: dict[str, Any] = {}
    for key, v in sens_raw.items():
        if key not in sens_fields:
            raise ConfigError(
                source, f"sensor.{key}", f"unknown key (allowed: {sorted(sens_fields)})"
            )
        if key == "offset_counts" or (key == "gain_N_per_count" and isinstance(v, list)):
            if not isinstance(v, list) or len(v) != rig.n_cables:
                raise ConfigError(source, f"sensor.{key}", f"expected {rig.n_cables} numbers")
            kw[key] = tuple(_f(source, f"sensor.{key}", x) for x in v)
        else:
            kw[key] = _f(source, f"sensor.{key}", v, 0.0)
    if np.any(np.asarray(kw.get("gain_N_per_count", 1.0)) <= 0):
        raise ConfigError(source, "sensor.gain_N_per_count", "must be > 0")
    seed = sch.get("seed", 0)
    if not isinstance(seed, int):
        raise ConfigError(source, "schedule.seed", f"expected an integer, got {seed!r}")
    bitrate = sch.get("bitrate", 1_000_000)
    if not isinstance(bitrate, int) or bitrate <= 0:
        raise ConfigError(
            source, "schedule.bitrate", f"expected a positive integer, got {bitrate!r}"
        )
    # the CAN transports send 4 frames per sample (data_samples/loadcell.dbc): they must fit the bus
    check_frame_budget(source, "schedule", bitrate, rate, 4)
    return Schedule(
        name=str(sch.get("name", Path(source).stem)),
        segments=tuple(segs),
        rate_hz=rate,
        tunnel_rate_hz=t_rate,
        method=method,
        seed=seed,
        bitrate=bitrate,
        faults=tuple(faults),
        sensor=SensorModel(**kw),
        aero=aero_from_mapping(data.get("aero"), source),
        source=source,
    )


def load_schedule(path: str | os.PathLike[str], rig: Rig) -> Schedule:
    """Read a schedule TOML file (errors name the file and key)."""
    return schedule_from_mapping(load_toml(path), str(Path(path)), rig)
