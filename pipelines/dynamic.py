"""The dynamic (forced-oscillation) points of a run through the reduction core (``cdpr analyze``).

:func:`split_plan` parts a run's test points into the steady ones (the steady order) and the
``oscillation`` / ``oscillation_tare`` ones; :func:`reduce_dynamic` runs the latter, with the run's
``zero`` points riding along for the zero drift, through :data:`cdpr.analysis.stages.
DYNAMIC_STAGES` (bound by :func:`cdpr.analysis.stages.dynamic_stages`, the samples on the load
cells' own clock: :func:`cdpr.analysis.clock.sample_clock` in ``load_run``) and returns their rows of the
per-point table (:func:`cdpr.pipelines.points_table.points_table` with the dynamic columns) and
the summary parts; :func:`harmonics_table` is the run's ``harmonics.csv``.  Pipelines only bind:
every number comes from :mod:`cdpr.analysis`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.balance import points_from_events
from cdpr.analysis.conventions import OSCILLATION_POINT_KINDS, WRENCH_COLUMNS
from cdpr.analysis.oscillation import (
    DYNAMIC_COEFFICIENTS,
    Body,
    Derivatives,
    DynamicSettings,
    InertiaRemoval,
)
from cdpr.analysis.reduction import Points, run_stages, with_updates
from cdpr.analysis.stages import Corrections, DynamicSamples, dynamic_stages

from .point_plan import PointPlan, point_conditions
from .points_table import points_table, steps_log
from .run_arrays import RunData


def _subset(plan: PointPlan, idx: list[int]) -> PointPlan:
    return PointPlan(
        [plan.ranges[i] for i in idx],
        [plan.labels[i] for i in idx],
        [plan.kind[i] for i in idx],
        plan.source,
        [plan.flags[i] for i in idx],
        {k: [v[i] for i in idx] for k, v in plan.targets.items()},
        {k: [v[i] for i in idx] for k, v in plan.motion.items()},
        [plan.event_ns[i] for i in idx] if plan.event_ns else [],
    )


def samples_of(run: RunData, plan: PointPlan) -> tuple[RunData, PointPlan]:
    """``run`` with only the load-cell samples (and the camera frames, :func:`frames_of`) within
    ``plan``'s points, and the plan with its ranges into those samples: a reduction of some of
    a run's points (the steady zeros of an hour of oscillations) does not pass over the rest."""
    run = frames_of(run, plan)
    n = len(run.t_ns)
    if not plan.ranges:
        return run, plan
    idx = np.asarray(plan.ranges, dtype=np.int64)
    mark = np.zeros(n + 1, np.int64)
    np.add.at(mark, idx[:, 0], 1)
    np.add.at(mark, idx[:, 1], -1)
    sel = np.cumsum(mark)[:n] > 0
    if sel.all():
        return run, plan
    new_index = np.cumsum(sel) - 1  # the kept samples' new indexes
    starts = [int(new_index[a]) if b > a else 0 for a, b in plan.ranges]
    ranges = [(s0, s0 + (b - a)) for s0, (a, b) in zip(starts, plan.ranges, strict=True)]

    def cut(x: Any) -> Any:
        return None if x is None else x[sel]

    out = replace(
        run,
        t_ns=run.t_ns[sel],
        tensions_N=run.tensions_N[sel],
        mask_bits=run.mask_bits[sel],
        tunnel=None if run.tunnel is None else (run.tunnel[0][sel], run.tunnel[1][sel]),
        pressure_temperature=None
        if run.pressure_temperature is None
        else (run.pressure_temperature[0][sel], run.pressure_temperature[1][sel]),
        humidity=cut(run.humidity),
        sample_counter=cut(run.sample_counter),
    )
    return out, replace(plan, ranges=ranges)


