"""Per-point corrections a tunnel lab applies: zero drift, wall corrections, repeatability.

Each function is pure (arrays in, arrays out), vectorised over points, and returns its correction,
its sigma and a :class:`~cdpr.analysis.records.CorrectionRecord` naming the formula's source.

Sources (named per function):

- BRP = Barlow, Rae & Pope, *Low-Speed Wind Tunnel Testing*, 3rd ed. (Wiley, 1999), ch. 10
  "Boundary corrections II: three-dimensional flow" (solid blockage, wake blockage, the downwash /
  lift-interference correction and streamline curvature for a closed section and an open jet).
- AG-336 = AGARD-AG-336, *Wind Tunnel Wall Correction* (Ewald ed., 1998), ch. 1-2 (classical
  linear corrections; the sign change of the boundary factors for an open jet).

The equations are named in each docstring by what they are ("Thom's short form", ...); the
equation numbers of the book are not quoted because the text was not at hand to check them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array
from .conventions import COEFFICIENTS
from .errors import InputError
from .records import CorrectionRecord

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# ---------------------------------------------------------------------------------------------
# zero drift


@dataclass(frozen=True)
class ZeroDrift:
    """Zero drift of each cable at each point.

    drift_N: (n, m) drift of the wind-off zero at the point's time relative to the reference zero;
      subtract it from the measured tensions.
    sigma_N: (n, m) its standard deviation (propagated from the zeros' sigma).
    no_closing_zero: (n,) True where no zero follows the point in time: the drift there is held
      at the last zero's value, not measured.
    no_opening_zero: (n,) True where no zero precedes the point (held at the first zero's value).
    record: what was done.
    weights: (n, k) ``drift = weights @ zero_T_N``: how much of each zero reading enters each
      point's drift (the same for every cable), so that a point, its tare and the zeros they share
      can be carried as one covariance.
    """

    drift_N: FloatArray
    sigma_N: FloatArray
    no_closing_zero: BoolArray
    no_opening_zero: BoolArray
    record: CorrectionRecord
    weights: FloatArray


def _interp_weights(t: FloatArray, knots: FloatArray) -> FloatArray:
    """(len(t), len(knots)) linear interpolation weights, held constant outside the knots."""
    k = knots.size
    W = np.zeros((t.size, k))
    if k == 1:
        W[:, 0] = 1.0
        return W
    j = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, k - 2)
    w = np.clip((t - knots[j]) / (knots[j + 1] - knots[j]), 0.0, 1.0)
    rows = np.arange(t.size)
    W[rows, j] = 1.0 - w
    W[rows, j + 1] += w
    return W


def zero_drift(
    t_ns: ArrayLike,
    zero_t_ns: ArrayLike,
    zero_T_N: ArrayLike,
    zero_sigma_N: ArrayLike,
    reference_t_ns: int | None = None,
) -> ZeroDrift:
    """Drift of each cable's wind-off zero, interpolated linearly in time between the zeros.

    t_ns: (n,) point times (integer ns); zero_t_ns: (k,) times of the wind-off zero readings,
    strictly increasing; zero_T_N: (k, m) the zero readings (N); zero_sigma_N: (k, m), (m,) or
    scalar, their standard deviations (N); reference_t_ns: the time the drift is measured from
    (default the first zero, i.e. the zero the weight tares were taken against).

    ``drift(t) = sum_j c_j(t) z_j`` with ``c = w(t) - w(t_ref)`` the differences of the linear
    interpolation weights, so ``sigma^2 = sum_j c_j^2 sigma_j^2`` (independent zeros).  Points after
    the last zero get the last zero's value and the flag ``no_closing_zero``: a run without its
    closing zero is never treated as drift-free in silence.
    """
    t = np.asarray(t_ns, dtype=np.int64).astype(np.float64).reshape(-1)
    tk = np.asarray(zero_t_ns, dtype=np.int64).astype(np.float64).reshape(-1)
    z = as_float_array(zero_T_N, "zero_T_N")
    if tk.size < 1:
        raise InputError("zero_t_ns: expected at least one wind-off zero, got none")
    if z.ndim != 2 or z.shape[0] != tk.size:
        raise InputError(f"zero_T_N: expected shape ({tk.size}, m), got {z.shape}")
    if np.any(np.diff(tk) <= 0):
        raise InputError("zero_t_ns: expected strictly increasing times")
    if not np.all(np.isfinite(z)):
        raise InputError("zero_T_N: expected finite values, got NaN or inf")
    s = np.broadcast_to(as_float_array(zero_sigma_N, "zero_sigma_N"), z.shape)
    if np.any(~np.isfinite(s)) or np.any(s < 0):
        raise InputError("zero_sigma_N: expected finite values >= 0 N")
    t_ref = tk[0] if reference_t_ns is None else float(int(reference_t_ns))
    C = _interp_weights(t, tk) - _interp_weights(np.array([t_ref]), tk)
    drift = C @ z
    sigma = np.sqrt((C * C) @ (s * s))
    no_close = t > tk[-1]
    no_open = t < tk[0]
    flags = tuple(
        f for f, bad in (("no_closing_zero", no_close), ("no_opening_zero", no_open)) if bad.any()
    )
    rec = CorrectionRecord(
        name="zero_drift",
        source="linear interpolation in time between wind-off zeros; sigma from independent zeros",
        values={
            "n_zeros": int(tk.size),
            "reference_t_ns": int(t_ref),
            "max_abs_drift_N": float(np.max(np.abs(drift))) if drift.size else 0.0,
            "closing_drift_N": (z[-1] - z[0]).tolist(),
            "n_points_no_closing_zero": int(no_close.sum()),
        },
        flags=flags,
    )
    return ZeroDrift(drift, sigma, no_close, no_open, rec, C)


# ---------------------------------------------------------------------------------------------
# wall corrections

SectionKind = Literal["closed", "open_jet"]


@dataclass(frozen=True)
class WallParameters:
    """What the classical wall corrections need about the section and the model (SI).

    kind: "closed" or "open_jet".
    area_m2: C, the jet (test-section) cross-section area at the model, m^2.
    delta: boundary-correction factor for lift interference (BRP ch. 10 figures; 0.125 for a closed
      circular section, -0.125 for an open circular jet; an octagon is close to the circle).
    tau1: solid-blockage tunnel/model-shape factor (BRP ch. 10, Thom's short form).
    tau2: streamline-curvature factor at a quarter chord behind the wing's quarter chord (BRP ch. 10).
    body_volume_m3, body_K3: the model's volume and body shape factor K3 (BRP ch. 10 figure of K vs
      fineness ratio; about 0.9-0.95 for fineness 6-8).
    wing_volume_m3, wing_K1: the wing's volume and its shape factor K1 (0 volume to lump it into the
      body).
    reference_area_m2: S, the coefficients' reference area.
    lift_slope_per_rad: a = dCL/daoa of the model, for the streamline-curvature lift correction.
    """

    kind: SectionKind
    area_m2: float
    delta: float
    tau1: float
    tau2: float
    body_volume_m3: float
    body_K3: float
    wing_volume_m3: float
    wing_K1: float
    reference_area_m2: float
    lift_slope_per_rad: float

    def __post_init__(self) -> None:
        if self.kind not in ("closed", "open_jet"):
            raise InputError(f"kind: expected 'closed' or 'open_jet', got {self.kind!r}")
        for name in ("area_m2", "reference_area_m2"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise InputError(f"{name}: expected a finite value > 0, got {v}")
        for name in ("body_volume_m3", "wing_volume_m3", "body_K3", "wing_K1", "tau1"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise InputError(f"{name}: expected a finite value >= 0, got {v}")


@dataclass(frozen=True)
class WallCorrections:
    """Wall-corrected longitudinal coefficients and each correction, all (n,).

    eps_solid, eps_wake: solid- and wake-blockage velocity increments (fractions of V);
    q_ratio: ``q_corrected / q_uncorrected = (1 + eps_solid + eps_wake)^2``: divide every force and
    moment coefficient by it (done here for CL, CD, Cm; do it for CY, Cl, Cn with this array);
    delta_aoa_rad: lift-interference (upwash) plus streamline-curvature angle increment;
    delta_cd_induced: induced-drag increment; delta_cl_curvature, delta_cm_curvature: streamline-
    curvature increments; aoa_rad, cl, cd, cm: corrected values; record: sizes and sources.
    """

    eps_solid: FloatArray
    eps_wake: FloatArray
    q_ratio: FloatArray
    delta_aoa_rad: FloatArray
    delta_cd_induced: FloatArray
    delta_cl_curvature: FloatArray
    delta_cm_curvature: FloatArray
    aoa_rad: FloatArray
    cl: FloatArray
    cd: FloatArray
    cm: FloatArray
    record: CorrectionRecord


def solid_blockage(p: WallParameters) -> float:
    """Solid-blockage velocity increment eps_sb (BRP ch. 10, Thom's short form, wing + body).

    Closed section: ``eps_sb = (K1 tau1 V_wing + K3 tau1 V_body) / C^1.5``.
    Open jet: the image system of a free boundary changes the sign of the blockage and reduces its
    size (AG-336 ch. 1-2); ``-0.25 x`` the closed value is taken here, an assumption of this code
    (recorded as ``open_jet_blockage_ratio``), to be replaced by the facility's calibration.
    """
    closed = (p.wing_K1 * p.tau1 * p.wing_volume_m3 + p.body_K3 * p.tau1 * p.body_volume_m3) / (
        p.area_m2**1.5
    )
    return closed if p.kind == "closed" else -0.25 * closed


def wake_blockage(p: WallParameters, cd_u: ArrayLike) -> FloatArray:
    """Wake-blockage velocity increment (BRP ch. 10, Thom's wake blockage, attached flow).

    Closed section: ``eps_wb = S / (4 C) CD_u``.  Open jet: zero (BRP: the jet boundary is free to
    expand, the wake does not accelerate the flow past the model).
    """
    cd = np.asarray(cd_u, dtype=np.float64)
    if p.kind == "open_jet":
        return np.zeros_like(cd)
    return np.asarray(p.reference_area_m2 / (4.0 * p.area_m2) * cd)


def wall_corrections(
    p: WallParameters,
    aoa_u_rad: ArrayLike,
    cl_u: ArrayLike,
    cd_u: ArrayLike,
    cm_u: ArrayLike,
) -> WallCorrections:
    """Classical wall corrections of one test section for n points (BRP ch. 10; AG-336 ch. 1-2).

    Inputs (n,) uncorrected: angle of attack (rad), CL, CD and Cm (about the quarter chord).

    - blockage (BRP ch. 10): ``eps_t = eps_sb + eps_wb``; ``q = q_u (1 + eps_t)^2``, every
      coefficient divided by ``(1 + eps_t)^2``;
    - lift interference / downwash (BRP ch. 10): ``d_aoa_w = delta (S/C) CL`` (rad) and
      ``dCD_i = delta (S/C) CL^2``;
    - streamline curvature (BRP ch. 10): ``d_aoa_sc = tau2 delta (S/C) CL``,
      ``dCL_sc = -d_aoa_sc a``, ``dCm_sc = -0.25 dCL_sc`` (about the quarter chord);
    - corrected: ``aoa = aoa_u + d_aoa_w + d_aoa_sc``, ``CL = CL_q + dCL_sc``,
      ``CD = CD_q + dCD_i``, ``Cm = Cm_q + dCm_sc`` (``_q``: divided by the q ratio).

    Not applied (and said in the record): horizontal buoyancy (needs the section's static-pressure
    gradient) and the tail-downwash moment correction (needs the tail's dCm/d(delta_t)).
    """
    a_u = as_float_array(aoa_u_rad, "aoa_u_rad")
    cl = as_float_array(cl_u, "cl_u")
    cd = as_float_array(cd_u, "cd_u")
    cm = as_float_array(cm_u, "cm_u")
    a_u, cl, cd, cm = np.broadcast_arrays(a_u, cl, cd, cm)
    for name, v in (("aoa_u_rad", a_u), ("cl_u", cl), ("cd_u", cd), ("cm_u", cm)):
        if not np.all(np.isfinite(v)):
            raise InputError(f"{name}: expected finite values, got NaN or inf")
    eps_sb = np.full(a_u.shape, solid_blockage(p))
    eps_wb = wake_blockage(p, cd)
    q_ratio = (1.0 + eps_sb + eps_wb) ** 2
    s_c = p.reference_area_m2 / p.area_m2
    d_aoa_w = p.delta * s_c * cl
    d_cdi = p.delta * s_c * cl * cl
    d_aoa_sc = p.tau2 * p.delta * s_c * cl
    d_cl_sc = -d_aoa_sc * p.lift_slope_per_rad
    d_cm_sc = -0.25 * d_cl_sc
    out_cl = cl / q_ratio + d_cl_sc
    out_cd = cd / q_ratio + d_cdi
    out_cm = cm / q_ratio + d_cm_sc
    d_aoa = d_aoa_w + d_aoa_sc
    rec = CorrectionRecord(
        name="wall_corrections",
        source="Barlow, Rae & Pope 3rd ed. ch. 10 (Thom's solid and wake blockage, lift "
        "interference, streamline curvature); AGARD-AG-336 ch. 1-2 (open jet)",
        values={
            "kind": p.kind,
            "area_m2": p.area_m2,
            "delta": p.delta,
            "tau1": p.tau1,
            "tau2": p.tau2,
            "eps_solid": float(eps_sb.flat[0]) if eps_sb.size else 0.0,
            "eps_wake_max": float(np.max(np.abs(eps_wb))) if eps_wb.size else 0.0,
            "delta_aoa_rad_max": float(np.max(np.abs(d_aoa))) if d_aoa.size else 0.0,
            "delta_cd_induced_max": float(np.max(np.abs(d_cdi))) if d_cdi.size else 0.0,
            "not_applied": "horizontal buoyancy; tail-downwash moment correction",
            "open_jet_blockage_ratio": -0.25 if p.kind == "open_jet" else None,
        },
    )
    return WallCorrections(
        eps_solid=eps_sb,
        eps_wake=eps_wb,
        q_ratio=q_ratio,
        delta_aoa_rad=d_aoa,
        delta_cd_induced=d_cdi,
        delta_cl_curvature=d_cl_sc,
        delta_cm_curvature=d_cm_sc,
        aoa_rad=a_u + d_aoa,
        cl=out_cl,
        cd=out_cd,
        cm=out_cm,
        record=rec,
    )


# ---------------------------------------------------------------------------------------------
# repeatability


@dataclass(frozen=True)
class Repeatability:
    """Measured repeatability against the propagated sigma, per quantity (k,).

    sigma_repeat: pooled standard deviation of the repeat groups; dof: its degrees of freedom;
    sigma_propagated: RMS of the propagated sigma over the repeat points; ratio: their quotient;
    interval: (2, k) the central ``confidence`` interval of the ratio when the propagated sigma is
    right (chi-square with ``dof``, or Fisher's F with ``dof`` and the propagated sigma's own
    degrees of freedom when it is itself an estimate); disagree: (k,) True where the ratio falls
    outside it.
    """

    sigma_repeat: FloatArray
    dof: int
    sigma_propagated: FloatArray
    ratio: FloatArray
    interval: FloatArray
    disagree: NDArray[np.bool_]
    record: CorrectionRecord


def repeatability(
    group: ArrayLike,
    values: ArrayLike,
    sigma_propagated: ArrayLike,
    confidence: float = 0.95,
    dof_propagated: ArrayLike | None = None,
) -> Repeatability:
    """Pooled repeatability sigma from repeat points and its check against the propagated sigma.

    group: (n,) integer group id per point (points with the same id are repeats of one condition;
    groups of one point carry no information and are skipped); values: (n, k) the quantities
    (e.g. the coefficients); sigma_propagated: (n, k) their propagated sigma.

    ``s_p^2 = sum_g sum_i (x_gi - mean_g)^2 / sum_g (n_g - 1)``; if the propagated sigma is right,
    ``dof s_p^2 / sigma^2 ~ chi^2(dof)``, which gives the expected spread of the ratio.  With
    ``dof_propagated`` (n, k), the degrees of freedom of each propagated sigma (the random part's,
    from the data's correlation), the mean propagated variance has ``nu`` by Welch-Satterthwaite
    and ``s_p^2 / sigma^2 ~ F(dof, nu)``: a short, correlated window does not make the test cry
    wolf.
    """
    from scipy.stats import chi2, f

    g = np.asarray(group).reshape(-1)
    x = as_float_array(values, "values")
    sp = as_float_array(sigma_propagated, "sigma_propagated")
    if x.ndim == 1:
        x = x[:, None]
    sp = np.broadcast_to(sp.reshape(x.shape) if sp.size == x.size else sp, x.shape)
    if x.shape[0] != g.size:
        raise InputError(f"values: expected {g.size} rows (one per point), got {x.shape[0]}")
    ids, inverse, counts = np.unique(g, return_inverse=True, return_counts=True)
    keep = counts[inverse] >= 2
    dof = int(np.sum(counts[counts >= 2] - 1))
    if dof < 1:
        raise InputError("group: expected at least one repeated condition (two points, one id)")
    sums = np.zeros((ids.size, x.shape[1]))
    np.add.at(sums, inverse, x)
    means = sums / counts[:, None]
    resid = (x - means[inverse])[keep]
    s_rep = np.sqrt(np.sum(resid**2, axis=0) / dof)
    s_prop = np.sqrt(np.mean(sp[keep] ** 2, axis=0))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = s_rep / s_prop
    if dof_propagated is None:
        lo = np.full(x.shape[1], np.sqrt(chi2.ppf((1 - confidence) / 2, dof) / dof))
        hi = np.full(x.shape[1], np.sqrt(chi2.ppf((1 + confidence) / 2, dof) / dof))
    else:
        nu = np.broadcast_to(as_float_array(dof_propagated, "dof_propagated"), x.shape)[keep]
        v = sp[keep] ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            nu_m = np.sum(v, axis=0) ** 2 / np.sum(np.where(np.isinf(nu), 0.0, v * v / nu), axis=0)
        nu_m = np.where(np.isfinite(nu_m), nu_m, 1e12)
        lo = np.sqrt(f.ppf((1 - confidence) / 2, dof, nu_m))
        hi = np.sqrt(f.ppf((1 + confidence) / 2, dof, nu_m))
    disagree = ~((ratio >= lo) & (ratio <= hi))
    rec = CorrectionRecord(
        name="repeatability",
        source="pooled standard deviation of repeat points; chi-square interval of s/sigma",
        values={
            "dof": dof,
            "n_groups": int(np.sum(counts >= 2)),
            "ratio": ratio.tolist(),
            "interval": [lo.tolist(), hi.tolist()],
            "confidence": confidence,
        },
        flags=("repeatability_disagrees",) if disagree.any() else (),
    )
    interval = np.array([lo, hi])
    return Repeatability(s_rep, dof, s_prop, ratio, interval, disagree, rec)


@dataclass(frozen=True)
class CorrectedCoefficients:
    """All six coefficients with the wall corrections (each (n, 6), order
    :data:`cdpr.analysis.conventions.COEFFICIENTS`) and the corrections themselves.

    coefficients: CL, CD and Cm from :func:`wall_corrections`; CY, Cl and Cn divided by the q
    ratio (blockage only); sd: every σ divided by the q ratio (the corrections' own spread is not
    included); walls: the :class:`WallCorrections` of the points."""

    coefficients: FloatArray
    sd: FloatArray
    walls: WallCorrections


def corrected_coefficients(
    p: WallParameters, aoa_u_rad: ArrayLike, coefficients_u: ArrayLike, sd_u: ArrayLike
) -> CorrectedCoefficients:
    """Wall-corrected coefficients of n points from the uncorrected ones.

    aoa_u_rad: (n,); coefficients_u, sd_u: (n, 6) ``CD, CY, CL, Cl, Cm, Cn`` and their σ."""
    C = as_float_array(coefficients_u, "coefficients_u")
    sd = as_float_array(sd_u, "sd_u")
    if C.ndim != 2 or C.shape[1] != 6 or sd.shape != C.shape:
        raise InputError(f"coefficients_u, sd_u: expected (n, 6) each, got {C.shape}, {sd.shape}")
    k = {c: i for i, c in enumerate(COEFFICIENTS)}
    wc = wall_corrections(p, aoa_u_rad, C[:, k["CL"]], C[:, k["CD"]], C[:, k["Cm"]])
    qr = np.broadcast_to(wc.q_ratio, C.shape[:1])[:, None]
    out = C / qr
    out[:, k["CL"]], out[:, k["CD"]], out[:, k["Cm"]] = wc.cl, wc.cd, wc.cm
    return CorrectedCoefficients(out, sd / qr, wc)
