"""The virtual rig's schedule: segments (pose, wind, test-point kind and targets), faults, the
sensor model and the rates, read from a schedule TOML file (format: docs/daq_drivers.md) or built
from a test matrix (:func:`cdpr.pipelines.campaign.schedule_from_matrix`).

One job: parse and validate.  The physics twin is :class:`cdpr.daq.virtual_rig.VirtualRig`, the
transports :class:`cdpr.daq.virtual_rig.RigRun`; both take a :class:`Schedule`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field

from cdpr.analysis.conventions import OSCILLATION_POINT_KINDS, POINT_KINDS
from cdpr.analysis.errors import ConfigError, InputError
from cdpr.analysis.motion import MOTION_AXES, Oscillation, OscillationFields
from cdpr.analysis.rig import Rig

from .aero_model import AeroModel, aero_from_mapping
from .files import load_toml
from .loadcell import check_frame_budget
from .schema import MAX_FORCE_N, Euler_rad, Force_N, Schema, Text, Vec3_m, parse

MAX_RATE_HZ = 1e6
"""Largest sample rate (Hz) a schedule may ask for."""
MAX_TIME_S = 1e7
"""Longest duration or start time (s): about four months of schedule."""
MAX_SPEED_MPS = 1e3
MAX_ANGLE_DEG = 1e4
MAX_COUNTS = 2.0**31
"""Largest amplifier offset (counts) in magnitude: a signed 32-bit reading."""
MAX_BITRATE = 10_000_000

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
class Segment(OscillationFields):
    """One constant test condition: pose of P in {O}, wind speed, duration.

    Values ramp linearly from the previous segment's over ``transition_s`` (quasi-static: the
    inertia of the slow move is neglected).  ``tare``: a wind-off tare segment (wind must be 0).
    An oscillation segment (``kind`` oscillation or oscillation_tare) carries its motion
    (:class:`~cdpr.analysis.motion.OscillationFields`, ``.oscillation``) about its pose.
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
    test_points_on_link: bool = False
    camera_clock_offset_ns: int = 0
    pose_camera: PoseCamera | None = None

    @property
    def duration_s(self) -> float:
        return float(sum(s.duration_s for s in self.segments))


@dataclass(frozen=True)
class PoseCamera:
    """A camera that delivers the platform pose (a motion-capture system; no frames rendered):
    the true pose at ``rate_hz`` with white noise of ``position_sd_m`` per axis and
    ``rotation_sd_rad`` per axis of a small rotation in {O} (``[pose_camera]`` of a schedule,
    ``[virtual_rig.pose_camera]`` of a test matrix)."""

    rate_hz: float = 200.0
    position_sd_m: float = 5.0e-5
    rotation_sd_rad: float = math.radians(0.01)


MAX_CLOCK_OFFSET_NS = 10**12
"""Largest camera clock offset (ns) in magnitude: 1000 s."""
PER_CABLE_FAULTS = ("slack", "saturate", "stuck", "sensor_fault")

_Rate_hz = Annotated[float, Field(gt=0.0, le=MAX_RATE_HZ)]
_Duration_s = Annotated[float, Field(gt=0.0, le=MAX_TIME_S)]
_Time_s = Annotated[float, Field(ge=0.0, le=MAX_TIME_S)]
_Speed_mps = Annotated[float, Field(ge=0.0, le=MAX_SPEED_MPS)]
_Angle_deg = Annotated[float, Field(ge=-MAX_ANGLE_DEG, le=MAX_ANGLE_DEG)]
_Sd = Annotated[float, Field(ge=0.0, le=MAX_FORCE_N)]
_Counts = Annotated[float, Field(ge=-MAX_COUNTS, le=MAX_COUNTS)]
_Gain = Annotated[float, Field(gt=0.0, le=MAX_FORCE_N)]


