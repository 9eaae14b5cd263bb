"""Aerodynamic axes, angles and coefficients from the wrench on the platform.

Frames (all right-handed):

- {O} tunnel frame: x downstream along the tunnel axis, y to the left looking downstream, z up.  The
  free stream blows along +x_O, so the model's velocity relative to the air is ``-V x_O``.
- {P} platform frame (pose ``R_O_P``).
- {B} AIAA body axes of the model: x to the nose, y to the right wing, z down.  The model is fixed to
  the platform; its nose direction and its "up" direction in {P} are parameters, by default
  ``nose_P = -x_P`` (nose upstream when the platform is level) and ``up_P = +z_P``, which gives
  ``R_P_B = diag(-1, 1, -1)``.
- {W} AIAA wind axes: x along the model's velocity relative to the air, z in the body x-z plane
  (down at zero angle of attack and sideslip), y completing the frame.

Angles: with ``(u, v, w)`` the components in {B} of the model's velocity relative to the air,
``aoa = atan2(w, u)`` (angle of attack, positive nose up relative to the wind) and
``sideslip = asin(v / V)`` (positive with the wind coming from the right).  With the default
mounting and small angles, ``aoa`` equals the platform pitch and ``sideslip`` its yaw.  The names
``aoa_rad``/``sideslip_rad`` keep them apart from the pose's roll/pitch/yaw.

Loads: the wrench ``W`` (..., 6) on the model is given at P in {O} axes (as
:mod:`cdpr.analysis.wrench` recovers it).  It is moved to the moment reference point (MRP, given in
{P}): ``M_mrp = M_P - r x F`` with ``r = R_O_P mrp_P`` the vector from P to the MRP.  Forces in wind
axes are ``F_W = (-D, Y, -L)`` (drag, side force, lift); moments in body axes at the MRP are
``(l, m, n)`` (roll, pitch, yaw).  Coefficients: ``CD = D/(q S)``, ``CY = Y/(q S)``,
``CL = L/(q S)``, ``Cl = l/(q S b)``, ``Cm = m/(q S c)``, ``Cn = n/(q S b)`` with
``q = rho V^2 / 2`` (Pa), reference area S (m^2), span b (m) and chord c (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .conventions import COEFFICIENTS
from .errors import InputError

FloatArray = NDArray[np.float64]

SPECIFIC_GAS_CONSTANT_AIR_JPKGK: float = 287.05287
"""Specific gas constant of dry air, J/(kg K) (ISA value)."""


def dynamic_pressure(density_kgpm3: ArrayLike, airspeed_mps: ArrayLike) -> FloatArray:
    """Dynamic pressure ``q = rho V^2 / 2`` (Pa) from density (kg/m^3) and airspeed (m/s)."""
    rho = as_float_array(density_kgpm3, "density_kgpm3")
    v = as_float_array(airspeed_mps, "airspeed_mps")
    if np.any(~np.isfinite(rho)) or np.any(rho <= 0):
        raise InputError("density_kgpm3: expected finite values > 0")
    return np.asarray(0.5 * rho * v * v, dtype=np.float64)


def body_axes_in_platform(
    nose_P: ArrayLike = (-1.0, 0.0, 0.0), up_P: ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """Rotation ``R_P_B`` (3, 3): columns are the AIAA body axes x_B, y_B, z_B in {P} components.

    nose_P: direction of the model's nose in {P} (x_B); up_P: the model's "up" (canopy) direction in
    {P}, made orthogonal to the nose (z_B = -up).  Defaults: nose upstream (-x_P), up +z_P.
    """
    x = check_trailing(nose_P, "nose_P", (3,))
    u = check_trailing(up_P, "up_P", (3,))
    if x.ndim != 1 or u.ndim != 1:
        raise InputError("nose_P, up_P: expected single vectors of shape (3,)")
    nx = np.linalg.norm(x)
    if nx < 1e-12:
        raise InputError("nose_P: expected a non-zero vector")
    x = x / nx
    z = -(u - np.dot(u, x) * x)
    nz = np.linalg.norm(z)
    if nz < 1e-9:
        raise InputError("up_P: expected a direction not parallel to nose_P")
    z = z / nz
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def body_from_tunnel(
    R_O_P: ArrayLike, nose_P: ArrayLike = (-1.0, 0.0, 0.0), up_P: ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """Rotation ``R_B_O`` (..., 3, 3) mapping {O} components to AIAA body-axis components.

    ``R_B_O = (R_O_P R_P_B)^T``; apply as ``v_B = R_B_O @ v_O``.
    """
    R = check_trailing(R_O_P, "R_O_P", (3, 3), allow_nan=True)
    R_O_B = R @ body_axes_in_platform(nose_P, up_P)
    return np.swapaxes(R_O_B, -1, -2)


@dataclass(frozen=True)
class ModelGeometry:
    """The model's reference geometry, from one place (the test matrix's ``[model]`` table, or
    options with ``source = "options"``, which the reduction flags).

    area_m2, span_m, chord_m: reference area S, span b, chord c (> 0); mrp_P_m: (3,) moment
    reference point in {P} (m); nose_P, up_P: the mounting (see :func:`body_axes_in_platform`);
    name: the model's name; volume_m3: its volume (the wall corrections' solid blockage; None: not
    given); source: where it came from (``"test matrix"`` or ``"options"``).
    """

    area_m2: float
    span_m: float
    chord_m: float
    mrp_P_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    nose_P: tuple[float, float, float] = (-1.0, 0.0, 0.0)
    up_P: tuple[float, float, float] = (0.0, 0.0, 1.0)
    source: str = "test matrix"
    name: str = "model"
    volume_m3: float | None = None

    def __post_init__(self) -> None:
        for name in ("area_m2", "span_m", "chord_m"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and v > 0):
                raise InputError(f"{name}: expected a finite value > 0, got {v!r}")
        for name in ("mrp_P_m", "nose_P", "up_P"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise InputError(f"{name}: expected 3 finite numbers, got {getattr(self, name)!r}")
        body_axes_in_platform(self.nose_P, self.up_P)


def flow_angles(
    R_O_P: ArrayLike, nose_P: ArrayLike = (-1.0, 0.0, 0.0), up_P: ArrayLike = (0.0, 0.0, 1.0)
) -> tuple[FloatArray, FloatArray]:
    """Angle of attack and sideslip ``(aoa_rad, sideslip_rad)``, each (...,), from the platform attitude.

    The free stream blows along +x_O; the model's velocity relative to the air is ``-x_O`` (unit
    speed).  ``aoa = atan2(w, u)``, ``sideslip = asin(v)`` with ``(u, v, w)`` its body components.
    """
    R_B_O = body_from_tunnel(R_O_P, nose_P, up_P)
    vel_B = -R_B_O[..., :, 0]  # R_B_O @ (-1, 0, 0)
    aoa = np.arctan2(vel_B[..., 2], vel_B[..., 0]) + 0.0  # + 0.0: no negative zeros
    sideslip = np.arcsin(np.clip(vel_B[..., 1], -1.0, 1.0)) + 0.0
    return aoa, sideslip


def wind_from_body(aoa_rad: ArrayLike, sideslip_rad: ArrayLike) -> FloatArray:
    """Rotation ``R_W_B`` (..., 3, 3) mapping body-axis components to wind-axis components.

    Rows are the wind axes in body components: ``x_W = (ca cb, sb, sa cb)``,
    ``y_W = (-ca sb, cb, -sa sb)``, ``z_W = (-sa, 0, ca)``.
    """
    a = as_float_array(aoa_rad, "aoa_rad")
    b = as_float_array(sideslip_rad, "sideslip_rad")
    a, b = np.broadcast_arrays(a, b)
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    R = np.empty(a.shape + (3, 3))
    R[..., 0, :] = np.stack([ca * cb, sb, sa * cb], axis=-1)
    R[..., 1, :] = np.stack([-ca * sb, cb, -sa * sb], axis=-1)
    R[..., 2, :] = np.stack([-sa, np.zeros_like(a), ca], axis=-1)
    return R


def transfer_moment(wrench: ArrayLike, offset_O_m: ArrayLike) -> FloatArray:
    """Move a wrench's moment to another point: ``[F; M - r x F]`` (..., 6) (NaN rows stay NaN).

    wrench: (..., 6) ``[F; M]`` with M about the old point (N, N m); offset_O_m: (..., 3) vector r
    from the old point to the new one, in the same axes as the wrench (m).
    """
    w = check_trailing(wrench, "wrench", (6,), allow_nan=True)
    r = check_trailing(offset_O_m, "offset_O_m", (3,), allow_nan=True)
    F = w[..., :3]
    M = w[..., 3:] - np.cross(r, F)
    return np.concatenate([np.broadcast_to(F, M.shape), M], axis=-1)


def _skew(r: FloatArray) -> FloatArray:
    """``[r]x`` (..., 3, 3) with ``[r]x v = r x v``."""
    rx = np.zeros(r.shape[:-1] + (3, 3))
    rx[..., 0, 1], rx[..., 0, 2] = -r[..., 2], r[..., 1]
    rx[..., 1, 0], rx[..., 1, 2] = r[..., 2], -r[..., 0]
    rx[..., 2, 0], rx[..., 2, 1] = -r[..., 1], r[..., 0]
    return rx


@dataclass(frozen=True)
class AeroAxes:
    """The aerodynamic wrench in the axes a lab reports it in (each field (...,) or more).

    wrench_mrp_O_N_Nm: (..., 6) the wrench with its moment about the MRP, {O} axes;
    wrench_mrp_cov: (..., 6, 6) its covariance (None when none was given);
    aoa_rad, sideslip_rad: angle of attack and sideslip (flow angles, not the pose's
    roll/pitch/yaw); force_B_N, moment_B_Nm: (..., 3) force and moment about the MRP in AIAA body
    axes; drag_N, side_N, lift_N: wind-axis forces ``F_W = (-D, Y, -L)``.
    """

    wrench_mrp_O_N_Nm: FloatArray
    wrench_mrp_cov: FloatArray | None
    aoa_rad: FloatArray
    sideslip_rad: FloatArray
    force_B_N: FloatArray
    moment_B_Nm: FloatArray
    drag_N: FloatArray
    side_N: FloatArray
    lift_N: FloatArray


def aero_axes(
    wrench_O: ArrayLike,
    R_O_P: ArrayLike,
    mrp_P_m: ArrayLike = (0.0, 0.0, 0.0),
    nose_P: ArrayLike = (-1.0, 0.0, 0.0),
    up_P: ArrayLike = (0.0, 0.0, 1.0),
    wrench_cov: ArrayLike | None = None,
) -> AeroAxes:
    """The wrench at the moment reference point and in body and wind axes, with its covariance.

    wrench_O: (..., 6) aerodynamic wrench on the model at P in {O} axes (N, N m); R_O_P:
    (..., 3, 3) platform attitude; mrp_P_m: (3,) moment reference point in {P} (m); nose_P, up_P:
    the mounting (:func:`body_axes_in_platform`); wrench_cov: (..., 6, 6) covariance of
    ``wrench_O``, carried to the MRP as ``X C X^T`` with ``X = [[I, 0], [-[r]x, I]]``.  A NaN in
    a wrench or an attitude gives NaN in that row, never a value at a default attitude.
    """
    w = check_trailing(wrench_O, "wrench_O", (6,), allow_nan=True)
    R = check_trailing(R_O_P, "R_O_P", (3, 3), allow_nan=True)
    r_O = np.einsum("...ij,j->...i", R, check_trailing(mrp_P_m, "mrp_P_m", (3,)))
    W_mrp = transfer_moment(w, r_O)
    R_B_O = body_from_tunnel(R, nose_P, up_P)
    aoa, sideslip = flow_angles(R, nose_P, up_P)
    F_B = np.einsum("...ij,...j->...i", R_B_O, W_mrp[..., :3])
    M_B = np.einsum("...ij,...j->...i", R_B_O, W_mrp[..., 3:])
    F_W = np.einsum("...ij,...j->...i", wind_from_body(aoa, sideslip), F_B)
    cov = None
    if wrench_cov is not None:
        C = check_trailing(wrench_cov, "wrench_cov", (6, 6), allow_nan=True)
        transfer = np.broadcast_to(np.eye(6), r_O.shape[:-1] + (6, 6)).copy()
        transfer[..., 3:, :3] = -_skew(r_O)  # M - r x F
        cov = np.asarray(transfer @ C @ np.swapaxes(transfer, -1, -2), dtype=np.float64)
    return AeroAxes(
        wrench_mrp_O_N_Nm=W_mrp,
        wrench_mrp_cov=cov,
        aoa_rad=aoa,
        sideslip_rad=sideslip,
        force_B_N=F_B,
        moment_B_Nm=M_B,
        drag_N=-F_W[..., 0],
        side_N=F_W[..., 1],
        lift_N=-F_W[..., 2],
    )


COEFFICIENT_NAMES: tuple[str, ...] = COEFFICIENTS
"""Order of the coefficients returned by :func:`coefficient_matrix` (the project's one list,
:data:`cdpr.analysis.conventions.COEFFICIENTS`)."""


@dataclass(frozen=True)
class AeroResult:
    """Aerodynamic angles, loads and coefficients over a batch of samples (each field (...,) or more).

    axes: the angles and loads (:class:`AeroAxes`); coefficients: (..., 6) ``CD, CY, CL, Cl, Cm,
    Cn`` (:data:`COEFFICIENT_NAMES`): wind-axis forces on ``q S``, body-axis moments about the MRP
    on ``q S b`` (roll, yaw) and ``q S c`` (pitch); cov: (..., 6, 6) their covariance from the
    wrench's (None when none was given; the attitude's and q's own errors are not in it).
    """

    axes: AeroAxes
    coefficients: FloatArray
    cov: FloatArray | None

    def __getattr__(self, name: str) -> FloatArray:
        if name in COEFFICIENT_NAMES:
            return self.coefficients[..., COEFFICIENT_NAMES.index(name)]
        if name in AeroAxes.__dataclass_fields__:
            return getattr(self.axes, name)  # type: ignore[no-any-return]
        raise AttributeError(name)


def _check_reference(
    R_O_P: ArrayLike,
    dynamic_pressure_Pa: ArrayLike,
    area_m2: float,
    span_m: float,
    chord_m: float,
    mrp_P_m: ArrayLike,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Checked attitude R (..., 3, 3), dynamic pressure q (Pa, > 0) and the moment reference point
    in {O} axes, ``R_O_P @ mrp_P_m`` (..., 3) in m; reference lengths and area must be > 0."""
    R = check_trailing(R_O_P, "R_O_P", (3, 3))
    q = as_float_array(dynamic_pressure_Pa, "dynamic_pressure_Pa")
    if np.any(~np.isfinite(q)) or np.any(q <= 0):
        raise InputError("dynamic_pressure_Pa: expected finite values > 0 Pa")
    for name, v in (("area_m2", area_m2), ("span_m", span_m), ("chord_m", chord_m)):
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"{name}: expected a finite value > 0, got {v}")
    mrp = check_trailing(mrp_P_m, "mrp_P_m", (3,))
    return R, q, np.einsum("...ij,...j->...i", R, mrp)


