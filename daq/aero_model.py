"""A documented, linear aerodynamic model of the SDM-like aircraft the paper tests (all assumptions).

The SDM (Standard Dynamics Model) the paper mounts in its tunnel is 377.6 mm long with a fuselage of
53.9 mm diameter and a 244.1 mm span (paper facts).  Everything else here is an **assumption**,
chosen to give plausible magnitudes for a small fighter-like model at low speed, and every number is
a field of :class:`AeroModel` that a schedule's ``[aero]`` table can override:

- reference chord ``c_ref = 0.060 m`` (mean aerodynamic chord, assumed), span ``b_ref = 0.2441 m``,
  reference area ``S_ref = b_ref * c_ref = 0.0146 m^2`` (assumed rectangular-equivalent wing);
- lift ``CL = CL0 + CL_alpha * aoa`` with ``CL0 = 0.0``, ``CL_alpha = 3.5 /rad`` (low aspect ratio
  ~4 delta-like wing);
- parabolic drag polar ``CD = CD0 + k * CL^2`` with ``CD0 = 0.035``, ``k = 0.09``;
- side force ``CY = CY_beta * sideslip``, ``CY_beta = -0.6 /rad``;
- rolling moment ``Cl = Cl_beta * sideslip``, ``Cl_beta = -0.08 /rad`` (dihedral effect);
- pitching moment ``Cm = Cm0 + Cm_alpha * aoa``, ``Cm0 = 0.0``, ``Cm_alpha = -0.4 /rad``
  (statically stable about the moment reference point);
- yawing moment ``Cn = Cn_beta * sideslip``, ``Cn_beta = 0.10 /rad`` (weathercock stable);
- dynamic derivatives (a moving model, :meth:`AeroModel.wrench_moving_O`; zero body rates on a
  steady point leave the quasi-steady model above unchanged), on the hats ``q c / (2V)``,
  ``aoa_dot c / (2V)`` (pitch) and ``p b / (2V)``, ``r b / (2V)``, ``sideslip_dot b / (2V)``
  (roll, yaw), with ``(p, q, r)`` the body rates and ``V`` the model's speed relative to the air:
  ``CL += CLq q_hat + CLadot alphadot_hat`` with ``CLq = 3.0``, ``CLadot = 1.0``;
  ``Cm += Cmq q_hat + Cmadot alphadot_hat`` with ``Cmq = -5.0``, ``Cmadot = -1.5`` (pitch damping
  ``Cmq + Cmadot = -6.5 /rad``); ``Cl += Clp p_hat + Clr r_hat`` with ``Clp = -0.25``,
  ``Clr = 0.05``; ``Cn += Cnr r_hat + Cnp p_hat + Cnbetadot betadot_hat`` with ``Cnr = -0.15``,
  ``Cnp = -0.02``, ``Cnbetadot = 0.0``.  No lift lag (the response follows the motion at once,
  apart from the aoa_dot terms);
- a moving model meets the air at the velocity of its moment reference point relative to the free
  stream: the angles, their rates and the dynamic pressure ``rho |v|^2 / 2`` use it (a heave or
  surge motion changes them; a pitch about the MRP does not); wind off, the aero load is zero;
- air: ``rho = p / (R T)`` with ``R = 287.05 J/(kg K)``, default ``p = 101325 Pa``, ``T = 293.15 K``;
- the moment reference point (MRP) is at P (``mrp_P_m = 0``);
- mounting: the nose points upstream (-x of {P}), the right wing along +y of {P}, so the AIAA body
  axes B (x nose, y right wing, z down) are ``R_P_B = diag(-1, 1, -1)``; the free stream blows
  along +x of {O} (downstream).

Angles: ``aoa = atan2(w, u)``, ``sideslip = asin(v / V)`` from the model's velocity relative to the air
in body axes ``(u, v, w)``.  Forces: drag opposite the relative velocity, lift perpendicular to it in
the body x-z plane, side force along body y (the usual wind-to-body rotation).  Moments use ``b`` for
roll and yaw and ``c`` for pitch, about the MRP.  The wrench returned is the **aero load on the
platform at P in {O} axes**, order ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N m), so the cables of a
platform at rest carry ``A T = -(G + W)``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from .schema import Schema, Vec3_m, parse

if TYPE_CHECKING:
    from cdpr.analysis.motion import Oscillation

FloatArray = NDArray[np.float64]

DERIVATIVE_COEFFICIENTS = ("CL", "CD", "CY", "CN", "CA", "Cl", "Cm", "Cn")
"""The coefficients :meth:`AeroModel.oscillation_derivatives` projects on a motion's phase."""
DERIVATIVE_NAMES = ("k",) + tuple(
    f"{c}_{w}" for c in DERIVATIVE_COEFFICIENTS for w in ("inphase", "quadrature")
)
"""The keys of :meth:`AeroModel.oscillation_derivatives`, in order."""
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
    CLq: float = 3.0
    CLadot: float = 1.0
    Cmq: float = -5.0
    Cmadot: float = -1.5
    Clp: float = -0.25
    Clr: float = 0.05
    Cnr: float = -0.15
    Cnp: float = -0.02
    Cnbetadot: float = 0.0
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
        """Density, kg/m^3 (:func:`cdpr.analysis.flow.air_density`: moist air at
        ``relative_humidity`` (0..1), dry air without one)."""
        from cdpr.analysis.flow import air_density

        rh = 0.0 if relative_humidity is None else relative_humidity
        return air_density(static_pressure_Pa, temperature_K, rh)

    def angles(self, R_O_P: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(aoa_rad, sideslip_rad) (...,) of the model at attitude ``R_O_P`` (..., 3, 3) in a free
        stream along +x of {O}."""
        R = np.asarray(R_O_P, dtype=np.float64)
        R_O_B = R @ R_P_B
        v_air_rel_O = np.array([-1.0, 0.0, 0.0])  # model velocity relative to the air, unit speed
        v_B = np.einsum("...ji,j->...i", R_O_B, v_air_rel_O)  # R_O_B^T v
        aoa = np.arctan2(v_B[..., 2], v_B[..., 0])
        sideslip = np.arcsin(np.clip(v_B[..., 1], -1.0, 1.0))
        return aoa, sideslip

    def coefficients(self, aoa_rad: ArrayLike, sideslip_rad: ArrayLike) -> dict[str, FloatArray]:
        """CL, CD, CY, Cl, Cm, Cn at (aoa, sideslip) (rad, broadcast)."""
        a = np.asarray(aoa_rad, dtype=np.float64)
        b = np.asarray(sideslip_rad, dtype=np.float64)
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
        """Aero wrench on the platform (..., 6) at P in {O} axes, N and N m, of the model at rest.

        airspeed_mps: (...,) free-stream speed along +x of {O}; R_O_P: (..., 3, 3) attitude.
        """
        V = np.asarray(airspeed_mps, dtype=np.float64)
        R = np.asarray(R_O_P, dtype=np.float64)
        q = 0.5 * self._density(static_pressure_Pa, temperature_K) * V**2
        aoa, sideslip = self.angles(R)
        return self._wrench(q, R, self.coefficients(aoa, sideslip), aoa, sideslip)

    def wrench_moving_O(
        self,
        airspeed_mps: ArrayLike,
        pose: ArrayLike,
        pose_rate: ArrayLike,
        pose_accel: ArrayLike,
        static_pressure_Pa: ArrayLike | None = None,
        temperature_K: ArrayLike | None = None,
    ) -> FloatArray:
        """Aero wrench (..., 6) at P in {O} axes (N, N m) on a moving model: the quasi-steady
        model at the instantaneous flow angles plus the dynamic derivatives.

        airspeed_mps: (...,) free-stream speed along +x of {O}; pose, pose_rate, pose_accel:
        (..., 6) ``[x, y, z, roll, pitch, yaw]`` and its first two time derivatives.  The model
        meets the air at ``v = v_MRP - V x_O``; ``(u, v, w)`` its body components,
        ``aoa = atan2(w, u)``, ``sideslip = asin(v / |v|)``, their rates from ``dv_B/dt =
        R_B_O a_MRP - omega_B x v_B``, and the hats normalised by ``|v|``.  Zero where the free
        stream is zero (wind off).
        """
        from cdpr.analysis.rotations import angular_rates, rotation_from_euler

        qp = np.asarray(pose, dtype=np.float64)
        qd = np.asarray(pose_rate, dtype=np.float64)
        qdd = np.asarray(pose_accel, dtype=np.float64)
        V = np.broadcast_to(np.asarray(airspeed_mps, dtype=np.float64), qp.shape[:-1])
        R = rotation_from_euler(qp[..., 3:])
        omega, omega_dot = angular_rates(qp[..., 3:], qd[..., 3:], qdd[..., 3:])
        r = np.einsum("...ij,j->...i", R, np.asarray(self.mrp_P_m, dtype=np.float64))
        v_mrp = qd[..., :3] + np.cross(omega, r)
        a_mrp = qdd[..., :3] + np.cross(omega_dot, r) + np.cross(omega, np.cross(omega, r))
        v_rel = v_mrp.copy()
        v_rel[..., 0] -= V
        R_B_O = np.swapaxes(R @ R_P_B, -1, -2)
        vB = np.einsum("...ij,...j->...i", R_B_O, v_rel)
        wB = np.einsum("...ij,...j->...i", R_B_O, omega)
        vB_dot = np.einsum("...ij,...j->...i", R_B_O, a_mrp) - np.cross(wB, vB)
        on = V > 0
        speed = np.where(on, np.linalg.norm(vB, axis=-1), 1.0)
        u, v, w = vB[..., 0], vB[..., 1], vB[..., 2]
        ud, vd, wd = vB_dot[..., 0], vB_dot[..., 1], vB_dot[..., 2]
        aoa = np.arctan2(w, u)
        sideslip = np.arcsin(np.clip(v / speed, -1.0, 1.0))
        uw2 = np.where(on, u * u + w * w, 1.0)
        aoa_dot = (u * wd - w * ud) / uw2
        speed_dot = np.einsum("...i,...i->...", vB, vB_dot) / speed
        sideslip_dot = (vd * speed - v * speed_dot) / (speed * np.sqrt(uw2))
        c = self.coefficients(aoa, sideslip)
        kc, kb = self.c_ref_m / (2.0 * speed), self.b_ref_m / (2.0 * speed)
        p_hat, q_hat, r_hat = wB[..., 0] * kb, wB[..., 1] * kc, wB[..., 2] * kb
        ad_hat, bd_hat = aoa_dot * kc, sideslip_dot * kb
        c["CL"] = c["CL"] + self.CLq * q_hat + self.CLadot * ad_hat
        c["CD"] = self.CD0 + self.k_induced * c["CL"] ** 2
        c["Cm"] = c["Cm"] + self.Cmq * q_hat + self.Cmadot * ad_hat
        c["Cl"] = c["Cl"] + self.Clp * p_hat + self.Clr * r_hat
        c["Cn"] = c["Cn"] + self.Cnr * r_hat + self.Cnp * p_hat + self.Cnbetadot * bd_hat
        q = np.where(on, 0.5 * self._density(static_pressure_Pa, temperature_K) * speed**2, 0.0)
        return self._wrench(q, R, c, aoa, sideslip)

    def _density(
        self, static_pressure_Pa: ArrayLike | None, temperature_K: ArrayLike | None
    ) -> FloatArray:
        p = self.static_pressure_Pa if static_pressure_Pa is None else static_pressure_Pa
        T = self.temperature_K if temperature_K is None else temperature_K
        return self.air_density(p, T, self.relative_humidity)

    def _wrench(
        self,
        q: ArrayLike,
        R: FloatArray,
        c: Mapping[str, FloatArray],
        aoa: FloatArray,
        sideslip: FloatArray,
    ) -> FloatArray:
        """The wrench at P in {O} (..., 6) of coefficients ``c`` at dynamic pressure ``q`` and
        flow angles ``aoa``, ``sideslip`` (body axes), attitude ``R``."""
        qS = np.asarray(q, dtype=np.float64) * self.s_ref_m2
        ca, sa, cb, sb = np.cos(aoa), np.sin(aoa), np.cos(sideslip), np.sin(sideslip)
        D, Y, L = qS * c["CD"], qS * c["CY"], qS * c["CL"]
        # wind axes force [-D, Y, -L] rotated to body axes (R_B_W = Ry(aoa)^T-style, standard)
        Fx_B = -D * ca * cb - Y * ca * sb + L * sa
        Fy_B = -D * sb + Y * cb
        Fz_B = -D * sa * cb - Y * sa * sb - L * ca
        F_B = np.stack(np.broadcast_arrays(Fx_B, Fy_B, Fz_B), axis=-1)
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

    def oscillation_derivatives(
        self, osc: Oscillation, mean_pose: ArrayLike, airspeed_mps: float, n_phase: int = 720
    ) -> dict[str, float]:
        """What a noiseless reduction of a forced oscillation of this model finds: over one cycle
        at full amplitude of ``osc`` about ``mean_pose`` (6,) at ``airspeed_mps``, each body
        coefficient ``C`` (on ``q S``, ``c`` for Cm, ``b`` for Cl and Cn, moments about the MRP;
        CL and CD in the wind axes of the attitude's flow angles; CN = -CZ, CA = -CX) is
        projected on the motion's phase: ``C_inphase = (2 <C sin>) / A`` (per rad or per m of the
        motion) and ``C_quadrature = (2 <C cos>) / (A k)``, ``k = omega l / (2V)`` with ``l = c``
        for surge, heave and pitch, ``b`` for sway, roll and yaw.  Also ``k``.  NaN wind off.

        For a pitch oscillation at small amplitude these are ``Cm_inphase = Cm_alpha`` and
        ``Cm_quadrature = Cmq + Cmadot`` (and ``CL_inphase = CL_alpha``, ``CL_quadrature = CLq +
        CLadot``); for yaw (r = -yaw_dot cos(aoa), p = yaw_dot sin(aoa) for this mounting)
        ``Cn_inphase = Cn_beta`` and ``Cn_quadrature = -Cnr cos(aoa) + Cnp sin(aoa) + Cnbetadot``.
        """
        from cdpr.analysis.aero import wind_from_body
        from cdpr.analysis.motion import oscillation_motion
        from cdpr.analysis.rotations import rotation_from_euler

        V = float(airspeed_mps)
        if not V > 0:
            return dict.fromkeys(DERIVATIVE_NAMES, math.nan)
        f, A = osc.frequency_Hz, osc.amplitude
        phase = 2.0 * math.pi * np.arange(n_phase) / n_phase
        mo = oscillation_motion(osc.window_s[0] + phase / (2.0 * math.pi * f), mean_pose, osc)
        W = self.wrench_moving_O(V, mo.pose, mo.rate, mo.accel)
        R = rotation_from_euler(mo.pose[:, 3:])
        R_B_O = np.swapaxes(R @ R_P_B, -1, -2)
        r = np.einsum("nij,j->ni", R, np.asarray(self.mrp_P_m, dtype=np.float64))
        F_B = np.einsum("nij,nj->ni", R_B_O, W[:, :3])
        M_B = np.einsum("nij,nj->ni", R_B_O, W[:, 3:] - np.cross(r, W[:, :3]))
        qS = 0.5 * float(self._density(None, None)) * V * V * self.s_ref_m2
        aoa, sideslip = self.angles(R)
        F_W = np.einsum("nij,nj->ni", wind_from_body(aoa, sideslip), F_B)
        C = {
            "CL": -F_W[:, 2] / qS,
            "CD": -F_W[:, 0] / qS,
            "CY": F_B[:, 1] / qS,
            "CN": -F_B[:, 2] / qS,
            "CA": -F_B[:, 0] / qS,
            "Cl": M_B[:, 0] / (qS * self.b_ref_m),
            "Cm": M_B[:, 1] / (qS * self.c_ref_m),
            "Cn": M_B[:, 2] / (qS * self.b_ref_m),
        }
        ref = self.b_ref_m if osc.axis in ("sway", "roll", "yaw") else self.c_ref_m
        k = osc.omega_rad_s * ref / (2.0 * V)
        out = {"k": k}
        for c in DERIVATIVE_COEFFICIENTS:
            out[f"{c}_inphase"] = float(2.0 * np.mean(C[c] * np.sin(phase)) / A)
            out[f"{c}_quadrature"] = float(2.0 * np.mean(C[c] * np.cos(phase)) / (A * k))
        return out

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
    CLq: _Coefficient | None = None
    CLadot: _Coefficient | None = None
    Cmq: _Coefficient | None = None
    Cmadot: _Coefficient | None = None
    Clp: _Coefficient | None = None
    Clr: _Coefficient | None = None
    Cnr: _Coefficient | None = None
    Cnp: _Coefficient | None = None
    Cnbetadot: _Coefficient | None = None
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
