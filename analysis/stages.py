"""The stages of the reduction core and their one canonical order.

Every stage is a thin ``@stage`` wrapper around exactly one public pure function of
:mod:`cdpr.analysis` (named in the decorator, and in the table below): it reads the per-point arrays
it needs from :class:`~cdpr.analysis.reduction.Points`, calls that function, and writes back its
result, its σ term and its flags.  :data:`STEADY_STAGES` is the order they run in;
:func:`core_stages` binds a run's settings to them (``cdpr analyze``, ``cdpr wrench`` and the on-line
reduction call it); :func:`stage_table` prints the order with the wrapped functions (the table in
docs/analysis.md is this function's output, and a test keeps the two equal).

Settings that are not per point (the rig, the model geometry, the test section) are bound with
:func:`functools.partial`; a stage whose inputs are missing for a point leaves NaN and a flag there.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .aero import (
    ModelGeometry,
    aero_axes,
    aero_coefficients,
    coefficient_matrix,
    dynamic_pressure,
)
from .balance_model import apply_balance_model
from .check import tension_check
from .conventions import COEFFICIENTS, WRENCH_COLUMNS
from .correction_stages import (
    PointSamples,
    flow_conditions_stage,
    repeatability_stage,
    spectrum_stage,
    wall_corrections_stage,
    wind_points,
    windage_stage,
    zero_drift_stage,
)
from .corrections import WallParameters
from .dynamic_stages import (
    DynamicSamples,
    balance_harmonics_stage,
    clock_offset_stage,
    derivatives_stage,
    inertia_removal_stage,
    motion_fit_stage,
    wrench_harmonics_stage,
)
from .dynamics import inertia_wrench, mean_inertia_covariance
from .errors import InputError
from .kinematics import structure_matrix
from .oscillation import DEFAULT_DYNAMIC, Body, DynamicSettings
from .reduction import (
    POSE,
    POSE_COV,
    STRUCTURE_MATRIX,
    WRENCH,
    Points,
    Stage,
    flag_masks,
    stage,
    with_updates,
)
from .rig import Rig
from .rotations import rotation_from_euler, skew
from .systematic import (
    INSTRUMENT_KEYS,
    BalanceFitCovariance,
    InstrumentAccuracy,
    LoadCellCalibrationSd,
)
from .systematic_stages import flow_uncertainty_stage, systematic_stage
from .tare import TARE_POSE_SD_REL, weight_tare
from .test_section import SectionGeometry
from .uncertainty import expanded_uncertainty, propagate
from .weight import WeightModel, fit_weight_model, weight_model_note

__all__ = [
    "DYNAMIC_STAGES",
    "STEADY_STAGES",
    "DynamicSamples",
    "Corrections",
    "SystematicInputs",
    "PointSamples",
    "ReduceSettings",
    "core_stages",
    "dynamic_stages",
    "flow_conditions_stage",
    "repeatability_stage",
    "spectrum_stage",
    "stage_table",
    "wall_corrections_stage",
    "windage_stage",
    "zero_drift_stage",
]

FloatArray = NDArray[np.float64]


def _attitudes(poses: FloatArray) -> FloatArray:
    """``R_O_P`` (s, 3, 3) of each pose (s, 6); NaN where the pose is not finite."""
    ok = np.isfinite(poses).all(axis=1)
    R = np.full((poses.shape[0], 3, 3), np.nan)
    R[ok] = rotation_from_euler(poses[ok, 3:])
    return R


# ------------------------------------------------------------------------------------------------
# inputs and the load cells' zero
# ------------------------------------------------------------------------------------------------
@stage("input_flags", wraps=flag_masks)
def input_flags(p: Points) -> Points:
    """Raise the flag words the inputs carry (``input_flags``: masked samples and why, no samples,
    no pose, dropped camera frames, a nominal pose covariance, the run's missing streams)."""
    return with_updates(p, flag=flag_masks([str(w) for w in p["input_flags"]]))


# ------------------------------------------------------------------------------------------------
# the cables' load, the weight, the flow
# ------------------------------------------------------------------------------------------------
@stage("structure_matrix", wraps=structure_matrix)
def structure_matrix_stage(p: Points, *, rig: Rig) -> Points:
    """``structure_matrix_O`` (s, 6, m) at each point's measured mean pose
    (:func:`cdpr.analysis.kinematics.structure_matrix`); ``-A T`` is the cables' load.  A point
    without a pose (no usable camera frame) gets NaN and the flag ``no_pose``."""
    q = p[POSE]
    if q.shape[0] and p["tension_N"].shape[1] != rig.n_cables:
        raise InputError(f"tension_N: expected {rig.n_cables} cables for rig {rig.name!r}")
    ok = np.isfinite(q).all(axis=1)
    A = np.full((p.n, 6, rig.n_cables), np.nan)
    A[ok] = structure_matrix(
        rig.anchors_O_m, rig.attach_P_m, q[ok, :3], rotation_from_euler(q[ok, 3:])
    )
    return with_updates(p, arrays={STRUCTURE_MATRIX: A}, flag={"no_pose": ~ok})


@stage("weight_model", wraps=fit_weight_model)
def weight_model_stage(
    p: Points,
    *,
    rig: Rig,
    prior_mass_rel_sd: float = 0.05,
    prior_com_sd_m: float = 0.01,
    model: WeightModel | None = None,
    fit: bool = True,
) -> Points:
    """Fit the weight model from the wind-off points (``tare`` and ``zero`` with finite data,
    :func:`cdpr.analysis.weight.fit_weight_model`), or take ``model`` (e.g. from a separate tare
    run).  Prior: the rig file's mass and centre of mass with ``prior_mass_rel_sd`` and
    ``prior_com_sd_m``.  Without a wind-off point and a model the weight tare flags every wind-on
    point ``no_tare``.  The model goes to ``meta["weight_model"]``."""
    if model is not None:
        return with_updates(p, meta={"weight_model": model, "_note": "weight model given"})
    if not fit:
        return with_updates(p, meta={"weight_model": None, "_note": "not fitted (settings)"})
    wm = fit_weight_model(
        rig,
        p["kind"],
        p[POSE],
        p["tension_N"],
        p["tension_cov_N2"],
        p[POSE_COV],
        prior_mass_rel_sd,
        prior_com_sd_m,
    )
    return with_updates(p, meta={"weight_model": wm, "_note": weight_model_note(wm, rig)})


@stage("weight_tare", wraps=weight_tare)
def weight_tare_stage(
    p: Points,
    *,
    rig: Rig,
    position_tol_m: float = 1e-3,
    angle_tol_rad: float = float(np.deg2rad(0.1)),
    allow_nominal_weight: bool = False,
    prior_mass_rel_sd: float = 0.05,
    prior_com_sd_m: float = 0.01,
    tare_shares_pose: bool = False,
    tare_pose_sd_rel: float | None = TARE_POSE_SD_REL,
) -> Points:
    """Remove the weight (:func:`cdpr.analysis.tare.weight_tare`): the point's wind-off twin at
    the same pose (flag ``tare``), else the weight model (``weight_model``), else NaN and
    ``no_tare`` (or, with ``allow_nominal_weight``, the rig file's mass: ``weight_nominal``).  A
    tared point's pose is its tare's plus the difference the camera and the stiffness model agree
    on (``tare_pose_sd_rel``, :func:`cdpr.analysis.tare.tare_pose`; ``deflection_O_m_rad`` beside
    the camera's ``deflection_measured_O_m_rad``).
    Adds ``wrench_P_O_N_Nm`` and ``tare_index``; the σ terms ``load_cells``, ``pose`` and
    ``weight_model`` (replacing any before)."""
    wt = weight_tare(
        rig,
        p["kind"],
        p["start_ns"],
        p[POSE],
        p[POSE_COV],
        p["tension_N"],
        p["tension_cov_N2"],
        p.meta.get("weight_model"),
        position_tol_m=position_tol_m,
        angle_tol_rad=angle_tol_rad,
        allow_nominal_weight=allow_nominal_weight,
        prior_mass_rel_sd=prior_mass_rel_sd,
        prior_com_sd_m=prior_com_sd_m,
        tare_shares_pose=tare_shares_pose,
        tension_mix=p.arrays.get("tension_mix"),
        tension_cov_raw_N2=p.arrays.get("tension_cov_raw_N2"),
        tare_pose_sd_rel=tare_pose_sd_rel,
        pose_motion_cov=p.arrays.get("pose_motion_cov"),
    )
    return with_updates(
        p,
        arrays={
            WRENCH: wt.wrench_P_O_N_Nm,
            "tare_index": wt.tare_index,
            "load_map": wt.load_map,
            "load_support": wt.load_support,
            "deflection_O_m_rad": wt.deflection_O_m_rad,
            "deflection_measured_O_m_rad": wt.deflection_measured_O_m_rad,
        },
        terms={
            "load_cells": wt.cov_load_cells,
            "pose": wt.cov_pose,
            "weight_model": wt.cov_weight_model,
        },
        flag=wt.flags,
        replace_terms=True,
    )


@stage("inertia", wraps=inertia_wrench)
def inertia_stage(p: Points, *, rig: Rig, pose_rate: FloatArray, pose_accel: FloatArray) -> Points:
    """Add back the inertia and Coriolis wrench ``M qdd + C`` of a moving platform
    (:func:`cdpr.analysis.dynamics.inertia_wrench`) at each point's pose, from its pose rate and
    acceleration (s, 6) (Euler-angle rates, rad/s and rad/s²): Newton–Euler,
    ``A T + G + W_ext = M qdd + C`` (:mod:`cdpr.analysis.wrench`)."""
    D = inertia_wrench(rig.mass_kg, rig.com_P_m, rig.inertia_P_kgm2, p[POSE], pose_rate, pose_accel)
    return with_updates(
        p, arrays={WRENCH: p[WRENCH] + D, "inertia_N": D}, meta={"_note": "M qdd + C"}
    )


@stage("window_motion", wraps=mean_inertia_covariance)
def window_motion_stage(p: Points, *, rig: Rig) -> Points:
    """The σ of the mean inertia wrench of a platform that is not at rest over a point (σ term
    ``motion``, random): over a window of T seconds the cables' mean wrench carries
    ``M (v_end - v_start) / T``, a ringing mode's share of order 1/T that the tensions' long-run
    covariance cannot see (the mode's acceleration has no power at zero frequency);
    :func:`cdpr.analysis.dynamics.mean_inertia_covariance` from the camera's pose-rate variance
    ``pose_rate_var`` (:func:`cdpr.analysis.point_inputs.pose_rate_variance`) over the window
    ``window_s``.  A tared point adds its tare's.  Points without camera rates pass unchanged
    (the log says how many)."""
    s = p.n
    rv = np.asarray(p.arrays.get("pose_rate_var", np.full((s, 6), np.nan)), dtype=np.float64)
    T_s = np.asarray(p.arrays.get("window_s", np.full(s, np.nan)), dtype=np.float64)
    ok = np.isfinite(rv).all(axis=1) & np.isfinite(T_s) & (T_s > 0)
    own = mean_inertia_covariance(
        rig.mass_kg, rig.com_P_m, rig.inertia_P_kgm2, np.nan_to_num(p[POSE]),
        np.where(ok[:, None], rv, 0.0), np.where(ok, T_s, 1.0),
    )  # fmt: skip
    cov = own.copy()
    tare = np.asarray(p.arrays.get("tare_index", np.full(s, -1)), dtype=np.int64)
    has = tare >= 0
    cov[has] += own[tare[has]]
    return with_updates(
        p,
        terms={"motion": cov},
        meta={"_note": f"{int(ok.sum())} of {s} points with camera rates"},
    )


@stage("balance_interaction", wraps=apply_balance_model)
def balance_interaction(p: Points, *, interaction: Any = None, second_order: Any = None) -> Points:
    """Apply the balance calibration of ``cdpr calibrate balance``: the 6x6 interaction matrix
    ``W <- K W``, or, when given, the second-order model ``second_order = (K1, K2)``:
    ``W <- K1 W + K2 q(W)`` (:func:`cdpr.analysis.balance_model.apply_balance_model`); every σ
    term is carried through the (linearised) map ``J C J^T``.  Without either, the wrench passes
    unchanged and the log says so."""
    if interaction is None and second_order is None:
        return with_updates(p, meta={"_note": "no balance calibration given: not applied"})
    if second_order is not None:
        K1, K2 = second_order
        note = "second-order balance model applied"
    else:
        K1, K2 = interaction, None
        note = "interaction matrix applied"
    K = np.asarray(K1, dtype=np.float64)
    if K.shape != (6, 6) or not np.all(np.isfinite(K)):
        raise InputError(f"interaction: expected a finite (6, 6) matrix, got {K.shape}")
    W, J = apply_balance_model(p[WRENCH], K, K2)
    W[~np.isfinite(p[WRENCH]).all(axis=1)] = np.nan
    terms = {k: propagate(J, v) for k, v in p.cov_terms.items()}
    arrays = {WRENCH: W}
    if "load_map" in p.arrays:  # the load cells' map on the raw means goes through J too
        arrays["load_map"] = np.einsum("sij,skjm->skim", J, p["load_map"])
    return with_updates(p, arrays=arrays, terms=terms, meta={"_note": note})


# ------------------------------------------------------------------------------------------------
# axes, coefficients and what corrects them
# ------------------------------------------------------------------------------------------------
@stage("axes_and_moments", wraps=aero_axes)
def axes_stage(p: Points, *, geometry: ModelGeometry | None) -> Points:
    """Moments moved to the moment reference point (``wrench_mrp_O_N_Nm``, {O} axes, with its
    total covariance ``wrench_mrp_cov_O``; ``cov_terms`` stay those of ``wrench_P_O_N_Nm``), the
    angles ``aoa_rad``/``sideslip_rad``, body-axis force and moment (``force_B_N``,
    ``moment_B_Nm``) and wind-axis ``drag_N, side_N, lift_N``
    (:func:`cdpr.analysis.aero.aero_axes`).  Without a model geometry nothing is added (the
    wrench stays at P) and the coefficients stage flags ``no_geometry``."""
    if geometry is None:
        return with_updates(p, meta={"_note": "no model geometry: the wrench stays at P"})
    ax = aero_axes(
        p[WRENCH],
        _attitudes(p[POSE]),
        geometry.mrp_P_m,
        geometry.nose_P,
        geometry.up_P,
        wrench_cov=p.wrench_cov,
    )
    arrays = {
        "wrench_mrp_O_N_Nm": ax.wrench_mrp_O_N_Nm,
        "wrench_mrp_cov_O": ax.wrench_mrp_cov,
        "aoa_rad": ax.aoa_rad,
        "sideslip_rad": ax.sideslip_rad,
        "force_B_N": ax.force_B_N,
        "moment_B_Nm": ax.moment_B_Nm,
        "drag_N": ax.drag_N,
        "side_N": ax.side_N,
        "lift_N": ax.lift_N,
    }
    flags = {"geometry_from_options": np.full(p.n, geometry.source == "options")}
    return with_updates(p, arrays=arrays, flag=flags)  # type: ignore[arg-type]


@stage("coefficients", wraps=aero_coefficients)
def coefficients_stage(
    p: Points, *, geometry: ModelGeometry | None, wind_off_mps: float = 1.0
) -> Points:
    """Dynamic pressure ``q_Pa = rho V^2 / 2`` and ``CD, CY, CL, Cl, Cm, Cn`` with ``sd_*`` (from
    the total wrench covariance; the attitude's and q's own errors are not included;
    :func:`cdpr.analysis.aero.aero_coefficients`) for wind-on points with a finite airspeed above
    ``wind_off_mps``; NaN elsewhere, flag ``no_airspeed`` on wind-on points without one
    (``no_density`` without a density).  Without a model geometry: no coefficients, flag
    ``no_geometry`` on the points in the wind."""
    s = p.n
    V = p["airspeed_mps"]
    rho = p["density_kgpm3"]
    okv = np.isfinite(V) & np.isfinite(rho) & (rho > 0)
    q_Pa = np.full(s, np.nan)
    q_Pa[okv] = dynamic_pressure(rho[okv], V[okv])
    out = {c: np.full(s, np.nan) for c in COEFFICIENTS}
    out.update({f"sd_{c}": np.full(s, np.nan) for c in COEFFICIENTS})
    wind_on = p["kind"] == "wind_on"
    flags = {
        "no_airspeed": wind_on & ~np.isfinite(V),
        "no_density": wind_on & np.isfinite(V) & ~(np.isfinite(rho) & (rho > 0)),
    }
    if geometry is None:
        return with_updates(
            p,
            arrays={"q_Pa": q_Pa, **out},
            flag={**flags, "no_geometry": wind_points(p)},
            meta={"_note": "no model geometry: no coefficients"},
        )
    wind = np.isin(p["kind"], ("wind_on", "windage", "unknown"))
    use = wind & okv & (V > wind_off_mps) & np.isfinite(p[WRENCH]).all(axis=1)
    if use.any():
        g = geometry
        res = aero_coefficients(
            p[WRENCH][use],
            rotation_from_euler(p[POSE][use, 3:]),
            q_Pa[use],
            g.area_m2,
            g.span_m,
            g.chord_m,
            g.mrp_P_m,
            g.nose_P,
            g.up_P,
            wrench_cov=p.wrench_cov[use],
        )
        assert res.cov is not None
        sd = np.sqrt(np.clip(np.diagonal(res.cov, axis1=1, axis2=2), 0.0, None))
        for k, c in enumerate(COEFFICIENTS):
            out[c][use] = res.coefficients[:, k]
            out[f"sd_{c}"][use] = sd[:, k]
    return with_updates(p, arrays={"q_Pa": q_Pa, **out}, flag=flags)


UNCERTAINTY_COLUMNS: tuple[str, ...] = ("sd_random", "sd_systematic", "dof", "U95")
"""Prefixes of the uncertainty stage's per-point columns (``<prefix>_<wrench column>`` and
``<prefix>_<coefficient>``)."""


@stage("uncertainty", wraps=expanded_uncertainty)
def uncertainty_stage(p: Points, *, geometry: ModelGeometry | None, level: float = 0.95) -> Points:
    """The random and systematic parts of each wrench component (at the MRP) and coefficient, their
    effective degrees of freedom (Welch-Satterthwaite over the load cells' raw means, each with
    its own from the data's correlation) and the expanded uncertainty ``U95 = k u``
    (:func:`cdpr.analysis.uncertainty.expanded_uncertainty`): ``sd_random_<c>``,
    ``sd_systematic_<c>``, ``dof_<c>``, ``U95_<c>`` for every wrench column and coefficient."""
    s = p.n
    R = _attitudes(p[POSE])
    X = np.tile(np.eye(6), (s, 1, 1))  # the moment transfer to the MRP: M - r x F
    if geometry is not None:
        r = np.einsum("sij,j->si", R, np.asarray(geometry.mrp_P_m, dtype=np.float64))
        X[:, 3:, :3] = -np.nan_to_num(skew(np.nan_to_num(r)))  # no pose: no wrench either
    Kc = np.full((s, 6, 6), np.nan)
    q_Pa = p.arrays.get("q_Pa", np.full(s, np.nan))
    have = np.isfinite(p.arrays.get("CL", np.full(s, np.nan))) & np.isfinite(q_Pa)
    if geometry is not None and have.any():
        g = geometry
        Kc[have] = coefficient_matrix(
            R[have], q_Pa[have], g.area_m2, g.span_m, g.chord_m, g.mrp_P_m, g.nose_P, g.up_P
        )
    m = p["tension_N"].shape[1]
    extra = None
    C_flow = p.arrays.get("coefficient_cov_flow")
    if C_flow is not None:  # the instruments' part of the coefficients (not of the wrench)
        extra = np.zeros((s, 12))
        extra[:, 6:] = np.nan_to_num(np.diagonal(np.asarray(C_flow), axis1=1, axis2=2))
    eu = expanded_uncertainty(
        dict(p.cov_terms),
        np.concatenate([X, Kc], axis=1),
        p.arrays.get("load_map", np.zeros((s, 0, 6, m))),
        p.arrays.get("load_support", np.zeros((s, 0), np.int64)),
        p.arrays.get("tension_sample_cov_N2", p["tension_cov_N2"]),
        p.arrays.get("tension_cov_raw_N2", p["tension_cov_N2"]),
        p.arrays.get("n_used", np.full(s, 2)),
        p.arrays.get("longrun_bandwidth"),
        extra_systematic_u2=extra,
        level=level,
        term_dof=p.meta.get("systematic_dof"),
    )
    names = [*WRENCH_COLUMNS, *COEFFICIENTS]
    out: dict[str, NDArray[Any]] = {}
    vals = (eu.u_random, eu.u_systematic, eu.dof, eu.U, eu.dof_random)
    for prefix, v in zip((*UNCERTAINTY_COLUMNS, "dof_random"), vals, strict=True):
        for k, c in enumerate(names):
            out[f"{prefix}_{c}"] = np.where(np.isfinite(p[WRENCH]).all(axis=1), v[:, k], np.nan)
    return with_updates(p, arrays=out, meta={"_note": f"level {level:g}"})


@stage("tension_check", wraps=tension_check)
def tension_check_stage(
    p: Points, *, rig: Rig, method: str = "exact", limit_N: float = 1.0
) -> Points:
    """The paper's check (:func:`cdpr.analysis.check.tension_check`): the tensions ``method``
    commands for ``-(G + W)`` (weight model, else the rig file's mass) against the measured ones:
    ``check_dT_N`` (s, m), ``check_max_abs_dT_N`` (s,), flag ``check_fail`` above ``limit_N``.
    Points without a wrench get NaN."""
    wm: WeightModel | None = p.meta.get("weight_model")
    tc = tension_check(
        rig,
        p[STRUCTURE_MATRIX],
        p[POSE],
        p["tension_N"],
        p[WRENCH],
        None if wm is None else wm.theta,
        method,
        limit_N,
    )
    return with_updates(
        p,
        arrays={"check_dT_N": tc.dT_N, "check_max_abs_dT_N": tc.max_abs_dT_N},
        flag={"check_fail": tc.fail},
        meta={"_note": f"method {method}, limit {limit_N} N"},
    )


# ------------------------------------------------------------------------------------------------
# the canonical order, and the binding of a run's settings
# ------------------------------------------------------------------------------------------------
STEADY_STAGES: tuple[Callable[..., Points], ...] = (
    input_flags,
    zero_drift_stage,
    spectrum_stage,
    structure_matrix_stage,
    weight_model_stage,
    weight_tare_stage,
    flow_conditions_stage,
    windage_stage,
    inertia_stage,
    window_motion_stage,
    systematic_stage,
    balance_interaction,
    axes_stage,
    coefficients_stage,
    flow_uncertainty_stage,
    uncertainty_stage,
    wall_corrections_stage,
    repeatability_stage,
    tension_check_stage,
)
"""The one order of the steady reduction.  A stage may be left out by :func:`core_stages` (the
corrections without a test matrix, the spectra without samples, the inertia of a platform at
rest); none runs in another order."""

CORRECTION_STAGES: frozenset[str] = frozenset(
    {"spectrum_check", "flow_conditions", "windage", "wall_corrections", "repeatability"}
)
"""Stages that run only with the corrections requested (``cdpr analyze --matrix``); zero drift
runs either way (it flags ``uncorrected`` when they are not)."""


@dataclass(frozen=True)
class ReduceSettings:
    """Settings of the core (recorded in every summary).

    method, check_limit_N: the tension check (controller's distribution method, pass mark).
    tare_position_tol_m, tare_angle_tol_rad: a wind-off point at the same pose within these is the
        point's tare (else the weight model).
    prior_mass_rel_sd, prior_com_sd_m: spread of the rig file's mass / centre of mass as the weight
        model's prior.
    allow_nominal_weight: reduce points without tare or weight model with the rig file's mass
        (flagged ``weight_nominal``); off by default.
    wind_off_mps: below this a point has no coefficients.
    fit_weight_model: fit the weight model from the wind-off points (``cdpr wrench`` pairs each row
        with its own tare and does not); tare_shares_pose: the tare row is at the same measured
        pose (one pose error for both, see :func:`cdpr.analysis.tare.weight_tare`).
    tare_pose_sd_rel: the stiffness model's relative σ when a point's pose is taken relative to its
        tare's (:func:`cdpr.analysis.tare.tare_pose`); None: the two measured poses as they are.
    """

    method: str = "exact"
    check_limit_N: float = 1.0
    tare_position_tol_m: float = 1e-3
    tare_angle_tol_rad: float = float(np.deg2rad(0.1))
    prior_mass_rel_sd: float = 0.05
    prior_com_sd_m: float = 0.01
    allow_nominal_weight: bool = False
    wind_off_mps: float = 1.0
    fit_weight_model: bool = True
    tare_shares_pose: bool = False
    tare_pose_sd_rel: float | None = TARE_POSE_SD_REL


@dataclass(frozen=True)
class SystematicInputs:
    """What the systematic σ stages need (``cdpr analyze``; :mod:`cdpr.analysis.systematic`):
    the load-cell calibration's own σ (None: not given, flagged
    ``loadcell_calibration_sd_not_given``), the balance calibration's fit covariance (None with a
    balance calibration: flagged ``interaction_matrix_sd_not_given``), the tunnel instruments'
    stated accuracy (None: every default, flagged ``tunnel_instrument_sd_default``); the rig
    geometry's σ comes from the rig file (default flagged ``rig_geometry_sd_default``)."""

    loadcell: LoadCellCalibrationSd | None = None
    balance_fit: BalanceFitCovariance | None = None
    instruments: InstrumentAccuracy | None = None


@dataclass(frozen=True)
class Corrections:
    """What the correction stages need (``cdpr analyze --matrix``): the test section's geometry
    (None: no windage model) and wall parameters (None: no wall corrections, flagged), the
    windage model's relative σ."""

    section: SectionGeometry | None = None
    walls: WallParameters | None = None
    windage_sigma_rel: float = 0.15


def core_stages(
    rig: Rig,
    geometry: ModelGeometry | None,
    settings: ReduceSettings = ReduceSettings(),
    *,
    interaction: Any = None,
    second_order: Any = None,
    weight_model: WeightModel | None = None,
    corrections: Corrections | None = None,
    samples: PointSamples | None = None,
    motion: tuple[FloatArray, FloatArray] | None = None,
    coefficients: bool = True,
    systematic: SystematicInputs | None = None,
) -> list[Stage]:
    """The stages of :data:`STEADY_STAGES` with a run's settings bound, in that order.

    geometry: the model's reference geometry (None: no axes or coefficients, flagged);
    interaction / second_order: the balance calibration; weight_model: a given weight model
    (else fitted from the wind-off points unless ``settings.fit_weight_model`` is False);
    corrections: run the correction stages (None: balance values, flagged ``uncorrected``);
    samples: the tension samples (the spectrum check, with the corrections); motion: the pose
    rate and acceleration (s, 6) each of a moving platform (the inertia stage); coefficients:
    False leaves out the axes and coefficients (``cdpr wrench`` without flow conditions: the wrench
    at P only, no ``no_geometry`` flag).
    systematic: the systematic σ terms' inputs (None: those stages left out, ``cdpr wrench``).
    """
    s = settings
    bound: dict[Callable[..., Points], Stage | None] = {
        input_flags: input_flags,
        zero_drift_stage: functools.partial(zero_drift_stage, apply=corrections is not None),
        spectrum_stage: None
        if corrections is None or samples is None
        else functools.partial(spectrum_stage, rig=rig, samples=samples),
        structure_matrix_stage: functools.partial(structure_matrix_stage, rig=rig),
        weight_model_stage: functools.partial(
            weight_model_stage,
            rig=rig,
            prior_mass_rel_sd=s.prior_mass_rel_sd,
            prior_com_sd_m=s.prior_com_sd_m,
            model=weight_model,
            fit=s.fit_weight_model,
        ),
        weight_tare_stage: functools.partial(
            weight_tare_stage,
            rig=rig,
            position_tol_m=s.tare_position_tol_m,
            angle_tol_rad=s.tare_angle_tol_rad,
            allow_nominal_weight=s.allow_nominal_weight,
            prior_mass_rel_sd=s.prior_mass_rel_sd,
            prior_com_sd_m=s.prior_com_sd_m,
            tare_shares_pose=s.tare_shares_pose,
            tare_pose_sd_rel=s.tare_pose_sd_rel,
        ),
        flow_conditions_stage: None
        if corrections is None or geometry is None
        else functools.partial(
            flow_conditions_stage, chord_m=geometry.chord_m, wind_off_mps=s.wind_off_mps
        ),
        windage_stage: None
        if corrections is None
        else functools.partial(
            windage_stage,
            rig=rig,
            section=corrections.section,
            geometry=geometry,
            sigma_rel=corrections.windage_sigma_rel,
            wind_off_mps=s.wind_off_mps,
        ),
        window_motion_stage: functools.partial(window_motion_stage, rig=rig),
        inertia_stage: None
        if motion is None
        else functools.partial(inertia_stage, rig=rig, pose_rate=motion[0], pose_accel=motion[1]),
        systematic_stage: None
        if systematic is None
        else functools.partial(
            systematic_stage,
            rig=rig,
            loadcell=systematic.loadcell,
            balance_fit=systematic.balance_fit,
            interaction=interaction,
            second_order=second_order,
        ),
        balance_interaction: functools.partial(
            balance_interaction, interaction=interaction, second_order=second_order
        ),
        axes_stage: functools.partial(axes_stage, geometry=geometry) if coefficients else None,
        coefficients_stage: functools.partial(
            coefficients_stage, geometry=geometry, wind_off_mps=s.wind_off_mps
        )
        if coefficients
        else None,
        flow_uncertainty_stage: None
        if systematic is None or not coefficients
        else functools.partial(
            flow_uncertainty_stage,
            instruments=systematic.instruments or InstrumentAccuracy(defaulted=INSTRUMENT_KEYS),
        ),
        uncertainty_stage: functools.partial(uncertainty_stage, geometry=geometry),
        wall_corrections_stage: None
        if corrections is None or geometry is None
        else functools.partial(wall_corrections_stage, walls=corrections.walls),
        repeatability_stage: None
        if corrections is None or geometry is None
        else repeatability_stage,
        tension_check_stage: functools.partial(
            tension_check_stage, rig=rig, method=s.method, limit_N=s.check_limit_N
        ),
    }
    return [b for st in STEADY_STAGES if (b := bound[st]) is not None]


RUNS_WHEN: dict[str, str] = {
    **{name: "with the corrections (`--matrix`)" for name in CORRECTION_STAGES},
    "zero_drift": "always (without the corrections: flags `uncorrected`)",
    "inertia": "a moving platform (`cdpr wrench --dynamic`)",
    "systematic": "`cdpr analyze` (not `cdpr wrench`)",
    "flow_uncertainty": "`cdpr analyze`, when coefficients are wanted",
    "axes_and_moments": "when coefficients are wanted",
    "coefficients": "when coefficients are wanted (`no_geometry` without a model geometry)",
}
"""When a stage of :data:`STEADY_STAGES` is bound by :func:`core_stages` (else always)."""


DYNAMIC_STAGES: tuple[Callable[..., Points], ...] = (
    input_flags,
    zero_drift_stage,
    motion_fit_stage,
    clock_offset_stage,
    wrench_harmonics_stage,
    inertia_removal_stage,
    flow_conditions_stage,
    balance_harmonics_stage,
    derivatives_stage,
)
"""The one order of a dynamic (forced-oscillation) point: the run's ``oscillation`` and
``oscillation_tare`` points (its ``zero`` points ride along for the zero drift).  The steady
points of the same run keep :data:`STEADY_STAGES`."""

DYNAMIC_RUNS_WHEN: dict[str, str] = {
    "flow_conditions": "with the corrections (`--matrix`)",
    "zero_drift": "always (without the corrections: flags `uncorrected`)",
    "balance_interaction": "always (logged when no balance calibration is given)",
}
"""When a stage of :data:`DYNAMIC_STAGES` is bound by :func:`dynamic_stages` (else always)."""


def dynamic_stages(
    rig: Rig,
    geometry: ModelGeometry | None,
    samples: DynamicSamples,
    settings: DynamicSettings = DEFAULT_DYNAMIC,
    *,
    body: Body | None = None,
    interaction: Any = None,
    second_order: Any = None,
    corrections: Corrections | None = None,
) -> list[Stage]:
    """The stages of :data:`DYNAMIC_STAGES` with a run's settings bound, in that order.

    samples: the run's samples (the load cells on their own clock, the camera's frames); body:
    the mass properties for gravity and the model inertia (the weight model's mass and centre of
    mass when the steady points fitted one; default the rig file's); interaction / second_order:
    the balance calibration; corrections: with ``cdpr analyze --matrix`` (the zero drift and the
    flow conditions)."""
    b = body or Body.of(rig)
    bound: dict[Callable[..., Points], Stage | None] = {
        input_flags: input_flags,
        zero_drift_stage: functools.partial(zero_drift_stage, apply=corrections is not None),
        motion_fit_stage: functools.partial(motion_fit_stage, samples=samples, settings=settings),
        clock_offset_stage: functools.partial(
            clock_offset_stage, rig=rig, samples=samples, settings=settings, body=b
        ),
        wrench_harmonics_stage: functools.partial(
            wrench_harmonics_stage, rig=rig, samples=samples, settings=settings, body=b
        ),
        inertia_removal_stage: functools.partial(inertia_removal_stage, settings=settings),
        flow_conditions_stage: None
        if corrections is None or geometry is None
        else functools.partial(
            flow_conditions_stage, chord_m=geometry.chord_m, wind_off_mps=settings.wind_off_mps
        ),
        balance_harmonics_stage: functools.partial(
            balance_harmonics_stage,
            interaction=interaction,
            second_order=second_order,
            n_grid=settings.n_grid,
        ),
        derivatives_stage: functools.partial(
            derivatives_stage, geometry=geometry, settings=settings
        ),
    }
    return [st for key in DYNAMIC_STAGES if (st := bound[key]) is not None]


def stage_table(order: str = "steady") -> str:
    """A canonical order as a Markdown table: stage, the pure function it wraps, when it runs
    (``order``: ``"steady"`` or ``"dynamic"``; docs/analysis.md prints both; a test keeps them
    equal)."""
    stages, when = (
        (STEADY_STAGES, RUNS_WHEN) if order == "steady" else (DYNAMIC_STAGES, DYNAMIC_RUNS_WHEN)
    )
    rows = ["| # | stage | wraps | runs |", "|---|---|---|---|"]
    for i, st in enumerate(stages, 1):
        name = st.stage_name  # type: ignore[attr-defined]
        fn = st.wraps  # type: ignore[attr-defined]
        target = f"`{fn.__module__.removeprefix('cdpr.')}.{fn.__qualname__}`"
        rows.append(f"| {i} | `{name}` | {target} | {when.get(name, 'always')} |")
    return "\n".join(rows)
