"""The test matrix: one TOML file describes a campaign (model, rig, calibrations, test points).

:func:`load_test_matrix` reads and validates the file and expands its sweeps into an ordered list of
:class:`TestPoint`; :func:`schedule_mapping` turns a matrix into the virtual rig's schedule, so a
campaign is rehearsed on the virtual rig (``cdpr simulate --campaign FILE``) with the same file the
tunnel uses.  Format (every key and its unit: ``docs/campaign.md``)::

    [campaign]
    name = "flat-alpha-sweep"
    rig = "flat_experiment2.toml"          # paths relative to this file
    loadcell_calibration = "..."           # optional; also balance_calibration, camera, markers

    [model]
    name = "SDM"
    area_m2 = 0.01465
    span_m = 0.2441
    chord_m = 0.060
    mrp_P_m = [0.0, 0.0, 0.0]              # moment reference point in {P}
    # volume_m3 = ...                      # optional

    [defaults]                             # optional: per-point defaults
    duration_s = 1.2
    transition_s = 0.3

    [[points]]                             # in the order the tunnel runs them
    label = "zero-start"
    kind = "zero"                          # "wind_on" | "tare" | "zero" | "windage"

    [[points]]                             # a list in aoa_deg, sideslip_deg or airspeed_mps
    label = "tare"                         # is a sweep: airspeed outer, sideslip, aoa inner;
    kind = "tare"                          # labels become tare-a-4-b0-v0, ...
    aoa_deg = [-4.0, -2.0, 0.0, 2.0]

    [[points]]
    label = "rep"
    kind = "wind_on"
    repeat_of = "alpha-a2-b0-v25.51"       # an earlier point with the same target

Conventions: the flow is along +x of {O}; the model sits on the platform nose upstream (-x_P), up
along +z_P (:mod:`cdpr.analysis.aero`); a test point's angle of attack and sideslip set the platform
attitude through :func:`cdpr.analysis.aero.attitude_from_flow_angles` (roll 0, pitch = aoa,
yaw = sideslip for this mounting).  Wind-off kinds ("tare", "zero") have airspeed 0, "zero" points
are level (aoa = sideslip = 0); "windage" points are model-off wind-on points.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from cdpr.analysis.aero import ModelGeometry, attitude_from_flow_angles
from cdpr.analysis.conventions import OSCILLATION_POINT_KINDS, WIND_OFF_KINDS
from cdpr.analysis.conventions import POINT_KINDS as KINDS
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.motion import ANGULAR_AXES, MOTION_AXES, Oscillation, OscillationFields
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import euler_from_rotation
from cdpr.analysis.systematic import INSTRUMENT_KEYS, InstrumentAccuracy
from cdpr.daq.files import load_toml
from cdpr.daq.virtual_rig import Schedule, schedule_from_mapping
from cdpr.daq.vrig_events import oscillation_event_fields

from .tunnel_section import TunnelSection, tunnel_section_from_mapping

_WIND_OFF = (*WIND_OFF_KINDS, "oscillation_tare")
"""Kinds whose airspeed must be 0: the wind-off ones at rest and the inertia tare."""

_TOP = {
    "campaign", "model", "tunnel", "instruments", "defaults", "points", "virtual_rig",
    "aero_estimate",
}  # fmt: skip
_CAMPAIGN = {
    "name", "rig", "loadcell_calibration", "balance_calibration", "camera", "markers", "pose_sd",
}  # fmt: skip
_MODEL = {"name", "area_m2", "span_m", "chord_m", "mrp_P_m", "volume_m3"}
_MODEL_WALLS = {
    "blockage_K3",
    "wing_volume_m3",
    "wing_K1",
    "reference_area_m2",
    "lift_slope_per_rad",
}
"""[model] keys the wall corrections read (:mod:`cdpr.pipelines.tunnel_section`), with [tunnel]."""
_DEFAULTS = {"duration_s", "transition_s", "position_O_m"}
_POINT = {
    "label",
    "kind",
    "aoa_deg",
    "sideslip_deg",
    "airspeed_mps",
    "duration_s",
    "transition_s",
    "repeat_of",
    "position_O_m",
}
_MOTION = {
    "axis",
    "amplitude_deg",
    "amplitude_m",
    "frequency_Hz",
    "cycles",
    "settling_cycles",
    "inertia_tare",
}
"""Keys of an oscillation point beside the steady ones (docs/dynamic_tests.md)."""
DEFAULT_SETTLING_CYCLES = 2
"""Settling cycles of an oscillation point that names none: the amplitude ramps up over them."""
_VRIG = {
    "rate_hz", "tunnel_rate_hz", "method", "seed", "bitrate", "sensor", "aero", "faults",
    "test_points_on_link", "camera_clock_offset_ns", "pose_camera",
}  # fmt: skip
_AERO_FROM_MODEL = ("c_ref_m", "b_ref_m", "s_ref_m2", "mrp_P_m")
_POSE_CAMERA = {"rate_hz", "position_sd_m", "rotation_sd_deg"}
_AERO_ESTIMATE = {
    "CL0", "CL_alpha", "CD0", "k_induced", "CY_beta", "Cl_beta", "Cm0", "Cm_alpha", "Cn_beta",
    "CLq", "CLadot", "Cmq", "Cmadot", "Clp", "Clr", "Cnr", "Cnp", "Cnbetadot",
    "static_pressure_Pa", "temperature_K", "relative_humidity",
}  # fmt: skip
"""Keys of ``[aero_estimate]``: the aero model's coefficients and air (geometry from [model])."""


