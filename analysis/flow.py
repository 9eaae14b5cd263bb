"""Flow conditions per point: density (with humidity), viscosity, q, Reynolds and Mach numbers.

All functions broadcast over per-point arrays (shape (n,) or any common shape), SI units:
pressure Pa, temperature K, relative humidity as a fraction 0..1, speed m/s, length m.

Formulas and sources:

- Saturation vapour pressure over water: the Arden Buck equation (Buck 1981, J. Appl. Meteor. 20,
  "New equations for computing vapor pressure and enhancement factor"; the form and coefficients
  of Buck's 1996 revision), ``e_s = 611.21 exp((18.678 - t/234.5) t/(257.14 + t))`` with ``t`` in
  deg C.
- Moist-air density: ideal mixture of dry air and water vapour,
  ``rho = (p - e)/(R_d T) + e/(R_v T)`` with ``e = RH e_s(T)``, ``R_d = 287.05287``,
  ``R_v = 461.495`` J/(kg K).  With ``RH = 0`` it is dry air, ``p / (R_d T)``.
- Dynamic viscosity: Sutherland's law, ``mu = mu_ref (T/T_ref)^1.5 (T_ref + S)/(T + S)``,
  ``mu_ref = 1.716e-5`` Pa s, ``T_ref = 273.15`` K, ``S = 110.4`` K (White, *Viscous Fluid Flow*).
- Speed of sound ``a = sqrt(gamma R_d T)``, ``gamma = 1.4``; Mach ``V / a``.
- Reynolds number ``Re = rho V L / mu`` on a reference length ``L`` (the model's reference chord).
- Dynamic pressure ``q = rho V^2 / 2`` (:func:`cdpr.analysis.aero.dynamic_pressure`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array
from .aero import SPECIFIC_GAS_CONSTANT_AIR_JPKGK, dynamic_pressure
from .errors import InputError
from .records import CorrectionRecord

FloatArray = NDArray[np.float64]

SPECIFIC_GAS_CONSTANT_VAPOUR_JPKGK: float = 461.495
"""Specific gas constant of water vapour, J/(kg K)."""

HEAT_CAPACITY_RATIO_AIR: float = 1.4
"""Ratio of specific heats of air."""

SUTHERLAND_MU_REF_PAS: float = 1.716e-5
SUTHERLAND_T_REF_K: float = 273.15
SUTHERLAND_S_K: float = 110.4


def _positive(value: ArrayLike, name: str, unit: str) -> FloatArray:
    arr = as_float_array(value, name)
    if np.any(~np.isfinite(arr)) or np.any(arr <= 0):
        raise InputError(f"{name}: expected finite values > 0 {unit}")
    return arr


def saturation_vapour_pressure(temperature_K: ArrayLike) -> FloatArray:
    """Saturation vapour pressure over water (Pa) at ``temperature_K`` (K): the Buck equation."""
    t_C = _positive(temperature_K, "temperature_K", "K") - 273.15
    return np.asarray(611.21 * np.exp((18.678 - t_C / 234.5) * (t_C / (257.14 + t_C))))


def air_density(
    static_pressure_Pa: ArrayLike, temperature_K: ArrayLike, relative_humidity: ArrayLike = 0.0
) -> FloatArray:
    """Moist-air density (kg/m^3) from p (Pa), T (K) and relative humidity (0..1), broadcast."""
    p = _positive(static_pressure_Pa, "static_pressure_Pa", "Pa")
    T = _positive(temperature_K, "temperature_K", "K")
    rh = as_float_array(relative_humidity, "relative_humidity")
    if np.any(~np.isfinite(rh)) or np.any((rh < 0) | (rh > 1)):
        raise InputError("relative_humidity: expected a fraction in [0, 1]")
    e = rh * saturation_vapour_pressure(T)
    if np.any(e >= p):
        raise InputError("relative_humidity: vapour pressure above the static pressure")
    rho = (p - e) / (SPECIFIC_GAS_CONSTANT_AIR_JPKGK * T) + e / (
        SPECIFIC_GAS_CONSTANT_VAPOUR_JPKGK * T
    )
    return np.asarray(rho, dtype=np.float64)


def sutherland_viscosity(temperature_K: ArrayLike) -> FloatArray:
    """Dynamic viscosity of air (Pa s) at ``temperature_K`` (K): Sutherland's law."""
    T = _positive(temperature_K, "temperature_K", "K")
    return np.asarray(
        SUTHERLAND_MU_REF_PAS
        * (T / SUTHERLAND_T_REF_K) ** 1.5
        * (SUTHERLAND_T_REF_K + SUTHERLAND_S_K)
        / (T + SUTHERLAND_S_K)
    )


