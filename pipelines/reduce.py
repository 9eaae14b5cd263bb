"""The ordered stage list of the reduction core, and the per-point table it gives.

:func:`reduction_stages` binds the settings of every stage (:mod:`cdpr.analysis.reduction`) in the
order of DESIGN.md; :func:`reduce_points` runs them; :func:`points_table` turns the result into the
per-point table (one row per test point, columns documented in docs/analysis.md).  ``cdpr analyze``,
``cdpr wrench`` and the live view call these.

Slots for later stages (zero drift, cable/platform windage, inertia of a moving platform, wall
corrections): pass them in
``extra`` under the slot's name; each is a :data:`cdpr.analysis.reduction.Stage` (points in, points
out) that adds its correction to ``wrench_N`` and its σ term to ``cov_terms``, flags the points it
cannot treat and is logged by the ``@stage`` decorator.

The correction stages of issue 13 live here too (each a thin stage around one pure function of
``cdpr.analysis``: ``zero_drift_stage``, ``spectrum_stage``, ``flow_conditions_stage``,
``windage_stage``, ``wall_corrections_stage``, ``repeatability_stage``); :func:`correction_stages`
fills the slots with them (``cdpr analyze --matrix``), :func:`correction_columns` gives their
per-point columns (docs/corrections.md, "In the reduction core").
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from cdpr.analysis.aero import ModelGeometry, flow_angles
from cdpr.analysis.conventions import POSE_COLUMNS, WRENCH_COLUMNS
from cdpr.analysis.corrections import (
    WallParameters,
    repeatability,
    wall_corrections,
    zero_drift,
)
from cdpr.analysis.errors import InputError
from cdpr.analysis.flow import (
    air_density,
    reynolds_number,
    speed_of_sound,
    sutherland_viscosity,
)
from cdpr.analysis.records import CorrectionRecord
from cdpr.analysis.reduction import (
    COEFFICIENTS,
    Points,
    Stage,
    axes_and_moments,
    balance_interaction,
    coefficients,
    run_stages,
    stage,
    structure_matrix_stage,
    tension_check,
    weight_model_stage,
    weight_tare,
    with_updates,
)
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.test_section import SectionGeometry
from cdpr.analysis.weight import WeightModel
from cdpr.analysis.windage import evaluate_windage_tare, fit_windage_tare, windage_of_rig

from .tunnel_section import TunnelSection

SLOTS: tuple[str, ...] = (
    "zero_drift",
    "flow_conditions",
    "windage",
    "inertia",
    "wall_corrections",
    "repeatability",
)
"""Names of the slots later stages plug into (see the module docstring).  In run order: zero drift
first (on the tensions), flow conditions and windage after the weight tare, inertia, and after the
coefficients the wall corrections (they correct coefficients) and the repeatability."""


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
        pose (one pose error for both, see :func:`cdpr.analysis.reduction.weight_tare`).
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


def reduction_stages(
    rig: Rig,
    geometry: ModelGeometry | None,
    settings: ReduceSettings = ReduceSettings(),
    interaction: Any = None,
    weight_model: WeightModel | None = None,
    second_order: Any = None,
    extra: Mapping[str, Sequence[Stage]] | None = None,
) -> list[Stage]:
    """The ordered stages with their settings bound."""
    extra = dict(extra or {})
    unknown = sorted(set(extra) - set(SLOTS))
    if unknown:
        raise InputError(f"extra: unknown slot {unknown[0]!r}, expected one of {SLOTS}")
    s = settings
    stages: list[Stage] = [*extra.get("zero_drift", ())]
    stages.append(functools.partial(structure_matrix_stage, rig=rig))
    stages.append(
        functools.partial(
            weight_model_stage,
            rig=rig,
            prior_mass_rel_sd=s.prior_mass_rel_sd,
            prior_com_sd_m=s.prior_com_sd_m,
            model=weight_model,
            fit=s.fit_weight_model,
        )
    )
    stages.append(
        functools.partial(
            weight_tare,
            rig=rig,
            position_tol_m=s.tare_position_tol_m,
            angle_tol_rad=s.tare_angle_tol_rad,
            allow_nominal_weight=s.allow_nominal_weight,
            prior_mass_rel_sd=s.prior_mass_rel_sd,
            prior_com_sd_m=s.prior_com_sd_m,
            tare_shares_pose=s.tare_shares_pose,
        )
    )
    stages += extra.get("flow_conditions", ())
    stages += extra.get("windage", ())
    stages += extra.get("inertia", ())
    stages.append(
        functools.partial(balance_interaction, interaction=interaction, second_order=second_order)
    )
    if geometry is not None:
        stages.append(functools.partial(axes_and_moments, geometry=geometry))
        stages.append(
            functools.partial(coefficients, geometry=geometry, wind_off_mps=s.wind_off_mps)
        )
        stages += extra.get("wall_corrections", ())
        stages += extra.get("repeatability", ())
    stages.append(
        functools.partial(tension_check, rig=rig, method=s.method, limit_N=s.check_limit_N)
    )
    return stages


# --------------------------------------------------------------------------------------------
# the correction stages (issue 13): each calls one pure function of cdpr.analysis, adds its
# correction, its σ term and its per-point size, records what it did (a CorrectionRecord in
# meta["corrections"]) and flags the points it cannot treat.
# --------------------------------------------------------------------------------------------
def _records(p: Points, *recs: CorrectionRecord) -> dict[str, Any]:
    return {"corrections": [*p.meta.get("corrections", ()), *(r.as_dict() for r in recs)]}


def _no_record(name: str, why: str, flags: tuple[str, ...]) -> CorrectionRecord:
    return CorrectionRecord(name=name, source="not applied", values={"why": why}, flags=flags)


@stage("zero_drift")
def zero_drift_stage(p: Points) -> Points:
    """Remove each cable's zero drift from the tensions of every point.

    The wind-off zeros are the points of kind ``zero`` (level, wind off: before and after a run and
    between blocks); their mean tensions are interpolated linearly in time
    (:func:`cdpr.analysis.corrections.zero_drift`, relative to the first zero) and subtracted, the
    drift's σ added to the tension covariance.  Points after the last zero are held there and
    flagged ``no_closing_zero``, before the first ``no_opening_zero``; without any zero point every
    point is flagged ``no_zero_drift_correction``.  Adds ``zero_drift_N`` and
    ``sd_zero_drift_N`` (s, m)."""
    s, m = p["tension_N"].shape
    zero = (p["kind"] == "zero") & np.isfinite(p["tension_N"]).all(axis=1)
    drift = np.zeros((s, m))
    sd = np.zeros((s, m))
    if not zero.any():
        why = "no wind-off zero point (kind 'zero') in the run"
        rec = _no_record("zero_drift", why, ("no_zero_drift_correction",))
        return with_updates(
            p,
            arrays={"zero_drift_N": np.full((s, m), np.nan), "sd_zero_drift_N": sd},
            flag={"no_zero_drift_correction": np.ones(s, bool)},
            meta={**_records(p, rec), "_note": why + ": drift not corrected"},
        )
    zsd = np.sqrt(np.clip(np.diagonal(p["tension_cov_N2"][zero], axis1=1, axis2=2), 0.0, None))
    d = zero_drift(p["start_ns"], p["start_ns"][zero], p["tension_N"][zero], zsd)
    drift, sd = d.drift_N, d.sigma_N
    cov = p["tension_cov_N2"] + sd[:, :, None] ** 2 * np.eye(m)
    return with_updates(
        p,
        arrays={
            "tension_N": p["tension_N"] - drift,
            "tension_cov_N2": cov,
            "zero_drift_N": drift,
            "sd_zero_drift_N": sd,
        },
        flag={"no_closing_zero": d.no_closing_zero, "no_opening_zero": d.no_opening_zero},
        meta={
            **_records(p, d.record),
            "_note": f"{int(zero.sum())} zeros, max |drift| {float(np.max(np.abs(drift))):.4g} N",
        },
    )


DENSITY_SOURCES = ("p_T_humidity", "p_T_dry", "stream")
"""Per point, where ``density_kgpm3`` came from: the point's mean p, T and relative humidity
(moist air), its mean p and T without a humidity (dry air, flag ``humidity_not_given``), or the
tunnel stream's density as given (no p and T in the stream: a measured density)."""


