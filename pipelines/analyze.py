"""One run through the reduction core (``cdpr analyze``): load → plan → reduce → write.

For a run file: its arrays (:mod:`cdpr.pipelines.run_arrays`, read through ``open_run``), its test
points (:mod:`cdpr.pipelines.point_plan`: the ``/events`` stream, or detected steady points), the
per-point inputs (:func:`cdpr.analysis.point_inputs.points_from_samples`), then the one reduction
core (:func:`cdpr.analysis.stages.core_stages`) with the run's settings bound, and its outputs in
``OUT/<run stem>/`` (written to a temporary folder, then renamed): ``points.csv`` (the per-point
table, :mod:`cdpr.pipelines.points_table`), ``summary.json`` (inputs with SHA-256, options, stage
log, weight model, warnings, software version), ``report.md`` and the figures
(:mod:`cdpr.pipelines.run_report`).  When the virtual rig's truth file sits beside the run, the
true wrench is compared too.  Many runs at once: :mod:`cdpr.pipelines.batch`.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.aero import ModelGeometry, transfer_moment
from cdpr.analysis.balance import SteadyRule, interpolate_at
from cdpr.analysis.conventions import WRENCH_COLUMNS
from cdpr.analysis.errors import CdprError, ConfigError
from cdpr.analysis.oscillation import DynamicSettings
from cdpr.analysis.point_inputs import points_from_samples
from cdpr.analysis.reduction import POSE, Points, run_stages, with_updates
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.stages import (
    Corrections,
    PointSamples,
    ReduceSettings,
    SystematicInputs,
    core_stages,
)

from . import __version__
from .config import file_sha256, read_balance_calibration, read_balance_fit
from .dynamic import merge_dynamic, reduce_dynamic, samples_of, split_plan
from .freshness import fingerprint
from .online_compare import compare_online
from .point_plan import PointPlan, plan_points, point_conditions
from .points_table import points_table, steps_log
from .run_arrays import RunData, check_recalibration, load_run
from .run_report import (
    camera_pose_error,
    dynamic_outputs,
    run_plots,
    run_report,
    spectrum_plots,
    warning_lines,
)
from .tunnel_section import TunnelSection

__all__ = ["AnalyzeOptions", "analyze_run", "check_recalibration", "reduce_run", "run_fingerprint"]

PAPER_POSE_SD: tuple[float, ...] = (5e-4, 5e-4, 5e-4, *(float(np.deg2rad(0.1)),) * 3)
"""The paper's camera precision (0.5 mm, 0.1 deg): the pose σ fallback, used only with a flag."""

INFO_FLAGS: frozenset[str] = frozenset(
    {"tare", "weight_model", "weight_model_prior_com_z", "weight_model_prior_com_x",
     "weight_model_prior_com_y", "weight_model_prior_mass", "geometry_from_options",
     "windage_tare", "wall_corrected", "uncorrected", "pose_cov_stated",
     "rig_geometry_sd_default", "tunnel_instrument_sd_default",
     "loadcell_calibration_correlation_not_given"}
)  # fmt: skip
"""Flag words that describe what was done; every other word is a warning (exit code 1)."""


@dataclass(frozen=True)
class AnalyzeOptions:
    """Settings of the analysis (all recorded in every summary).

    geometry: the model's reference geometry (from the test matrix, or options: flagged); None:
        no coefficients (flag ``no_geometry`` on wind-on points).
    corrections: run the correction stages (zero drift, flow conditions, windage, wall
        corrections, repeatability; ``cdpr analyze --matrix``); tunnel: the matrix's ``[tunnel]``
        (None: no windage model and no wall corrections, flagged); matrix_file: its path.
    pose_sd_fallback: pose σ per frame when the pose stream carries no covariance;
        pose_sd_from: where it came from (``paper``: the paper's 0.5 mm / 0.1°, flagged
        ``pose_cov_nominal``, a warning; else the lab's stated precision, ``--pose-sd`` or the test
        matrix's ``campaign.pose_sd``, flagged ``pose_cov_stated``).
    balance_file: ``cdpr calibrate balance`` output whose interaction matrix is applied.
    loadcell_calibration_file: a load-cell calibration file (``cdpr calibrate loadcells``): every
        tension is re-derived from the run's recorded raw counts, ``T = (counts - offset) * gain``,
        before the reduction (None: the recorded tensions); loadcell_calibration_from: who named
        it (``--loadcell-calibration`` or the test matrix), said in the summary and report.
    instruments: the tunnel instruments' stated accuracy (the test matrix's ``[instruments]``,
        :class:`cdpr.analysis.systematic.InstrumentAccuracy`); None: the stated defaults (flagged
        ``tunnel_instrument_sd_default``).
    """

    geometry: ModelGeometry | None = None
    pose_sd_fallback: tuple[float, ...] = PAPER_POSE_SD
    pose_sd_from: str = "paper"
    balance_file: str | None = None
    rule: SteadyRule = field(default_factory=SteadyRule)
    reduce: ReduceSettings = field(default_factory=ReduceSettings)
    corrections: bool = False
    tunnel: TunnelSection | None = None
    matrix_file: str | None = None
    loadcell_calibration_file: str | None = None
    loadcell_calibration_from: str | None = None
    instruments: Any = None
    dynamic: DynamicSettings = field(default_factory=DynamicSettings)