@dataclass(frozen=True)
class TestPoint(OscillationFields):
    """One test point of the matrix, in run order.

    kind: one of :data:`KINDS`; targets in degrees and m/s; duration_s: time held at the target
    after a ramp of transition_s (an oscillation: its motion, ramp-down included); repeat_of:
    label of the point it repeats or ""; an oscillation point's motion and inertia tare
    (:class:`~cdpr.analysis.motion.OscillationFields`, ``.oscillation``).
    """

    __test__ = False  # not a pytest class

    label: str
    kind: str
    aoa_deg: float
    sideslip_deg: float
    airspeed_mps: float
    duration_s: float
    transition_s: float
    repeat_of: str = ""
    position_O_m: tuple[float, float, float] | None = None

    def event_fields(self) -> dict[str, Any]:
        """The fields of this point's ``test_point`` events (docs/campaign.md): ``point``,
        ``kind``, the targets, ``repeat_of``, and an oscillation's motion and inertia tare."""
        out: dict[str, Any] = {
            "point": self.label,
            "kind": self.kind,
            "target_aoa_deg": self.aoa_deg,
            "target_sideslip_deg": self.sideslip_deg,
            "target_airspeed_mps": self.airspeed_mps,
            "repeat_of": self.repeat_of,
        }
        if self.kind in OSCILLATION_POINT_KINDS:
            out.update(oscillation_event_fields(self))
        return out

    def motion_key(self) -> tuple[Any, ...]:
        """What an oscillation and its inertia tare share: the motion and the mean pose."""
        return (
            self.motion_axis,
            self.motion_amplitude,
            self.motion_frequency_Hz,
            self.aoa_deg,
            self.sideslip_deg,
            self.position_O_m,
        )

    @property
    def euler_rad(self) -> tuple[float, float, float]:
        """Platform attitude (roll, pitch, yaw), rad, that puts the model at the target angles."""
        R = attitude_from_flow_angles(math.radians(self.aoa_deg), math.radians(self.sideslip_deg))
        e = euler_from_rotation(R)
        return (float(e[0]), float(e[1]), float(e[2]))


