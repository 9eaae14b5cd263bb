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
  ``R_v = 461.495`` J/(kg K).  With ``RH = 0`` it is :func:`cdpr.analysis.aero.air_density`.
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


@dataclass(frozen=True)
class FlowConditions:
    """Flow conditions per point, each (n,) (or the broadcast shape of the inputs).

    density_kgpm3, viscosity_Pas, q_Pa (dynamic pressure), reynolds (on the reference chord),
    mach, speed_of_sound_mps; record says what was used.
    """

    density_kgpm3: FloatArray
    viscosity_Pas: FloatArray
    q_Pa: FloatArray
    reynolds: FloatArray
    mach: FloatArray
    speed_of_sound_mps: FloatArray
    record: CorrectionRecord


def flow_conditions(
    airspeed_mps: ArrayLike,
    static_pressure_Pa: ArrayLike,
    temperature_K: ArrayLike,
    chord_m: float,
    relative_humidity: ArrayLike | None = None,
) -> FlowConditions:
    """Density, viscosity, q, Re (on ``chord_m``) and Mach per point.

    ``relative_humidity=None`` means not measured: dry air is used and the record carries the
    flag ``humidity_not_given`` (dry air overestimates the density by up to about 1 % at 30 deg C).
    """
    flags: tuple[str, ...] = ()
    if relative_humidity is None:
        relative_humidity = 0.0
        flags = ("humidity_not_given",)
    v = as_float_array(airspeed_mps, "airspeed_mps")
    if np.any(~np.isfinite(v)) or np.any(v < 0):
        raise InputError("airspeed_mps: expected finite values >= 0 m/s")
    rho = air_density(static_pressure_Pa, temperature_K, relative_humidity)
    mu = sutherland_viscosity(temperature_K)
    a = speed_of_sound(temperature_K)
    q = dynamic_pressure(rho, v)
    re = reynolds_number(rho, v, chord_m, mu)
    mach = np.asarray(v / a)
    rec = CorrectionRecord(
        name="flow_conditions",
        source="Buck equation (1981/1996) vapour pressure; ideal-gas moist air; Sutherland's law (White); "
        "q = rho V^2/2; Re on the reference chord; M = V/sqrt(1.4 R T)",
        values={
            "chord_m": float(chord_m),
            "q_Pa_max": float(np.max(q)) if q.size else 0.0,
            "reynolds_max": float(np.max(re)) if re.size else 0.0,
            "mach_max": float(np.max(mach)) if mach.size else 0.0,
        },
        flags=flags,
    )
    return FlowConditions(
        density_kgpm3=rho,
        viscosity_Pas=mu,
        q_Pa=q,
        reynolds=re,
        mach=mach,
        speed_of_sound_mps=a,
        record=rec,
    )