class ScheduleSection(Schema):
    """``[schedule]``: name, rates, the controller's tension method, seed, CAN bit rate."""

    name: Text | None = None
    rate_hz: _Rate_hz = 200.0
    tunnel_rate_hz: _Rate_hz = 10.0
    method: Text = "exact"
    seed: int = 0
    bitrate: Annotated[int, Field(gt=0, le=MAX_BITRATE)] = 1_000_000
    test_points_on_link: bool = False
    camera_clock_offset_ns: Annotated[
        int, Field(ge=-MAX_CLOCK_OFFSET_NS, le=MAX_CLOCK_OFFSET_NS)
    ] = 0


class SegmentSection(Schema):
    """One ``[[segments]]`` table (pose, wind, ramp, test-point kind and targets)."""

    label: Text | None = None
    duration_s: _Duration_s
    wind_mps: _Speed_mps = 0.0
    position_O_m: Vec3_m | None = None
    euler_rad: Euler_rad | None = None
    euler_deg: Annotated[list[_Angle_deg], Field(min_length=3, max_length=3)] | None = None
    transition_s: _Time_s = 0.0
    tare: bool = False
    kind: Text = ""
    target_aoa_deg: _Angle_deg = 0.0
    target_sideslip_deg: _Angle_deg = 0.0
    repeat_of: Text = ""
    motion_axis: Text = ""
    motion_amplitude: Annotated[float, Field(ge=0.0, le=10.0)] = 0.0
    motion_frequency_Hz: Annotated[float, Field(ge=0.0, le=1e4)] = 0.0
    motion_cycles: Annotated[int, Field(ge=0, le=10**7)] = 0
    motion_settling_cycles: Annotated[int, Field(ge=0, le=10**6)] = 0
    inertia_tare: Text = ""


class FaultSection(Schema):
    """One ``[[faults]]`` table."""

    kind: Literal[
        "dropout", "slack", "saturate", "stuck", "noise_burst", "sensor_fault", "port_vanish"
    ]
    start_s: _Time_s = 0.0
    duration_s: _Duration_s
    cable: Text | int | None = None
    factor: Annotated[float, Field(ge=0.0, le=1e6)] = 50.0
    value_N: Force_N = 0.3


class SensorSection(Schema):
    """``[sensor]``: the load cells' noise, drift, latency, flags and true calibration."""

    noise_sd_N: _Sd = SensorModel.noise_sd_N
    drift_N_per_s: _Sd = SensorModel.drift_N_per_s
    latency_s: Annotated[float, Field(ge=0.0, le=10.0)] = SensorModel.latency_s
    slack_threshold_N: _Sd = SensorModel.slack_threshold_N
    offset_counts: list[_Counts] | None = None
    gain_N_per_count: _Gain | list[_Gain] = 5.0e-5
    tunnel_airspeed_sd_mps: _Sd = SensorModel.tunnel_airspeed_sd_mps
    tunnel_pressure_sd_Pa: Annotated[float, Field(ge=0.0, le=1e6)] = (
        SensorModel.tunnel_pressure_sd_Pa
    )
    tunnel_temperature_sd_K: Annotated[float, Field(ge=0.0, le=1e3)] = (
        SensorModel.tunnel_temperature_sd_K
    )


class PoseCameraSection(Schema):
    """``[pose_camera]``: a camera that delivers the pose (:class:`PoseCamera`)."""

    rate_hz: Annotated[float, Field(gt=0.0, le=1e5)] = PoseCamera.rate_hz
    position_sd_m: Annotated[float, Field(ge=0.0, le=1.0)] = PoseCamera.position_sd_m
    rotation_sd_deg: Annotated[float, Field(ge=0.0, le=90.0)] = 0.01


class ScheduleFile(Schema):
    """A schedule file: ``[schedule]``, ``[[segments]]``, ``[[faults]]``, ``[sensor]``,
    ``[pose_camera]``, ``[aero]`` (the last one checked by
    :class:`cdpr.daq.aero_model.AeroSection`)."""

    schedule: ScheduleSection = Field(default_factory=ScheduleSection)
    segments: Annotated[list[SegmentSection], Field(min_length=1, max_length=100_000)]
    faults: Annotated[list[FaultSection], Field(max_length=10_000)] = Field(default_factory=list)
    sensor: SensorSection = Field(default_factory=SensorSection)
    pose_camera: PoseCameraSection | None = None
    aero: dict[str, Any] | None = None