@stage("flow_conditions")
def flow_conditions_stage(p: Points, *, chord_m: float, wind_off_mps: float = 1.0) -> Points:
    """Density, Reynolds number on the reference chord (viscosity by Sutherland's law), Mach
    number and the viscosity per point (``density_kgpm3``, ``density_source``,
    ``relative_humidity``, ``reynolds``, ``mach``, ``viscosity_Pas``).

    Where the point has its mean ``static_pressure_Pa`` and ``temperature_K``, the density is
    moist air (:func:`cdpr.analysis.flow.air_density`, the Buck vapour pressure) at the point's
    mean ``relative_humidity``; a point without a humidity (none in the stream, or a sample of
    the point without one) is computed as dry air and flagged ``humidity_not_given`` (wind-on
    and windage points, where the density enters q); without p and T the stream's density is
    kept (``density_source`` ``stream``).  Wind-on points without a temperature get NaN Re and
    Mach and ``no_temperature``."""
    s = p.n
    V = p["airspeed_mps"]
    nan = np.full(s, np.nan)
    TK = np.asarray(p.arrays.get("temperature_K", nan), dtype=np.float64)
    ps = np.asarray(p.arrays.get("static_pressure_Pa", nan), dtype=np.float64)
    rh = np.asarray(p.arrays.get("relative_humidity", nan), dtype=np.float64)
    rho = np.array(p["density_kgpm3"], dtype=np.float64)
    pT = np.isfinite(ps) & (ps > 0) & np.isfinite(TK) & (TK > 0)
    wet = pT & np.isfinite(rh)
    source = np.full(s, DENSITY_SOURCES[2], dtype=object)
    if pT.any():
        rho[pT] = air_density(ps[pT], TK[pT], np.where(wet, rh, 0.0)[pT])
        source[wet], source[pT & ~wet] = DENSITY_SOURCES[0], DENSITY_SOURCES[1]
    ok = np.isfinite(V) & (V >= 0) & np.isfinite(rho) & (rho > 0) & np.isfinite(TK) & (TK > 0)
    mu, re, mach = np.full(s, np.nan), np.full(s, np.nan), np.full(s, np.nan)
    if ok.any():
        mu[ok] = sutherland_viscosity(TK[ok])
        re[ok] = reynolds_number(rho[ok], V[ok], chord_m, mu[ok])
        mach[ok] = V[ok] / speed_of_sound(TK[ok])
    windy = np.isin(p["kind"], ("wind_on", "windage")) & np.isfinite(V) & (V > wind_off_mps)
    dry = windy & pT & ~wet
    rec = CorrectionRecord(
        name="flow_conditions",
        source="density: ideal-gas moist air at the point's mean p, T and relative humidity "
        "(Buck vapour pressure), dry air where no humidity is given; Re = rho V c / mu with "
        "Sutherland's law (White); M = V / sqrt(1.4 R T)",
        values={
            "chord_m": float(chord_m),
            "points_with_humidity": int((windy & wet).sum()),
            "points_without_humidity": int(dry.sum()),
            "reynolds_max": float(np.nanmax(re)) if ok.any() else None,
            "mach_max": float(np.nanmax(mach)) if ok.any() else None,
        },
        flags=tuple(
            f for f, m in (("humidity_not_given", dry), ("no_temperature", windy & ~ok)) if m.any()
        ),
    )
    return with_updates(
        p,
        arrays={
            "density_kgpm3": rho,
            "density_source": source.astype(str),
            "relative_humidity": rh,
            "viscosity_Pas": mu,
            "reynolds": re,
            "mach": mach,
        },
        flag={"no_temperature": windy & ~ok, "humidity_not_given": dry},
        meta={
            **_records(p, rec),
            "_note": f"humidity at {int((windy & wet).sum())} wind-on point(s), "
            f"dry air at {int(dry.sum())} (humidity_not_given)",
        },
    )


