"""The lab generator's own aerodynamic model (nothing here imports cdpr).

Axes (AIAA): body axes {B} x to the nose, y to the right wing, z down.  The model sits on the
platform nose upstream (``-x_P``) with its up along ``+z_P``: ``R_P_B = diag(-1, 1, -1)`` (the
mounting docs/wrench.md states; written here again).  The free stream blows along ``+x_O`` at V;
the model's velocity relative to the air at the moment reference point (MRP) is
``v_rel = v_MRP - V x_O`` (the platform's own motion included); with ``(u, v, w)`` its body
components, ``aoa = atan2(w, u)`` and ``sideslip = asin(v / |v_rel|)``.  With this mounting a
platform pitch is the angle of attack (nose up positive) and a platform yaw the sideslip.

Coefficients on ``q S`` (forces), ``q S c`` (pitch) and ``q S b`` (roll, yaw) with the free
stream's dynamic pressure ``q = rho V^2 / 2`` (the motion changes the flow angles, not q):

- lift, drag and side force in wind axes, ``F_W = (-D, Y, -L)``; the wind axes in body components
  ``x_W = (ca cb, sb, sa cb)``, ``y_W = (-ca sb, cb, -sa sb)``, ``z_W = (-sa, 0, ca)``;
- static part at the instantaneous angles: ``CL = CL0 + CLa aoa``,
  ``CD = CD0 + CDk CL_static^2 + CDb2 sideslip^2`` (``CL_static = CL0 + CLa aoa``),
  ``CY = CYb sideslip``, ``Cl = Clb sideslip``, ``Cm = Cm0 + Cma aoa``, ``Cn = Cnb sideslip``;
- dynamic part (helpers/dynamic_spec.md), body rates ``(p, q, r)`` and hats ``p b/2V``,
  ``q c/2V``, ``r b/2V``, ``aoa_dot c/2V``, ``sideslip_dot b/2V``: ``CL += CLq q^ + CLadot aoadot^``,
  ``Cm += Cmq q^ + Cmadot aoadot^``, ``Cl += Clp p^ + Clr r^``, ``Cn += Cnr r^ + Cnp p^ +
  Cnbdot sideslipdot^``, ``CY += CYp p^ + CYr r^``;
- moments about the MRP in body axes ``(l, m, n)``; the wrench on the model at P in {O} axes is
  ``[F_O; M_MRP_O + r x F_O]`` with ``r = R mrp_P`` from P to the MRP.

Air: ``rho = (p - e)/(R_d T) + e/(R_v T)``, ``e = RH e_s(T)`` with Buck's (1981) saturation vapour
pressure over water.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from _lab_physics import rate_matrix, rot

R_DRY = 287.05287
R_VAPOUR = 461.495
R_P_B = np.diag([-1.0, 1.0, -1.0])
COEFFICIENTS = ("CD", "CY", "CL", "Cl", "Cm", "Cn")


def saturation_pressure_Pa(temperature_K: np.ndarray) -> np.ndarray:
    """Buck (1981): ``e_s = 611.21 exp((18.678 - t/234.5) t / (257.14 + t))`` Pa, t in deg C."""
    t = np.asarray(temperature_K, float) - 273.15
    return 611.21 * np.exp((18.678 - t / 234.5) * (t / (257.14 + t)))


def moist_air_density(p_Pa: np.ndarray, T_K: np.ndarray, rh: np.ndarray) -> np.ndarray:
    """Density (kg/m^3) of moist air: dry air and water vapour as ideal gases (Dalton)."""
    e = np.asarray(rh, float) * saturation_pressure_Pa(T_K)
    return (np.asarray(p_Pa, float) - e) / (R_DRY * np.asarray(T_K, float)) + e / (
        R_VAPOUR * np.asarray(T_K, float)
    )


@dataclass(frozen=True)
class Geometry:
    """Reference area S (m^2), span b (m), chord c (m), moment reference point in {P} (m)."""

    area_m2: float = 0.014646
    span_m: float = 0.2441
    chord_m: float = 0.060
    mrp_P_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class AeroModel:
    """Static coefficients and dynamic derivatives (per rad; see the module docstring)."""

    CL0: float = 0.05
    CLa: float = 4.2
    CLq: float = 6.0
    CLadot: float = 1.5
    CD0: float = 0.025
    CDk: float = 0.06
    CDb2: float = 0.3
    CYb: float = -0.35
    CYp: float = 0.0
    CYr: float = 0.0
    Clb: float = -0.06
    Clp: float = -0.45
    Clr: float = 0.10
    Cm0: float = 0.01
    Cma: float = -0.55
    Cmq: float = -12.0
    Cmadot: float = -4.0
    Cnb: float = 0.09
    Cnr: float = -0.25
    Cnp: float = -0.03
    Cnbdot: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return asdict(self)

    def coefficients(
        self,
        aoa: np.ndarray,
        sideslip: np.ndarray,
        p_hat: np.ndarray | float = 0.0,
        q_hat: np.ndarray | float = 0.0,
        r_hat: np.ndarray | float = 0.0,
        aoadot_hat: np.ndarray | float = 0.0,
        sideslipdot_hat: np.ndarray | float = 0.0,
    ) -> np.ndarray:
        """``[CD, CY, CL, Cl, Cm, Cn]`` (..., 6) (moments about the MRP, body axes)."""
        a, b = np.broadcast_arrays(np.asarray(aoa, float), np.asarray(sideslip, float))
        CL = self.CL0 + self.CLa * a + self.CLq * q_hat + self.CLadot * aoadot_hat
        CD = self.CD0 + self.CDk * (self.CL0 + self.CLa * a) ** 2 + self.CDb2 * b**2
        CY = self.CYb * b + self.CYp * p_hat + self.CYr * r_hat
        Cl = self.Clb * b + self.Clp * p_hat + self.Clr * r_hat
        Cm = self.Cm0 + self.Cma * a + self.Cmq * q_hat + self.Cmadot * aoadot_hat
        Cn = self.Cnb * b + self.Cnr * r_hat + self.Cnp * p_hat + self.Cnbdot * sideslipdot_hat
        return np.stack(np.broadcast_arrays(CD, CY, CL, Cl, Cm, Cn), axis=-1)


def wind_from_body(aoa: np.ndarray, sideslip: np.ndarray) -> np.ndarray:
    """``R_W_B`` (..., 3, 3): rows are the wind axes in body components."""
    ca, sa, cb, sb = np.cos(aoa), np.sin(aoa), np.cos(sideslip), np.sin(sideslip)
    z = np.zeros_like(ca)
    return np.stack(
        [
            np.stack([ca * cb, sb, sa * cb], axis=-1),
            np.stack([-ca * sb, cb, -sa * sb], axis=-1),
            np.stack([-sa, z, ca], axis=-1),
        ],
        axis=-2,
    )


def _flow(
    q: np.ndarray, qd: np.ndarray, V: np.ndarray, mrp_P: np.ndarray
) -> tuple[np.ndarray, ...]:
    """aoa, sideslip, body rates (..., 3), R_O_B (..., 3, 3) at states q, qd."""
    R = rot(q[..., 3:])
    R_O_B = R @ R_P_B
    w_O = np.einsum("...ij,...j->...i", rate_matrix(q[..., 3:]), qd[..., 3:])
    r = np.einsum("...ij,j->...i", R, mrp_P)
    v_rel = qd[..., :3] + np.cross(w_O, r)
    v_rel = v_rel - np.stack([V, np.zeros_like(V), np.zeros_like(V)], axis=-1)
    vB = np.einsum("...ji,...j->...i", R_O_B, v_rel)  # R_B_O v = R_O_B^T v
    aoa = np.arctan2(vB[..., 2], vB[..., 0])
    sideslip = np.arcsin(np.clip(vB[..., 1] / np.linalg.norm(vB, axis=-1), -1.0, 1.0))
    rates = np.einsum("...ji,...j->...i", R_O_B, w_O)
    return aoa, sideslip, rates, R_O_B


@dataclass(frozen=True)
class AeroLoads:
    """The model's loads over a batch of states (each field (...,) or (..., k))."""

    wrench_P_O: np.ndarray  # (..., 6) on the model, at P, {O} axes
    wrench_mrp_O: np.ndarray  # (..., 6) forces {O}, moments about the MRP in {O} axes
    force_B_N: np.ndarray  # (..., 3) body axes
    moment_B_Nm: np.ndarray  # (..., 3) about the MRP, body axes
    coefficients: np.ndarray  # (..., 6) CD, CY, CL, Cl, Cm, Cn
    aoa_rad: np.ndarray
    sideslip_rad: np.ndarray
    rates_B: np.ndarray  # (..., 3) p, q, r (rad/s)
    q_Pa: np.ndarray
    R_O_B: np.ndarray  # (..., 3, 3) body axes in {O}
    r_mrp_O: np.ndarray  # (..., 3) from P to the MRP, {O} axes