def speed_of_sound(temperature_K: ArrayLike) -> FloatArray:
    """Speed of sound in dry air (m/s): ``sqrt(gamma R_d T)``."""
    T = _positive(temperature_K, "temperature_K", "K")
    return np.asarray(np.sqrt(HEAT_CAPACITY_RATIO_AIR * SPECIFIC_GAS_CONSTANT_AIR_JPKGK * T))


def reynolds_number(
    density_kgpm3: ArrayLike, airspeed_mps: ArrayLike, length_m: ArrayLike, viscosity_Pas: ArrayLike
) -> FloatArray:
    """Reynolds number ``rho V L / mu`` (dimensionless), broadcast."""
    rho = _positive(density_kgpm3, "density_kgpm3", "kg/m^3")
    v = as_float_array(airspeed_mps, "airspeed_mps")
    length = _positive(length_m, "length_m", "m")
    mu = _positive(viscosity_Pas, "viscosity_Pas", "Pa s")
    return np.asarray(rho * np.abs(v) * length / mu)


DENSITY_SOURCES: tuple[str, ...] = ("p_T_humidity", "p_T_dry", "stream")
"""Per point, where the density came from: its p, T and relative humidity (moist air), its p and T
without a humidity (dry air, flag ``humidity_not_given``), or the density as given (no p and T:
a measured density, e.g. the tunnel stream's)."""


@dataclass(frozen=True)
class FlowConditions:
    """Flow conditions per point, each (n,).

    density_kgpm3; density_source: (n,) str, one of :data:`DENSITY_SOURCES`; viscosity_Pas,
    q_Pa (dynamic pressure), reynolds (on the reference chord), mach, speed_of_sound_mps: NaN where
    the point lacks a temperature, a density or a speed; known: (n,) True where Re and Mach could
    be had; dry: (n,) True where p and T were given without a humidity (computed as dry air);
    record says what was used (flag ``humidity_not_given`` when a point in the wind was dry,
    ``no_temperature`` when one had no Re or Mach).
    """

    density_kgpm3: FloatArray
    density_source: NDArray[np.str_]
    viscosity_Pas: FloatArray
    q_Pa: FloatArray
    reynolds: FloatArray
    mach: FloatArray
    speed_of_sound_mps: FloatArray
    known: NDArray[np.bool_]
    dry: NDArray[np.bool_]
    record: CorrectionRecord


def _nan_or_positive(value: ArrayLike, name: str, unit: str, n: int) -> FloatArray:
    """``value`` broadcast to (n,): NaN means not given; anything else must be finite and > 0."""
    arr = np.array(np.broadcast_to(as_float_array(value, name), (n,)), dtype=np.float64)
    bad = ~np.isnan(arr) & ~(np.isfinite(arr) & (arr > 0))
    if bad.any():
        raise InputError(f"{name}: expected finite values > 0 {unit} (NaN: not given)")
    return arr