WINDAGE_SOURCES = ("measured", "model", "none")


@stage("windage")
def windage_stage(
    p: Points,
    *,
    rig: Rig,
    section: SectionGeometry | None,
    geometry: ModelGeometry | None,
    sigma_rel: float = 0.15,
    aoa_degree: int = 2,
    sideslip_degree: int = 2,
    wind_off_mps: float = 1.0,
    angle_tol_rad: float = float(np.deg2rad(0.1)),
) -> Points:
    """Subtract the cable and platform windage from the wind-on points' wrench (at P in {O}).

    - measured tare: the run's model-off wind-on points (kind ``windage``) fitted per speed in
      aoa/sideslip (:func:`cdpr.analysis.windage.fit_windage_tare`), evaluated at each wind-on
      point (flag ``windage_tare``; outside the fitted attitudes ``windage_tare_extrapolated``);
    - else the model from the rig file and the test section
      (:func:`cdpr.analysis.windage.windage_of_rig`, flag ``windage_modelled``);
    - else nothing is subtracted: flag ``no_windage_correction``.

    Adds ``windage_N`` (s, 6, what was subtracted), ``windage_source`` (s,), ``windage_tare_N``
    (the measured fit at every point: on the windage points, their residuals are
    ``wrench_N - windage_tare_N``), ``windage_model_N`` (the model, shown beside the measured tare)
    and the σ term ``windage``.

    An angle the windage points hold within ``angle_tol_rad`` (the sideslip of an alpha sweep) is
    not a fit variable: points within that tolerance of it count as at it (as the weight tare's
    pose tolerance does), and a point within it beyond the ends of the fitted range is evaluated at
    the end; further out a point is flagged as extrapolated."""
    s = p.n
    kind = p["kind"]
    V = p["airspeed_mps"]
    W = p["wrench_N"]
    nose = (-1.0, 0.0, 0.0) if geometry is None else geometry.nose_P
    up = (0.0, 0.0, 1.0) if geometry is None else geometry.up_P
    R = rotation_from_euler(np.nan_to_num(p["pose"][:, 3:]))
    aoa, slip = (np.array(a, dtype=np.float64) for a in flow_angles(R, nose, up))
    finite = np.isfinite(W).all(axis=1) & np.isfinite(V)
    on = (kind == "wind_on") & finite & (V > wind_off_mps)
    wnd = (kind == "windage") & finite & (V > wind_off_mps)
    recs: list[CorrectionRecord] = []
    notes: list[str] = []
    flags: dict[str, NDArray[np.bool_]] = {}
    measured = np.full((s, 6), np.nan)
    measured_sd = np.full((s, 6), np.nan)
    extrap = np.zeros(s, bool)
    if wnd.any():
        for ang in (aoa, slip):
            if np.ptp(ang[wnd]) < angle_tol_rad:
                held = float(np.mean(ang[wnd]))
                ang[np.abs(ang - held) <= angle_tol_rad] = held
        # a windage point whose speed has too few others (a speed ramp caught in its window)
        # cannot be fitted: it is left out and flagged, the other speeds are still fitted
        close = (np.abs(V[:, None] - V[None, :]) <= 0.03 * V[None, :]) & wnd[None, :]
        lonely = wnd & (close.sum(axis=1) < aoa_degree + 2)
        fitset = wnd & ~lonely
        flags["windage_tare_unfit"] = lonely
        if lonely.any():
            notes.append(f"{int(lonely.sum())} windage point(s) left out: too few at their speed")
        try:
            if not fitset.any():
                raise InputError("no speed with enough windage points")
            fit = fit_windage_tare(
                V[fitset], aoa[fitset], slip[fitset], W[fitset], aoa_degree, sideslip_degree
            )
        except InputError as exc:
            notes.append(f"measured tare not fitted: {exc}")
            flags["windage_tare_unfit"] = wnd
        else:
            recs.append(fit.record)
            at = np.flatnonzero(on | wnd)
            g = np.argmin(np.abs(V[at, None] - fit.speeds_mps[None, :]), axis=1)
            for ang, rng in ((aoa, "aoa_range_rad"), (slip, "sideslip_range_rad")):
                lo, hi = (np.array([getattr(f, rng)[k] for f in fit.fits])[g] for k in (0, 1))
                x = ang[at]
                x = np.where((x < lo) & (x >= lo - angle_tol_rad), lo, x)
                ang[at] = np.where((x > hi) & (x <= hi + angle_tol_rad), hi, x)
            ev = evaluate_windage_tare(fit, V[at], aoa[at], slip[at])
            measured[at], measured_sd[at], extrap[at] = ev.tare_N, ev.sigma_N, ev.extrapolated
            recs.append(ev.record)
            notes.append(f"measured tare from {int(fitset.sum())} model-off points")
    model = np.full((s, 6), np.nan)
    model_cov = np.full((s, 6, 6), np.nan)
    if section is not None:
        mu = np.asarray(p.arrays.get("viscosity_Pas", np.full(s, np.nan)), dtype=np.float64)
        ok = (on | wnd) & np.isfinite(mu) & np.isfinite(p["density_kgpm3"])
        if ok.any():
            cw = windage_of_rig(
                rig, section, p["pose"][ok, :3], R[ok], p["tension_N"][ok], V[ok],
                p["density_kgpm3"][ok], mu[ok], sigma_rel,
            )  # fmt: skip
            model[ok], model_cov[ok] = cw.wrench_N, cw.cov
            recs.append(cw.record)
    use_meas = on & np.isfinite(measured).all(axis=1)
    use_model = on & ~use_meas & np.isfinite(model).all(axis=1)
    none = on & ~use_meas & ~use_model
    applied = np.zeros((s, 6))
    applied[use_meas] = measured[use_meas]
    applied[use_model] = model[use_model]
    cov = np.zeros((s, 6, 6))
    cov[use_meas] = measured_sd[use_meas, :, None] ** 2 * np.eye(6)
    cov[use_model] = model_cov[use_model]
    source = np.full(s, "", dtype=object)
    source[use_meas], source[use_model], source[none] = WINDAGE_SOURCES
    flags.update(
        {
            "windage_tare": use_meas,
            "windage_tare_extrapolated": use_meas & extrap,
            "windage_modelled": use_model,
            "no_windage_correction": none,
        }
    )
    if wnd.any() and (on & ~use_meas).any():
        flags["windage_tare_missing"] = on & ~use_meas
    if not recs:
        recs.append(
            _no_record(
                "windage",
                "no model-off windage points and no test section ([tunnel])",
                ("no_windage_correction",) if none.any() else (),
            )
        )
    notes.append(
        f"{int(use_meas.sum())} measured, {int(use_model.sum())} modelled, "
        f"{int(none.sum())} uncorrected"
    )
    W_out = W.copy()
    W_out[on] = W[on] - applied[on]
    return with_updates(
        p,
        arrays={
            "wrench_N": W_out,
            "windage_N": np.where(on[:, None], applied, np.nan),
            "windage_source": source.astype(str),
            "windage_tare_N": measured,
            "sd_windage_tare_N": measured_sd,
            "windage_model_N": model,
        },
        terms={"windage": cov},
        flag=flags,
        meta={**_records(p, *recs), "_note": "; ".join(notes)},
    )