def frames_of(run: RunData, plan: PointPlan) -> RunData:
    """``run`` with only the camera frames within the time spans of ``plan``'s points (each
    reduction looks at no other frame; a 200 Hz camera over the dynamic points need not be
    averaged again for the steady ones)."""
    if not plan.ranges or len(run.pose_t_ns) == 0:
        return run
    idx = np.asarray(plan.ranges, dtype=np.int64)
    last = len(run.t_ns) - 1
    a = run.t_ns[np.clip(idx[:, 0], 0, last)]
    b = run.t_ns[np.clip(idx[:, 1] - 1, 0, last)]
    if plan.event_ns:
        ev = np.asarray(plan.event_ns, dtype=np.int64)
        a, b = np.minimum(a, ev[:, 0]), np.maximum(b, ev[:, 1])
    margin = 1_000_000_000  # a camera clock offset is far below a second
    lo = np.searchsorted(run.pose_t_ns, a - margin, side="left")
    hi = np.searchsorted(run.pose_t_ns, b + margin, side="right")
    keep = np.zeros(len(run.pose_t_ns) + 1, np.int64)
    np.add.at(keep, lo, 1)
    np.add.at(keep, hi, -1)
    sel = np.cumsum(keep)[:-1] > 0
    if sel.all():
        return run
    return replace(
        run,
        pose_t_ns=run.pose_t_ns[sel],
        poses=run.poses[sel],
        pose_cov=None if run.pose_cov is None else run.pose_cov[sel],
        pose_bad=run.pose_bad[sel],
    )


def split_plan(plan: PointPlan) -> tuple[PointPlan, PointPlan]:
    """The steady points (every kind but the oscillation ones) and the oscillation points with
    the run's ``zero`` points (for the zero drift), each in run order."""
    moving = [i for i, k in enumerate(plan.kind) if k in OSCILLATION_POINT_KINDS]
    steady = [i for i in range(len(plan.kind)) if i not in set(moving)]
    dyn = sorted(moving + [i for i in steady if plan.kind[i] == "zero"]) if moving else []
    return _subset(plan, steady), _subset(plan, dyn)


