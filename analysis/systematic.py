"""The systematic parts of a point's uncertainty: each source's covariance, where its numbers come
from, and their degrees of freedom.

A point's wrench has a *random* part (the noise of its own window: the load cells' long-run
covariance, the camera's pose noise) and *systematic* parts: errors that are the same for every
point of a campaign because they come from a calibration or a stated accuracy.  This module gives,
per point and per source, the covariance (s, 6, 6) of the wrench at P in {O} axes (N, N m), and
for the coefficients the covariance from the tunnel instruments.  The expanded uncertainty U95 of
the GUM (JCGM 100:2008, annex G) and AIAA S-071A, ``U = k u_c`` with ``k = t_p(nu_eff)`` at the
Welch–Satterthwaite degrees of freedom, is :func:`cdpr.analysis.uncertainty.expanded_uncertainty`
(its ``term_dof`` takes the degrees of freedom given here, its ``extra_systematic_u2`` the
instruments' part of the coefficients).

The sources, where their numbers come from and where they enter:

- **load-cell calibration** (``loadcell_calibration``): each cable's straight line
  ``T = (counts - offset) gain`` fitted by ``cdpr calibrate loadcells``, with the fit's parameter
  covariance (``sd_offset_counts``, ``sd_gain_N_per_count``, ``corr_offset_gain`` and ``n_points`` in
  the calibration file).  With ``e_o = gain * d_offset`` (N) and ``e_g = d_gain / gain`` the reading
  errs by ``dT = -e_o + T e_g``.  Degrees of freedom ``n_points - 2`` per cable.
- **rig geometry** (``rig_geometry``): the anchors ``b_i`` and attachment points ``pp_i`` known to
  ``anchor_sd_m`` / ``attach_sd_m`` (σ per coordinate; rig file, per cable or in ``[uncertainty]``),
  else :func:`default_geometry_sd` (ISO 2768-1 class m, flag ``rig_geometry_sd_default``).  Entered
  by the analytic Jacobian of ``-A(q) T`` with respect to ``b_i`` and ``pp_i``
  (:func:`geometry_jacobian`).  Type B: infinite degrees of freedom.
- **interaction matrix** (``interaction_matrix``): ``W' = K W`` (or the second-order model) fitted by
  ``cdpr calibrate balance``; its covariance is ``cov(K[i, j], K[k, l]) = S[i, k] M[j, l]`` (a
  multivariate least-squares fit: residual covariance S, ``M = (X^T X)^-1`` of the regressors),
  so a point's corrected wrench errs with covariance ``S (x^T M x)`` (:func:`interaction_covariance`).
  Degrees of freedom: check loads minus regressors.
- **tunnel instruments**: airspeed, static pressure, temperature and humidity to their stated
  accuracy (:class:`InstrumentAccuracy`, the test matrix's ``[instruments]``), through
  ``q = rho V^2 / 2`` and the moist-air density into the coefficients ``C ∝ 1/q``:
  ``dC = -C dq/q`` (:func:`flow_coefficient_covariance`).  Type B.

What the tare cancels (a point i reduced against a wind-off tare j, ``W = -A_i T_i + A_j T_j`` plus
the weight model's small pose difference; ``W = A (T_j - T_i)`` at one pose):

- the zero error cancels exactly: both readings carry ``-e_o``, and ``A_i e_o - A_j e_o = 0`` at
  one pose; the gain error acts on the difference only: ``dW = -A (T_i - T_j) e_g``, i.e.
  ``-A diag(ΔT) e_g`` with ``ΔT = T_w - T_0``, the wind's load, not the pretension;
- the geometry error: ``dW = -dA_i T_i + dA_j T_j``, at one pose ``-dA (T_w - T_0)``: the
  pretension and the weight (held by ``T_0``) drop out, only the aerodynamic load is turned by the
  geometry error.  Both are computed with each point's own pose and its tare's, so a small pose
  difference between the two is carried exactly to first order.
- Without a tare (weight model or the rig file's mass) the whole tensions act: ``dW = -A dT`` and
  ``-dA T``.  The weight model fitted from wind-off points absorbs part of these errors (its four
  parameters take up what looks like a weight); that part is not credited, so the term is an upper
  bound there.

Overlap: a balance calibration on the same rig absorbs the part of the geometry and gain errors
that is linear in the wrench at the check-load poses; the geometry and calibration terms are then
counted again beside the interaction matrix's, which makes the sum conservative.

The degrees of freedom of each systematic source (``dof`` of :class:`SystematicWrench`) feed the
Welch–Satterthwaite formula (:func:`cdpr.analysis.uncertainty.welch_satterthwaite`); the random
part brings its own (the long-run estimate, :mod:`cdpr.analysis.longrun`).  Pure numpy: arrays in,
arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .balance_model import apply_balance_model, quadratic_terms
from .errors import InputError
from .flow import air_density
from .rig import Rig
from .rotations import rotation_from_euler, skew

FloatArray = NDArray[np.float64]

# ------------------------------------------------------------------------------------------------
# where the numbers come from: defaults and the calibrations' own uncertainty
# ------------------------------------------------------------------------------------------------
ISO_2768_MEDIUM_MM: tuple[tuple[float, float], ...] = (
    (3.0, 0.1),
    (6.0, 0.1),
    (30.0, 0.2),
    (120.0, 0.3),
    (400.0, 0.5),
    (1000.0, 0.8),
    (2000.0, 1.2),
    (4000.0, 2.0),
)
"""ISO 2768-1 general tolerances, class m (medium): (nominal size up to, mm; permissible deviation
±, mm).  Sizes below 0.5 mm take the first row; above 4 m the last row scaled with the size."""

RECTANGULAR: float = 1.0 / math.sqrt(3.0)
"""σ of a rectangular distribution of half-width 1 (GUM 4.3.7): a tolerance ``±a`` is ``a/√3``."""


def iso2768_medium_sd_m(size_m: float) -> float:
    """σ (m) of a dimension of nominal ``size_m`` (m) held to ISO 2768-1 class m: its permissible
    deviation as a rectangular distribution (GUM 4.3.7)."""
    mm = abs(float(size_m)) * 1e3
    for upper, tol in ISO_2768_MEDIUM_MM:
        if mm <= upper:
            return tol * 1e-3 * RECTANGULAR
    return ISO_2768_MEDIUM_MM[-1][1] * mm / ISO_2768_MEDIUM_MM[-1][0] * 1e-3 * RECTANGULAR


def default_geometry_sd(anchors_O_m: ArrayLike, attach_P_m: ArrayLike) -> tuple[float, float]:
    """The default σ per coordinate (m) of the anchors and of the attachment points when the rig
    file gives none: the frame and the platform each built to ISO 2768-1 class m (the general
    tolerance a drawing without tolerances implies), at the size of the largest coordinate of the
    part measured from its datum ({O}'s origin for the frame, P for the platform), as a rectangular
    distribution.  The flat rig (frame about 0.7 m, platform 15 mm): 0.46 mm and 0.12 mm; the cubic
    rig (2 m, 0.15 m): 0.69 mm and 0.29 mm.  An assumption, flagged ``rig_geometry_sd_default``:
    a surveyed frame states its own σ."""
    b = check_trailing(anchors_O_m, "anchors_O_m", (3,))
    pp = check_trailing(attach_P_m, "attach_P_m", (3,))
    return iso2768_medium_sd_m(float(np.abs(b).max())), iso2768_medium_sd_m(float(np.abs(pp).max()))


@dataclass(frozen=True)
class GeometrySd:
    """σ (m) per coordinate of each cable's anchor in {O} and attachment point in {P} (m, 3) each,
    and which cables took the default (m,) (:func:`rig_geometry_sd`)."""

    anchor_sd_m: FloatArray
    attach_sd_m: FloatArray
    defaulted: NDArray[np.bool_]


def rig_geometry_sd(rig: Rig) -> GeometrySd:
    """The rig's geometry σ: the rig file's ``anchor_sd_m`` / ``attach_sd_m`` where given (per cable
    or from ``[uncertainty]``), :func:`default_geometry_sd` where not (``defaulted``)."""
    da, dp = default_geometry_sd(rig.anchors_O_m, rig.attach_P_m)
    a = np.asarray(rig.anchor_sd_m, dtype=np.float64)
    p = np.asarray(rig.attach_sd_m, dtype=np.float64)
    na, np_ = np.isnan(a), np.isnan(p)
    return GeometrySd(np.where(na, da, a), np.where(np_, dp, p), np.asarray((na | np_).any(axis=1)))


@dataclass(frozen=True)
class InstrumentAccuracy:
    """The tunnel instruments' stated accuracy as standard uncertainties (the test matrix's
    ``[instruments]``; each key that is not given takes its default and is named in ``defaulted``).

    airspeed_sd_mps, airspeed_rel_sd: σ of the airspeed, m/s plus a fraction of the reading
    (combined in quadrature); static_pressure_sd_Pa; temperature_sd_K; relative_humidity_sd (a
    fraction, 0.03 = 3 % RH).

    Defaults (stated accuracies ±a taken as rectangular, σ = a/√3, GUM 4.3.7; assumptions, flagged
    ``tunnel_instrument_sd_default``): airspeed ±1 % of reading (a Prandtl tube read by a 0.25 %-of-
    full-scale differential transducer used above a quarter of its range), static pressure ±100 Pa
    (a 0.1 %-class absolute transducer), temperature ±0.4 K (IEC 60751 class B platinum sensor at
    20 °C: ±(0.3 + 0.005 |t|) °C), relative humidity ±3 % RH (a capacitive hygrometer).
    """

    airspeed_sd_mps: float = 0.0
    airspeed_rel_sd: float = 0.01 * RECTANGULAR
    static_pressure_sd_Pa: float = 100.0 * RECTANGULAR
    temperature_sd_K: float = 0.4 * RECTANGULAR
    relative_humidity_sd: float = 0.03 * RECTANGULAR
    defaulted: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        for name in INSTRUMENT_KEYS:
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise InputError(f"{name}: expected a finite number >= 0, got {v!r}")
        unknown = set(self.defaulted) - set(INSTRUMENT_KEYS)
        if unknown:
            raise InputError(f"defaulted: unknown instrument keys {sorted(unknown)}")


INSTRUMENT_KEYS: tuple[str, ...] = (
    "airspeed_sd_mps",
    "airspeed_rel_sd",
    "static_pressure_sd_Pa",
    "temperature_sd_K",
    "relative_humidity_sd",
)
"""The keys of the test matrix's ``[instruments]`` (:class:`InstrumentAccuracy`)."""