WALL_COEFFICIENTS = ("CD", "CY", "CL", "Cl", "Cm", "Cn")


@stage("wall_corrections")
def wall_corrections_stage(p: Points, *, walls: WallParameters | None) -> Points:
    """Wall corrections of the coefficients (:func:`cdpr.analysis.corrections.wall_corrections`):
    the uncorrected ``CD ... Cn``, ``aoa_rad`` and ``q_Pa`` stay; the corrected ones are added as
    ``CD_corrected ...``, ``aoa_corrected_rad``, ``q_corrected_Pa`` with each correction's size
    (``wall_eps_solid``, ``wall_eps_wake``, ``wall_q_ratio``, ``wall_delta_aoa_rad``,
    ``wall_delta_CD_induced``, ``wall_delta_CL_curvature``, ``wall_delta_Cm_curvature``).  CY, Cl, Cn
    take the blockage only.  σ of a corrected coefficient: the uncorrected σ over the q ratio (the
    corrections' own spread is not included).  Without a test section: NaN and
    ``no_wall_correction`` on every point with coefficients."""
    s = p.n
    cols = {f"{c}_corrected": np.full(s, np.nan) for c in WALL_COEFFICIENTS}
    cols.update({f"sd_{c}_corrected": np.full(s, np.nan) for c in WALL_COEFFICIENTS})
    sizes = {
        k: np.full(s, np.nan)
        for k in (
            "wall_eps_solid", "wall_eps_wake", "wall_q_ratio", "wall_delta_aoa_rad",
            "wall_delta_CD_induced", "wall_delta_CL_curvature", "wall_delta_Cm_curvature",
            "aoa_corrected_rad", "q_corrected_Pa",
        )
    }  # fmt: skip
    have = np.isfinite(p["CL"]) & np.isfinite(p["CD"]) & np.isfinite(p["Cm"])
    have &= np.isfinite(p["aoa_rad"]) & (p["kind"] == "wind_on")  # the model is in the flow
    if walls is None:
        rec = _no_record("wall_corrections", "no test section ([tunnel])", ("no_wall_correction",))
        return with_updates(
            p,
            arrays={**cols, **sizes},
            flag={"no_wall_correction": have},
            meta=_records(p, rec),
        )
    if have.any():
        wc = wall_corrections(
            walls, p["aoa_rad"][have], p["CL"][have], p["CD"][have], p["Cm"][have]
        )
        qr = wc.q_ratio
        for c in WALL_COEFFICIENTS:
            cols[f"{c}_corrected"][have] = p[c][have] / qr
            cols[f"sd_{c}_corrected"][have] = p[f"sd_{c}"][have] / qr
        cols["CL_corrected"][have] = wc.cl
        cols["CD_corrected"][have] = wc.cd
        cols["Cm_corrected"][have] = wc.cm
        for k, v in (
            ("wall_eps_solid", wc.eps_solid), ("wall_eps_wake", wc.eps_wake),
            ("wall_q_ratio", qr), ("wall_delta_aoa_rad", wc.delta_aoa_rad),
            ("wall_delta_CD_induced", wc.delta_cd_induced),
            ("wall_delta_CL_curvature", wc.delta_cl_curvature),
            ("wall_delta_Cm_curvature", wc.delta_cm_curvature),
            ("aoa_corrected_rad", wc.aoa_rad), ("q_corrected_Pa", p["q_Pa"][have] * qr),
        ):  # fmt: skip
            sizes[k][have] = v
        rec = wc.record
    else:
        rec = _no_record("wall_corrections", "no point with coefficients", ())
    return with_updates(
        p,
        arrays={**cols, **sizes},
        flag={"wall_corrected": have},
        meta={**_records(p, rec), "_note": f"{rec.values.get('kind', '')} section; Cm taken "
              "about the MRP as the quarter chord"},
    )  # fmt: skip


