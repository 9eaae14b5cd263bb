"""Options of the force-sensitivity study (:class:`StudyOptions`), their documented defaults
(``OPTION_DOCS``), their TOML loader and their schema (:class:`OptionsFile`).

Everything the paper leaves open is an option with a documented default; a TOML file with the
sections ``[cubic]``, ``[flat]``, ``[aero]`` and ``[study]`` overrides any of them
(:func:`options_from_toml`); its keys are laid over the defaults and the whole checked by
:class:`OptionsFile` (pydantic: unknown keys, types, ranges and the rules relating keys), whose
errors name the file and the key through the one formatter of :mod:`cdpr.daq.schema`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

from pydantic import Field, model_validator

from cdpr.analysis import sensitivity as sens
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import DEFAULT_CABLE_EA_N
from cdpr.analysis.tension import METHODS
from cdpr.daq.schema import (
    MAX_FORCE_N,
    MAX_LENGTH_M,
    Mass_kg,
    Position_m,
    Schema,
    Stiffness_N,
    Tension_N,
    parse,
    plain,
    rule_error,
)

from .config import load_toml

PAPER_FORCES_N = (19.041, 32.183, 48.327, 60.949, 70.043, 75.706)
PAPER_SPEEDS_MPS = (17.27, 25.51, 41.42)


def _arange(a: float, b: float, step: float) -> tuple[float, ...]:
    n = int(round((b - a) / step))
    return tuple(float(round(a + i * step, 6)) for i in range(n + 1))


@dataclass
class CubicOptions:
    """Cubic rig (paper Fig. 3) and its studies (Figs. 6-11)."""

    L_m: float = 2.0
    W_m: float = 1.2
    H_m: float = 1.4
    mass_kg: float = 5.0
    t_min_N: float = 35.0
    t_max_N: float = 1000.0
    layout: str = "crossed"
    k1_values: tuple[float, ...] = (0.1, 0.15, 0.2, 0.3, 0.4)
    k2_values: tuple[float, ...] = (0.075, 0.1, 0.15, 0.2, 0.3)
    k3_values: tuple[float, ...] = (0.025, 0.05, 0.075, 0.1, 0.15)
    forces_N: tuple[float, ...] = PAPER_FORCES_N
    baseline_k: tuple[float, float, float] = (0.15, 0.075, 0.075)
    Z_values_m: tuple[float, ...] = _arange(0.3, 1.1, 0.05)
    deflection_values_m: tuple[float, ...] = _arange(-0.3, 0.3, 0.025)
    methods: tuple[str, ...] = ("penalty", "exact")


@dataclass
class FlatOptions:
    """Flat rig (paper Fig. 4) and its Table 3 study (Figs. 12-15)."""

    L_m: float = 1.0
    l_m: float = 0.03
    w1_m: float = 0.01
    w2_m: float = 0.04
    mass_kg: float = 0.64
    t_min_N: float = 35.0
    t_max_N: float = 300.0
    K21_values: tuple[float, ...] = _arange(46, 96, 5)
    K22_values: tuple[float, ...] = _arange(25, 55, 3)
    H_values_m: tuple[float, ...] = _arange(0.52, 0.92, 0.05)
    X_values_m: tuple[float, ...] = _arange(0.5, 0.95, 0.05)
    baseline: tuple[float, float, float, float] = (51.0, 28.0, 0.67, 0.5)
    methods: tuple[str, ...] = ("penalty", "improved-closed-form")
    full_grid: bool = True


@dataclass
class AeroOptions:
    """The flat study's external wrench: an SDM-like model, coefficients in {O} axes."""

    speeds_mps: tuple[float, ...] = PAPER_SPEEDS_MPS
    max_speed_mps: float = 51.0
    rho_kgpm3: float = 1.225
    S_ref_m2: float = 0.0199
    span_m: float = 0.2441
    chord_m: float = 0.0815
    coefficients: tuple[float, ...] = (0.08, 0.02, 0.45, 0.01, -0.05, 0.01)


@dataclass
class MetricOptions:
    """Metrics beyond the paper."""

    sigma_T_N: float = 0.2
    margin_method: str = "exact"
    near_singular_condition: float = 1e3
    EA_N: float = DEFAULT_CABLE_EA_N