@dataclass(frozen=True)
class LoadCellCalibrationSd:
    """The load-cell calibration's uncertainty per cable, in the units the analysis needs.

    cov: (m, 2, 2) covariance of ``(e_o, e_g)``: the zero error in newtons (``gain * d_offset``)
    and the relative gain error (``d_gain / gain``); dof: (m,) degrees of freedom of each fit
    (``n_points - 2``); correlation_given: False when the file gave the two σ without their
    correlation (the term is then bounded, see :func:`loadcell_calibration_covariance`).
    """

    cov: FloatArray
    dof: FloatArray
    correlation_given: bool = True


def loadcell_sd_from_fit(
    gain_N_per_count: ArrayLike,
    sd_offset_counts: ArrayLike,
    sd_gain_N_per_count: ArrayLike,
    corr_offset_gain: ArrayLike | None,
    n_points: ArrayLike,
) -> LoadCellCalibrationSd:
    """:class:`LoadCellCalibrationSd` from the fit statistics a calibration file holds (m,) each
    (``corr_offset_gain`` None: not given).  ``e_o = g d_offset`` has σ ``|g| sd_offset``,
    ``e_g = d_gain / g`` has σ ``sd_gain / |g|``, and their correlation is the fit's."""
    g = as_float_array(gain_N_per_count, "gain_N_per_count").reshape(-1)
    so = np.broadcast_to(as_float_array(sd_offset_counts, "sd_offset_counts"), g.shape)
    sg = np.broadcast_to(as_float_array(sd_gain_N_per_count, "sd_gain_N_per_count"), g.shape)
    n = np.broadcast_to(as_float_array(n_points, "n_points"), g.shape)
    rho = np.zeros_like(g)
    if corr_offset_gain is not None:
        rho = np.broadcast_to(as_float_array(corr_offset_gain, "corr_offset_gain"), g.shape)
    if np.any(g == 0) or not np.all(np.isfinite(g)):
        raise InputError("gain_N_per_count: expected finite, non-zero gains")
    for name, v in (("sd_offset_counts", so), ("sd_gain_N_per_count", sg)):
        if not np.all(np.isfinite(v)) or np.any(v < 0):
            raise InputError(f"{name}: expected finite values >= 0")
    if not np.all(np.isfinite(rho)) or np.any(np.abs(rho) > 1):
        raise InputError("corr_offset_gain: expected correlations in [-1, 1]")
    if not np.all(np.isfinite(n)) or np.any(n < 3):
        raise InputError("n_points: expected >= 3 calibration points per cable")
    s_o, s_g = np.abs(g) * so, sg / np.abs(g)
    cov = np.empty(g.shape + (2, 2))
    cov[:, 0, 0], cov[:, 1, 1] = s_o**2, s_g**2
    cov[:, 0, 1] = cov[:, 1, 0] = rho * s_o * s_g
    return LoadCellCalibrationSd(cov, n - 2.0, corr_offset_gain is not None)