@stage("repeatability")
def repeatability_stage(p: Points) -> Points:
    """Measured repeatability σ per coefficient from repeat points
    (:func:`cdpr.analysis.corrections.repeatability`): ``repeat_group`` (s,) names each point's
    condition (the index of the point it repeats, or its own; -1 none).  Adds ``sd_repeat_<C>``
    (the pooled σ, on every wind-on point) and ``sd_propagated_<C>`` (RMS of the propagated σ over
    the repeat points); flag ``repeatability_disagrees`` on the repeat points when the two disagree
    beyond their expected (chi-square) spread.  Without repeat points: NaN and a note."""
    s = p.n
    g = np.asarray(p.arrays.get("repeat_group", np.full(s, -1)), dtype=np.int64)
    C = np.stack([p[c] for c in COEFFICIENTS], axis=1)
    sdC = np.stack([p[f"sd_{c}"] for c in COEFFICIENTS], axis=1)
    on = (p["kind"] == "wind_on") & np.isfinite(C).all(axis=1) & (g >= 0)
    ids, counts = np.unique(g[on], return_counts=True)
    rep = on & np.isin(g, ids[counts >= 2])
    out = {f"sd_repeat_{c}": np.full(s, np.nan) for c in COEFFICIENTS}
    out.update({f"sd_propagated_{c}": np.full(s, np.nan) for c in COEFFICIENTS})
    if not rep.any():
        rec = _no_record("repeatability", "no repeated wind-on point in the run", ())
        return with_updates(p, arrays=out, meta={**_records(p, rec), "_note": "no repeat points"})
    r = repeatability(g[rep], C[rep], sdC[rep])
    windy = (p["kind"] == "wind_on") & np.isfinite(C).all(axis=1)
    for k, c in enumerate(COEFFICIENTS):
        out[f"sd_repeat_{c}"][windy] = r.sigma_repeat[k]
        out[f"sd_propagated_{c}"][windy] = r.sigma_propagated[k]
    bad = [c for k, c in enumerate(COEFFICIENTS) if r.disagree[k]]
    return with_updates(
        p,
        arrays=out,
        flag={"repeatability_disagrees": rep & bool(bad)},
        meta={
            **_records(p, r.record),
            "_note": f"dof {r.dof}" + (f"; disagree: {', '.join(bad)}" if bad else ""),
        },
    )