def _number(x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v


def inertia_tares(plan: PointPlan) -> np.ndarray:
    """Each oscillation point's inertia tare (index into the plan, -1 none): the point its events
    name (``inertia_tare``), else the nearest ``oscillation_tare`` before it with the same motion
    (axis, amplitude, frequency) and mean attitude, else the first after it."""
    s = len(plan.kind)
    out = np.full(s, -1, np.int64)
    mo = plan.motion
    if not mo:
        return out
    labels = {lab: i for i, lab in enumerate(plan.labels)}

    def key(i: int) -> tuple[Any, ...]:
        return (
            str(mo["motion_axis"][i]),
            round(_number(mo["motion_amplitude"][i]), 12),
            round(_number(mo["motion_frequency_Hz"][i]), 9),
            round(_number(plan.targets.get("target_aoa_deg", [0.0] * s)[i]), 6),
            round(_number(plan.targets.get("target_sideslip_deg", [0.0] * s)[i]), 6),
        )

    tares = [i for i in range(s) if plan.kind[i] == "oscillation_tare"]
    for i in range(s):
        if plan.kind[i] != "oscillation":
            continue
        named = str(mo["inertia_tare"][i] or "")
        j = labels.get(named, -1) if named else -1
        if j >= 0 and plan.kind[j] == "oscillation_tare":
            out[i] = j
            continue
        same = [t for t in tares if key(t) == key(i)]
        before = [t for t in same if t < i]
        if before:
            out[i] = before[-1]
        elif same:
            out[i] = same[0]
    return out


def _pose_variances(run: RunData, fallback: tuple[float, ...]) -> np.ndarray:
    """Each camera frame's variances (k, 6) in (x, y, z, roll, pitch, yaw): the diagonal of the
    covariance the stream carries, else the fallback σ (the points carry ``pose_cov_nominal``)."""
    if run.pose_cov is not None:
        return np.asarray(np.diagonal(run.pose_cov, axis1=1, axis2=2), dtype=np.float64)
    return np.broadcast_to(np.asarray(fallback, dtype=np.float64) ** 2, run.poses.shape).copy()


def reduce_dynamic(
    run: RunData, plan: PointPlan, opts: Any, weight_model: Any = None
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The oscillation points of ``plan`` (with its zeros) through the dynamic order: their rows
    of the per-point table and the summary parts (stage log, the clock offset, the run's clock,
    the harmonics table and the hysteresis bins for the report)."""
    from .analyze import _input_words, run_point_inputs  # the steady points' inputs and words

    run = frames_of(run, plan)  # every load-cell sample stays: the points cover most of them
    rig = run.rig
    settings: DynamicSettings = getattr(opts, "dynamic", None) or DynamicSettings()
    pts, extra = run_point_inputs(run, plan, opts)
    s = len(plan.kind)
    mo = plan.motion
    arrays: dict[str, Any] = {
        "input_flags": _input_words(run, plan, pts["input_flags"]),
        "motion_axis": np.array([str(x or "") for x in mo["motion_axis"]]),
        "inertia_tare_index": inertia_tares(plan),
    }
    for k in ("motion_amplitude", "motion_frequency_Hz", "motion_cycles", "motion_settling_cycles"):
        arrays[k] = np.array([_number(x) for x in mo[k]])
    corrections = None
    if opts.corrections:
        arrays.update(point_conditions(run, plan))
        corrections = Corrections()
    t_clock = run.t_ns  # the load cells' own clock when the stream has a counter (load_run)
    # each point's samples by their own clock between its events (not by reception time)
    ranges = points_from_events(
        t_clock, [a for a, _ in plan.event_ns], [b for _, b in plan.event_ns]
    )
    samples = DynamicSamples(
        t_clock,
        run.tensions_N,
        run.mask_bits == 0,
        ranges,
        run.pose_t_ns,
        run.poses,
        _pose_variances(run, opts.pose_sd_fallback),
        ~run.pose_bad,
    )
    from .config import read_balance_calibration

    K, second = read_balance_calibration(opts.balance_file)
    body = (
        Body.of(rig)
        if weight_model is None
        else Body.of(rig, weight_model.mass_kg, weight_model.com_P_m)
    )
    stages = dynamic_stages(
        rig, opts.geometry, samples, settings, body=body, interaction=K, second_order=second,
        corrections=corrections,
    )  # fmt: skip
    out = run_stages(with_updates(pts, arrays=arrays), stages)
    keep = np.isin(out["kind"], OSCILLATION_POINT_KINDS)
    after: dict[str, Any] = {
        "source": [plan.source] * s,
        **{k: extra[k] for k in ("start_ns", "stop_ns", "n_samples", "n_masked", "n_pose_frames")},
        **plan.targets,
    }
    df = points_table(out, rig, plan.labels, {"run": [run.path.name] * s}, after)
    df = pd.concat([df, pd.DataFrame(dynamic_columns(out, plan.labels))], axis=1)
    if run.truth is not None and "segment_derivatives" in run.truth:
        _truth_derivatives(df, run)
    df = df[keep].reset_index(drop=True)
    co = out.meta.get("clock_offset")
    info: dict[str, Any] = {
        "point_source": plan.source,
        "dynamic_stages": steps_log(out),
        "dynamic_settings": asdict(settings),
        "load_cell_clock": {"source": run.tension_clock},
        "clock_offset": None
        if co is None
        else {
            "offset_ms": co.offset_ns * 1e-6,
            "sd_ms": co.sd_ns * 1e-6,
            "identified": co.identified,
            "per_tare_ms": (co.estimates_ns * 1e-6).tolist(),
            "sd_per_tare_ms": (co.sd_estimates_ns * 1e-6).tolist(),
            "chi2_per_dof": co.chi2_per_dof,
            "note": co.note,
        },
        "_harmonics": harmonics_table(out, plan.labels, run.path.name),
        "_loops": hysteresis_data(out, plan.labels),
    }
    return df, info


def dynamic_columns(p: Points, labels: list[str]) -> dict[str, Any]:
    """The columns the dynamic stages add to the per-point table (docs/analysis.md): the motion
    (planned and fitted), the window, the clock offset, the inertia removal, the reduced
    frequency, each coefficient's in-phase and out-of-phase parts with σ and harmonic content,
    the named derivatives with σ, the dwell time to the goals and the model's value beside."""
    s = p.n
    a = p.arrays
    cols: dict[str, Any] = {
        "motion_axis": a["motion_axis"],
        "motion_amplitude_plan": a["motion_amplitude"],
        "motion_amplitude": a.get("motion_amplitude_fit", np.full(s, np.nan)),
        "sd_motion_amplitude": a.get("sd_motion_amplitude_fit", np.full(s, np.nan)),
        "motion_frequency_plan_Hz": a["motion_frequency_Hz"],
        "motion_frequency_Hz": a.get("motion_frequency_fit_Hz", np.full(s, np.nan)),
        "sd_motion_frequency_Hz": a.get("sd_motion_frequency_fit_Hz", np.full(s, np.nan)),
        "motion_phase_sd_rad": a.get("motion_phase_sd_rad", np.full(s, np.nan)),
        "motion_distortion": a.get("motion_distortion", np.full(s, np.nan)),
        "motion_cycles_plan": a["motion_cycles"],
        "cycles_analysed": a.get("cycles_analysed", np.zeros(s)),
        "window_s": (a["window_ns"][:, 1] - a["window_ns"][:, 0]) * 1e-9
        if "window_ns" in a
        else np.full(s, np.nan),
        "clock_offset_ms": a.get("clock_offset_ns", np.full(s, np.nan)) * 1e-6,
        "sd_clock_offset_ms": a.get("sd_clock_offset_ns", np.full(s, np.nan)) * 1e-6,
        "inertia_method": a.get("inertia_method", np.full(s, "")),
        "tension_outside_samples": a.get("tension_outside_samples", np.zeros(s)),
        "min_tension_margin_N": a.get("min_tension_margin_N", np.full(s, np.nan)),
    }
    for key in sorted(k for k in a if _is_dynamic_column(k)):
        cols[key] = a[key]
    return cols


def _is_dynamic_column(key: str) -> bool:
    from cdpr.analysis.oscillation import NAMED_DERIVATIVES

    if key == "reduced_frequency":
        return True
    names = {n for v in NAMED_DERIVATIVES.values() for n, *_ in v}
    base = key.removeprefix("sd_").removeprefix("U95_").removeprefix("dwell_s_")
    base = base.removesuffix("_model")
    if base in names:
        return True
    for c in DYNAMIC_COEFFICIENTS:
        if key in (f"{c}_inphase", f"{c}_outphase", f"sd_{c}_inphase", f"sd_{c}_outphase"):
            return True
        if key == f"harmonic_content_{c}":
            return True
    return False


def _truth_derivatives(df: pd.DataFrame, run: RunData) -> None:
    """``true_<C>_inphase`` / ``true_<C>_outphase`` of the virtual rig's truth file
    (``segment_derivatives``, matched by label) on the oscillation rows (in place)."""
    assert run.truth is not None
    names = [str(x) for x in run.truth["derivative_names"]]
    labels = [str(x) for x in run.truth["segment_labels"]]
    vals = np.asarray(run.truth["segment_derivatives"], dtype=np.float64)
    row = {lab: i for i, lab in enumerate(labels)}
    for k, name in enumerate(names):
        col = "true_" + name.replace("_quadrature", "_outphase")
        df[col] = [vals[row[p], k] if p in row else np.nan for p in df["point"]]


HARMONIC_COLUMNS: tuple[str, ...] = (
    "run", "point", "kind", "quantity", "source", "harmonic", "mean_or_inphase", "sd_inphase",
    "quadrature", "sd_quadrature", "amplitude", "phase_deg",
)  # fmt: skip


def _rows(
    run: str, point: str, kind: str, names: list[str], source: str, coef: np.ndarray, sd: np.ndarray
) -> list[tuple[Any, ...]]:
    out = []
    H = (coef.shape[1] - 1) // 2
    for i, q in enumerate(names):
        out.append(
            (run, point, kind, q, source, 0, coef[i, 0], sd[i, 0], 0.0, 0.0, abs(coef[i, 0]), 0.0)
        )
        for h in range(1, H + 1):
            a, b = coef[i, 2 * h - 1], coef[i, 2 * h]
            out.append(
                (run, point, kind, q, source, h, a, sd[i, 2 * h - 1], b, sd[i, 2 * h],
                 math.hypot(a, b), math.degrees(math.atan2(b, a)))
            )  # fmt: skip
    return out


def _sd(terms: Any, shape: tuple[int, int]) -> np.ndarray:
    tot = sum(np.asarray(v) for v in terms.values())
    return np.sqrt(np.clip(np.diag(tot), 0.0, None)).reshape(shape)


def harmonics_table(p: Points, labels: list[str], run: str) -> pd.DataFrame:
    """The run's ``harmonics.csv``: per oscillation point, quantity and harmonic, the mean (h = 0)
    or the in-phase and quadrature parts with σ, the amplitude and phase (deg, relative to the
    motion's displacement).  Quantities: the motion (``x_m .. yaw_rad``, source ``motion``), the
    cable wrench ``-A T - G`` (``measured``), the inertia the tare measured (``inertia_tare``) and
    the rig file's (``inertia_model``) and their difference (``inertia_model_minus_tare``), the
    aerodynamic wrench about the MRP (``aero``: inertia removed by the tare, or the model without
    one; ``aero_model``: by the model), the coefficients (``aero``, ``aero_model``)."""
    from cdpr.analysis.conventions import POSE_COLUMNS

    rows: list[tuple[Any, ...]] = []
    wnames = list(WRENCH_COLUMNS)
    for i in np.flatnonzero(np.isin(p["kind"], OSCILLATION_POINT_KINDS)):
        f = p["motion_fit"][i]
        w = p["cable_harmonics"][i] if "cable_harmonics" in p.arrays else None
        if f is None or w is None:
            continue
        pt, kd = labels[i], str(p["kind"][i])
        pp = f.coef.shape[1]
        rows += _rows(run, pt, kd, list(POSE_COLUMNS), "motion", f.coef, _sd({"c": f.cov}, (6, pp)))
        rows += _rows(run, pt, kd, wnames, "measured", w.coef,
                      _sd({"a": w.cov_load_cells, "b": w.cov_pose}, (6, pp)))  # fmt: skip
        r: InertiaRemoval | None = (
            p["inertia_removal"][i] if "inertia_removal" in p.arrays else None
        )
        if r is None:
            continue
        zero = np.zeros((6, pp))
        if r.method == "tare":
            rows += _rows(run, pt, kd, wnames, "inertia_tare", r.inertia_tare, zero * np.nan)
            rows += _rows(run, pt, kd, wnames, "inertia_model_minus_tare",
                          r.inertia_model - r.inertia_tare, zero * np.nan)  # fmt: skip
        rows += _rows(run, pt, kd, wnames, "inertia_model", r.inertia_model, zero * np.nan)
        for src, key in (("aero", "derivatives"), ("aero_model", "derivatives_model")):
            d: Derivatives | None = p[key][i] if key in p.arrays else None
            if d is None:
                continue
            rows += _rows(run, pt, kd, wnames, src, d.wrench_mrp, _sd(d.wrench_mrp_terms, (6, pp)))
            if np.isfinite(d.coef).all():
                rows += _rows(run, pt, kd, list(DYNAMIC_COEFFICIENTS), src, d.coef,
                              _sd(d.terms, (8, pp)))  # fmt: skip
    return pd.DataFrame(rows, columns=list(HARMONIC_COLUMNS))


def hysteresis_data(p: Points, labels: list[str]) -> list[dict[str, Any]]:
    """Per wind-on oscillation point with coefficients: its label, axis, the coefficients per
    cycle and phase bin (n_c, bins, 8), the moved coordinate at the bins and the cycle-averaged
    loop from the fitted series (on a fine grid): what the report's hysteresis figure draws."""
    from cdpr.analysis.harmonics import grid_phases, harmonic_values

    out = []
    if "derivatives" not in p.arrays:
        return out
    for i in np.flatnonzero(p["kind"] == "oscillation"):
        d: Derivatives | None = p["derivatives"][i]
        f = p["motion_fit"][i]
        if d is None or d.loops is None or not np.isfinite(d.coef).all():
            continue
        g = grid_phases(180)
        angle = f.pose(g)[0][:, f.axis]
        out.append(
            {
                "point": labels[i],
                "axis": str(p["motion_axis"][i]),
                "coefficients": list(DYNAMIC_COEFFICIENTS),
                "loops": d.loops,
                "loop_angle": d.loop_angle,
                "mean_angle": angle,
                "mean_loop": harmonic_values(d.coef, g).T,
            }
        )
    return out


def merge_dynamic(
    df: pd.DataFrame | None, info: dict[str, Any] | None, ddf: pd.DataFrame, dinfo: dict[str, Any]
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The steady and the dynamic rows in one table (run order), the summary parts together."""
    if df is None or info is None:  # a run of oscillation points only
        df = ddf.iloc[0:0]
        info = {"stages": [], "weight_model": None, "lines": [], "warnings": [],
                "corrections": "see dynamic_stages"}  # fmt: skip
    from .analyze import INFO_FLAGS

    all_df = pd.concat([df, ddf], ignore_index=True, sort=False)
    all_df = all_df.sort_values("start_ns", kind="stable").reset_index(drop=True)
    flag_sets = [set(filter(None, str(f).split(";"))) for f in all_df["flags"]]
    warn = sorted(set().union(*flag_sets) - INFO_FLAGS) if flag_sets else []
    out = dict(info)
    out.update(dinfo)
    out["points"] = len(all_df)
    out["warnings"] = warn
    out["points_with_warnings"] = int(sum(bool(f - INFO_FLAGS) for f in flag_sets))
    out["lines"] = list(info.get("lines", [])) + dynamic_lines(ddf, dinfo)
    out["_steady_rows"] = np.flatnonzero(~all_df["kind"].isin(OSCILLATION_POINT_KINDS).to_numpy())
    return all_df, out


DYNAMIC_FLAG_LINES: dict[str, str] = {
    "too_few_cycles": "fewer whole cycles than the matrix asks (the ones recorded are analysed)",
    "motion_amplitude_off_plan": "the fitted motion's amplitude is off the plan",
    "motion_frequency_off_plan": "the fitted motion's frequency is off the plan",
    "motion_not_fitted": "no motion fitted (too few camera frames or cycles): no derivatives",
    "cable_wrench_not_fitted": "too few usable load-cell samples or cycles: no derivatives",
    "clock_offset_not_identified": "the points reduced without the camera's clock offset",
    "tension_limit_in_cycle": "a tension left its limits during the cycle",
    "no_inertia_tare": "no wind-off oscillation serves the point: the rig file's mass and inertia "
    "removed the inertia instead (said in inertia_method)",
    "inertia_tare_motion_mismatch": "the inertia tare's motion differs from the point's",
    "inertia_tare_unusable": "the inertia tare has no fitted wrench: the model's inertia used",
    "nonlinear_response": "a non-linear response: harmonics above the threshold (the derivatives "
    "describe the fundamental; see harmonics.csv)",
    "wind_off_oscillation": "an oscillation point below the wind-off speed: no coefficients",
}
"""One sentence per dynamic flag word (the CLI and the report print them)."""


def dynamic_lines(ddf: pd.DataFrame, info: dict[str, Any]) -> list[str]:
    """The run-level sentences of the dynamic points (their flags, the clock offset)."""
    lines = []
    co = info.get("clock_offset")
    if co is not None and not co["identified"]:
        lines.append(
            f"camera clock offset not identified ({co['note']}; estimate {co['offset_ms']:.4g} ms "
            f"± {co['sd_ms']:.3g} ms): none removed"
        )
    words = {w for f in ddf["flags"] for w in str(f).split(";") if w}
    for w, text in DYNAMIC_FLAG_LINES.items():
        if w in words:
            pts = [
                str(p)
                for p, f in zip(ddf["point"], ddf["flags"], strict=True)
                if w in str(f).split(";")
            ]
            lines.append(f"{text} (flag {w}: {', '.join(pts)})")
    return lines


def with_dynamic_settings(opts: Any, settings: DynamicSettings) -> Any:
    """``opts`` (an :class:`~cdpr.pipelines.analyze.AnalyzeOptions`) with other dynamic settings."""
    return replace(opts, dynamic=settings)