@dataclass(frozen=True)
class BalanceFitCovariance:
    """The covariance of the balance calibration's fit (``cdpr calibrate balance``):
    ``W' = B^T x(W)`` with ``x(W) = W`` (first order, 6 regressors) or ``[W, q(W)]`` (second order,
    27), fitted by least squares on the check loads.  ``cov(B[j, i], B[l, k]) = residual_cov[i, k]
    inverse_gram[j, l]``: residual_cov (6, 6) of the check-load residuals (over ``dof``),
    inverse_gram (p, p) ``(X^T X)^-1`` of the regressors (unscaled units), dof: check loads minus
    p."""

    residual_cov: FloatArray
    inverse_gram: FloatArray
    dof: float

    def __post_init__(self) -> None:
        S = as_float_array(self.residual_cov, "residual_cov")
        M = as_float_array(self.inverse_gram, "inverse_gram")
        if S.shape != (6, 6) or M.shape not in ((6, 6), (27, 27)):
            raise InputError(
                f"residual_cov (6, 6) and inverse_gram (6, 6) or (27, 27) expected, got {S.shape}, "
                f"{M.shape}"
            )
        if not (np.all(np.isfinite(S)) and np.all(np.isfinite(M))):
            raise InputError("residual_cov, inverse_gram: expected finite values")
        if not (self.dof > 0):
            raise InputError(f"dof: expected > 0, got {self.dof}")
        object.__setattr__(self, "residual_cov", S)
        object.__setattr__(self, "inverse_gram", M)

    @property
    def second_order(self) -> bool:
        return bool(self.inverse_gram.shape[0] == 27)