@dataclass(frozen=True)
class PointSpectra:
    """The spectrum check of every point (computed from the samples, which the core does not
    hold): ``modes_Hz`` (s, 6) the rig's natural frequencies at each point's pose (NaN: none),
    ``too_few_periods`` and ``peak_near_mode`` (s,), ``peak_Hz`` (s, m), and the spectra of each
    point for the report's plot (``freqs_Hz`` (s) arrays, ``psd`` (s) (m, nf) arrays)."""

    modes_Hz: NDArray[np.float64]
    too_few_periods: NDArray[np.bool_]
    peak_near_mode: NDArray[np.bool_]
    peak_Hz: NDArray[np.float64]
    freqs_Hz: list[NDArray[np.float64]]
    psd: list[NDArray[np.float64]]


def point_spectra(
    rig: Rig,
    t_ns: NDArray[np.int64],
    tensions_N: NDArray[np.float64],
    ranges: Sequence[tuple[int, int]],
    poses: NDArray[np.float64],
) -> PointSpectra:
    """:func:`cdpr.analysis.stiffness.spectrum_check` of each point's tension window against the
    rig's modes at the point's mean pose (:func:`cdpr.analysis.stiffness.rig_modes`).  A window
    with fewer than 8 finite samples, or a pose where no tension distribution exists, gets NaN."""
    from cdpr.analysis.errors import CdprError
    from cdpr.analysis.stiffness import rig_modes, spectrum_check

    s, m = len(ranges), tensions_N.shape[1]
    # the mean sample rate over the run: reception times come in bursts (a loaded host, a pty), so
    # the median interval can be near zero while the samples are evenly spaced at the source
    span_ns = float(t_ns[-1] - t_ns[0]) if len(t_ns) > 1 else 0.0
    fs = (len(t_ns) - 1) * 1e9 / span_ns if span_ns > 0 else float("nan")
    modes = np.full((s, 6), np.nan)
    few = np.zeros(s, bool)
    near = np.zeros(s, bool)
    peak = np.full((s, m), np.nan)
    freqs: list[NDArray[np.float64]] = []
    psd: list[NDArray[np.float64]] = []
    for i, (a, b) in enumerate(ranges):  # one Welch estimate per point (vectorised inside)
        freqs.append(np.zeros(0))
        psd.append(np.zeros((m, 0)))
        x = tensions_N[a:b]
        x = x[np.isfinite(x).all(axis=1)]
        if x.shape[0] < 8 or not np.isfinite(poses[i]).all() or not np.isfinite(fs):
            continue
        try:
            f = rig_modes(rig, poses[i, :3], poses[i, 3:]).modes.frequencies_Hz
        except CdprError:
            continue
        modes[i] = f
        if not np.isfinite(f).any():
            continue
        sc = spectrum_check(x, fs, f)
        few[i], near[i], peak[i] = sc.too_few_periods, bool(sc.peak_near_mode.any()), sc.peak_Hz
        freqs[i], psd[i] = sc.freqs_Hz, sc.psd
    return PointSpectra(modes, few, near, peak, freqs, psd)


