"""A documented, linear aerodynamic model of the SDM-like aircraft the paper tests (all assumptions).

The SDM (Standard Dynamics Model) the paper mounts in its tunnel is 377.6 mm long with a fuselage of
53.9 mm diameter and a 244.1 mm span (paper facts).  Everything else here is an **assumption**,
chosen to give plausible magnitudes for a small fighter-like model at low speed, and every number is
a field of :class:`AeroModel` that a schedule's ``[aero]`` table can override:

- reference chord ``c_ref = 0.060 m`` (mean aerodynamic chord, assumed), span ``b_ref = 0.2441 m``,
  reference area ``S_ref = b_ref * c_ref = 0.0146 m^2`` (assumed rectangular-equivalent wing);
- lift ``CL = CL0 + CL_alpha * alpha`` with ``CL0 = 0.0``, ``CL_alpha = 3.5 /rad`` (low aspect ratio
  ~4 delta-like wing);
- parabolic drag polar ``CD = CD0 + k * CL^2`` with ``CD0 = 0.035``, ``k = 0.09``;
- side force ``CY = CY_beta * beta``, ``CY_beta = -0.6 /rad``;
- rolling moment ``Cl = Cl_beta * beta``, ``Cl_beta = -0.08 /rad`` (dihedral effect);
- pitching moment ``Cm = Cm0 + Cm_alpha * alpha``, ``Cm0 = 0.0``, ``Cm_alpha = -0.4 /rad``
  (statically stable about the moment reference point);
- yawing moment ``Cn = Cn_beta * beta``, ``Cn_beta = 0.10 /rad`` (weathercock stable);
- air: ``rho = p / (R T)`` with ``R = 287.05 J/(kg K)``, default ``p = 101325 Pa``, ``T = 293.15 K``;
- the moment reference point (MRP) is at P (``mrp_P_m = 0``);
- mounting: the nose points upstream (-x of {P}), the right wing along +y of {P}, so the AIAA body
  axes B (x nose, y right wing, z down) are ``R_P_B = diag(-1, 1, -1)``; the free stream blows
  along +x of {O} (downstream).

Angles: ``alpha = atan2(w, u)``, ``beta = asin(v / V)`` from the model's velocity relative to the air
in body axes ``(u, v, w)``.  Forces: drag opposite the relative velocity, lift perpendicular to it in
the body x-z plane, side force along body y (the usual wind-to-body rotation).  Moments use ``b`` for
roll and yaw and ``c`` for pitch.  The wrench returned is the **aero load on the platform at P in {O}
axes**, order ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N m), so the cables carry ``A T = -(G + W)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Annotated, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from .schema import Schema, Vec3_m, parse

FloatArray = NDArray[np.float64]

R_AIR_J_PER_KGK = 287.05
R_P_B = np.diag([-1.0, 1.0, -1.0])
"""Rotation from the AIAA body axes B (x nose, y right wing, z down) to {P} (nose upstream)."""


@dataclass(frozen=True)
class AeroModel:
    """Linear SDM-like aero model; every field is an assumption (see the module docstring)."""

    c_ref_m: float = 0.060
    b_ref_m: float = 0.2441
    s_ref_m2: float = 0.2441 * 0.060
    length_m: float = 0.3776
    fuselage_diameter_m: float = 0.0539
    CL0: float = 0.0
    CL_alpha: float = 3.5
    CD0: float = 0.035
    k_induced: float = 0.09
    CY_beta: float = -0.6
    Cl_beta: float = -0.08
    Cm0: float = 0.0
    Cm_alpha: float = -0.4
    Cn_beta: float = 0.10
    mrp_P_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    static_pressure_Pa: float = 101325.0
    temperature_K: float = 293.15
    relative_humidity: float | None = None

    @staticmethod
    def air_density(
        static_pressure_Pa: ArrayLike,
        temperature_K: ArrayLike,
        relative_humidity: float | None = None,
    ) -> FloatArray:
        """Ideal-gas density ``p / (R T)``, kg/m^3; moist air
        (:func:`cdpr.analysis.flow.air_density`) when ``relative_humidity`` (0..1) is given."""
        if relative_humidity is not None:
            from cdpr.analysis.flow import air_density as moist

            return moist(static_pressure_Pa, temperature_K, relative_humidity)
        return np.asarray(static_pressure_Pa, float) / (
            R_AIR_J_PER_KGK * np.asarray(temperature_K, float)
        )

    def angles(self, R_O_P: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(alpha_rad, beta_rad) (...,) of the model at attitude ``R_O_P`` (..., 3, 3) in a free
        stream along +x of {O}."""
        R = np.asarray(R_O_P, dtype=np.float64)
        R_O_B = R @ R_P_B
        v_air_rel_O = np.array([-1.0, 0.0, 0.0])  # model velocity relative to the air, unit speed
        v_B = np.einsum("...ji,j->...i", R_O_B, v_air_rel_O)  # R_O_B^T v
        alpha = np.arctan2(v_B[..., 2], v_B[..., 0])
        beta = np.arcsin(np.clip(v_B[..., 1], -1.0, 1.0))
        return alpha, beta

    def coefficients(self, alpha_rad: ArrayLike, beta_rad: ArrayLike) -> dict[str, FloatArray]:
        """CL, CD, CY, Cl, Cm, Cn at (alpha, beta) (rad, broadcast)."""
        a = np.asarray(alpha_rad, dtype=np.float64)
        b = np.asarray(beta_rad, dtype=np.float64)
        CL = self.CL0 + self.CL_alpha * a
        return {
            "CL": CL,
            "CD": self.CD0 + self.k_induced * CL**2 + 0.0 * b,
            "CY": self.CY_beta * b + 0.0 * a,
            "Cl": self.Cl_beta * b + 0.0 * a,
            "Cm": self.Cm0 + self.Cm_alpha * a + 0.0 * b,
            "Cn": self.Cn_beta * b + 0.0 * a,
        }

    def wrench_O(
        self,
        airspeed_mps: ArrayLike,
        R_O_P: ArrayLike,
        static_pressure_Pa: ArrayLike | None = None,
        temperature_K: ArrayLike | None = None,
    ) -> FloatArray:
        """Aero wrench on the platform (..., 6) at P in {O} axes, N and N m.

        airspeed_mps: (...,) free-stream speed along +x of {O}; R_O_P: (..., 3, 3) attitude.
        """
        V = np.asarray(airspeed_mps, dtype=np.float64)
        R = np.asarray(R_O_P, dtype=np.float64)
        p = self.static_pressure_Pa if static_pressure_Pa is None else static_pressure_Pa
        T = self.temperature_K if temperature_K is None else temperature_K
        rho = self.air_density(p, T, self.relative_humidity)
        q = 0.5 * rho * V**2
        alpha, beta = self.angles(R)
        c = self.coefficients(alpha, beta)
        ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
        D, Y, L = (
            q * self.s_ref_m2 * c["CD"],
            q * self.s_ref_m2 * c["CY"],
            q * self.s_ref_m2 * c["CL"],
        )
        # wind axes force [-D, Y, -L] rotated to body axes (R_B_W = Ry(alpha)^T-style, standard)
        Fx_B = -D * ca * cb - Y * ca * sb + L * sa
        Fy_B = -D * sb + Y * cb
        Fz_B = -D * sa * cb - Y * sa * sb - L * ca
        F_B = np.stack(np.broadcast_arrays(Fx_B, Fy_B, Fz_B), axis=-1)
        qS = q * self.s_ref_m2
        M_B = np.stack(
            np.broadcast_arrays(
                qS * self.b_ref_m * c["Cl"],
                qS * self.c_ref_m * c["Cm"],
                qS * self.b_ref_m * c["Cn"],
            ),
            axis=-1,
        )
        R_O_B = R @ R_P_B
        F_O = np.einsum("...ij,...j->...i", R_O_B, F_B)
        M_O = np.einsum("...ij,...j->...i", R_O_B, M_B)
        r_O = np.einsum("...ij,j->...i", R, np.asarray(self.mrp_P_m, dtype=np.float64))
        M_O = M_O + np.cross(r_O, F_O)
        return np.concatenate([F_O, M_O], axis=-1)

    def to_mapping(self) -> dict[str, Any]:
        d = asdict(self)
        d["mrp_P_m"] = list(self.mrp_P_m)
        return d