def regression_fit_covariance(
    regressors: ArrayLike, residuals: ArrayLike, ridge_gram: ArrayLike | None = None
) -> BalanceFitCovariance:
    """The fit covariance of a multivariate least-squares fit ``Y = X B`` from its design X (n, p)
    and residuals (n, 6): ``residual_cov = r^T r / (n - p)``, ``inverse_gram = (X^T X)^-1``.  With
    ``ridge_gram`` (p, p), the matrix the fit actually inverted (``X^T X`` plus a ridge), the
    sandwich ``G^-1 X^T X G^-1`` of that estimator."""
    X = as_float_array(regressors, "regressors")
    r = as_float_array(residuals, "residuals")
    if X.ndim != 2 or r.ndim != 2 or r.shape[0] != X.shape[0] or r.shape[1] != 6:
        raise InputError(f"regressors (n, p), residuals (n, 6) expected, got {X.shape}, {r.shape}")
    n, p = X.shape
    if n <= p:
        raise InputError(f"regressors: {n} rows leave no degrees of freedom for {p} regressors")
    XtX = X.T @ X
    if ridge_gram is None:
        M = np.linalg.pinv(XtX)
    else:
        Gi = np.linalg.inv(as_float_array(ridge_gram, "ridge_gram"))
        M = Gi @ XtX @ Gi
    return BalanceFitCovariance(r.T @ r / (n - p), 0.5 * (M + M.T), float(n - p))