def flow_conditions(
    airspeed_mps: ArrayLike,
    static_pressure_Pa: ArrayLike,
    temperature_K: ArrayLike,
    chord_m: float,
    relative_humidity: ArrayLike | None = None,
    density_kgpm3: ArrayLike | None = None,
    in_flow: ArrayLike | None = None,
) -> FlowConditions:
    """Density, viscosity, q, Re (on ``chord_m``) and Mach per point.

    airspeed_mps: (n,) (NaN: unknown); static_pressure_Pa, temperature_K: (n,) or scalars (NaN:
    not given); relative_humidity: (n,) or scalar fraction 0..1, NaN or None where not measured;
    density_kgpm3: (n,) a measured density kept where p and T are not given (else NaN);
    in_flow: (n,) bool, the points in the wind (wind-on and model-off windage points above the
    wind-off speed: those whose q the density sets), for the flags and the record's counts
    (default: all).

    Where p and T are given the density is moist air (:func:`air_density`, the Buck vapour
    pressure); without a humidity it is dry air and the point is ``dry`` (up to about 1 % high at
    30 deg C); elsewhere the given density stays (``stream``).  Viscosity (Sutherland), Re and
    Mach where the point has a temperature, a positive density and a speed >= 0.
    """
    v = np.atleast_1d(as_float_array(airspeed_mps, "airspeed_mps")).astype(np.float64)
    n = v.shape[0]
    if np.any(np.isfinite(v) & (v < 0)) or np.any(np.isinf(v)):
        raise InputError("airspeed_mps: expected finite values >= 0 m/s (NaN: unknown)")
    p = _nan_or_positive(static_pressure_Pa, "static_pressure_Pa", "Pa", n)
    TK = _nan_or_positive(temperature_K, "temperature_K", "K", n)
    rh = (
        np.full(n, np.nan)
        if relative_humidity is None
        else as_float_array(relative_humidity, "relative_humidity")
    )
    rh = np.array(np.broadcast_to(rh, (n,)), dtype=np.float64)
    rho = (
        np.full(n, np.nan)
        if density_kgpm3 is None
        else np.array(
            np.broadcast_to(as_float_array(density_kgpm3, "density_kgpm3"), (n,)), dtype=np.float64
        )
    )
    wind = np.ones(n, bool) if in_flow is None else np.asarray(in_flow, dtype=bool)
    pT = np.isfinite(p) & np.isfinite(TK)
    wet = pT & np.isfinite(rh)
    source = np.full(n, DENSITY_SOURCES[2], dtype=object)
    if pT.any():
        rho[pT] = air_density(p[pT], TK[pT], np.where(wet, rh, 0.0)[pT])
        source[wet], source[pT & ~wet] = DENSITY_SOURCES[0], DENSITY_SOURCES[1]
    known = np.isfinite(v) & np.isfinite(rho) & (rho > 0) & np.isfinite(TK)
    mu, re, mach, a, q = (np.full(n, np.nan) for _ in range(5))
    if known.any():
        mu[known] = sutherland_viscosity(TK[known])
        re[known] = reynolds_number(rho[known], v[known], chord_m, mu[known])
        a[known] = speed_of_sound(TK[known])
        mach[known] = v[known] / a[known]
    has_q = np.isfinite(v) & np.isfinite(rho) & (rho > 0)
    if has_q.any():
        q[has_q] = dynamic_pressure(rho[has_q], v[has_q])
    dry = pT & ~wet
    rec = CorrectionRecord(
        name="flow_conditions",
        source="density: ideal-gas moist air at the point's mean p, T and relative humidity "
        "(Buck vapour pressure), dry air where no humidity is given; Re = rho V c / mu with "
        "Sutherland's law (White); M = V / sqrt(1.4 R T)",
        values={
            "chord_m": float(chord_m),
            "points_with_humidity": int((wind & wet).sum()),
            "points_without_humidity": int((wind & dry).sum()),
            "reynolds_max": float(np.nanmax(re)) if known.any() else None,
            "mach_max": float(np.nanmax(mach)) if known.any() else None,
        },
        flags=tuple(
            f
            for f, m in (("humidity_not_given", wind & dry), ("no_temperature", wind & ~known))
            if m.any()
        ),
    )
    return FlowConditions(
        density_kgpm3=rho,
        density_source=source.astype(str),
        viscosity_Pas=mu,
        q_Pa=q,
        reynolds=re,
        mach=mach,
        speed_of_sound_mps=a,
        known=known,
        dry=dry,
        record=rec,
    )