def _input_words(run: RunData, plan: PointPlan, words: Any) -> np.ndarray:
    """Each point's input flag words with the plan's (``no_end_event``) and the run's (a missing
    pose or tunnel stream) appended."""
    run_words = []
    if not run.camera:
        run_words.append("pose_from_truth" if run.truth is not None else "no_pose_stream")
    if run.tunnel is None:
        run_words.append("no_airspeed")
    return np.array(
        [
            ";".join(filter(None, [str(w), f, *run_words]))
            for w, f in zip(words, plan.flags, strict=True)
        ]
    )


def reduce_run(run: RunData, opts: AnalyzeOptions) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The per-point table of one run and the summary parts of the reduction (stage log, weight
    model, warnings, the spectra for the figures): the steady points through the steady order,
    the oscillation points through the dynamic one (:mod:`cdpr.pipelines.dynamic`)."""
    plan = plan_points(run, opts.rule)
    if not plan.ranges:
        raise ConfigError(
            str(run.path),
            "/tensions",
            f"no test point ({plan.source}): run too short or never steady?",
        )
    steady, moving = split_plan(plan)
    if not moving.ranges:
        return _reduce_steady(run, plan, opts)[:2]
    df, info, out = (
        _reduce_steady(*samples_of(run, steady), opts) if steady.ranges else (None, None, None)
    )
    wm = None if out is None else out.meta.get("weight_model")
    return merge_dynamic(df, info, *reduce_dynamic(run, moving, opts, wm))


def run_point_inputs(
    run: RunData, plan: PointPlan, opts: AnalyzeOptions
) -> tuple[Points, dict[str, Any]]:
    """The core's inputs of ``plan``'s points from the run's samples
    (:func:`cdpr.analysis.point_inputs.points_from_samples`; the steady and the dynamic
    reductions both start here)."""
    airspeed, density = run.tunnel if run.tunnel is not None else (None, None)
    return points_from_samples(
        kind=plan.kind,
        ranges=plan.ranges,
        t_ns=run.t_ns,
        tensions_N=run.tensions_N,
        mask_bits=run.mask_bits,
        airspeed_mps=airspeed,
        density_kgpm3=density,
        pose_t_ns=run.pose_t_ns,
        poses=run.poses,
        pose_cov=run.pose_cov,
        pose_sd_fallback=None if run.pose_cov is not None else np.array(opts.pose_sd_fallback),
        pose_bad=run.pose_bad,
        pose_sd_word="pose_cov_nominal" if opts.pose_sd_from == "paper" else "pose_cov_stated",
    )


def _reduce_steady(
    run: RunData, plan: PointPlan, opts: AnalyzeOptions
) -> tuple[pd.DataFrame, dict[str, Any], Points]:
    """The steady points of ``plan`` through the steady order: their table, the summary parts
    and the reduced points."""
    rig = run.rig
    pts, extra = run_point_inputs(run, plan, opts)
    arrays = {"input_flags": _input_words(run, plan, pts["input_flags"])}
    corrections = None
    if opts.corrections:
        arrays.update(point_conditions(run, plan))
        t = opts.tunnel
        corrections = Corrections(
            section=None if t is None else t.geometry, walls=None if t is None else t.walls
        )
    K, second = read_balance_calibration(opts.balance_file)
    systematic = SystematicInputs(
        loadcell=run.loadcell_sd,
        balance_fit=read_balance_fit(opts.balance_file),
        instruments=opts.instruments,
    )
    stages = core_stages(
        rig,
        opts.geometry,
        opts.reduce,
        interaction=K,
        second_order=second,
        corrections=corrections,
        samples=PointSamples(run.t_ns, run.tensions_N, plan.ranges),
        systematic=systematic,
    )
    out = run_stages(with_updates(pts, arrays=arrays), stages)
    after: dict[str, Any] = {
        "source": [plan.source] * out.n,
        **{k: extra[k] for k in ("start_ns", "stop_ns", "n_samples", "n_masked", "n_pose_frames")},
        **_sample_counters(run, plan),
        **plan.targets,
    }
    df = points_table(out, rig, plan.labels, {"run": [run.path.name] * out.n}, after)
    first = ["run", "point", "kind", "source", "start_ns", "stop_ns", "n_samples", "n_masked"]
    first.append("flags")  # identification first
    df = df[first + [c for c in df.columns if c not in first]]
    if run.truth is not None and "wrench_aero_O" in run.truth:
        _truth_columns(df, run, out, opts.geometry, extra)
    flag_sets = [set(filter(None, f.split(";"))) for f in df["flags"]]
    warn_words = sorted(set().union(*flag_sets) - INFO_FLAGS) if flag_sets else []
    wm = out.meta.get("weight_model")
    info: dict[str, Any] = {
        "points": int(out.n),
        "point_source": plan.source,
        "warnings": warn_words,
        "points_with_warnings": int(sum(bool(f - INFO_FLAGS) for f in flag_sets)),
        "stages": steps_log(out),
        "weight_model": None
        if wm is None
        else {
            "mass_kg": wm.mass_kg,
            "com_P_m": wm.com_P_m.tolist(),
            "theta_cov": wm.theta_cov.tolist(),
            "n_tares": wm.n_tares,
            "chi2_per_dof": wm.chi2_per_dof,
            "left_to_prior": list(wm.weak),
        },
        "lines": warning_lines(run, plan, warn_words),
        "_spectra": out.meta.get("spectra"),
        "corrections": list(out.meta.get("corrections", []))
        if opts.corrections
        else "not applied (no test matrix given: cdpr analyze --matrix)",
    }
    return df, info, out


def systematic_sources(run: RunData, opts: AnalyzeOptions) -> dict[str, str]:
    """Where each systematic σ term of a run's points comes from (summary and report)."""
    from cdpr.analysis.systematic import rig_geometry_sd

    g = rig_geometry_sd(run.rig)
    inst = opts.instruments
    return {
        "loadcell_calibration": run.loadcell_sd_from
        + ("" if run.loadcell_sd is not None else " (term left out)"),
        "rig_geometry": "the rig file's anchor_sd_m / attach_sd_m"
        if not g.defaulted.any()
        else f"ISO 2768-1 class m default for {int(g.defaulted.sum())} of {run.rig.n_cables} cables "
        f"(anchors {1e3 * float(np.max(g.anchor_sd_m)):.2f} mm, attachments "
        f"{1e3 * float(np.max(g.attach_sd_m)):.2f} mm)",
        "interaction_matrix": "no balance calibration applied"
        if opts.balance_file is None
        else f"{Path(opts.balance_file).name}"
        + (
            ""
            if read_balance_fit(opts.balance_file) is not None
            else ": no fit covariance (term left out)"
        ),
        "tunnel_instruments": "the stated defaults (no test matrix [instruments])"
        if inst is None
        else "the test matrix's [instruments]"
        + (f", defaults for {', '.join(inst.defaulted)}" if inst.defaulted else ""),
    }