# ------------------------------------------------------------------------------------------------
# the wrench's covariance per source
# ------------------------------------------------------------------------------------------------
def loadcell_calibration_covariance(
    A: ArrayLike,
    tensions_N: ArrayLike,
    calibration: LoadCellCalibrationSd,
    A_tare: ArrayLike | None = None,
    tare_tensions_N: ArrayLike | None = None,
) -> FloatArray:
    """Covariance (s, 6, 6) of ``W = -A T + A_tare T_tare`` from the load cells' calibration errors.

    A: (s, 6, m) structure matrix at each point; tensions_N: (s, m); A_tare, tare_tensions_N: the
    tare's (zeros where a point has no tare: then the absolute method ``-A T``).  Cable c's
    ``(e_o, e_g)`` move its reading by ``-e_o + T e_g``, so W moves by
    ``(A - A_tare)[:, c] e_o - (A T - A_tare T_tare)[:, c] e_g``; the cables' calibrations are
    independent.  Without the correlation (``correlation_given`` False) the bound
    ``2 (C_o + C_g)`` (``(a + b)(a + b)^T <= 2 (a a^T + b b^T)``) replaces the unknown cross term.
    """
    a = check_trailing(A, "A", (6, np.shape(A)[-1]), allow_nan=True)
    m = a.shape[-1]
    T = check_trailing(tensions_N, "tensions_N", (m,), allow_nan=True)
    C = as_float_array(calibration.cov, "calibration.cov")
    if C.shape != (m, 2, 2):
        raise InputError(f"calibration.cov: expected ({m}, 2, 2), got {C.shape}")
    a0 = np.zeros_like(a) if A_tare is None else check_trailing(A_tare, "A_tare", (6, m), True)
    T0 = (
        np.zeros_like(T)
        if tare_tensions_N is None
        else check_trailing(tare_tensions_N, "tare_tensions_N", (m,), allow_nan=True)
    )
    d_o = a - a0  # (s, 6, m): column c is dW/de_o of cable c
    d_g = -(a * T[..., None, :] - a0 * T0[..., None, :])  # dW/de_g
    if calibration.correlation_given:
        J = np.stack([d_o, d_g], axis=-1)  # (s, 6, m, 2)
        return np.asarray(np.einsum("sicp,cpq,sjcq->sij", J, C, J), dtype=np.float64)
    var_o, var_g = C[:, 0, 0], C[:, 1, 1]
    return np.asarray(
        2.0
        * (
            np.einsum("sic,c,sjc->sij", d_o, var_o, d_o)
            + np.einsum("sic,c,sjc->sij", d_g, var_g, d_g)
        ),
        dtype=np.float64,
    )


def geometry_jacobian(
    anchors_O_m: ArrayLike, attach_P_m: ArrayLike, poses: ArrayLike, tensions_N: ArrayLike
) -> FloatArray:
    """``d(-A(q) T)/d(b_c, pp_c)`` (s, m, 6, 6): for each cable c, the derivative of the cables'
    load ``-A T`` at P in {O} with respect to its anchor ``b_c`` (columns 0-2, {O}) and its
    attachment point ``pp_c`` (columns 3-5, {P}), analytic.

    With ``r = R pp``, ``l = b - p - r``, ``L = |l|``, ``u = l / L``, ``P = I - u u^T``, the column
    ``a = [u; r x u]`` varies as ``da/db = [P/L; [r]x P/L]`` and
    ``da/dpp = [-P R/L; -[u]x R - [r]x P R/L]``; the load ``-T_c a_c`` as ``-T_c`` times these.
    """
    b = check_trailing(anchors_O_m, "anchors_O_m", (3,))
    m = b.shape[0]
    pp = check_trailing(attach_P_m, "attach_P_m", (3,))
    q = check_trailing(poses, "poses", (6,))
    T = check_trailing(tensions_N, "tensions_N", (m,))
    R = rotation_from_euler(q[..., 3:])  # (s, 3, 3)
    r = np.einsum("sij,cj->sci", R, pp)  # (s, m, 3)
    lv = b[None] - q[:, None, :3] - r
    L = np.linalg.norm(lv, axis=-1)
    if np.any(L < 1e-12):
        raise InputError("geometry_jacobian: a cable has zero length")
    u = lv / L[..., None]
    P = (np.eye(3) - u[..., :, None] * u[..., None, :]) / L[..., None, None]  # (s, m, 3, 3)
    rx, ux = skew(r), skew(u)
    PR = P @ R[:, None]  # (s, m, 3, 3)
    J = np.empty(q.shape[:-1] + (m, 6, 6))
    J[..., :3, :3] = P
    J[..., 3:, :3] = rx @ P
    J[..., :3, 3:] = -PR
    J[..., 3:, 3:] = -ux @ R[:, None] - rx @ PR
    return np.asarray(-T[..., None, None] * J, dtype=np.float64)


def _per_coordinate(value: ArrayLike, m: int, name: str) -> FloatArray:
    """σ per cable and coordinate (m, 3) from a scalar, (m,) or (m, 3); finite and >= 0."""
    v = as_float_array(value, name)
    if v.shape == (m,):
        v = v[:, None]
    if v.ndim > 2 or (v.ndim and v.shape not in ((m, 1), (m, 3))):
        raise InputError(f"{name}: expected a scalar, ({m},) or ({m}, 3), got {v.shape}")
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise InputError(f"{name}: expected finite values >= 0")
    return np.array(np.broadcast_to(v, (m, 3)), dtype=np.float64)