@dataclass
class StudyOptions:
    """All options of the study; see ``OPTION_DOCS`` for what each one means and why."""

    cubic: CubicOptions = field(default_factory=CubicOptions)
    flat: FlatOptions = field(default_factory=FlatOptions)
    aero: AeroOptions = field(default_factory=AeroOptions)
    study: MetricOptions = field(default_factory=MetricOptions)


OPTION_DOCS: dict[str, str] = {
    "cubic.L_m, W_m, H_m": "frame 2 x 1.2 x 1.4 m (paper)",
    "cubic.mass_kg, t_min_N, t_max_N": "5 kg, 35 N, 1000 N (paper)",
    "cubic.layout": "cable layout of Fig. 3 (not given by the paper): 'crossed' (default, bottom "
    "cables to the opposite y side) or 'cube' (every corner to its own frame corner); see "
    "cdpr.analysis.rigs",
    "cubic.k1_values, k2_values, k3_values": "the grid standing in for the missing Tables 1-2: "
    "k1 in {0.1, 0.15, 0.2, 0.3, 0.4}, k2 in {0.075, 0.1, 0.15, 0.2, 0.3}, k3 in {0.025, 0.05, "
    "0.075, 0.1, 0.15} with 0.025 <= k3 <= k2 <= k1 <= 0.4 (eq. 13): 80 geometries x 6 forces x 2 "
    "directions = 960 cases; it contains every value the paper names",
    "cubic.forces_N": "19.041 ... 75.706 N (paper), applied at P along x and along y",
    "cubic.baseline_k": "(0.15, 0.075, 0.075), the paper's optimum, used by the Z and deflection "
    "studies",
    "cubic.Z_values_m": "0.3 ... 1.1 m step 0.05 (Figs. 8-9)",
    "cubic.deflection_values_m": "-0.3 ... 0.3 m step 0.025 (Figs. 10-11): Fig. 10 a force along "
    "y applied at (d, 0, 0) from P (moment Mz = d Fy), Fig. 11 a force along x applied at "
    "(0, d, 0) (Mz = -d Fx)",
    "cubic.methods": "tension distribution methods (the paper does not say which one the cubic "
    "study used): 'penalty' (the paper's, min |T - Tmin|) and 'exact' (min |T - Tmid|)",
    "flat.*": "L = 1 m, l = 0.03 m, w1 = 0.01 m, w2 = 0.04 m, 0.64 kg, 35-300 N, Table 3 values "
    "(paper); baseline (K21, K22, H, X) = (51, 28, 0.67 m, 0.5 m) for the one-at-a-time sweeps; "
    "full_grid also evaluates all 11 x 11 x 9 x 10 Table 3 combinations",
    "flat.methods": "'penalty' and 'improved-closed-form', as the paper compares them",
    "aero.*": "the flat study's wrench (not given by the paper): W = q S_ref [C_Fx, C_Fy, C_Fz, "
    "b C_Mx, c C_My, b C_Mz] with q = rho V^2 / 2, rho = 1.225 kg/m^3, S_ref = 0.0199 m^2 (span "
    "0.2441 m squared over an aspect ratio of 3), chord 0.0815 m = S_ref / span, coefficients in "
    "{O} axes (drag +x, lift +z) typical of the SDM at about 8 deg angle of attack and 2 deg "
    "sideslip: (0.08, 0.02, 0.45, 0.01, -0.05, 0.01); speeds 17.27, 25.51, 41.42 m/s (paper); the "
    "feasibility margin covers 0 ... 51 m/s (the tunnel's range) and the mirrored sideslip",
    "study.sigma_T_N": "load-cell noise (1 sigma per reading, N) for the wrench uncertainty; the "
    "tare method reads twice, so the covariance is A (2 sigma^2 I) A^T",
    "study.EA_N": "cable axial stiffness E*A (N) for the natural frequencies of the paper's optima: "
    "7e4 N, a 1 mm 7x7 steel rope (assumed; the paper does not give it)",
    "study.margin_method": "method whose tensions define the feasibility margin",
    "study.near_singular_condition": "condition number above which a configuration is reported "
    "as near-singular",
}