def _tuple3(v: list[float]) -> tuple[float, float, float]:
    return (v[0], v[1], v[2])


def schedule_from_mapping(data: Mapping[str, Any], source: str, rig: Rig) -> Schedule:
    """Build and validate a :class:`Schedule` from a parsed schedule file (TOML mapping).

    :class:`ScheduleFile` checks keys, types and ranges; what depends on several keys or on the
    rig is checked here.  ``rig`` gives the default pose (its reference pose) and the cable names
    faults may use.  Errors are :class:`ConfigError` naming ``source`` and the key
    (``segments[2].wind_mps``).
    """
    f = parse(ScheduleFile, data, source)
    sch = f.schedule
    from cdpr.analysis.tension import METHODS

    if sch.method not in METHODS:
        raise ConfigError(
            source,
            "schedule.method",
            f"unknown tension method {sch.method!r} (known: {sorted(METHODS)})",
        )
    segs = []
    rp, re_ = rig.reference_position_O_m, rig.reference_euler_rad
    prev_p = (float(rp[0]), float(rp[1]), float(rp[2]))
    prev_e = (float(re_[0]), float(re_[1]), float(re_[2]))
    for i, s in enumerate(f.segments):
        k = f"segments[{i}]"
        if s.kind not in ("", *POINT_KINDS):
            raise ConfigError(
                source, f"{k}.kind", f"expected one of {list(POINT_KINDS)}, got {s.kind!r}"
            )
        tare = s.tare or s.kind in ("tare", "zero", "oscillation_tare")
        if s.kind in ("oscillation", "wind_on", "windage") and s.wind_mps == 0:
            raise ConfigError(source, f"{k}.wind_mps", f"a {s.kind} point needs wind > 0")
        _check_motion(source, k, s, f.schedule.test_points_on_link)
        if tare and s.wind_mps != 0:
            raise ConfigError(source, f"{k}.wind_mps", "a tare segment is wind-off: must be 0")
        if s.euler_rad is not None and s.euler_deg is not None:
            raise ConfigError(source, f"{k}.euler_deg", "give euler_rad or euler_deg, not both")
        if s.transition_s > s.duration_s:
            raise ConfigError(
                source, f"{k}.transition_s", f"longer than the segment ({s.duration_s:g} s)"
            )
        pos = _tuple3(s.position_O_m) if s.position_O_m is not None else prev_p
        if s.euler_rad is not None:
            eul = _tuple3(s.euler_rad)
        elif s.euler_deg is not None:
            eul = _tuple3([math.radians(d) for d in s.euler_deg])
        else:
            eul = prev_e
        segs.append(
            Segment(
                s.label if s.label is not None else f"seg{i}",
                s.duration_s,
                s.wind_mps,
                pos,
                eul,
                s.transition_s,
                tare,
                s.kind,
                s.target_aoa_deg,
                s.target_sideslip_deg,
                s.repeat_of,
                motion_axis=s.motion_axis,
                motion_amplitude=s.motion_amplitude,
                motion_frequency_Hz=s.motion_frequency_Hz,
                motion_cycles=s.motion_cycles,
                motion_settling_cycles=s.motion_settling_cycles,
                inertia_tare=s.inertia_tare,
            )
        )
        prev_p, prev_e = pos, eul
    total = sum(s.duration_s for s in segs)
    faults = []
    for i, fr in enumerate(f.faults):
        k = f"faults[{i}]"
        if fr.start_s >= total:
            raise ConfigError(
                source, f"{k}.start_s", f"after the end of the schedule ({total:g} s)"
            )
        cable = -1
        if fr.kind in PER_CABLE_FAULTS:
            c = fr.cable
            if c is None:
                raise ConfigError(
                    source, f"{k}.cable", f"a {fr.kind} fault needs a cable (name or index)"
                )
            if isinstance(c, str):
                if c not in rig.cable_names:
                    raise ConfigError(
                        source,
                        f"{k}.cable",
                        f"unknown cable {c!r} (rig has {list(rig.cable_names)})",
                    )
                cable = rig.cable_names.index(c)
            elif 0 <= c < rig.n_cables:
                cable = c
            else:
                raise ConfigError(
                    source, f"{k}.cable", f"expected a cable name or 0..{rig.n_cables - 1}"
                )
        elif fr.cable is not None:
            raise ConfigError(source, f"{k}.cable", f"a {fr.kind} fault is not on one cable")
        faults.append(Fault(fr.kind, fr.start_s, fr.duration_s, cable, fr.factor, fr.value_N))
    sens = f.sensor
    kw = sens.model_dump()
    for key in ("offset_counts", "gain_N_per_count"):
        v = kw[key]
        if isinstance(v, list):
            if len(v) != rig.n_cables:
                raise ConfigError(
                    source, f"sensor.{key}", f"expected {rig.n_cables} numbers, got {len(v)}"
                )
            kw[key] = tuple(v)
    # the CAN transports send 4 frames per sample (data_samples/loadcell.dbc): they must fit the bus
    check_frame_budget(source, "schedule", sch.bitrate, sch.rate_hz, 4)
    return Schedule(
        name=sch.name if sch.name is not None else Path(source).stem,
        segments=tuple(segs),
        rate_hz=sch.rate_hz,
        tunnel_rate_hz=sch.tunnel_rate_hz,
        method=sch.method,
        seed=sch.seed,
        bitrate=sch.bitrate,
        faults=tuple(faults),
        sensor=SensorModel(**kw),
        aero=aero_from_mapping(f.aero, source),
        source=source,
        test_points_on_link=sch.test_points_on_link,
        camera_clock_offset_ns=sch.camera_clock_offset_ns,
        pose_camera=(
            None
            if f.pose_camera is None
            else PoseCamera(
                f.pose_camera.rate_hz,
                f.pose_camera.position_sd_m,
                math.radians(f.pose_camera.rotation_sd_deg),
            )
        ),
    )