def coefficient_matrix(
    R_O_P: ArrayLike,
    dynamic_pressure_Pa: ArrayLike,
    area_m2: float,
    span_m: float,
    chord_m: float,
    mrp_P_m: ArrayLike = (0.0, 0.0, 0.0),
    nose_P: ArrayLike = (-1.0, 0.0, 0.0),
    up_P: ArrayLike = (0.0, 0.0, 1.0),
) -> FloatArray:
    """Linear map ``K`` (..., 6, 6) with ``[CD, CY, CL, Cl, Cm, Cn] = K @ W_O`` at a given attitude.

    ``W_O`` (..., 6) is the aerodynamic wrench at P in {O} axes; the other arguments are those of
    :func:`aero_coefficients`.  For a fixed attitude the coefficients are linear in the wrench, so a
    wrench covariance ``Sigma_W`` gives the coefficient covariance ``K Sigma_W K^T`` (the attitude's
    own error, which turns the axes, is left out: it adds about ``|F| sigma_angle``).
    """
    R, q, r = _check_reference(R_O_P, dynamic_pressure_Pa, area_m2, span_m, chord_m, mrp_P_m)
    R_B_O = body_from_tunnel(R, nose_P, up_P)
    aoa, sideslip = flow_angles(R, nose_P, up_P)
    sign = np.array([-1.0, 1.0, -1.0])[:, None]
    Fmap = sign * (wind_from_body(aoa, sideslip) @ R_B_O)  # (..., 3, 3): (D, Y, L) from F_O
    # moment about the MRP: M - r x F = M - skew(r) F
    rx = _skew(r)
    shape = np.broadcast_shapes(Fmap.shape[:-2], R_B_O.shape[:-2], np.shape(q))
    K = np.zeros(shape + (6, 6))
    K[..., :3, :3] = Fmap
    K[..., 3:, :3] = -R_B_O @ rx
    K[..., 3:, 3:] = R_B_O
    qS = (q * float(area_m2))[..., None, None]
    scale = np.array([1.0, 1.0, 1.0, 1 / float(span_m), 1 / float(chord_m), 1 / float(span_m)])
    return np.asarray(K * scale[:, None] / qS, dtype=np.float64)