# ------------------------------------------------------------------------------------ options


_Len_m = Annotated[float, Field(gt=0.0, le=MAX_LENGTH_M)]
_K = Annotated[float, Field(ge=0.025, le=0.4)]  # paper eq. 13
_Ratio = Annotated[float, Field(gt=1.0, le=1e6)]  # K21, K22: cable length ratios
_Speed_mps = Annotated[float, Field(gt=0.0, le=1e3)]
_Force_N = Annotated[float, Field(gt=0.0, le=MAX_FORCE_N)]
_Method = Literal[tuple(METHODS)]  # type: ignore[valid-type]


_SWEEP = Field(min_length=1, max_length=10_000)  # a non-empty list: each value a sweep point
_Ks = Annotated[list[_K], _SWEEP]
_Ratios = Annotated[list[_Ratio], _SWEEP]
_Lens_m = Annotated[list[_Len_m], _SWEEP]
_Positions_m = Annotated[list[Position_m], _SWEEP]
_Forces_N = Annotated[list[_Force_N], _SWEEP]
_Speeds_mps = Annotated[list[_Speed_mps], _SWEEP]
_Methods = Annotated[list[_Method], _SWEEP]  # type: ignore[valid-type]
_Coefficient = Annotated[float, Field(ge=-1e3, le=1e3)]


def _tension_limits(m: Any) -> None:
    if not m.t_min_N < m.t_max_N:
        raise rule_error("expected 0 <= t_min_N < t_max_N", "t_min_N")


class CubicSection(Schema):
    """``[cubic]``: every key of :class:`CubicOptions`, typed and in range; the rules relating
    them (t_min < t_max, a non-empty k grid, the baseline and sweeps inside the frame)."""

    L_m: _Len_m
    W_m: _Len_m
    H_m: _Len_m
    mass_kg: Mass_kg
    t_min_N: Tension_N
    t_max_N: Tension_N
    layout: Literal[sens.CUBIC_LAYOUTS]  # type: ignore[valid-type]
    k1_values: _Ks
    k2_values: _Ks
    k3_values: _Ks
    forces_N: _Forces_N
    baseline_k: Annotated[list[_K], Field(min_length=3, max_length=3)]
    Z_values_m: _Lens_m
    deflection_values_m: _Positions_m
    methods: _Methods

    @model_validator(mode="after")
    def _relations(self) -> CubicSection:
        _tension_limits(self)
        if not any(True for _ in _cubic_grid(self)):
            raise rule_error("no (k1, k2, k3) of the grids satisfies k3 <= k2 <= k1", "k1_values")
        k1, k2, k3 = self.baseline_k
        if not k3 <= k2 <= k1:
            raise rule_error(
                f"expected 0.025 <= k3 <= k2 <= k1 <= 0.4, got {tuple(self.baseline_k)}",
                "baseline_k",
            )
        half = 0.5 * k3 * self.H_m
        if not all(half < z < self.H_m - half for z in self.Z_values_m):
            raise rule_error(
                f"expected {half:g} < Z < {self.H_m - half:g} m (platform inside the frame)",
                "Z_values_m",
            )
        d_max = 0.5 * min(self.L_m, self.W_m)
        if not all(abs(d) <= d_max for d in self.deflection_values_m):
            raise rule_error(
                f"expected |d| <= {d_max:g} m (inside the frame)", "deflection_values_m"
            )
        return self


class FlatSection(Schema):
    """``[flat]``: every key of :class:`FlatOptions`; X values and the baseline inside the frame."""

    L_m: _Len_m
    l_m: _Len_m
    w1_m: _Len_m
    w2_m: _Len_m
    mass_kg: Mass_kg
    t_min_N: Tension_N
    t_max_N: Tension_N
    K21_values: _Ratios
    K22_values: _Ratios
    H_values_m: _Lens_m
    X_values_m: _Lens_m
    baseline: Annotated[
        list[Annotated[float, Field(ge=-1e6, le=1e6)]], Field(min_length=4, max_length=4)
    ]
    methods: _Methods
    full_grid: bool

    @model_validator(mode="after")
    def _relations(self) -> FlatSection:
        _tension_limits(self)
        lo, hi = self.l_m / 2, self.L_m - self.l_m / 2
        if not all(lo < x < hi for x in self.X_values_m):
            raise rule_error(f"expected {lo:g} < X < {hi:g} m (inside the frame)", "X_values_m")
        b21, b22, bH, bX = self.baseline
        if not (b21 > 1 and b22 > 1):
            raise rule_error("expected K21, K22 > 1", "baseline")
        if not bH > 0:
            raise rule_error("expected H > 0", "baseline")
        if not lo < bX < hi:
            raise rule_error("expected X inside the frame", "baseline")
        return self