def _check_motion(source: str, k: str, s: SegmentSection, on_link: bool) -> None:
    """An oscillation segment has its motion (and fits it), any other has none."""
    moving = s.kind in OSCILLATION_POINT_KINDS
    if not moving:
        if s.motion_axis:
            raise ConfigError(
                source, f"{k}.motion_axis", f"only an oscillation point moves (kind {s.kind!r})"
            )
        return
    if on_link:
        raise ConfigError(
            source,
            f"{k}.kind",
            "an oscillation point cannot go on the tunnel link ($TPT lines carry no motion): "
            "set test_points_on_link = false",
        )
    if not s.motion_axis:
        raise ConfigError(
            source,
            f"{k}.motion_axis",
            f"missing: an {s.kind} point needs one of {list(MOTION_AXES)}",
        )
    try:
        osc = Oscillation(
            s.motion_axis,
            s.motion_amplitude,
            s.motion_frequency_Hz,
            s.motion_cycles,
            s.motion_settling_cycles,
        )
    except InputError as exc:
        key = str(exc).split(":")[0]
        raise ConfigError(source, f"{k}.motion_{key}", str(exc).split(": ", 1)[-1]) from None
    need = s.transition_s + osc.duration_s
    if s.duration_s < need - 1e-9:
        raise ConfigError(
            source,
            f"{k}.duration_s",
            f"{s.duration_s:g} s is shorter than the ramp and the motion ({need:g} s: "
            f"{osc.settling_cycles} + {osc.cycles} + {osc.ramp_down_cycles} cycles at "
            f"{osc.frequency_Hz:g} Hz)",
        )


def load_schedule(path: str | os.PathLike[str], rig: Rig) -> Schedule:
    """Read a schedule TOML file (errors name the file and key)."""
    return schedule_from_mapping(load_toml(path), str(Path(path)), rig)