def geometry_covariance(
    anchors_O_m: ArrayLike,
    attach_P_m: ArrayLike,
    anchor_sd_m: ArrayLike,
    attach_sd_m: ArrayLike,
    poses: ArrayLike,
    tensions_N: ArrayLike,
    tare_poses: ArrayLike | None = None,
    tare_tensions_N: ArrayLike | None = None,
) -> FloatArray:
    """Covariance (s, 6, 6) of ``W = -A(q) T + A(q_tare) T_tare`` from the anchor and attachment
    errors (independent per coordinate, σ ``anchor_sd_m``, ``attach_sd_m``: scalars, (m,) or
    (m, 3)).  Where a point has no tare pass its own pose and zero tare tensions (the absolute
    method: the full tensions act).  Linear in the geometry errors (second-order terms are of
    relative size σ/L, below 1e-3 for millimetres on cables of a metre)."""
    b = check_trailing(anchors_O_m, "anchors_O_m", (3,))
    m = b.shape[0]
    sd = np.concatenate(
        [
            _per_coordinate(anchor_sd_m, m, "anchor_sd_m"),
            _per_coordinate(attach_sd_m, m, "attach_sd_m"),
        ],
        axis=1,
    )  # (m, 6)
    J = geometry_jacobian(b, attach_P_m, poses, tensions_N)
    if tare_tensions_N is not None:
        qt = poses if tare_poses is None else tare_poses
        J = J - geometry_jacobian(b, attach_P_m, qt, tare_tensions_N)
    Js = J * sd[None, :, None, :]
    return np.asarray(np.einsum("scik,scjk->sij", Js, Js), dtype=np.float64)


def interaction_covariance(wrench: ArrayLike, fit: BalanceFitCovariance) -> FloatArray:
    """Covariance (s, 6, 6) of the corrected wrench ``W' = B^T x(W)`` from the fit's own error, at
    the uncorrected wrenches (s, 6): ``residual_cov * (x^T inverse_gram x)`` (the variance of a
    least-squares prediction, per output the residual variance times the regressors' leverage)."""
    w = check_trailing(wrench, "wrench", (6,), allow_nan=True)
    x = np.concatenate([w, quadratic_terms(np.nan_to_num(w))], axis=-1) if fit.second_order else w
    lev = np.einsum("si,ij,sj->s", x, fit.inverse_gram, x)
    return np.asarray(lev[:, None, None] * fit.residual_cov, dtype=np.float64)


# ------------------------------------------------------------------------------------------------
# the tunnel instruments: q and the coefficients
# ------------------------------------------------------------------------------------------------
ISA_TEMPERATURE_K: float = 288.15
"""Where a point has no temperature (the stream's density only), the density's sensitivities are
taken at the ISA sea-level temperature (they enter as σ/T: a 5 % error in a small term)."""


@dataclass(frozen=True)
class FlowUncertainty:
    """The tunnel instruments' part of each point's coefficients.

    cov: (s, 6, 6) covariance of ``[CD, CY, CL, Cl, Cm, Cn]`` (``C C^T (σ_q/q)^2``); q_rel_sd,
    density_rel_sd, airspeed_rel_sd: (s,) relative σ of q, ρ and V; humidity_unknown: (s,) points
    whose density was taken dry for want of a humidity (σ covers the whole 0..1 range then).
    """

    cov: FloatArray
    q_rel_sd: FloatArray
    density_rel_sd: FloatArray
    airspeed_rel_sd: FloatArray
    humidity_unknown: NDArray[np.bool_]