class AeroSection(Schema):
    """``[aero]``: every key of :class:`AeroOptions`."""

    speeds_mps: _Speeds_mps
    max_speed_mps: _Speed_mps
    rho_kgpm3: Annotated[float, Field(gt=0.0, le=1e3)]
    S_ref_m2: Annotated[float, Field(gt=0.0, le=1e4)]
    span_m: _Len_m
    chord_m: _Len_m
    coefficients: Annotated[list[_Coefficient], Field(min_length=6, max_length=6)]


class MetricSection(Schema):
    """``[study]``: every key of :class:`MetricOptions`."""

    sigma_T_N: Tension_N
    margin_method: _Method  # type: ignore[valid-type]
    near_singular_condition: Annotated[float, Field(gt=1.0, le=1e16)]
    EA_N: Stiffness_N


class OptionsFile(Schema):
    """Study options: ``[cubic]``, ``[flat]``, ``[aero]``, ``[study]``, every key present (a
    file's keys are laid over the defaults of :class:`StudyOptions` first)."""

    cubic: CubicSection
    flat: FlatSection
    aero: AeroSection
    study: MetricSection


def _merged(data: Mapping[str, Any]) -> dict[str, Any]:
    """The defaults with a file's sections laid over them (what is not a table stays as it is,
    for the schema to refuse)."""
    out: dict[str, Any] = dataclasses.asdict(StudyOptions())
    for sec, body in data.items():
        if isinstance(body, Mapping) and isinstance(out.get(sec), dict):
            out[sec] = {**out[sec], **body}
        else:
            out[sec] = body
    return out


def _options(f: OptionsFile) -> StudyOptions:
    """The dataclasses of a checked file (numbers as floats, lists as tuples)."""

    def value(v: Any) -> Any:
        if isinstance(v, list):
            return tuple(value(x) for x in v)
        if isinstance(v, int) and not isinstance(v, bool):
            return float(v)
        return v

    parts = {
        sec: {k: value(v) for k, v in getattr(f, sec).model_dump().items()}
        for sec in ("cubic", "flat", "aero", "study")
    }
    return StudyOptions(
        cubic=CubicOptions(**parts["cubic"]),
        flat=FlatOptions(**parts["flat"]),
        aero=AeroOptions(**parts["aero"]),
        study=MetricOptions(**parts["study"]),
    )


def options_from_mapping(data: Mapping[str, Any], source: str = "<options>") -> StudyOptions:
    """Defaults overridden by a mapping ``{section: {key: value}}``, checked by
    :class:`OptionsFile` (unknown keys, types, ranges, the rules relating them)."""
    if not isinstance(data, Mapping):
        raise ConfigError(source, "", "expected a table")
    return _options(parse(OptionsFile, plain(_merged(data)), source))


def options_from_toml(path: str) -> StudyOptions:
    """Load study options from a TOML file (sections cubic, flat, aero, study)."""
    return options_from_mapping(load_toml(path), source=str(path))


def validate_options(o: StudyOptions, source: str = "<options>") -> None:
    """Check options built or changed by code (command-line overrides) with the same schema as a
    file's (:class:`OptionsFile`); a :class:`ConfigError` names the option and the problem."""
    parse(OptionsFile, plain(dataclasses.asdict(o)), source)


def _cubic_grid(c: CubicOptions | CubicSection) -> Iterator[tuple[float, float, float]]:
    for k1 in c.k1_values:
        for k2 in c.k2_values:
            for k3 in c.k3_values:
                if k3 <= k2 <= k1:
                    yield (k1, k2, k3)