_Length = Annotated[float, Field(gt=0.0, le=100.0)]
_Coefficient = Annotated[float, Field(ge=-1e3, le=1e3)]


class AeroSection(Schema):
    """Schema of a schedule's ``[aero]`` table: every :class:`AeroModel` field, each optional,
    with plausible ranges (a reference length of 1e300 m or a negative pressure is refused)."""

    c_ref_m: _Length | None = None
    b_ref_m: _Length | None = None
    s_ref_m2: Annotated[float, Field(gt=0.0, le=1e4)] | None = None
    length_m: _Length | None = None
    fuselage_diameter_m: _Length | None = None
    CL0: _Coefficient | None = None
    CL_alpha: _Coefficient | None = None
    CD0: _Coefficient | None = None
    k_induced: _Coefficient | None = None
    CY_beta: _Coefficient | None = None
    Cl_beta: _Coefficient | None = None
    Cm0: _Coefficient | None = None
    Cm_alpha: _Coefficient | None = None
    Cn_beta: _Coefficient | None = None
    mrp_P_m: Vec3_m | None = None
    static_pressure_Pa: Annotated[float, Field(gt=0.0, le=1e7)] | None = None
    temperature_K: Annotated[float, Field(gt=0.0, le=1e4)] | None = None
    relative_humidity: Annotated[float, Field(ge=0.0, le=1.0)] | None = None


def aero_from_mapping(data: Mapping[str, Any] | None, source: str, key: str = "aero") -> AeroModel:
    """An :class:`AeroModel` with the defaults overridden by ``data`` (a schedule's ``[aero]``),
    validated by :class:`AeroSection` (errors name ``source`` and ``<key>.<field>``).

    ``s_ref_m2`` defaults to ``b_ref_m * c_ref_m`` when only those are given.
    """
    if not data:
        return AeroModel()
    kw: dict[str, Any] = parse(AeroSection, data, source, prefix=key).model_dump(exclude_none=True)
    if "mrp_P_m" in kw:
        kw["mrp_P_m"] = tuple(kw["mrp_P_m"])
    if "s_ref_m2" not in kw and ("b_ref_m" in kw or "c_ref_m" in kw):
        kw["s_ref_m2"] = kw.get("b_ref_m", AeroModel.b_ref_m) * kw.get("c_ref_m", AeroModel.c_ref_m)
    return AeroModel(**kw)