@dataclass(frozen=True)
class TestMatrix:
    """A loaded test matrix: ``points`` in run order, ``model``, resolved paths."""

    __test__ = False

    name: str
    source: str
    rig_path: Path
    model: ModelGeometry
    points: list[TestPoint]
    loadcell_calibration: Path | None = None
    balance_calibration: Path | None = None
    camera: Path | None = None
    markers: Path | None = None
    virtual_rig: Mapping[str, Any] = field(default_factory=dict)
    tunnel: TunnelSection | None = None
    """The ``[tunnel]`` table with the wall-correction keys of ``[model]`` (None: no test section
    given: no wall corrections and no windage model, said by the reduction's flags)."""
    instruments: InstrumentAccuracy = field(
        default_factory=lambda: InstrumentAccuracy(defaulted=INSTRUMENT_KEYS)
    )
    """The tunnel instruments' stated accuracy (``[instruments]``; the keys not given take their
    defaults, named in ``instruments.defaulted``: the reduction flags
    ``tunnel_instrument_sd_default``)."""
    pose_sd: tuple[float, ...] | None = None
    """``campaign.pose_sd``: the camera's precision per frame (x, y, z in m; roll, pitch, yaw in
    rad), used for runs whose pose stream carries no covariance (None: not stated)."""
    aero_estimate: Mapping[str, Any] | None = None
    """The ``[aero_estimate]`` table: the expected aerodynamic coefficients the motion planner
    loads the plan with (keys of the virtual rig's aero model, geometry from ``[model]``); None
    when the matrix gives none (the planner then says it uses the aero model's defaults)."""

    def point(self, label: str) -> TestPoint:
        for p in self.points:
            if p.label == label:
                return p
        raise KeyError(label)

    def missing_tares(self) -> list[str]:
        """Labels of wind-on points with no wind-off tare point at the same attitude."""
        tares = {(p.aoa_deg, p.sideslip_deg) for p in self.points if p.kind == "tare"}
        return [
            p.label
            for p in self.points
            if p.kind == "wind_on" and (p.aoa_deg, p.sideslip_deg) not in tares
        ]

    def missing_inertia_tares(self) -> list[str]:
        """Labels of oscillation points no ``oscillation_tare`` serves (flag ``no_inertia_tare``:
        the reduction then removes the inertia of the rig file's mass and inertia, said so)."""
        return [p.label for p in self.points if p.kind == "oscillation" and not p.inertia_tare]