def wrench_from_coefficients(
    C: np.ndarray,
    aoa: np.ndarray,
    sideslip: np.ndarray,
    R_O_B: np.ndarray,
    q_Pa: np.ndarray,
    geom: Geometry,
    r_mrp_O: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The loads of coefficients ``C`` (..., 6) (``CD, CY, CL, Cl, Cm, Cn``) at the flow angles,
    attitude ``R_O_B`` and dynamic pressure: the wrench at P in {O} (..., 6), the wrench with its
    moment about the MRP in {O} axes (..., 6), the body force and the body moment (..., 3).
    Linear in C at a fixed state."""
    qS = np.asarray(q_Pa, float) * geom.area_m2
    F_W = np.stack([-C[..., 0], C[..., 1], -C[..., 2]], axis=-1) * qS[..., None]
    F_B = np.einsum("...ji,...j->...i", wind_from_body(aoa, sideslip), F_W)  # R_W_B^T F_W
    M_B = C[..., 3:] * (qS[..., None] * np.array([geom.span_m, geom.chord_m, geom.span_m]))
    F_O = np.einsum("...ij,...j->...i", R_O_B, F_B)
    M_O = np.einsum("...ij,...j->...i", R_O_B, M_B)
    W_P = np.concatenate([F_O, M_O + np.cross(r_mrp_O, F_O)], axis=-1)
    return W_P, np.concatenate([F_O, M_O], axis=-1), F_B, M_B


def aero_loads(
    model: AeroModel,
    geom: Geometry,
    q: np.ndarray,
    qd: np.ndarray | None,
    qdd: np.ndarray | None,
    V: np.ndarray,
    rho: np.ndarray,
    step_s: float = 1e-5,
) -> AeroLoads:
    """The model's loads at states ``q, qd, qdd`` (..., 6) (qd, qdd None: at rest) in a free
    stream V (m/s), density rho (kg/m^3) (broadcast to the states).  ``aoa_dot`` and
    ``sideslip_dot`` are central differences along the path over ``step_s`` (the state advanced
    by ``qd`` and ``qdd``).  Where V is 0 the loads are 0."""
    q = np.asarray(q, dtype=np.float64)
    qd = np.zeros_like(q) if qd is None else np.asarray(qd, dtype=np.float64)
    qdd = np.zeros_like(q) if qdd is None else np.asarray(qdd, dtype=np.float64)
    shape = q.shape[:-1]
    V = np.broadcast_to(np.asarray(V, float), shape).copy()
    rho = np.broadcast_to(np.asarray(rho, float), shape)
    on = V > 0
    Vs = np.where(on, V, 1.0)
    mrp = np.asarray(geom.mrp_P_m, float)
    aoa, beta, rates, R_O_B = _flow(q, qd, Vs, mrp)
    h = step_s
    ap, bp, _, _ = _flow(q + h * qd, qd + h * qdd, Vs, mrp)
    am, bm, _, _ = _flow(q - h * qd, qd - h * qdd, Vs, mrp)
    aoadot, betadot = (ap - am) / (2 * h), (bp - bm) / (2 * h)
    b, c = geom.span_m, geom.chord_m
    C = model.coefficients(
        aoa,
        beta,
        p_hat=rates[..., 0] * b / (2 * Vs),
        q_hat=rates[..., 1] * c / (2 * Vs),
        r_hat=rates[..., 2] * b / (2 * Vs),
        aoadot_hat=aoadot * c / (2 * Vs),
        sideslipdot_hat=betadot * b / (2 * Vs),
    )
    qbar = np.where(on, 0.5 * rho * V * V, 0.0)
    r = np.einsum("...ij,j->...i", rot(q[..., 3:]), mrp)
    W_P, W_mrp, F_B, M_B = wrench_from_coefficients(C, aoa, beta, R_O_B, qbar, geom, r)
    return AeroLoads(
        wrench_P_O=W_P,
        wrench_mrp_O=W_mrp,
        force_B_N=F_B,
        moment_B_Nm=M_B,
        coefficients=np.where(on[..., None], C, np.nan),
        aoa_rad=aoa,
        sideslip_rad=beta,
        rates_B=rates,
        q_Pa=qbar,
        R_O_B=R_O_B,
        r_mrp_O=r,
    )