def flow_coefficient_covariance(
    coefficients: ArrayLike,
    airspeed_mps: ArrayLike,
    density_kgpm3: ArrayLike,
    static_pressure_Pa: ArrayLike,
    temperature_K: ArrayLike,
    relative_humidity: ArrayLike,
    accuracy: InstrumentAccuracy,
) -> FlowUncertainty:
    """The coefficients' covariance from the instruments' accuracy (per point, (s,) inputs; the
    coefficients (s, 6)).

    ``q = rho V^2 / 2`` so ``σ_q/q = sqrt((σ_ρ/ρ)^2 + 4 (σ_V/V)^2)`` (the instruments' errors
    independent), ``σ_V^2 = airspeed_sd^2 + (airspeed_rel_sd V)^2``; ``σ_ρ`` from p, T and RH
    through the moist-air density (:func:`cdpr.analysis.flow.air_density`; its partial derivatives
    by differences: exact for p and RH, in which it is linear, central for T).  Where p or T is
    missing (NaN: the stream's density) the sensitivities are taken dry at ``ISA_TEMPERATURE_K`` and
    ``p = rho R T``; where RH is missing (dry air assumed) its σ covers the unknown humidity,
    ``1/√3`` (the rms of a humidity anywhere in 0..1 about the dry value).  ``C ∝ 1/q``:
    ``dC = -C dq/q``, so ``cov = C C^T (σ_q/q)^2``.  Points with a NaN coefficient or speed get NaN.
    """
    from .aero import SPECIFIC_GAS_CONSTANT_AIR_JPKGK

    C = check_trailing(coefficients, "coefficients", (6,), allow_nan=True)
    s = C.shape[0]

    def vec(v: ArrayLike, name: str) -> FloatArray:
        return np.array(np.broadcast_to(as_float_array(v, name), (s,)), dtype=np.float64)

    V = vec(airspeed_mps, "airspeed_mps")
    rho = vec(density_kgpm3, "density_kgpm3")
    p = vec(static_pressure_Pa, "static_pressure_Pa")
    TK = vec(temperature_K, "temperature_K")
    rh = vec(relative_humidity, "relative_humidity")
    acc = accuracy
    sd_V = np.sqrt(acc.airspeed_sd_mps**2 + (acc.airspeed_rel_sd * V) ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        v_rel = sd_V / np.abs(V)
    known = np.isfinite(p) & np.isfinite(TK) & (p > 0) & (TK > 0)
    no_rh = ~np.isfinite(rh)
    T_use = np.where(known, TK, ISA_TEMPERATURE_K)
    p_use = np.where(known, p, rho * SPECIFIC_GAS_CONSTANT_AIR_JPKGK * ISA_TEMPERATURE_K)
    rh_use = np.where(no_rh | ~known, 0.0, rh)
    ok = np.isfinite(p_use) & (p_use > 0) & np.isfinite(rho) & (rho > 0)
    rho_rel = np.full(s, np.nan)
    if ok.any():
        P, T, H = p_use[ok], T_use[ok], rh_use[ok]
        r0 = air_density(P, T, H)
        h_T = 1e-3
        d_p = (air_density(P + 1.0, T, H) - r0) / 1.0
        d_T = (air_density(P, T + h_T, H) - air_density(P, T - h_T, H)) / (2 * h_T)
        H2 = np.where(H > 0.5, H - 0.1, H + 0.1)  # linear in RH: any step is exact
        d_h = (air_density(P, T, H2) - r0) / (H2 - H)
        sd_h = np.where(no_rh[ok], RECTANGULAR, acc.relative_humidity_sd)
        var = (d_p * acc.static_pressure_sd_Pa) ** 2 + (d_T * acc.temperature_sd_K) ** 2
        var = var + (d_h * sd_h) ** 2
        rho_rel[ok] = np.sqrt(var) / r0
    q_rel = np.sqrt(rho_rel**2 + 4.0 * v_rel**2)
    cov = C[:, :, None] * C[:, None, :] * (q_rel**2)[:, None, None]
    return FlowUncertainty(
        np.asarray(cov, dtype=np.float64), q_rel, rho_rel, v_rel, np.asarray(no_rh & known)
    )


# ------------------------------------------------------------------------------------------------
# every systematic term of the wrench, for the core
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SystematicWrench:
    """The systematic covariances of each point's *uncorrected* wrench (the one the balance
    calibration multiplies), by source: terms name -> (s, 6, 6); dof name -> degrees of freedom of
    that source (the load-cell calibration's: the smallest over the cables); flags word -> (s,)
    mask."""

    terms: dict[str, FloatArray]
    dof: dict[str, float]
    flags: dict[str, NDArray[np.bool_]]


def systematic_wrench_covariance(
    rig: Rig,
    poses: ArrayLike,
    tensions_N: ArrayLike,
    tare_index: ArrayLike,
    wrench: ArrayLike,
    loadcell: LoadCellCalibrationSd | None = None,
    balance_fit: BalanceFitCovariance | None = None,
    interaction: ArrayLike | None = None,
    second_order: tuple[ArrayLike, ArrayLike] | None = None,
) -> SystematicWrench:
    """The load-cell calibration, rig geometry and interaction-matrix covariances of every point.

    rig: its geometry σ from :func:`rig_geometry_sd` (flag ``rig_geometry_sd_default`` on every
    point with a wrench when a cable took the default); poses (s, 6), tensions_N (s, m): each
    point's mean pose and tensions; tare_index (s,): the point that served as its tare (-1: none,
    the absolute method's full tensions act); wrench (s, 6): the uncorrected wrench at P (NaN:
    the point has none and gets NaN terms).

    loadcell: the calibration's uncertainty (None: the term is left out and every point with a
    wrench is flagged ``loadcell_calibration_sd_not_given``; a file with σ but no correlation:
    the bound of :func:`loadcell_calibration_covariance`, flag
    ``loadcell_calibration_correlation_not_given``).  interaction / second_order: the balance
    calibration applied after this term (None: no balance term); balance_fit: its fit covariance
    (None with a calibration applied: flag ``interaction_matrix_sd_not_given``).

    The interaction matrix's term is returned as the *equivalent error of the uncorrected wrench*,
    ``J^-1 C J^-T`` with ``J`` the balance model's Jacobian: ``(K + dK) W = K (W + K^-1 dK W)``, so
    the balance stage's ``J C J^T``, which carries every term, gives back ``C`` exactly.
    """
    q = check_trailing(poses, "poses", (6,), allow_nan=True)
    s = q.shape[0]
    m = rig.n_cables
    T = check_trailing(tensions_N, "tensions_N", (m,), allow_nan=True)
    W = check_trailing(wrench, "wrench", (6,), allow_nan=True)
    j = np.asarray(tare_index, dtype=np.int64).reshape(-1)
    if T.shape[0] != s or W.shape[0] != s or j.shape[0] != s:
        raise InputError(f"poses, tensions_N, wrench, tare_index: expected {s} points each")
    ok = np.isfinite(q).all(axis=1) & np.isfinite(T).all(axis=1) & np.isfinite(W).all(axis=1)
    has = ok & (j >= 0)
    jj = np.where(has, j, np.arange(s))
    ok &= ~has | (np.isfinite(q[jj]).all(axis=1) & np.isfinite(T[jj]).all(axis=1))
    has &= ok
    idx = np.flatnonzero(ok)
    qi, Ti = q[idx], T[idx]
    qj = np.where(has[idx, None], q[jj[idx]], qi)
    Tj = np.where(has[idx, None], T[jj[idx]], 0.0)
    terms: dict[str, FloatArray] = {}
    dof: dict[str, float] = {}
    flags: dict[str, NDArray[np.bool_]] = {}

    def full(c: FloatArray) -> FloatArray:
        out = np.full((s, 6, 6), np.nan)
        out[idx] = c
        return out

    gsd = rig_geometry_sd(rig)
    terms["rig_geometry"] = full(
        geometry_covariance(
            rig.anchors_O_m, rig.attach_P_m, gsd.anchor_sd_m, gsd.attach_sd_m, qi, Ti, qj, Tj
        )
    )
    dof["rig_geometry"] = math.inf
    flags["rig_geometry_sd_default"] = ok & bool(gsd.defaulted.any())
    if loadcell is None:
        flags["loadcell_calibration_sd_not_given"] = ok.copy()
    else:
        from .kinematics import structure_matrix

        Ai = structure_matrix(
            rig.anchors_O_m, rig.attach_P_m, qi[:, :3], rotation_from_euler(qi[:, 3:])
        )
        Aj = structure_matrix(
            rig.anchors_O_m, rig.attach_P_m, qj[:, :3], rotation_from_euler(qj[:, 3:])
        )
        Aj = np.where(has[idx, None, None], Aj, 0.0)
        terms["loadcell_calibration"] = full(
            loadcell_calibration_covariance(Ai, Ti, loadcell, Aj, Tj)
        )
        dof["loadcell_calibration"] = float(np.min(loadcell.dof))
        flags["loadcell_calibration_correlation_not_given"] = ok & (not loadcell.correlation_given)
    K1, K2 = (second_order[0], second_order[1]) if second_order is not None else (interaction, None)
    if K1 is not None:
        if balance_fit is None:
            flags["interaction_matrix_sd_not_given"] = ok.copy()
        else:
            if balance_fit.second_order != (K2 is not None):
                raise InputError(
                    "balance_fit: its regressors do not match the balance model applied "
                    f"({'second' if K2 is not None else 'first'} order)"
                )
            C = interaction_covariance(W[idx], balance_fit)
            _, J = apply_balance_model(W[idx], np.asarray(K1, dtype=np.float64), K2)
            Ji = np.linalg.inv(J)
            terms["interaction_matrix"] = full(Ji @ C @ np.swapaxes(Ji, -1, -2))
            dof["interaction_matrix"] = float(balance_fit.dof)
    return SystematicWrench(terms, dof, flags)