def aero_coefficients(
    wrench_O: ArrayLike,
    R_O_P: ArrayLike,
    dynamic_pressure_Pa: ArrayLike,
    area_m2: float,
    span_m: float,
    chord_m: float,
    mrp_P_m: ArrayLike = (0.0, 0.0, 0.0),
    nose_P: ArrayLike = (-1.0, 0.0, 0.0),
    up_P: ArrayLike = (0.0, 0.0, 1.0),
    wrench_cov: ArrayLike | None = None,
) -> AeroResult:
    """Angles, wind-axis forces and the six coefficients from the aerodynamic wrench.

    wrench_O: (..., 6) aerodynamic wrench on the model at P in {O} axes (N, N m), e.g. ``W_ext``.
    R_O_P: (..., 3, 3) platform attitude; dynamic_pressure_Pa: (...,) or scalar, > 0;
    area_m2, span_m, chord_m: reference area, span and chord (> 0); mrp_P_m: (3,) moment reference
    point in {P} (m); nose_P, up_P: the model's mounting (see :func:`body_axes_in_platform`);
    wrench_cov: (..., 6, 6) the wrench's covariance, carried to the coefficients as
    ``K C K^T`` (:func:`coefficient_matrix`).
    """
    w = check_trailing(wrench_O, "wrench_O", (6,))
    K = coefficient_matrix(
        R_O_P, dynamic_pressure_Pa, area_m2, span_m, chord_m, mrp_P_m, nose_P, up_P
    )
    C = np.einsum("...ij,...j->...i", K, w)
    cov = None
    if wrench_cov is not None:
        S = check_trailing(wrench_cov, "wrench_cov", (6, 6))
        cov = np.asarray(K @ S @ np.swapaxes(K, -1, -2), dtype=np.float64)
    axes = aero_axes(w, check_trailing(R_O_P, "R_O_P", (3, 3)), mrp_P_m, nose_P, up_P)
    return AeroResult(axes=axes, coefficients=C, cov=cov)