# --------------------------------------------------------------------------------------------
# validation helpers: every error is ConfigError(file, key, problem)
# --------------------------------------------------------------------------------------------
def _num(src: str, key: str, v: Any, lo: float | None = None, strict: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ConfigError(src, key, f"expected a number, got {v!r}")
    x = float(v)
    if not math.isfinite(x):
        raise ConfigError(src, key, "expected a finite number")
    if lo is not None and (x < lo or (strict and x == lo)):
        raise ConfigError(src, key, f"must be {'>' if strict else '>='} {lo:g}, got {x:g}")
    return x


def _nums(src: str, key: str, v: Any, lo: float | None = None) -> list[float]:
    """A number or a non-empty list of distinct numbers, as a list."""
    if isinstance(v, list):
        if not v:
            raise ConfigError(src, key, "expected a number or a non-empty list of numbers")
        out = [_num(src, f"{key}[{i}]", x, lo) for i, x in enumerate(v)]
        if len(set(out)) != len(out):
            raise ConfigError(src, key, "repeated value in a sweep (use repeat_of for repeats)")
        return out
    return [_num(src, key, v, lo)]


def _vec3(src: str, key: str, v: Any) -> tuple[float, float, float]:
    if not isinstance(v, list) or len(v) != 3:
        raise ConfigError(src, key, f"expected 3 numbers, got {v!r}")
    a, b, c = (_num(src, key, x) for x in v)
    return (a, b, c)


def _table(src: str, key: str, v: Any, allowed: set[str]) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise ConfigError(src, key, "expected a table")
    for k in v:
        if k not in allowed:
            raise ConfigError(src, f"{key}.{k}", f"unknown key (allowed: {sorted(allowed)})")
    return v


def _str(src: str, key: str, v: Any) -> str:
    if not isinstance(v, str) or not v.strip():
        raise ConfigError(src, key, f"expected a non-empty string, got {v!r}")
    return v


def _path(src: str, key: str, v: Any, base: Path) -> Path:
    p = base / _str(src, key, v)
    if not p.is_file():
        raise ConfigError(src, key, f"file not found: {p}")
    return p


def _fmt(x: float) -> str:
    return f"{x:g}"


# --------------------------------------------------------------------------------------------
# loader
# --------------------------------------------------------------------------------------------
def model_geometry_from_mapping(data: Any, src: str) -> ModelGeometry:
    """The ``[model]`` table of a test matrix (also as attached to a run by ``cdpr simulate
    --campaign``: ``campaign/<file>.toml``), checked; errors name ``src`` and ``model.<key>``."""
    mod = _table(src, "model", data, _MODEL | _MODEL_WALLS)
    for k in ("area_m2", "span_m", "chord_m", "mrp_P_m"):
        if k not in mod:
            raise ConfigError(src, f"model.{k}", "missing")
    return ModelGeometry(
        name=_str(src, "model.name", mod.get("name", "model")),
        area_m2=_num(src, "model.area_m2", mod["area_m2"], 0.0, True),
        span_m=_num(src, "model.span_m", mod["span_m"], 0.0, True),
        chord_m=_num(src, "model.chord_m", mod["chord_m"], 0.0, True),
        mrp_P_m=_vec3(src, "model.mrp_P_m", mod["mrp_P_m"]),
        volume_m3=(
            _num(src, "model.volume_m3", mod["volume_m3"], 0.0, True)
            if "volume_m3" in mod
            else None
        ),
    )


def test_matrix_from_mapping(data: Mapping[str, Any], source: str, base: Path) -> TestMatrix:
    """Validate a parsed test-matrix file and expand its sweeps (paths relative to ``base``)."""
    src = source
    unknown = sorted(set(data) - _TOP)
    if unknown:
        raise ConfigError(src, unknown[0], f"unknown key (allowed: {sorted(_TOP)})")
    if "campaign" not in data:
        raise ConfigError(src, "campaign", "missing [campaign] table")
    camp = _table(src, "campaign", data["campaign"], _CAMPAIGN)
    if "rig" not in camp:
        raise ConfigError(src, "campaign.rig", "missing (the rig file, relative to this file)")
    rig_path = _path(src, "campaign.rig", camp["rig"], base)
    optional = {
        k: (_path(src, f"campaign.{k}", camp[k], base) if k in camp else None)
        for k in ("loadcell_calibration", "balance_calibration", "camera", "markers")
    }
    if (optional["camera"] is None) != (optional["markers"] is None):
        raise ConfigError(src, "campaign.camera", "camera and markers go together")
    pose_sd = None
    if "pose_sd" in camp:
        v = camp["pose_sd"]
        if not isinstance(v, list) or len(v) != 6:
            raise ConfigError(
                src, "campaign.pose_sd", "expected 6 numbers: x_m, y_m, z_m, roll, pitch, yaw (rad)"
            )
        pose_sd = tuple(_num(src, f"campaign.pose_sd[{i}]", x, 0.0, True) for i, x in enumerate(v))

    if "model" not in data:
        raise ConfigError(src, "model", "missing [model] table")
    model = model_geometry_from_mapping(data["model"], src)
    tunnel = _tunnel(data, src, model)
    instruments = _instruments(data, src)

    dft = _table(src, "defaults", data.get("defaults", {}), _DEFAULTS)
    dft_dur = _num(src, "defaults.duration_s", dft.get("duration_s", 1.0), 0.0, True)
    dft_tr = _num(src, "defaults.transition_s", dft.get("transition_s", 0.3), 0.0)
    dft_pos = (
        _vec3(src, "defaults.position_O_m", dft["position_O_m"]) if "position_O_m" in dft else None
    )

    raw = data.get("points")
    if not isinstance(raw, list) or not raw:
        raise ConfigError(src, "points", "expected a non-empty array of [[points]] tables")
    points: list[TestPoint] = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(raw):
        key = f"points[{i}]"
        t = _table(src, key, entry, _POINT | _MOTION)
        if "label" not in t:
            raise ConfigError(src, f"{key}.label", "missing")
        label = _str(src, f"{key}.label", t["label"])
        if "kind" not in t:
            raise ConfigError(src, f"{key}.kind", f"missing (one of {list(KINDS)})")
        kind = t["kind"]
        if kind not in KINDS:
            raise ConfigError(src, f"{key}.kind", f"expected one of {list(KINDS)}, got {kind!r}")
        aoas = _nums(src, f"{key}.aoa_deg", t.get("aoa_deg", 0.0))
        betas = _nums(src, f"{key}.sideslip_deg", t.get("sideslip_deg", 0.0))
        speeds = _nums(src, f"{key}.airspeed_mps", t.get("airspeed_mps", 0.0), 0.0)
        for name, vals in (("aoa_deg", aoas), ("sideslip_deg", betas)):
            if any(abs(v) >= 90.0 for v in vals):
                raise ConfigError(src, f"{key}.{name}", "expected angles within (-90, 90) degrees")
        if kind in _WIND_OFF and any(v != 0.0 for v in speeds):
            raise ConfigError(src, f"{key}.airspeed_mps", f"a {kind} point is wind-off: must be 0")
        if kind in ("wind_on", "windage", "oscillation") and any(v == 0.0 for v in speeds):
            raise ConfigError(src, f"{key}.airspeed_mps", f"a {kind} point needs airspeed > 0")
        if kind == "zero" and any(v != 0.0 for v in aoas + betas):
            raise ConfigError(src, f"{key}.aoa_deg", "a zero point is level: aoa and sideslip 0")
        motion = _motion(src, key, t, kind)
        dur = _num(src, f"{key}.duration_s", t.get("duration_s", dft_dur), 0.0, True)
        tr = _num(src, f"{key}.transition_s", t.get("transition_s", dft_tr), 0.0)
        pos = (
            _vec3(src, f"{key}.position_O_m", t["position_O_m"]) if "position_O_m" in t else dft_pos
        )
        repeat_of = t.get("repeat_of", "")
        if not isinstance(repeat_of, str):
            raise ConfigError(src, f"{key}.repeat_of", f"expected a label, got {repeat_of!r}")
        amps, freqs = motion.amplitudes, motion.frequencies
        sweep = len(aoas) * len(betas) * len(speeds) * len(amps) * len(freqs) > 1
        if sweep and repeat_of:
            raise ConfigError(src, f"{key}.repeat_of", "a sweep cannot repeat one point")
        for v in speeds:
            for b in betas:
                for a in aoas:
                    for amp in amps:
                        for fr in freqs:
                            lab = label
                            if sweep:
                                lab = f"{label}-a{_fmt(a)}-b{_fmt(b)}-v{_fmt(v)}"
                                if motion.axis:
                                    lab = (
                                        f"{label}-A{_fmt(amp)}-f{_fmt(fr)}-a{_fmt(a)}-b{_fmt(b)}"
                                        f"-v{_fmt(v)}"
                                    )
                            if lab in seen:
                                raise ConfigError(
                                    src,
                                    f"{key}.label",
                                    f"label {lab!r} already used by points[{seen[lab]}]",
                                )
                            seen[lab] = i
                            points.append(
                                _point(lab, kind, a, b, v, dur, tr, repeat_of, pos, motion, amp, fr)
                            )
        if repeat_of:
            _check_repeat(src, key, points[-1], points[:-1])
    points = _resolve_inertia_tares(src, points, seen)
    vrig = _table(src, "virtual_rig", data.get("virtual_rig", {}), _VRIG)
    aero = vrig.get("aero", {})
    if isinstance(aero, Mapping):
        for k in _AERO_FROM_MODEL:
            if k in aero:
                raise ConfigError(
                    src, f"virtual_rig.aero.{k}", "the model geometry comes from [model] only"
                )
    if "pose_camera" in vrig:
        _table(src, "virtual_rig.pose_camera", vrig["pose_camera"], _POSE_CAMERA)
    if "camera_clock_offset_ns" in vrig:
        off = vrig["camera_clock_offset_ns"]
        if isinstance(off, bool) or not isinstance(off, int):
            raise ConfigError(
                src, "virtual_rig.camera_clock_offset_ns", f"expected an integer (ns), got {off!r}"
            )
    if "pose_camera" in vrig and optional["camera"] is not None:
        raise ConfigError(
            src,
            "virtual_rig.pose_camera",
            "one camera: campaign.camera (rendered frames) or [virtual_rig.pose_camera], not both",
        )
    aero_estimate = None
    if "aero_estimate" in data:
        aero_estimate = _table(src, "aero_estimate", data["aero_estimate"], _AERO_ESTIMATE)
        from cdpr.daq.aero_model import aero_from_mapping

        aero_from_mapping(aero_estimate, src, key="aero_estimate")  # checked here, used by plan
    name = camp.get("name", Path(src).stem)
    return TestMatrix(
        name=_str(src, "campaign.name", name),
        source=src,
        rig_path=rig_path,
        model=model,
        points=points,
        virtual_rig=dict(vrig),
        tunnel=tunnel,
        instruments=instruments,
        aero_estimate=None if aero_estimate is None else dict(aero_estimate),
        pose_sd=pose_sd,
        **optional,
    )


def _tunnel(data: Mapping[str, Any], src: str, model: ModelGeometry) -> TunnelSection | None:
    """The ``[tunnel]`` table (None without one).  The wall corrections' reference area is the
    model's ``area_m2`` (``reference_area_m2`` may repeat it, never contradict it); span and chord
    are the model's."""
    if "tunnel" not in data:
        extra = sorted(set(data["model"]) & _MODEL_WALLS)
        if extra:
            raise ConfigError(
                src, f"model.{extra[0]}", "a wall-correction key needs a [tunnel] table"
            )
        return None
    mod = dict(data["model"])
    ref = mod.setdefault("reference_area_m2", model.area_m2)
    if ref != model.area_m2:
        raise ConfigError(
            src, "model.reference_area_m2", f"{ref} contradicts model.area_m2 = {model.area_m2}"
        )
    return tunnel_section_from_mapping({**data, "model": mod}, src)


_INSTRUMENT_LIMITS = {
    "airspeed_sd_mps": 100.0,
    "airspeed_rel_sd": 1.0,
    "static_pressure_sd_Pa": 1e5,
    "temperature_sd_K": 100.0,
    "relative_humidity_sd": 1.0,
}
"""The largest plausible value of each ``[instruments]`` key (a larger one is a typo)."""


def _instruments(data: Mapping[str, Any], src: str) -> InstrumentAccuracy:
    """The ``[instruments]`` table: the tunnel instruments' standard uncertainties (each >= 0; a
    key not given takes the default of :class:`~cdpr.analysis.systematic.InstrumentAccuracy`, except
    that the airspeed's absolute and relative parts are one statement: given one, the other is 0)."""
    t = _table(src, "instruments", data.get("instruments", {}), set(INSTRUMENT_KEYS))
    given: dict[str, float] = {}
    for k in INSTRUMENT_KEYS:
        if k in t:
            v = _num(src, f"instruments.{k}", t[k], 0.0)
            if v > _INSTRUMENT_LIMITS[k]:
                raise ConfigError(
                    src, f"instruments.{k}", f"must be <= {_INSTRUMENT_LIMITS[k]:g}, got {v:g}"
                )
            given[k] = v
    pair = ("airspeed_sd_mps", "airspeed_rel_sd")  # one instrument: absolute + relative part
    if any(k in given for k in pair):
        given = {**{k: 0.0 for k in pair}, **given}
    return InstrumentAccuracy(
        **given, defaulted=tuple(k for k in INSTRUMENT_KEYS if k not in given)
    )


def _check_repeat(src: str, key: str, p: TestPoint, before: Sequence[TestPoint]) -> None:
    ref = next((q for q in before if q.label == p.repeat_of), None)
    if ref is None:
        raise ConfigError(src, f"{key}.repeat_of", f"no earlier point labelled {p.repeat_of!r}")
    if (ref.kind, ref.aoa_deg, ref.sideslip_deg, ref.airspeed_mps, ref.motion_key()[:3]) != (
        p.kind,
        p.aoa_deg,
        p.sideslip_deg,
        p.airspeed_mps,
        p.motion_key()[:3],  # and the same motion (axis, amplitude, frequency)
    ):
        raise ConfigError(
            src,
            f"{key}.repeat_of",
            f"{ref.label!r} has another target ({ref.kind}, aoa {ref.aoa_deg:g} deg, "
            f"sideslip {ref.sideslip_deg:g} deg, {ref.airspeed_mps:g} m/s)",
        )
    if ref.repeat_of:
        raise ConfigError(src, f"{key}.repeat_of", f"{ref.label!r} is itself a repeat")


@dataclass(frozen=True)
class _Motion:
    """The motion keys of one ``[[points]]`` table (empty axis: a steady point)."""

    axis: str = ""
    amplitudes: tuple[float, ...] = (0.0,)
    frequencies: tuple[float, ...] = (0.0,)
    unit: str = ""
    cycles: int = 0
    settling_cycles: int = 0
    inertia_tare: str = ""


def _int(src: str, key: str, v: Any, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(src, key, f"expected a whole number, got {v!r}")
    if v < lo:
        raise ConfigError(src, key, f"must be >= {lo}, got {v}")
    return v


def _motion(src: str, key: str, t: Mapping[str, Any], kind: str) -> _Motion:
    """The motion of an oscillation point (checked), or the empty motion of a steady one."""
    given = sorted(set(t) & _MOTION)
    if kind not in OSCILLATION_POINT_KINDS:
        if given:
            raise ConfigError(
                src, f"{key}.{given[0]}", f"only an oscillation point takes it (kind {kind!r})"
            )
        return _Motion()
    if "duration_s" in t:
        raise ConfigError(
            src,
            f"{key}.duration_s",
            "an oscillation point lasts its cycles: (settling_cycles + cycles + 1) / frequency_Hz",
        )
    if kind == "oscillation_tare" and "inertia_tare" in t:
        raise ConfigError(src, f"{key}.inertia_tare", "only an oscillation point has a tare")
    if "axis" not in t:
        raise ConfigError(src, f"{key}.axis", f"missing (one of {list(MOTION_AXES)})")
    axis = t["axis"]
    if axis not in MOTION_AXES:
        raise ConfigError(src, f"{key}.axis", f"expected one of {list(MOTION_AXES)}, got {axis!r}")
    unit = "deg" if axis in ANGULAR_AXES else "m"
    other = "m" if unit == "deg" else "deg"
    if f"amplitude_{other}" in t:
        raise ConfigError(
            src, f"{key}.amplitude_{other}", f"a {axis} oscillation takes amplitude_{unit}"
        )
    if f"amplitude_{unit}" not in t:
        raise ConfigError(src, f"{key}.amplitude_{unit}", f"missing (the {axis} amplitude)")
    amps = _nums(src, f"{key}.amplitude_{unit}", t[f"amplitude_{unit}"], 0.0)
    if any(a <= 0 for a in amps):
        raise ConfigError(src, f"{key}.amplitude_{unit}", "must be > 0")
    if unit == "deg" and any(a >= 90.0 for a in amps):
        raise ConfigError(src, f"{key}.amplitude_deg", "expected an amplitude below 90 degrees")
    if "frequency_Hz" not in t:
        raise ConfigError(src, f"{key}.frequency_Hz", "missing (the oscillation's frequency)")
    freqs = _nums(src, f"{key}.frequency_Hz", t["frequency_Hz"], 0.0)
    if any(f <= 0 for f in freqs):
        raise ConfigError(src, f"{key}.frequency_Hz", "must be > 0")
    if "cycles" not in t:
        raise ConfigError(src, f"{key}.cycles", "missing (whole cycles to analyse)")
    cycles = _int(src, f"{key}.cycles", t["cycles"], 1)
    settling = _int(
        src, f"{key}.settling_cycles", t.get("settling_cycles", DEFAULT_SETTLING_CYCLES), 1
    )
    tare = t.get("inertia_tare", "")
    if not isinstance(tare, str):
        raise ConfigError(src, f"{key}.inertia_tare", f"expected a label, got {tare!r}")
    return _Motion(axis, tuple(amps), tuple(freqs), unit, cycles, settling, tare)


def _point(
    label: str,
    kind: str,
    aoa: float,
    beta: float,
    speed: float,
    duration: float,
    transition: float,
    repeat_of: str,
    pos: tuple[float, float, float] | None,
    motion: _Motion,
    amplitude: float,
    frequency: float,
) -> TestPoint:
    """One expanded point; an oscillation's duration is its motion's (ramp down included)."""
    if not motion.axis:
        return TestPoint(label, kind, aoa, beta, speed, duration, transition, repeat_of, pos)
    amp = math.radians(amplitude) if motion.unit == "deg" else amplitude
    osc = Oscillation(motion.axis, amp, frequency, motion.cycles, motion.settling_cycles)
    return TestPoint(
        label, kind, aoa, beta, speed, osc.duration_s, transition, repeat_of, pos,
        motion_axis=motion.axis, motion_amplitude=amp, motion_frequency_Hz=frequency,
        motion_cycles=motion.cycles, motion_settling_cycles=motion.settling_cycles,
        inertia_tare=motion.inertia_tare,
    )  # fmt: skip


def _resolve_inertia_tares(
    src: str, points: list[TestPoint], table_of: Mapping[str, int]
) -> list[TestPoint]:
    """Each oscillation point with the label of the ``oscillation_tare`` that serves it: the one
    it names (checked: same motion and mean pose), else the nearest matching one before it,
    else the first after it, else "" (missing: :meth:`TestMatrix.missing_inertia_tares`)."""
    out = list(points)
    for i, p in enumerate(points):
        if p.kind != "oscillation":
            continue
        key = f"points[{table_of[p.label]}].inertia_tare"
        if p.inertia_tare:
            ref = next((q for q in points if q.label == p.inertia_tare), None)
            if ref is None:
                raise ConfigError(src, key, f"no point labelled {p.inertia_tare!r}")
            if ref.kind != "oscillation_tare":
                raise ConfigError(
                    src, key, f"{ref.label!r} is a {ref.kind} point, not an oscillation_tare"
                )
            if ref.motion_key() != p.motion_key():
                raise ConfigError(
                    src,
                    key,
                    f"{ref.label!r} has another motion or mean pose than {p.label!r} (axis, "
                    "amplitude, frequency, aoa, sideslip and position must match)",
                )
            continue
        match = [j for j, q in enumerate(points)
                 if q.kind == "oscillation_tare" and q.motion_key() == p.motion_key()]  # fmt: skip
        before = [j for j in match if j < i]
        j = before[-1] if before else (match[0] if match else None)
        if j is not None:
            out[i] = replace(p, inertia_tare=points[j].label)
    return out


def load_test_matrix(path: str | os.PathLike[str]) -> TestMatrix:
    """Read a test-matrix TOML file; errors are ``ConfigError(file, key, problem)``."""
    p = Path(path)
    return test_matrix_from_mapping(load_toml(p), str(p), p.parent)


# --------------------------------------------------------------------------------------------
# the virtual rig's schedule
# --------------------------------------------------------------------------------------------
def schedule_mapping(matrix: TestMatrix) -> dict[str, Any]:
    """The virtual-rig schedule (a TOML mapping for :func:`cdpr.daq.virtual_rig.schedule_from_mapping`)
    that runs the matrix: one segment per point (ramp ``transition_s`` then ``duration_s`` held,
    or the oscillation's motion about the point's mean pose), carrying the point's label, kind,
    targets and motion so the rig emits the test-point events.

    The aero model takes its reference geometry and MRP from ``[model]``; ``[virtual_rig]`` sets
    rates, method, seed, the sensor and aero tables and faults.
    """
    vr = dict(matrix.virtual_rig)
    m = matrix.model
    aero = dict(vr.pop("aero", {}))
    aero.update(c_ref_m=m.chord_m, b_ref_m=m.span_m, s_ref_m2=m.area_m2, mrp_P_m=list(m.mrp_P_m))
    out: dict[str, Any] = {
        "schedule": {
            "name": matrix.name,
            **{k: v for k, v in vr.items() if k not in ("sensor", "faults", "pose_camera")},
        },
        "aero": aero,
    }
    if "sensor" in vr:
        out["sensor"] = dict(vr["sensor"])
    if "pose_camera" in vr:
        out["pose_camera"] = dict(vr["pose_camera"])
    if "faults" in vr:
        out["faults"] = list(vr["faults"])
    segs = []
    for p in matrix.points:
        seg: dict[str, Any] = {
            "label": p.label,
            "kind": p.kind,
            "duration_s": p.transition_s + p.duration_s,
            "transition_s": p.transition_s,
            "wind_mps": p.airspeed_mps,
            "euler_rad": list(p.euler_rad),
            "target_aoa_deg": p.aoa_deg,
            "target_sideslip_deg": p.sideslip_deg,
            "repeat_of": p.repeat_of,
        }
        if p.position_O_m is not None:
            seg["position_O_m"] = list(p.position_O_m)
        if p.kind in OSCILLATION_POINT_KINDS:
            seg.update(oscillation_event_fields(p))
        segs.append(seg)
    out["segments"] = segs
    return out


def schedule_from_matrix(
    matrix: TestMatrix, rig: Rig, extra_faults: Sequence[Mapping[str, Any]] = ()
) -> Schedule:
    """The validated virtual-rig :class:`~cdpr.daq.virtual_rig.Schedule` of a matrix (plus
    ``extra_faults``, as ``--fault`` adds them); an error names the matrix file and its own key
    (``virtual_rig.sensor.noise_sd_N``, ``points (label).wind_mps``)."""
    data = schedule_mapping(matrix)
    if extra_faults:
        data["faults"] = list(data.get("faults", [])) + [dict(f) for f in extra_faults]
    try:
        return schedule_from_mapping(data, matrix.source, rig)
    except ConfigError as exc:
        key = exc.key
        n_own = len(matrix.virtual_rig.get("faults", []))
        if key.startswith("faults[") and int(key[len("faults[") : key.index("]")]) >= n_own:
            i = int(key[len("faults[") : key.index("]")]) - n_own  # a --fault of the command line
            raise ConfigError(
                "--fault", f"#{i + 1}{key[key.index(']') + 1 :]}", exc.problem
            ) from None
        if key.startswith("segments["):
            i = int(key[len("segments[") : key.index("]")])
            key = f"points ({matrix.points[i].label})" + key[key.index("]") + 1 :]
        elif key.split(".")[0].split("[")[0] in (
            "schedule", "sensor", "aero", "faults", "pose_camera",
        ):  # fmt: skip
            key = (
                "virtual_rig" + key[len("schedule") :]
                if key.startswith("schedule")
                else ("virtual_rig." + key)
            )
        raise ConfigError(exc.source, key, exc.problem) from None


test_matrix_from_mapping.__test__ = False  # type: ignore[attr-defined]  # not a pytest test
