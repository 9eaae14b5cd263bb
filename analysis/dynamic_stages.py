"""The stages of a dynamic (forced-oscillation) point: more stages of the one reduction core.

Each is a thin ``@stage`` wrapper around one public function of :mod:`cdpr.analysis.oscillation`,
:mod:`cdpr.analysis.balance_model` (or, shared with the steady order, of
:mod:`cdpr.analysis.corrections` and :mod:`cdpr.analysis.flow`); their one order is
:data:`cdpr.analysis.stages.DYNAMIC_STAGES`, bound by :func:`cdpr.analysis.stages.dynamic_stages`.
The samples come as a bound setting (:class:`DynamicSamples`).  The points an order treats are
the ``oscillation`` and ``oscillation_tare`` points of a run; its wind-off ``zero`` points ride
along for the zero drift and are left alone by the other stages.

Per point the stages add (besides the flags): the motion's fit (``motion_fit``, its amplitude,
frequency and σ, the analysed window), the clock offset, the cable wrench's harmonics
(``cable_harmonics``), the inertia removed (``inertia_removal``: by the tare and by the model), the
derivatives (``derivatives``, ``derivatives_model`` and their columns); the objects (dataclasses of
:mod:`cdpr.analysis.oscillation`) sit in object arrays, one per point (None where a stage could not
treat the point).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .aero import ModelGeometry, flow_angles
from .balance_model import apply_balance_model
from .conventions import COEFFICIENTS
from .errors import InputError
from .harmonics import grid_phases, harmonic_linear_map, harmonic_values, harmonics_from_grid
from .motion import Oscillation
from .oscillation import (
    DYNAMIC_COEFFICIENTS,
    NAMED_DERIVATIVES,
    Body,
    DynamicSettings,
    InertiaRemoval,
    OffsetInput,
    analysis_window,
    clock_offset,
    coverage_factor,
    dynamic_derivatives,
    fit_motion,
    remove_inertia,
    wrench_harmonics,
)
from .reduction import POSE, POSE_COV, WRENCH, Points, stage, with_updates
from .rig import Rig
from .rotations import rotation_from_euler

FloatArray = NDArray[np.float64]

MOVING_KINDS: tuple[str, ...] = ("oscillation", "oscillation_tare")


@dataclass(frozen=True)
class DynamicSamples:
    """The samples of a run the dynamic stages need.

    t_ns: (n,) the load cells' own clock (:func:`cdpr.analysis.oscillation.sample_clock`);
    tensions_N: (n, m); usable: (n,) samples whose mask bits are 0; ranges: (s) ``[start, stop)``
    of each point; pose_t_ns: (k,) camera times (its clock); poses: (k, 6); pose_var: (k, 6) each
    frame's variances in (x, y, z, roll, pitch, yaw); pose_usable: (k,).
    """

    t_ns: NDArray[np.int64]
    tensions_N: FloatArray
    usable: NDArray[np.bool_]
    ranges: Sequence[tuple[int, int]]
    pose_t_ns: NDArray[np.int64]
    poses: FloatArray
    pose_var: FloatArray
    pose_usable: NDArray[np.bool_]


def _moving(p: Points) -> NDArray[np.bool_]:
    return np.isin(p["kind"], MOVING_KINDS)


def _objects(n: int) -> NDArray[Any]:
    return np.full(n, None, dtype=object)


def _oscillation(p: Points, i: Any) -> Oscillation:
    return Oscillation(
        str(p["motion_axis"][i]),
        float(p["motion_amplitude"][i]),
        float(p["motion_frequency_Hz"][i]),
        int(p["motion_cycles"][i]),
        int(p["motion_settling_cycles"][i]),
    )


def _slice(samples: DynamicSamples, i: Any) -> tuple[NDArray[np.int64], FloatArray, Any]:
    a, b = samples.ranges[i]
    return samples.t_ns[a:b], samples.tensions_N[a:b], samples.usable[a:b]


# ------------------------------------------------------------------------------------------------
@stage("motion_fit", wraps=fit_motion)
def motion_fit_stage(p: Points, *, samples: DynamicSamples, settings: DynamicSettings) -> Points:
    """The motion of every oscillation point from its camera frames
    (:func:`cdpr.analysis.oscillation.fit_motion`): the analysed window (whole cycles after the
    settling ones, on the load cells' clock), the pose coordinates as harmonics of the motion's
    phase, the frequency refined.  Adds ``motion_fit`` (objects), ``window_ns`` (s, 2),
    ``cycles_analysed``, ``motion_amplitude_fit`` and ``sd_``, ``motion_frequency_fit_Hz`` and
    ``sd_``, ``motion_phase_sd_rad``, ``motion_distortion``; the point's pose becomes the fitted
    mean with its covariance.  Flags: ``too_few_cycles`` (fewer whole cycles than asked: the
    ones there are analysed), ``motion_amplitude_off_plan``, ``motion_frequency_off_plan``,
    ``motion_not_fitted`` (too few camera frames or cycles: NaN)."""
    if len(samples.ranges) != p.n:
        raise InputError(f"samples: expected {p.n} point ranges, got {len(samples.ranges)}")
    s = p.n
    fits = _objects(s)
    win = np.zeros((s, 2), np.int64)
    cyc = np.zeros(s, np.int64)
    amp, sd_amp, fr, sd_fr, sd_ph, dist = (np.full(s, np.nan) for _ in range(6))
    pose, pose_cov = p[POSE].copy(), p[POSE_COV].copy()
    flags = {w: np.zeros(s, bool) for w in ("too_few_cycles", "motion_amplitude_off_plan",
                                            "motion_frequency_off_plan", "motion_not_fitted")}  # fmt: skip
    H = settings.n_harmonics
    pp = 2 * H + 1
    for i in np.flatnonzero(_moving(p)):  # points, not samples
        osc = _oscillation(p, i)
        t, _, _ = _slice(samples, i)
        if t.size < 2:
            flags["motion_not_fitted"][i] = True
            continue
        a, b, n_c = analysis_window(int(t[0]), int(t[-1]), osc)
        win[i], cyc[i] = (a, b), n_c
        flags["too_few_cycles"][i] = n_c < osc.cycles
        lo, hi = np.searchsorted(samples.pose_t_ns, (a, b))  # frames in time order
        n_frames = int(np.count_nonzero(samples.pose_usable[lo:hi]))
        if n_c < 3 or n_frames < max(4 * pp, settings.min_frames_per_cycle * n_c):
            flags["motion_not_fitted"][i] = True
            pose[i] = np.nan
            continue
        try:
            f = fit_motion(
                samples.pose_t_ns, samples.poses, samples.pose_var, samples.pose_usable, (a, b),
                osc, H,
            )  # fmt: skip
        except InputError:  # too few usable frames or cycles in the window: NaN and the flag
            flags["motion_not_fitted"][i] = True
            pose[i] = np.nan
            continue
        fits[i] = f
        amp[i], sd_amp[i] = f.amplitude, f.sd_amplitude
        fr[i], sd_fr[i] = f.omega_rad_s / (2 * math.pi), f.sd_omega_rad_s / (2 * math.pi)
        sd_ph[i], dist[i] = f.sd_phase_rad, f.distortion
        flags["motion_amplitude_off_plan"][i] = (
            abs(f.amplitude / osc.amplitude - 1.0) > settings.amplitude_tol_rel
        )
        flags["motion_frequency_off_plan"][i] = (
            abs(fr[i] / osc.frequency_Hz - 1.0) > settings.frequency_tol_rel
        )
        pose[i] = f.coef[:, 0]
        pose_cov[i] = f.cov[0::pp, 0::pp]
    return with_updates(
        p,
        arrays={
            "motion_fit": fits,
            "window_ns": win,
            "cycles_analysed": cyc,
            "motion_amplitude_fit": amp,
            "sd_motion_amplitude_fit": sd_amp,
            "motion_frequency_fit_Hz": fr,
            "sd_motion_frequency_fit_Hz": sd_fr,
            "motion_phase_sd_rad": sd_ph,
            "motion_distortion": dist,
            POSE: pose,
            POSE_COV: pose_cov,
        },  # fmt: skip
        flag=flags,
        meta={
            "_note": f"{int(np.sum([f is not None for f in fits]))} motion(s) fitted, {H} harmonics"
        },
    )


@stage("clock_offset", wraps=clock_offset)
def clock_offset_stage(
    p: Points, *, rig: Rig, samples: DynamicSamples, settings: DynamicSettings, body: Body
) -> Points:
    """The camera's clock offset from the run's wind-off oscillations
    (:func:`cdpr.analysis.oscillation.clock_offset`): ``clock_offset_ns``, ``sd_clock_offset_ns``
    on every oscillation point, the estimate in ``meta["clock_offset"]``.  Flag
    ``clock_offset_not_identified`` on every oscillation point when the run has no wind-off
    oscillation with a fitted motion or the σ is above the settings' bound: the offset is then 0
    (no correction) and its σ is not counted, which the flag says."""
    tares = []
    for i in np.flatnonzero(p["kind"] == "oscillation_tare"):  # points, not samples
        f = p["motion_fit"][i]
        if f is None:
            continue
        t, T, u = _slice(samples, i)
        a, b = (int(x) for x in p["window_ns"][i])
        tares.append(OffsetInput(t, T, u, f, (a, b)))
    co = clock_offset(rig, tares, body, settings.offset_prior_ns, settings.max_offset_sd_ns)
    moving = _moving(p)
    off = co.offset_ns if co.identified else 0.0
    sd = co.sd_ns if co.identified else math.nan
    note = (
        f"{co.offset_ns / 1e6:.4f} ms ± {co.sd_ns / 1e6:.4f} ms ({co.note})"
        if co.identified
        else f"not identified ({co.note}; estimate {co.offset_ns / 1e6:.4g} ms ± "
        f"{co.sd_ns / 1e6:.3g} ms): 0 used"
    )
    return with_updates(
        p,
        arrays={
            "clock_offset_ns": np.where(moving, off, np.nan),
            "sd_clock_offset_ns": np.where(moving, sd, np.nan),
        },
        flag={"clock_offset_not_identified": moving & (not co.identified)},
        meta={"clock_offset": co, "_note": note},
    )


@stage("cable_wrench_harmonics", wraps=wrench_harmonics)
def wrench_harmonics_stage(
    p: Points, *, rig: Rig, samples: DynamicSamples, settings: DynamicSettings, body: Body
) -> Points:
    """The cable wrench ``-A(q) T - G(q)`` at every load-cell sample of each point's window, the
    pose from its fitted motion at the camera's time (the clock offset removed), and its
    harmonics (:func:`cdpr.analysis.oscillation.wrench_harmonics`), the tensions less the zero
    drift when that stage ran.  Adds ``cable_harmonics`` (objects), ``tension_outside_samples``,
    ``min_tension_margin_N``.  Flag ``tension_limit_in_cycle``: a tension outside its limits at
    some sample of the window; ``cable_wrench_not_fitted`` (too few usable samples or cycles in
    the window: NaN)."""
    s = p.n
    out = _objects(s)
    outside = np.zeros(s, np.int64)
    margin = np.full(s, np.nan)
    no_fit = np.zeros(s, bool)
    drift = p.arrays.get("zero_drift_N")
    for i in np.flatnonzero(_moving(p)):  # points, not samples
        f = p["motion_fit"][i]
        if f is None:
            continue
        t, T, u = _slice(samples, i)
        if drift is not None and np.isfinite(drift[i]).all():
            T = T - drift[i]
        a, b = (int(x) for x in p["window_ns"][i])
        off = float(np.nan_to_num(p["clock_offset_ns"][i]))
        try:
            w = wrench_harmonics(
                rig, t, T, u, f, off, (a, b), body, settings.loop_bins, settings.n_grid
            )
        except InputError:  # too few usable load-cell samples or cycles in the window
            no_fit[i] = True
            continue
        out[i] = w
        outside[i], margin[i] = w.tension_outside, w.min_margin_N
    return with_updates(
        p,
        arrays={
            "cable_harmonics": out,
            "tension_outside_samples": outside,
            "min_tension_margin_N": margin,
        },
        flag={"tension_limit_in_cycle": outside > 0, "cable_wrench_not_fitted": no_fit},
    )


@stage("inertia_removal", wraps=remove_inertia)
def inertia_removal_stage(p: Points, *, settings: DynamicSettings) -> Points:
    """The inertia removed from each oscillation point (:func:`cdpr.analysis.oscillation.
    remove_inertia`): by its wind-off oscillation tare (``inertia_tare_index``) and, beside it,
    by the rig file's mass and inertia.  Adds ``inertia_removal`` (objects), ``inertia_method``,
    ``tare_index``; the point's mean wrench (``wrench_P_O_N_Nm``) and its σ terms become the
    aerodynamic wrench's mean.  Flags: ``no_inertia_tare`` (none serves the point: the model's
    inertia used, said as such), ``inertia_tare_motion_mismatch`` (the tare's fitted amplitude or
    frequency differs from the point's beyond the plan tolerances), ``inertia_tare_unusable``
    (the tare named has no fitted wrench: the model used)."""
    s = p.n
    out = _objects(s)
    method = np.full(s, "", dtype=object)
    tix = np.asarray(p.arrays.get("inertia_tare_index", np.full(s, -1)), dtype=np.int64)
    used = np.full(s, -1, np.int64)
    W = np.full((s, 6), np.nan)
    terms = {k: np.zeros((s, 6, 6)) for k in ("load_cells", "pose", "clock_offset")}
    flags = {w: np.zeros(s, bool) for w in ("no_inertia_tare", "inertia_tare_motion_mismatch",
                                            "inertia_tare_unusable")}  # fmt: skip
    for i in np.flatnonzero(p["kind"] == "oscillation"):  # points, not samples
        w = p["cable_harmonics"][i]
        if w is None:
            continue
        j = int(tix[i])
        tare = p["cable_harmonics"][j] if j >= 0 else None
        if j < 0:
            flags["no_inertia_tare"][i] = True
        elif tare is None:
            flags["inertia_tare_unusable"][i] = True
        else:
            used[i] = j
            fa, fb = p["motion_fit"][i], p["motion_fit"][j]
            flags["inertia_tare_motion_mismatch"][i] = (
                abs(fa.amplitude / fb.amplitude - 1.0) > settings.amplitude_tol_rel
                or abs(fa.omega_rad_s / fb.omega_rad_s - 1.0) > settings.frequency_tol_rel
            )
        sd_off = float(np.nan_to_num(p["sd_clock_offset_ns"][i]))
        r = remove_inertia(w, tare, sd_off)
        out[i], method[i] = r, r.method
        pp = r.aero.shape[1]
        W[i] = r.aero[:, 0]
        for k in terms:
            terms[k][i] = np.asarray(r.terms[k])[0::pp, 0::pp]
    return with_updates(
        p,
        arrays={
            "inertia_removal": out,
            "inertia_method": method.astype(str),
            "tare_index": used,
            WRENCH: W,
        },  # fmt: skip
        terms=terms,
        flag=flags,
        replace_terms=True,
    )


@stage("balance_interaction", wraps=apply_balance_model)
def balance_harmonics_stage(
    p: Points, *, interaction: Any = None, second_order: Any = None, n_grid: int = 128
) -> Points:
    """The balance calibration of ``cdpr calibrate balance`` applied along the cycle
    (:func:`cdpr.analysis.balance_model.apply_balance_model` at each phase of one cycle of the
    series, the harmonics again; σ by the same map): the aerodynamic wrench's harmonics (both
    inertia removals) and the hysteresis bins.  Without a calibration: nothing, said in the log."""
    if interaction is None and second_order is None:
        return with_updates(p, meta={"_note": "no balance calibration given: not applied"})
    K1, K2 = second_order if second_order is not None else (interaction, None)
    K1 = np.asarray(K1, dtype=np.float64)
    if K1.shape != (6, 6) or not np.all(np.isfinite(K1)):
        raise InputError(f"interaction: expected a finite (6, 6) matrix, got {K1.shape}")
    out = _objects(p.n)
    W = p[WRENCH].copy()
    g = grid_phases(n_grid)
    for i in np.flatnonzero(p["kind"] == "oscillation"):  # points, not samples
        r: InertiaRemoval | None = p["inertia_removal"][i]
        if r is None:
            continue
        H = (r.aero.shape[1] - 1) // 2

        def through(coef: FloatArray, H: int = H) -> tuple[FloatArray, FloatArray]:
            Wg, Jg = apply_balance_model(harmonic_values(coef, g).T, K1, K2)
            return harmonics_from_grid(Wg, H), harmonic_linear_map(Jg, H)

        aero, J = through(r.aero)
        aero_m, Jm = through(r.aero_model)
        loops = r.loops
        if loops is not None:
            flat = loops.reshape(-1, 6)
            ok = np.isfinite(flat).all(axis=1)
            new = np.full_like(flat, np.nan)
            new[ok] = apply_balance_model(flat[ok], K1, K2)[0]
            loops = new.reshape(loops.shape)
        out[i] = dataclasses.replace(
            r,
            aero=aero,
            aero_model=aero_m,
            terms={k: J @ v @ J.T for k, v in r.terms.items()},
            terms_model={k: Jm @ v @ Jm.T for k, v in r.terms_model.items()},
            loops=loops,
        )
        W[i] = aero[:, 0]
    keep = np.array([o is None for o in out])
    out[keep] = p["inertia_removal"][keep]
    return with_updates(
        p,
        arrays={"inertia_removal": out, WRENCH: W},
        meta={"_note": "applied along the cycle" + (" (second order)" if K2 is not None else "")},
    )


def _mean_flow(pose: FloatArray, geometry: ModelGeometry | None) -> tuple[FloatArray, FloatArray]:
    ok = np.isfinite(pose).all(axis=1)
    aoa, beta = np.full(pose.shape[0], np.nan), np.full(pose.shape[0], np.nan)
    if ok.any():
        nose = (-1.0, 0.0, 0.0) if geometry is None else geometry.nose_P
        up = (0.0, 0.0, 1.0) if geometry is None else geometry.up_P
        aoa[ok], beta[ok] = flow_angles(rotation_from_euler(pose[ok, 3:]), nose, up)
    return aoa, beta


@stage("dynamic_derivatives", wraps=dynamic_derivatives)
def derivatives_stage(
    p: Points, *, geometry: ModelGeometry | None, settings: DynamicSettings
) -> Points:
    """The derivatives of each oscillation point in body axes
    (:func:`cdpr.analysis.oscillation.dynamic_derivatives`), with the inertia removed by the tare
    (or the model when none serves) and, beside them, by the model: per coefficient of
    :data:`~cdpr.analysis.oscillation.DYNAMIC_COEFFICIENTS` ``<C>_inphase``, ``<C>_outphase``
    with ``sd_``, ``harmonic_content_<C>``; the named derivatives of the axis with ``sd_``,
    ``U95_`` (the 95 % half-width, Student's t on the Welch-Satterthwaite degrees of freedom),
    ``dwell_s_`` (the dwell reaching the goals) and ``<name>_model``; ``reduced_frequency``;
    the means: ``wrench_mrp_O_N_Nm`` (and its covariance), ``CD ... Cn`` with ``sd_``, ``q_Pa``,
    ``aoa_rad``, ``sideslip_rad``.  Flags: ``nonlinear_response`` (the primary coefficients'
    harmonics 2..H above the threshold and significant: the derivatives describe the fundamental
    only), ``no_airspeed`` / ``no_density`` (no coefficients), ``wind_off_oscillation`` (an
    oscillation point below the wind-off speed: the aerodynamic wrench's harmonics only),
    ``no_geometry``."""
    s = p.n
    names = list(DYNAMIC_COEFFICIENTS)
    arr: dict[str, Any] = {"reduced_frequency": np.full(s, np.nan)}
    for c in names:
        for part in ("inphase", "outphase"):
            arr[f"{c}_{part}"] = np.full(s, np.nan)
            arr[f"sd_{c}_{part}"] = np.full(s, np.nan)
        arr[f"harmonic_content_{c}"] = np.full(s, np.nan)
    named = sorted({n for v in NAMED_DERIVATIVES.values() for n, *_ in v})
    for n in named:
        for pre in ("", "sd_", "U95_", "dwell_s_"):
            arr[f"{pre}{n}"] = np.full(s, np.nan)
        arr[f"{n}_model"] = np.full(s, np.nan)
    for c in COEFFICIENTS:
        arr[c] = np.full(s, np.nan)
        arr[f"sd_{c}"] = np.full(s, np.nan)
    wm = np.full((s, 6), np.nan)
    wm_cov = np.full((s, 6, 6), np.nan)
    q_Pa = np.full(s, np.nan)
    ders, ders_m = _objects(s), _objects(s)
    V, rho = p["airspeed_mps"], p["density_kgpm3"]
    osc = p["kind"] == "oscillation"
    flags = {w: np.zeros(s, bool) for w in ("nonlinear_response", "no_airspeed", "no_density",
                                            "wind_off_oscillation", "no_geometry")}  # fmt: skip
    for i in np.flatnonzero(osc):  # points, not samples
        r: InertiaRemoval | None = p["inertia_removal"][i]
        f = p["motion_fit"][i]
        if r is None or f is None:
            continue
        q = 0.5 * rho[i] * V[i] ** 2
        if not np.isfinite(V[i]):
            flags["no_airspeed"][i] = True
        elif not (np.isfinite(rho[i]) and rho[i] > 0):
            flags["no_density"][i] = True
        elif V[i] <= settings.wind_off_mps:
            flags["wind_off_oscillation"][i] = True
        if geometry is None:
            flags["no_geometry"][i] = True
            continue
        windy = bool(np.isfinite(q) and V[i] > settings.wind_off_mps)
        qq = float(q) if windy else 0.0
        a, b = p["window_ns"][i]
        g = geometry
        common: dict[str, Any] = dict(
            area_m2=g.area_m2, span_m=g.span_m, chord_m=g.chord_m, mrp_P_m=g.mrp_P_m,
            nose_P=g.nose_P, up_P=g.up_P, settings=settings,
        )  # fmt: skip
        d = dynamic_derivatives(
            r.aero, r.terms, f, str(p["motion_axis"][i]), qq, float(V[i]),
            window_s=(int(b) - int(a)) * 1e-9, loops=r.loops,
            loop_phase=p["cable_harmonics"][i].loop_phase, dof=r.dof, **common,
        )  # fmt: skip
        dm = dynamic_derivatives(
            r.aero_model, r.terms_model, f, str(p["motion_axis"][i]), qq, float(V[i]),
            dof=r.dof_model, **common,
        )  # fmt: skip
        ders[i], ders_m[i] = d, dm
        wm[i] = d.wrench_mrp[:, 0]
        pp = d.wrench_mrp.shape[1]
        wm_cov[i] = sum(np.asarray(v)[0::pp, 0::pp] for v in d.wrench_mrp_terms.values())
        if not windy:
            continue
        q_Pa[i] = q
        arr["reduced_frequency"][i] = d.k
        for k, c in enumerate(names):
            arr[f"{c}_inphase"][i], arr[f"sd_{c}_inphase"][i] = d.inphase[k], d.sd_inphase[k]
            arr[f"{c}_outphase"][i], arr[f"sd_{c}_outphase"][i] = d.outphase[k], d.sd_outphase[k]
            arr[f"harmonic_content_{c}"][i] = d.harmonic_content[k]
        for n, (v, sd) in d.named.items():
            arr[n][i], arr[f"sd_{n}"][i], arr[f"dwell_s_{n}"][i] = v, sd, d.dwell_s[n]
            arr[f"U95_{n}"][i] = coverage_factor(d.named_dof[n]) * sd
            arr[f"{n}_model"][i] = dm.named[n][0]
        tot = sum(d.terms.values())
        sdc = np.sqrt(np.clip(np.diag(tot), 0.0, None)).reshape(8, pp)
        for c in COEFFICIENTS:
            k = names.index(c)
            arr[c][i], arr[f"sd_{c}"][i] = d.coef[k, 0], sdc[k, 0]
        flags["nonlinear_response"][i] = d.nonlinear
    aoa, beta = _mean_flow(p[POSE], geometry)
    keep = ~_moving(p)
    aoa[keep], beta[keep] = np.nan, np.nan
    return with_updates(
        p,
        arrays={
            **arr,
            "derivatives": ders,
            "derivatives_model": ders_m,
            "q_Pa": q_Pa,
            "wrench_mrp_O_N_Nm": wm,
            "wrench_mrp_cov_O": wm_cov,
            "aoa_rad": aoa,
            "sideslip_rad": beta,
        },  # fmt: skip
        flag=flags,
    )
