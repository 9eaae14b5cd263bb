"""The correction stages of the reduction core (``cdpr analyze --matrix``): zero drift, the tension
spectra against the rig's modes, flow conditions, windage, wall corrections and repeatability.

Each is a thin ``@stage`` wrapper around one public function of :mod:`cdpr.analysis.corrections`,
:mod:`cdpr.analysis.stiffness`, :mod:`cdpr.analysis.flow` or :mod:`cdpr.analysis.windage`, records
what it did (a :class:`~cdpr.analysis.records.CorrectionRecord` in ``meta["corrections"]``), adds its
size per point and flags the points it cannot treat.  Their place in the one order is in
:data:`cdpr.analysis.stages.STEADY_STAGES`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .aero import ModelGeometry
from .conventions import COEFFICIENTS
from .corrections import WallParameters, corrected_coefficients, repeatability, zero_drift
from .errors import InputError
from .flow import flow_conditions
from .records import CorrectionRecord
from .reduction import POSE, WRENCH, Points, stage, with_updates
from .rig import Rig
from .stiffness import point_spectra
from .test_section import SectionGeometry
from .windage import windage_correction

FloatArray = NDArray[np.float64]


def wind_points(p: Points) -> NDArray[np.bool_]:
    """Points that carry an aerodynamic load of interest (wind on, or not known to be off)."""
    return np.isin(p["kind"], ("wind_on", "oscillation", "unknown"))


def _records(p: Points, *recs: CorrectionRecord) -> dict[str, Any]:
    """``meta`` with the correction records appended (the report lists them per run)."""
    return {"corrections": [*p.meta.get("corrections", ()), *(r.as_dict() for r in recs)]}


def _not_applied(name: str, why: str, flags: tuple[str, ...] = ()) -> CorrectionRecord:
    return CorrectionRecord(name=name, source="not applied", values={"why": why}, flags=flags)


@stage("zero_drift", wraps=zero_drift)
def zero_drift_stage(p: Points, *, apply: bool = True) -> Points:
    """Remove each cable's zero drift from the tensions of every point.

    The wind-off zeros are the points of kind ``zero`` (level, wind off: before and after a run and
    between blocks); their mean tensions are interpolated linearly in time to the middle of each
    point's window (:func:`cdpr.analysis.corrections.zero_drift`, relative to the first zero) and
    subtracted.  A
    point's corrected tensions are then a combination of several points' raw means (its own and the
    zeros'), ``tension_mix`` (s, s): the covariance is carried as one, so that the drift a wind-on
    point shares with its tare cancels in their difference (``tension_cov_raw_N2`` keeps each
    point's own; ``tension_cov_N2`` becomes that of the corrected tensions).  Points after the last
    zero are held there and flagged ``no_closing_zero``, before the first ``no_opening_zero``;
    without any zero point every point is flagged ``no_zero_drift_correction``.  Adds
    ``zero_drift_N`` and ``sd_zero_drift_N`` (s, m).  With ``apply=False`` (no test matrix:
    balance values) nothing is corrected here or in the later correction stages, and the wind-on
    points are flagged ``uncorrected``."""
    s, m = p["tension_N"].shape
    if not apply:
        return with_updates(
            p,
            flag={"uncorrected": wind_points(p)},
            meta={"_note": "corrections not requested (no test matrix): balance values"},
        )
    zero = (p["kind"] == "zero") & np.isfinite(p["tension_N"]).all(axis=1)
    if not zero.any():
        why = "no wind-off zero point (kind 'zero') in the run"
        rec = _not_applied("zero_drift", why, ("no_zero_drift_correction",))
        return with_updates(
            p,
            arrays={"zero_drift_N": np.full((s, m), np.nan), "sd_zero_drift_N": np.zeros((s, m))},
            flag={"no_zero_drift_correction": np.ones(s, bool)},
            meta={**_records(p, rec), "_note": why + ": drift not corrected"},
        )
    raw = p["tension_cov_N2"]
    zsd = np.sqrt(np.clip(np.diagonal(raw[zero], axis1=1, axis2=2), 0.0, None))
    # at the middle of each window: a point's mean is its tensions there (a drift is linear)
    t_mid = np.asarray(p.arrays.get("mid_ns", p["start_ns"]), dtype=np.int64)
    d = zero_drift(t_mid, t_mid[zero], p["tension_N"][zero], zsd)
    mix = np.asarray(p.arrays.get("tension_mix", np.eye(s)), dtype=np.float64)
    mix = mix - d.weights @ mix[zero]  # T'_i = T_i - sum_z w_iz T_z, on the raw means
    return with_updates(
        p,
        arrays={
            "tension_N": p["tension_N"] - d.drift_N,
            "tension_cov_N2": np.einsum("sk,kab->sab", mix**2, raw),
            "tension_cov_raw_N2": raw,
            "tension_mix": mix,
            "zero_drift_N": d.drift_N,
            "sd_zero_drift_N": d.sigma_N,
        },
        flag={"no_closing_zero": d.no_closing_zero, "no_opening_zero": d.no_opening_zero},
        meta={
            **_records(p, d.record),
            "_note": f"{int(zero.sum())} zeros, max |drift| {float(np.max(np.abs(d.drift_N))):.4g} N",
        },
    )


@dataclass(frozen=True)
class PointSamples:
    """The tension samples of a run and each point's range in them (what the stages that look at
    a point's time series need): ``t_ns`` (n,), ``tensions_N`` (n, m), ``ranges`` (s) of
    ``[start, stop)`` indices."""

    t_ns: NDArray[np.int64]
    tensions_N: FloatArray
    ranges: Sequence[tuple[int, int]]


@stage("spectrum_check", wraps=point_spectra)
def spectrum_stage(p: Points, *, rig: Rig, samples: PointSamples) -> Points:
    """The tension spectrum of every point against the rig's modes at its pose
    (:func:`cdpr.analysis.stiffness.point_spectra`): ``lowest_mode_Hz``, ``spectrum_peak_Hz`` and
    the flags ``too_few_periods`` (the window holds fewer than 10 periods of the lowest mode),
    ``spectrum_peak_near_mode`` (a tension's spectral peak within 10 % of a mode), ``no_modes``
    (no mode could be computed at the point).  The spectra go to ``meta["spectra"]`` (the
    report's figures)."""
    if len(samples.ranges) != p.n:
        raise InputError(f"samples: expected {p.n} point ranges, got {len(samples.ranges)}")
    sp = point_spectra(rig, samples.t_ns, samples.tensions_N, samples.ranges, p[POSE])
    none = np.asarray(~np.isfinite(sp.modes_Hz).any(axis=1))
    rec = CorrectionRecord(
        name="spectrum_check",
        source="Welch PSD of each tension over the point's window; the rig's modes at the "
        "point's pose (stiffness: EA/l + tension term; mass and inertia from the rig file)",
        values={
            "points_too_few_periods": int(sp.too_few_periods.sum()),
            "points_peak_near_mode": int(sp.peak_near_mode.sum()),
        },
    )
    low = np.where(none, np.nan, np.nanmin(np.where(none[:, None], 1.0, sp.modes_Hz), axis=1))
    return with_updates(
        p,
        arrays={"lowest_mode_Hz": low, "spectrum_peak_Hz": sp.peak_Hz},
        flag={
            "too_few_periods": sp.too_few_periods,
            "spectrum_peak_near_mode": sp.peak_near_mode,
            "no_modes": none,
        },
        meta={**_records(p, rec), "spectra": sp},
    )


@stage("flow_conditions", wraps=flow_conditions)
def flow_conditions_stage(p: Points, *, chord_m: float, wind_off_mps: float = 1.0) -> Points:
    """Density, Reynolds number on the reference chord (viscosity by Sutherland's law), Mach
    number and the viscosity per point (:func:`cdpr.analysis.flow.flow_conditions`):
    ``density_kgpm3``, ``density_source``, ``relative_humidity``, ``reynolds``, ``mach``,
    ``viscosity_Pas``.  Where the point has its mean ``static_pressure_Pa`` and ``temperature_K``
    the density is moist air at its mean ``relative_humidity``; without a humidity it is dry air,
    flagged ``humidity_not_given`` on the points in the wind (wind-on and windage points above
    ``wind_off_mps``: their q depends on it); without p and T the stream's density is kept.
    Points in the wind without a temperature get NaN Re and Mach and ``no_temperature``."""
    s = p.n
    nan = np.full(s, np.nan)
    V = p["airspeed_mps"]
    windy = np.isin(p["kind"], ("wind_on", "windage", "oscillation"))
    windy &= np.isfinite(V) & (V > wind_off_mps)
    rh = np.asarray(p.arrays.get("relative_humidity", nan), dtype=np.float64)
    fc = flow_conditions(
        V,
        np.asarray(p.arrays.get("static_pressure_Pa", nan), dtype=np.float64),
        np.asarray(p.arrays.get("temperature_K", nan), dtype=np.float64),
        chord_m,
        relative_humidity=rh,
        density_kgpm3=p["density_kgpm3"],
        in_flow=windy,
    )
    return with_updates(
        p,
        arrays={
            "density_kgpm3": fc.density_kgpm3,
            "density_source": fc.density_source,
            "relative_humidity": rh,
            "viscosity_Pas": fc.viscosity_Pas,
            "reynolds": fc.reynolds,
            "mach": fc.mach,
        },
        flag={"no_temperature": windy & ~fc.known, "humidity_not_given": windy & fc.dry},
        meta={
            **_records(p, fc.record),
            "_note": f"humidity at {fc.record.values['points_with_humidity']} wind-on point(s), "
            f"dry air at {fc.record.values['points_without_humidity']} (humidity_not_given)",
        },
    )


@stage("windage", wraps=windage_correction)
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
    """Subtract the cable and platform windage from the wind-on points' wrench
    (:func:`cdpr.analysis.windage.windage_correction`: the measured model-off tare, else the model
    from the rig file and the test section, else flag ``no_windage_correction``).  Adds
    ``windage_N`` (what was subtracted), ``windage_source``, ``windage_tare_N`` and
    ``sd_windage_tare_N`` (the measured fit at every point), ``windage_model_N`` and the σ term
    ``windage``."""
    s = p.n
    nose = (-1.0, 0.0, 0.0) if geometry is None else geometry.nose_P
    up = (0.0, 0.0, 1.0) if geometry is None else geometry.up_P
    wc = windage_correction(
        rig,
        section,
        p["kind"],
        p["airspeed_mps"],
        p[WRENCH],
        p[POSE],
        p["tension_N"],
        p["density_kgpm3"],
        np.asarray(p.arrays.get("viscosity_Pas", np.full(s, np.nan)), dtype=np.float64),
        nose,
        up,
        sigma_rel=sigma_rel,
        aoa_degree=aoa_degree,
        sideslip_degree=sideslip_degree,
        wind_off_mps=wind_off_mps,
        angle_tol_rad=angle_tol_rad,
    )
    recs = wc.records or (
        _not_applied(
            "windage",
            "no model-off windage points and no test section ([tunnel])",
            ("no_windage_correction",) if wc.flags["no_windage_correction"].any() else (),
        ),
    )
    on = wc.source != ""
    W = p[WRENCH].copy()
    W[on] = W[on] - wc.applied_N[on]
    return with_updates(
        p,
        arrays={
            WRENCH: W,
            "windage_N": np.where(on[:, None], wc.applied_N, np.nan),
            "windage_source": wc.source,
            "windage_tare_N": wc.measured_N,
            "sd_windage_tare_N": wc.measured_sd_N,
            "windage_model_N": wc.model_N,
        },
        terms={"windage": wc.cov},
        flag=wc.flags,
        meta={**_records(p, *recs), "_note": "; ".join(wc.notes)},
    )


WALL_SIZES: tuple[str, ...] = (
    "wall_eps_solid", "wall_eps_wake", "wall_q_ratio", "wall_delta_aoa_rad",
    "wall_delta_CD_induced", "wall_delta_CL_curvature", "wall_delta_Cm_curvature",
    "aoa_corrected_rad", "q_corrected_Pa",
)  # fmt: skip
"""The per-point sizes of the wall corrections (columns of the points table)."""


@stage("wall_corrections", wraps=corrected_coefficients)
def wall_corrections_stage(p: Points, *, walls: WallParameters | None) -> Points:
    """Wall corrections of the coefficients
    (:func:`cdpr.analysis.corrections.corrected_coefficients`): the uncorrected ``CD ... Cn``,
    ``aoa_rad`` and ``q_Pa`` stay; the corrected ones are added as ``CD_corrected ...``,
    ``aoa_corrected_rad``, ``q_corrected_Pa`` with each correction's size (:data:`WALL_SIZES`).
    CY, Cl, Cn take the blockage only.  Without a test section: NaN and ``no_wall_correction`` on
    every wind-on point with coefficients."""
    s = p.n
    cols = {f"{c}_corrected": np.full(s, np.nan) for c in COEFFICIENTS}
    cols.update({f"sd_{c}_corrected": np.full(s, np.nan) for c in COEFFICIENTS})
    sizes = {k: np.full(s, np.nan) for k in WALL_SIZES}
    have = np.isfinite(p["CL"]) & np.isfinite(p["CD"]) & np.isfinite(p["Cm"])
    have &= np.isfinite(p["aoa_rad"]) & (p["kind"] == "wind_on")  # the model is in the flow
    if walls is None:
        rec = _not_applied(
            "wall_corrections", "no test section ([tunnel])", ("no_wall_correction",)
        )
        return with_updates(
            p, arrays={**cols, **sizes}, flag={"no_wall_correction": have}, meta=_records(p, rec)
        )
    if not have.any():
        rec = _not_applied("wall_corrections", "no point with coefficients")
        return with_updates(p, arrays={**cols, **sizes}, meta=_records(p, rec))
    C = np.stack([p[c][have] for c in COEFFICIENTS], axis=1)
    sdC = np.stack([p[f"sd_{c}"][have] for c in COEFFICIENTS], axis=1)
    cc = corrected_coefficients(walls, p["aoa_rad"][have], C, sdC)
    wc = cc.walls
    for k, c in enumerate(COEFFICIENTS):
        cols[f"{c}_corrected"][have] = cc.coefficients[:, k]
        cols[f"sd_{c}_corrected"][have] = cc.sd[:, k]
    for key, v in (
        ("wall_eps_solid", wc.eps_solid), ("wall_eps_wake", wc.eps_wake),
        ("wall_q_ratio", wc.q_ratio), ("wall_delta_aoa_rad", wc.delta_aoa_rad),
        ("wall_delta_CD_induced", wc.delta_cd_induced),
        ("wall_delta_CL_curvature", wc.delta_cl_curvature),
        ("wall_delta_Cm_curvature", wc.delta_cm_curvature),
        ("aoa_corrected_rad", wc.aoa_rad), ("q_corrected_Pa", p["q_Pa"][have] * wc.q_ratio),
    ):  # fmt: skip
        sizes[key][have] = v
    return with_updates(
        p,
        arrays={**cols, **sizes},
        flag={"wall_corrected": have},
        meta={**_records(p, wc.record), "_note": f"{wc.record.values.get('kind', '')} section; "
              "Cm taken about the MRP as the quarter chord"},
    )  # fmt: skip


@stage("repeatability", wraps=repeatability)
def repeatability_stage(p: Points) -> Points:
    """Measured repeatability σ per coefficient from repeat points
    (:func:`cdpr.analysis.corrections.repeatability`): ``repeat_group`` (s,) names each point's
    condition (the index of the point it repeats, or its own; -1 none).  Adds ``sd_repeat_<C>``
    (the pooled σ, on every wind-on point) and ``sd_propagated_<C>`` (RMS of the propagated σ over
    the repeat points); flag ``repeatability_disagrees`` on the repeat points when the two disagree
    beyond their expected spread.  The repeat scatter is compared with the *random* part of σ
    (``sd_random_<C>``, with its own degrees of freedom ``dof_random_<C>``: Fisher's F) when the
    uncertainty stage ran, else with the total σ (chi-square).  Without repeat points: NaN and a
    note."""
    s = p.n
    g = np.asarray(p.arrays.get("repeat_group", np.full(s, -1)), dtype=np.int64)
    C = np.stack([p[c] for c in COEFFICIENTS], axis=1)
    random = all(f"sd_random_{c}" in p.arrays for c in COEFFICIENTS)
    sdC = np.stack([p[f"sd_random_{c}" if random else f"sd_{c}"] for c in COEFFICIENTS], axis=1)
    nuC = np.stack([p[f"dof_random_{c}"] for c in COEFFICIENTS], axis=1) if random else None
    on = (p["kind"] == "wind_on") & np.isfinite(C).all(axis=1) & (g >= 0)
    ids, counts = np.unique(g[on], return_counts=True)
    rep = on & np.isin(g, ids[counts >= 2])
    out = {f"sd_repeat_{c}": np.full(s, np.nan) for c in COEFFICIENTS}
    out.update({f"sd_propagated_{c}": np.full(s, np.nan) for c in COEFFICIENTS})
    if not rep.any():
        rec = _not_applied("repeatability", "no repeated wind-on point in the run")
        return with_updates(p, arrays=out, meta={**_records(p, rec), "_note": "no repeat points"})
    r = repeatability(g[rep], C[rep], sdC[rep], dof_propagated=None if nuC is None else nuC[rep])
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