def attitude_from_flow_angles(
    aoa_rad: ArrayLike,
    sideslip_rad: ArrayLike,
    nose_P: ArrayLike = (-1.0, 0.0, 0.0),
    up_P: ArrayLike = (0.0, 0.0, 1.0),
) -> FloatArray:
    """Platform attitude ``R_O_P`` (..., 3, 3) that sets the model at ``(aoa_rad, sideslip_rad)``.

    The inverse of :func:`flow_angles` on the wings-level family: the wind axes {W} sit in {O} as
    ``x_W = -x_O`` (the model's velocity relative to the air), ``z_W = -z_O`` (down), so
    ``R_O_B = diag(-1, 1, -1) R_W_B`` with ``R_W_B`` from :func:`wind_from_body`, and
    ``R_O_P = R_O_B R_P_B^T``.  With the default mounting (nose upstream, up along +z_P) this is
    roll 0, pitch ``aoa``, yaw ``sideslip`` exactly (Z-Y-X Euler angles, ``Rz(yaw) Ry(pitch)``).
    """
    R_W_B = wind_from_body(aoa_rad, sideslip_rad)
    R_O_W = np.diag([-1.0, 1.0, -1.0])
    R_O_B = R_O_W @ R_W_B
    return np.asarray(R_O_B @ body_axes_in_platform(nose_P, up_P).T, dtype=np.float64)