@stage("spectrum_check")
def spectrum_stage(p: Points, *, spectra: PointSpectra) -> Points:
    """Per point the rig's lowest natural frequency (``lowest_mode_Hz``) and the flags of the
    tension-spectrum check: ``too_few_periods`` (the averaging window holds fewer than 10 periods
    of the lowest mode), ``spectrum_peak_near_mode`` (a tension's spectral peak within 10 % of a
    mode), ``no_modes`` (no mode could be computed at the point)."""
    sp = spectra
    if sp.modes_Hz.shape[0] != p.n:
        raise InputError(f"spectra: expected {p.n} points, got {sp.modes_Hz.shape[0]}")
    none = ~np.isfinite(sp.modes_Hz).any(axis=1)
    rec = CorrectionRecord(
        name="spectrum_check",
        source="Welch PSD of each tension over the point's window; the rig's modes at the "
        "point's pose (stiffness: EA/l + tension term; mass and inertia from the rig file)",
        values={"points_too_few_periods": int(sp.too_few_periods.sum()),
                "points_peak_near_mode": int(sp.peak_near_mode.sum())},
    )  # fmt: skip
    low = np.where(none, np.nan, np.nanmin(np.where(none[:, None], 1.0, sp.modes_Hz), axis=1))
    return with_updates(
        p,
        arrays={"lowest_mode_Hz": low, "spectrum_peak_Hz": sp.peak_Hz},
        flag={
            "too_few_periods": sp.too_few_periods,
            "spectrum_peak_near_mode": sp.peak_near_mode,
            "no_modes": none,
        },
        meta=_records(p, rec),
    )


def correction_stages(
    rig: Rig,
    geometry: ModelGeometry | None,
    tunnel: TunnelSection | None,
    wind_off_mps: float = 1.0,
    windage_sigma_rel: float = 0.15,
    spectra: PointSpectra | None = None,
) -> dict[str, list[Stage]]:
    """The correction stages for :func:`reduction_stages`'s slots: zero drift, flow conditions,
    windage, wall corrections, repeatability (``tunnel``: the test matrix's ``[tunnel]``; None:
    windage from measured tares only, no wall corrections, both flagged), and the spectrum check
    when ``spectra`` (:func:`point_spectra`) is given."""
    out: dict[str, list[Stage]] = {
        "zero_drift": [zero_drift_stage]
        + ([] if spectra is None else [functools.partial(spectrum_stage, spectra=spectra)]),
        "windage": [
            functools.partial(
                windage_stage,
                rig=rig,
                section=None if tunnel is None else tunnel.geometry,
                geometry=geometry,
                sigma_rel=windage_sigma_rel,
                wind_off_mps=wind_off_mps,
            )
        ],
    }
    if geometry is not None:
        out["flow_conditions"] = [
            functools.partial(
                flow_conditions_stage, chord_m=geometry.chord_m, wind_off_mps=wind_off_mps
            )
        ]
        out["wall_corrections"] = [
            functools.partial(
                wall_corrections_stage, walls=None if tunnel is None else tunnel.walls
            )
        ]
        out["repeatability"] = [repeatability_stage]
    return out


def reduce_points(points: Points, stages: list[Stage]) -> Points:
    """Run the stages (see :func:`cdpr.analysis.reduction.run_stages`)."""
    return run_stages(points, stages)


def _sd(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0.0, None))


def points_table(
    p: Points,
    rig: Rig,
    labels: Sequence[str],
    columns_before: Mapping[str, Any] | None = None,
    columns_after: Mapping[str, Any] | None = None,
) -> pd.DataFrame:
    """The per-point table: one row per test point (see docs/analysis.md for every column)."""
    s = p.n
    if len(labels) != s:
        raise InputError(f"labels: expected {s}, got {len(labels)}")
    cols: dict[str, Any] = dict(columns_before or {})
    cols["point"] = list(labels)
    cols["kind"] = p["kind"]
    cols["flags"] = p.flag_text()
    for k, c in enumerate(POSE_COLUMNS):
        cols[c] = p["pose"][:, k]
    for k, c in enumerate(POSE_COLUMNS):
        cols[f"sd_{c}"] = _sd(p["pose_cov"])[:, k]
    cols["airspeed_mps"] = p["airspeed_mps"]
    cols["density_kgpm3"] = p["density_kgpm3"]
    cols["q_Pa"] = p.arrays.get("q_Pa", np.full(s, np.nan))
    cols["aoa_rad"] = p.arrays.get("aoa_rad", np.full(s, np.nan))
    cols["sideslip_rad"] = p.arrays.get("sideslip_rad", np.full(s, np.nan))
    cols["tare_point"] = [labels[j] if j >= 0 else "" for j in p["tare_index"]]
    at_mrp = "wrench_mrp_N" in p.arrays
    W = p["wrench_mrp_N"] if at_mrp else p["wrench_N"]
    sd = _sd(p["wrench_mrp_cov"] if at_mrp else p.wrench_cov)
    for k, c in enumerate(WRENCH_COLUMNS):
        cols[c] = W[:, k]
        cols[f"sd_{c}"] = sd[:, k]
    for name, term in p.cov_terms.items():
        for k, c in enumerate(WRENCH_COLUMNS):
            cols[f"sd_{name}_{c}"] = _sd(term)[:, k]
    if "force_B_N" in p.arrays:
        for k, c in enumerate(("fx_B_N", "fy_B_N", "fz_B_N")):
            cols[c] = p["force_B_N"][:, k]
        for k, c in enumerate(("mx_B_Nm", "my_B_Nm", "mz_B_Nm")):
            cols[c] = p["moment_B_Nm"][:, k]
        for c in ("drag_N", "side_N", "lift_N"):
            cols[c] = p[c]
    for c in COEFFICIENTS:
        cols[c] = p.arrays.get(c, np.full(s, np.nan))
        cols[f"sd_{c}"] = p.arrays.get(f"sd_{c}", np.full(s, np.nan))
    for k, name in enumerate(rig.cable_names):
        cols[f"T_{name}_N"] = p["tension_N"][:, k]
        cols[f"sd_T_{name}_N"] = np.sqrt(np.clip(p["tension_cov_N2"][:, k, k], 0.0, None))
        cols[f"dT_{name}_N"] = p["check_dT_N"][:, k]
    cols["check_max_abs_dT_N"] = p["check_max_abs_dT_N"]
    cols.update(correction_columns(p, rig))
    cols.update(columns_after or {})
    return pd.DataFrame(cols)


