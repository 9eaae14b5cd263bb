"""Options of the force-sensitivity study (:class:`StudyOptions`), their documented defaults
(``OPTION_DOCS``), their TOML loader and their validation.

Everything the paper leaves open is an option with a documented default; a TOML file with the
sections ``[cubic]``, ``[flat]``, ``[aero]`` and ``[study]`` overrides any of them
(:func:`options_from_toml`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from cdpr.analysis import sensitivity as sens
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import DEFAULT_CABLE_EA_N
from cdpr.analysis.tension import METHODS

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


def _coerce(source: str, key: str, value: Any, default: Any) -> Any:
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(source, key, f"expected true or false, got {value!r}")
        return value
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(source, key, f"expected a string, got {value!r}")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list | tuple) or not value:
            raise ConfigError(source, key, f"expected a non-empty list, got {value!r}")
        if isinstance(default[0], str):
            if not all(isinstance(v, str) for v in value):
                raise ConfigError(source, key, f"expected a list of strings, got {value!r}")
            return tuple(value)
        out = []
        for v in value:
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(source, key, f"expected finite numbers, got {v!r}")
            out.append(float(v))
        return tuple(out)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(source, key, f"expected a finite number, got {value!r}")
    return float(value)


def options_from_mapping(data: Mapping[str, Any], source: str = "<options>") -> StudyOptions:
    """Defaults overridden by a mapping ``{section: {key: value}}``; unknown keys are errors."""
    opts = StudyOptions()
    for sec, body in data.items():
        if sec not in ("cubic", "flat", "aero", "study"):
            raise ConfigError(source, sec, "unknown section (allowed: cubic, flat, aero, study)")
        if not isinstance(body, Mapping):
            raise ConfigError(source, sec, "expected a table")
        target = getattr(opts, sec)
        names = {f.name for f in dataclasses.fields(target)}
        for key, value in body.items():
            if key not in names:
                raise ConfigError(source, f"{sec}.{key}", f"unknown key (allowed: {sorted(names)})")
            setattr(target, key, _coerce(source, f"{sec}.{key}", value, getattr(target, key)))
    validate_options(opts, source)
    return opts


def options_from_toml(path: str) -> StudyOptions:
    """Load study options from a TOML file (sections cubic, flat, aero, study)."""
    return options_from_mapping(load_toml(path), source=str(path))


def validate_options(o: StudyOptions, source: str = "<options>") -> None:
    """Check every option's range; a :class:`ConfigError` names the option and the problem."""

    def need(ok: bool, key: str, problem: str) -> None:
        if not ok:
            raise ConfigError(source, key, problem)

    c, f, a, s = o.cubic, o.flat, o.aero, o.study
    for key in ("L_m", "W_m", "H_m", "mass_kg"):
        need(getattr(c, key) > 0, f"cubic.{key}", f"expected > 0, got {getattr(c, key)}")
    need(0 <= c.t_min_N < c.t_max_N, "cubic.t_min_N", "expected 0 <= t_min_N < t_max_N")
    need(c.layout in sens.CUBIC_LAYOUTS, "cubic.layout", f"expected one of {sens.CUBIC_LAYOUTS}")
    for key in ("k1_values", "k2_values", "k3_values"):
        v = getattr(c, key)
        need(
            all(0.025 <= k <= 0.4 for k in v),
            f"cubic.{key}",
            f"expected values in [0.025, 0.4] (paper eq. 13), got {list(v)}",
        )
    need(
        len(tuple(_cubic_grid(c))) > 0,
        "cubic.k1_values",
        "no (k1, k2, k3) of the grids satisfies k3 <= k2 <= k1",
    )
    need(len(c.baseline_k) == 3, "cubic.baseline_k", "expected 3 values (k1, k2, k3)")
    k1, k2, k3 = c.baseline_k
    need(
        0.025 <= k3 <= k2 <= k1 <= 0.4,
        "cubic.baseline_k",
        f"expected 0.025 <= k3 <= k2 <= k1 <= 0.4, got {tuple(c.baseline_k)}",
    )
    need(all(x > 0 for x in c.forces_N), "cubic.forces_N", "expected forces > 0 N")
    half = 0.5 * k3 * c.H_m
    need(
        all(half < z < c.H_m - half for z in c.Z_values_m),
        "cubic.Z_values_m",
        f"expected {half:g} < Z < {c.H_m - half:g} m (platform inside the frame)",
    )
    need(
        all(abs(d) <= 0.5 * min(c.L_m, c.W_m) for d in c.deflection_values_m),
        "cubic.deflection_values_m",
        f"expected |d| <= {0.5 * min(c.L_m, c.W_m):g} m (inside the frame)",
    )
    for key in ("L_m", "l_m", "w1_m", "w2_m", "mass_kg"):
        need(getattr(f, key) > 0, f"flat.{key}", f"expected > 0, got {getattr(f, key)}")
    need(0 <= f.t_min_N < f.t_max_N, "flat.t_min_N", "expected 0 <= t_min_N < t_max_N")
    need(all(k > 1 for k in f.K21_values), "flat.K21_values", "expected K21 > 1")
    need(all(k > 1 for k in f.K22_values), "flat.K22_values", "expected K22 > 1")
    need(all(h > 0 for h in f.H_values_m), "flat.H_values_m", "expected H > 0 m")
    need(
        all(f.l_m / 2 < x < f.L_m - f.l_m / 2 for x in f.X_values_m),
        "flat.X_values_m",
        f"expected {f.l_m / 2:g} < X < {f.L_m - f.l_m / 2:g} m (inside the frame)",
    )
    need(len(f.baseline) == 4, "flat.baseline", "expected 4 values (K21, K22, H, X)")
    b21, b22, bH, bX = f.baseline
    need(b21 > 1 and b22 > 1, "flat.baseline", "expected K21, K22 > 1")
    need(bH > 0, "flat.baseline", "expected H > 0")
    need(f.l_m / 2 < bX < f.L_m - f.l_m / 2, "flat.baseline", "expected X inside the frame")
    need(all(v > 0 for v in a.speeds_mps), "aero.speeds_mps", "expected speeds > 0 m/s")
    need(a.max_speed_mps > 0, "aero.max_speed_mps", "expected > 0 m/s")
    for key in ("rho_kgpm3", "S_ref_m2", "span_m", "chord_m"):
        need(getattr(a, key) > 0, f"aero.{key}", f"expected > 0, got {getattr(a, key)}")
    need(len(a.coefficients) == 6, "aero.coefficients", "expected 6 coefficients")
    for key, methods in (("cubic.methods", c.methods), ("flat.methods", f.methods)):
        bad = [m for m in methods if m not in METHODS]
        need(not bad, key, f"unknown method {bad} (known: {sorted(METHODS)})")
    need(s.margin_method in METHODS, "study.margin_method", f"expected one of {sorted(METHODS)}")
    need(s.sigma_T_N >= 0, "study.sigma_T_N", "expected >= 0 N")
    need(s.near_singular_condition > 1, "study.near_singular_condition", "expected > 1")
    need(math.isfinite(s.EA_N) and s.EA_N > 0, "study.EA_N", "expected a finite E*A > 0 N")


def _cubic_grid(c: CubicOptions) -> Iterator[tuple[float, float, float]]:
    for k1 in c.k1_values:
        for k2 in c.k2_values:
            for k3 in c.k3_values:
                if k3 <= k2 <= k1:
                    yield (k1, k2, k3)