def _sample_counters(run: RunData, plan: PointPlan) -> dict[str, np.ndarray]:
    """``first_sample``, ``last_sample``: the sample counter of each point's first and last tension
    samples (which samples made the point, whatever clock the times are on); none without one."""
    if run.sample_counter is None:
        return {}
    idx = np.asarray(plan.ranges, dtype=np.int64).reshape(-1, 2)
    ok = idx[:, 1] > idx[:, 0]
    c = run.sample_counter
    first = np.where(ok, c[np.minimum(idx[:, 0], len(c) - 1)], -1)
    last = np.where(ok, c[np.maximum(idx[:, 1] - 1, 0)], -1)
    return {"first_sample": first, "last_sample": last}


def _truth_columns(
    df: pd.DataFrame,
    run: RunData,
    out: Points,
    geometry: ModelGeometry | None,
    extra: dict[str, Any],
) -> None:
    """``true_<c>`` and ``err_<c>``: the virtual rig's true aerodynamic wrench at each point's
    middle, moved to the MRP, and the recovered minus the true one (in place)."""
    assert run.truth is not None
    mid = (extra["start_ns"] + extra["stop_ns"]) // 2
    W_true = interpolate_at(mid, run.truth["t_ns"], run.truth["wrench_aero_O"])
    mrp = np.zeros(3) if geometry is None else np.asarray(geometry.mrp_P_m)
    R = rotation_from_euler(np.nan_to_num(out[POSE][:, 3:]))
    W_true = transfer_moment(W_true, R @ mrp)
    for k, c in enumerate(WRENCH_COLUMNS):
        df[f"true_{c}"] = W_true[:, k]
        df[f"err_{c}"] = df[c] - W_true[:, k]


def options_json(opts: AnalyzeOptions) -> Any:
    """The options as plain JSON (the summary's ``options``, part of the fingerprint)."""
    return json.loads(
        json.dumps(asdict(opts), default=lambda o: list(o) if isinstance(o, tuple) else str(o))
    )