def _correction_text(p: Points, i: int) -> str:
    """The corrections applied to point i, their sizes and sources, one ``; ``-joined string."""
    a = p.arrays
    out = []
    if "zero_drift_N" in a and np.isfinite(a["zero_drift_N"][i]).all():
        out.append(
            f"zero drift max {np.max(np.abs(a['zero_drift_N'][i])):.4f} N "
            "(linear in time between wind-off zeros)"
        )
    src = str(a["windage_source"][i]) if "windage_source" in a else ""
    if src in ("measured", "model"):
        w = a["windage_N"][i]
        how = (
            "measured tare, fit per speed in aoa/sideslip"
            if src == "measured"
            else ("model: cable drag CD(Re), taut-string end share, from the rig file and [tunnel]")
        )
        out.append(f"windage Fx {w[0]:.4f} N, |F| {np.linalg.norm(w[:3]):.4f} N ({how})")
    if "wall_q_ratio" in a and np.isfinite(a["wall_q_ratio"][i]):
        out.append(
            f"walls q x{a['wall_q_ratio'][i]:.5f}, d_aoa {np.degrees(a['wall_delta_aoa_rad'][i]):.4f}"
            f" deg, dCD_i {a['wall_delta_CD_induced'][i]:.2e} (Barlow, Rae & Pope ch. 10)"
        )
    return "; ".join(out)


def correction_columns(p: Points, rig: Rig) -> dict[str, Any]:
    """The per-point columns of the correction stages that ran (docs/analysis.md): each
    correction's size, the corrected beside the uncorrected coefficients, q/Re/Mach, the
    repeatability σ and the ``corrections`` text (what was applied, its size, its source)."""
    a = p.arrays
    cols: dict[str, Any] = {}
    if "zero_drift_N" in a:
        d = a["zero_drift_N"]
        cols["zero_drift_max_abs_N"] = np.abs(d).max(axis=1) if d.size else np.zeros(p.n)
        for k, name in enumerate(rig.cable_names):
            cols[f"zero_drift_{name}_N"] = d[:, k]
            cols[f"sd_zero_drift_{name}_N"] = a["sd_zero_drift_N"][:, k]
    for key in (
        "relative_humidity", "density_source", "reynolds", "mach", "viscosity_Pas",
        "lowest_mode_Hz",
    ):  # fmt: skip
        if key in a:
            cols[key] = a[key]
    if "windage_N" in a:
        cols["windage_source"] = a["windage_source"]
        for prefix, key in (
            ("windage", "windage_N"),
            ("windage_tare", "windage_tare_N"),
            ("sd_windage_tare", "sd_windage_tare_N"),
            ("windage_model", "windage_model_N"),
        ):
            for k, c in enumerate(WRENCH_COLUMNS):
                cols[f"{prefix}_{c}"] = a[key][:, k]
    for key in (
        "aoa_corrected_rad", "q_corrected_Pa", "wall_eps_solid", "wall_eps_wake", "wall_q_ratio",
        "wall_delta_aoa_rad", "wall_delta_CD_induced", "wall_delta_CL_curvature",
        "wall_delta_Cm_curvature",
        *(f"{c}_corrected" for c in COEFFICIENTS), *(f"sd_{c}_corrected" for c in COEFFICIENTS),
        *(f"sd_repeat_{c}" for c in COEFFICIENTS), *(f"sd_propagated_{c}" for c in COEFFICIENTS),
    ):  # fmt: skip
        if key in a:
            cols[key] = a[key]
    if "corrections" in p.meta:
        cols["corrections"] = [_correction_text(p, i) for i in range(p.n)]
    return cols


def steps_log(p: Points) -> list[dict[str, Any]]:
    """The stage log as plain dicts (for summary.json and the report)."""
    return [
        {
            "stage": st.name,
            "settings": dict(st.settings),
            "points_flagged": st.flagged,
            "note": st.note,
        }
        for st in p.steps
    ]