def run_fingerprint(path: str, opts: AnalyzeOptions) -> dict[str, Any]:
    """The input fingerprint of one run's analysis (:mod:`cdpr.pipelines.freshness`): the run
    file, the balance calibration, the test matrix, the load-cell calibration the tensions are
    re-derived with, the virtual rig's truth file beside the run (absent is recorded too), the
    options and the software version."""
    p = Path(path)
    truth = p.with_name(p.name.removesuffix(".mcap") + ".truth.npz")
    inputs = [opts.balance_file, opts.matrix_file, opts.loadcell_calibration_file, truth]
    return fingerprint(p, options_json(opts), __version__, inputs)


def loadcell_provenance(run: RunData, opts: AnalyzeOptions) -> dict[str, Any]:
    """Where the run's tensions come from (summary ``loadcell_calibration``; ``tensions_from`` is
    the points.csv column): the recorded tensions, or the ones re-derived from the raw counts with
    a load-cell calibration (file, SHA-256, id, date, who named it, largest change per cable)."""
    if opts.loadcell_calibration_file is None or run.recalibration is None:
        return {
            "applied": False,
            "tensions_from": "recorded tensions (no load-cell re-calibration)",
        }
    f = opts.loadcell_calibration_file
    sha = file_sha256(f)
    rc = run.recalibration
    return {
        "applied": True,
        "file": str(f),
        "name": Path(f).name,
        "sha256": sha,
        "id": rc["calibration_id"],
        "created_utc": rc["created_utc"],
        "given_by": opts.loadcell_calibration_from,
        "tensions_from": f"re-derived from raw counts with {Path(f).name} sha256={sha} "
        f"id={rc['calibration_id']}",
        "formula": "T_N = (raw_counts - offset_counts) * gain_N_per_count",
        "max_abs_change_N": rc["max_abs_change_N"],
    }


def result_folder(path: str, out_dir: str) -> Path:
    """``OUT/<run stem>``: where the results of run ``path`` go."""
    return Path(out_dir) / Path(path).name.removesuffix(".mcap")


def analyze_run(
    path: str, out_dir: str, opts: AnalyzeOptions, fp: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Analyse one run and write its folder atomically; returns the summary (with ``fp``, the
    input fingerprint, computed here when not given)."""
    if fp is None:
        fp = run_fingerprint(path, opts)
    try:
        lc_file = None
        if opts.loadcell_calibration_file is not None:
            from cdpr.daq.loadcell import read_calibration_file

            lc_file = read_calibration_file(opts.loadcell_calibration_file)
        run = load_run(path, lc_file)
        df, red = reduce_run(run, opts)
        df, online = compare_online(path, df)  # the on-line results kept in the run
        lc = loadcell_provenance(run, opts)
        df.insert(int(df.columns.get_loc("source")) + 1, "tensions_from", lc["tensions_from"])
    except ConfigError:
        raise
    except CdprError as exc:  # name the file in the one line
        raise ConfigError(str(path), "", str(exc)) from None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    final = result_folder(path, out_dir)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=out))
    try:
        dmax = df["check_max_abs_dT_N"]
        summary: dict[str, Any] = {
            "run": str(run.path),
            "run_sha256": fp["run_sha256"],
            "software_version": __version__,
            "fingerprint": fp,
            "rig": run.rig.name,
            "pose_source": run.pose_source,
            "tension_clock": run.tension_clock,
            "systematic_sources": systematic_sources(run, opts),
            "options": options_json(opts),
            "balance_file": None
            if opts.balance_file is None
            else f"{opts.balance_file} sha256={file_sha256(opts.balance_file)}",
            "loadcell_calibration": lc,
            "points": len(df),
            "check_max_abs_dT_N": float(dmax.max()) if dmax.notna().any() else float("nan"),
            "check_pass": bool((dmax.dropna() <= opts.reduce.check_limit_N).all()),
            "reduction": {k: v for k, v in red.items() if not k.startswith("_")},
            "online": online,
        }
        pose_err = camera_pose_error(run)
        if pose_err is not None:
            summary["camera_pose_error_vs_truth"] = pose_err
        if "err_fx_N" in df:
            on = df[df.kind == "wind_on"]
            summary["max_abs_error_vs_truth"] = {
                c: float(np.abs(on[f"err_{c}"]).max()) for c in WRENCH_COLUMNS
            }
        df.to_csv(tmp / "points.csv", index=False)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
        run_plots(run, df, tmp)
        summary["spectra_figures"] = spectrum_plots(run, df, red.get("_spectra"), tmp)
        summary["dynamic_outputs"] = dynamic_outputs(df, red, tmp)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
        (tmp / "report.md").write_text(run_report(run, df, summary, red.get("_harmonics")))
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    summary["folder"] = str(final)
    return summary
