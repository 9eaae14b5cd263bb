"""The report of one analysed run: ``report.md`` with its warnings, the per-point table, the
corrections and the stage log, and its figures (tensions with the test points shaded, the wrench per
point with ±2σ, the tension check, the tension spectra against the rig's modes).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.balance import interpolate_at
from cdpr.analysis.conventions import MASK_NAMES, WRENCH_COLUMNS
from cdpr.analysis.rotations import rotation_from_euler

from .point_plan import PointPlan
from .run_arrays import RunData


def warning_lines(run: RunData, plan: PointPlan, words: list[str]) -> list[str]:
    """One sentence per run-level problem (the CLI and the report print them)."""
    lines = []
    if run.tunnel is None:
        lines.append(
            "no airspeed data in the run: no coefficient; "
            + (
                "points come from events"
                if plan.source == "events"
                else "wind-on and wind-off cannot be told apart, so no wrench is reported"
            )
        )
    if "pose_cov_nominal" in words:
        lines.append(
            "the pose stream carries no covariance and no camera precision was stated "
            "(--pose-sd, or campaign.pose_sd in the test matrix): pose σ from the paper's "
            "0.5 mm / 0.1° (flag pose_cov_nominal)"
        )
    if "window_too_short" in words:
        lines.append(
            "points whose window is too short for the correlation of their own noise (fewer than "
            "10 effective samples): their σ is not stable; dwell_needed_s gives the time they "
            "would need (flag window_too_short)"
        )
    if "no_pose_stream" in words:
        lines.append("no pose stream: the rig's reference pose is used (flag no_pose_stream)")
    if "no_tare" in words:
        lines.append("wind-on points without a tare or weight model: no wrench (flag no_tare)")
    if "masked" in words:
        lines.append("samples masked (status bits, counter gaps, NaN): see n_masked and flags")
    if "no_geometry" in words:
        lines.append("no model geometry given: no coefficients (flag no_geometry)")
    if "check_fail" in words:
        lines.append("measured vs simulated tensions above the limit (flag check_fail)")
    if "humidity_not_given" in words:
        lines.append(
            "wind-on points without a humidity reading in the tunnel stream: density of dry air "
            "(up to about 1 % high; flag humidity_not_given)"
        )
    said = {"pose_cov_nominal", "no_pose_stream", "no_tare", "masked", "no_geometry", "check_fail"}
    said |= {"humidity_not_given", "window_too_short"}
    said |= {"no_airspeed"} | set(MASK_NAMES.values())
    rest = [w for w in words if w not in said]
    if rest:
        lines.append(f"other flags: {', '.join(rest)} (see the flags column)")
    return lines


def camera_pose_error(run: RunData) -> dict[str, float] | None:
    """RMS position (mm) and rotation (deg) error of the camera poses against the virtual rig's
    truth, when the run has both."""
    if not run.camera or run.truth is None or "position_O_m" not in run.truth:
        return None
    good = ~run.pose_bad
    cam_t, cam_q = run.pose_t_ns[good], run.poses[good]
    q_true = np.concatenate([run.truth["position_O_m"], run.truth["euler_rad"]], axis=1)
    tq = interpolate_at(cam_t, run.truth["t_ns"], q_true)
    pos_err = np.linalg.norm(cam_q[:, :3] - tq[:, :3], axis=1)
    R_rel = np.swapaxes(rotation_from_euler(tq[:, 3:]), -1, -2) @ rotation_from_euler(cam_q[:, 3:])
    cos = np.clip((np.trace(R_rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    return {
        "n_poses": int(len(pos_err)),
        "position_rms_mm": float(1e3 * np.sqrt(np.mean(pos_err**2))),
        "position_max_mm": float(1e3 * pos_err.max()),
        "rotation_rms_deg": float(np.sqrt(np.mean(ang**2))),
        "rotation_max_deg": float(ang.max()),
    }


def run_plots(run: RunData, df: pd.DataFrame, folder: Path) -> None:
    """tensions.png (min/max envelope of every cable and of the airspeed, test points shaded),
    wrench.png (per wind-on point, ±2σ), check.png (measured − expected tension per point).  The
    cost does not grow with the number of samples: 2000 envelope bins, one shading collection per
    kind; with many points the check plot draws markers and thins its labels."""
    from .plotting import minmax_envelope, png_figure

    t0 = run.t_ns[0]
    t_s = (run.t_ns - t0) * 1e-9
    # min/max envelope over 2000 bins (every spike stays visible), never every sample
    ts, T_env = minmax_envelope(t_s, run.tensions_N)
    tare = df.kind.isin(("tare", "zero")).to_numpy()
    spans = np.column_stack(
        [
            (df.start_ns.to_numpy() - t0) * 1e-9,
            (df.stop_ns.to_numpy() - df.start_ns.to_numpy()) * 1e-9,
        ]
    )
    with png_figure(folder / "tensions.png", 2, 1, (10, 6), sharex=True, height_ratios=[3, 1]) as (
        fig,
        axes,
    ):
        ax = axes[:, 0]
        for k, name in enumerate(run.rig.cable_names):
            ax[0].plot(ts, T_env[:, k], lw=0.8, label=name)
        for a in ax:  # one collection per kind of point, spanning the axes' height
            for sel, color in ((tare, "0.9"), (~tare, "#dde8f7")):
                if sel.any():
                    a.broken_barh(
                        spans[sel].tolist(), (0, 1), transform=a.get_xaxis_transform(),
                        color=color, zorder=0,
                    )  # fmt: skip
        ax[0].set_ylabel("tension (N)")
        ax[0].legend(fontsize=7, ncol=4, loc="upper left")
        ax[0].set_title(
            f"{run.path.name}: tensions (min/max envelope); shaded = test points "
            f"({df['source'].iloc[0]}; grey: tares)"
        )
        if run.tunnel is not None:
            tv, v_env = minmax_envelope(t_s, run.tunnel[0])
            ax[1].plot(tv, v_env, color="k", lw=1)
        else:
            ax[1].text(0.5, 0.5, "no airspeed data", transform=ax[1].transAxes, ha="center")
        ax[1].set_ylabel("airspeed (m/s)")
        ax[1].set_xlabel("time (s)")

    on = df[~df.kind.isin(("tare", "zero"))]
    x = on["airspeed_mps"] if run.tunnel is not None else np.arange(len(on))
    with png_figure(folder / "wrench.png", 2, 3, (11, 6)) as (fig, axes):
        for k, c in enumerate(WRENCH_COLUMNS):
            a = axes.flat[k]
            a.errorbar(
                x, on[c], yerr=2 * on[f"sd_{c}"], fmt="o", capsize=3, label="recovered (±2σ)"
            )
            if f"true_{c}" in on:
                a.plot(x, on[f"true_{c}"], "x", color="C3", label="virtual-rig truth")
            a.set_title(c)
            a.set_xlabel("airspeed (m/s)" if run.tunnel is not None else "point")
            a.grid(alpha=0.3)
        axes.flat[0].legend(fontsize=7, loc="upper left")
        fig.suptitle("Recovered aerodynamic wrench per test point (at the MRP, {O} axes)")

    dcols = [f"dT_{n}_N" for n in run.rig.cable_names]
    with png_figure(folder / "check.png", size=(10, 4)) as (fig, axes):
        ax = axes[0, 0]
        idx = np.arange(len(df))
        if len(df) <= 40:
            width = 0.8 / len(dcols)
            for k, c in enumerate(dcols):
                ax.bar(idx + (k - len(dcols) / 2) * width, df[c], width, label=c[3:-2])
            ax.set_xticks(idx, df["point"], rotation=90, fontsize=6)
        else:  # many points: one marker per cable and point, every k-th label
            for c in dcols:
                ax.plot(idx, df[c], ".", ms=3, label=c[3:-2])
            step = int(np.ceil(len(df) / 40))
            ax.set_xticks(idx[::step], df["point"].iloc[::step], rotation=90, fontsize=6)
        ax.axhline(1.0, color="r", ls="--", lw=1)
        ax.axhline(-1.0, color="r", ls="--", lw=1, label="±1 N (paper)")
        ax.set_ylabel("measured − expected tension (N)")
        ax.set_title("Measured vs simulated tensions (the paper's ≈1 N check)")
        ax.legend(fontsize=7, ncol=5, loc="upper left")


def spectrum_plots(run: RunData, df: pd.DataFrame, spectra: Any, folder: Path) -> list[str]:
    """``spectrum.png``: the tension spectra of the fastest wind-on point with the rig's modes
    at its pose marked, and ``spectra.png`` (``spectra_1.png``, ... beyond 24 points): every
    point's spectra as small multiples (when the spectrum check ran).  Returns the file names of
    the small-multiples figures."""
    from .report import spectra_grid_figures, spectrum_figure

    if spectra is None:
        return []
    if len(df) != len(spectra.freqs_Hz):  # the spectra are the steady points'
        from cdpr.analysis.conventions import OSCILLATION_POINT_KINDS

        df = df[~df["kind"].isin(OSCILLATION_POINT_KINDS)].reset_index(drop=True)
    grid = spectra_grid_figures(
        folder,
        [str(x) for x in df["point"]],
        [str(x) for x in df["flags"].fillna("")],
        spectra.freqs_Hz,
        spectra.psd,
        spectra.modes_Hz,
        run.rig.cable_names,
    )
    names = [f.name for f in grid.figures]
    on = np.flatnonzero((df["kind"] == "wind_on").to_numpy())
    on = [i for i in on if spectra.freqs_Hz[i].size]
    if not on:
        return names
    i = max(on, key=lambda k: np.nan_to_num(df["airspeed_mps"].iloc[k]))
    spectrum_figure(
        folder / "spectrum.png",
        spectra.freqs_Hz[i],
        spectra.psd[i],
        run.rig.cable_names,
        spectra.modes_Hz[i],
        f"Tension spectra of point {df['point'].iloc[i]} "
        f"({df['airspeed_mps'].iloc[i]:.2f} m/s) with the rig's modes at its pose",
    )
    return names


def _fmt(v: float, sd: float) -> str:
    return "–" if not np.isfinite(v) else f"{v:.3f} ± {sd:.3f}"


def run_report(
    run: RunData, df: pd.DataFrame, summary: dict[str, Any], harmonics: Any = None
) -> str:
    """``report.md`` of one run (``harmonics``: the dynamic points' harmonic table, when any)."""
    red = summary["reduction"]
    lines = [
        f"# Analysis of `{run.path.name}`",
        "",
        f"- rig: **{run.rig.name}** ({run.rig.n_cables} cables); pose from: {run.pose_source}",
        f"- tension times from {run.tension_clock}",
        "- systematic σ from: "
        + "; ".join(
            f"{k.replace('_', ' ')}: {v}" for k, v in summary["systematic_sources"].items()
        ),
        f"- {len(df)} test points from **{red['point_source']}**"
        f" ({'the /events stream' if red['point_source'] == 'events' else 'steady-point detection'})"
        f", {int(df.kind.isin(('tare', 'zero')).sum())} wind-off",
        f"- measured vs simulated tensions: max |ΔT| = {summary['check_max_abs_dT_N']:.3f} N "
        f"(paper: about 1 N) → **{'pass' if summary['check_pass'] else 'FAIL'}**",
    ]
    lc = summary["loadcell_calibration"]
    if lc["applied"]:
        worst = max((v for v in lc["max_abs_change_N"].values() if v is not None), default=0.0)
        lines.append(
            f"- tensions **re-derived from the recorded raw counts** with the load-cell "
            f"calibration `{lc['name']}` (id `{lc['id']}`, created {lc['created_utc'] or 'not given'},"
            f" sha256 `{lc['sha256']}`, given by {lc['given_by']}): T = (counts − offset) · gain; "
            f"largest change against the recorded tensions {worst:.4g} N"
        )
    else:
        lines.append("- tensions as recorded (no load-cell re-calibration)")
    wm = red["weight_model"]
    if wm:
        lines.append(
            f"- weight model from {wm['n_tares']} wind-off points: mass {wm['mass_kg']:.5f} kg, "
            f"CoM_P {np.round(np.array(wm['com_P_m']) * 1e3, 3).tolist()} mm"
            + (
                f" (left to the prior: {', '.join(wm['left_to_prior'])})"
                if wm["left_to_prior"]
                else ""
            )
        )
    if red["lines"]:
        lines += ["", "**Warnings**", ""] + [f"- {w}" for w in red["lines"]]
    lines += [
        "",
        "| point | kind | V (m/s) | Fx (N) | Fy (N) | Fz (N) | Mx (N m) | My (N m) | Mz (N m) "
        "| CL | CD | max ΔT (N) | masked | flags |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for _, r in df.iterrows():
        w = [_fmt(r[c], r["sd_" + c]) for c in WRENCH_COLUMNS]
        coef = ["–" if not np.isfinite(r[c]) else f"{r[c]:.3f}" for c in ("CL", "CD")]
        lines.append(
            f"| {r.point} | {r.kind} | {r.airspeed_mps:.2f} | "
            + " | ".join(w)
            + " | "
            + " | ".join(coef)
            + f" | {r.check_max_abs_dT_N:.3f} | {int(r.n_masked)} | {r['flags']} |"
        )
    pe = summary.get("camera_pose_error_vs_truth")
    if pe:
        lines += [
            "",
            f"Camera pose against the virtual rig's truth ({pe['n_poses']} poses): position RMS "
            f"{pe['position_rms_mm']:.3f} mm (max {pe['position_max_mm']:.3f}), rotation RMS "
            f"{pe['rotation_rms_deg']:.4f}° (max {pe['rotation_max_deg']:.4f}°).",
        ]
    if "max_abs_error_vs_truth" in summary:
        errs = ", ".join(f"{c} {v:.3g}" for c, v in summary["max_abs_error_vs_truth"].items())
        lines += ["", f"Against the virtual rig's true aerodynamic wrench, max |error|: {errs}."]
    lines += _corrections_section(df, red)
    if summary.get("online"):
        lines += ["", "## On-line against final values", "", *(f"- {x}" for x in summary["online"])]
    lines += dynamic_section(df, summary, harmonics)
    lines += ["", "Stages of the reduction:", ""]
    for st in red["stages"]:
        note = f": {st['note']}" if st["note"] else ""
        lines.append(f"1. `{st['stage']}` — {st['points_flagged']} points flagged{note}")
    lines += [
        "",
        "σ, each source its own column (`sd_<source>_<column>` in points.csv): the load cells (the "
        "long-run covariance of each point's mean from the data's own correlation, across the "
        "cables; `n_eff_min` its effective samples), the pose (the camera's covariance per frame, "
        "else a stated or the paper's constant, flagged; the tare-to-point difference from the "
        "stiffness model and the camera), the platform's motion over the window, the weight model, "
        "and the systematic terms (load-cell calibration, rig geometry, interaction matrix, flow "
        "instruments); `U95_<column>` = k u with k from the effective degrees of freedom "
        "(docs/analysis.md).",
        "",
        "![tensions](tensions.png)",
        "",
        "![wrench](wrench.png)",
        "",
        "![check](check.png)",
        "",
        *(["![spectrum](spectrum.png)", ""] if "lowest_mode_Hz" in df else []),
    ]
    grids = summary.get("spectra_figures") or []
    if grids:
        lines += [
            "Tension spectra of every point (one panel per point: label and spectrum flags in "
            "its title, the rig's modes at its pose dashed):",
            "",
        ]
        lines += [f"![spectra of every point]({g})\n" for g in grids]
    return "\n".join(lines)


def _corrections_section(df: pd.DataFrame, red: dict[str, Any]) -> list[str]:
    """The report's corrections: every record (name, source, values, flags) and per wind-on point
    the size of each correction, the corrected beside the uncorrected coefficients, Re and Mach."""
    recs = red.get("corrections")
    if not isinstance(recs, list):
        return ["", f"Corrections: {recs}."]
    lines = ["", "## Corrections", ""]
    for r in recs:
        flags = f" — flags: {', '.join(r['flags'])}" if r["flags"] else ""
        lines.append(f"- **{r['name']}** ({r['source']}){flags}")
    on = df[df.kind == "wind_on"]
    if on.empty or "corrections" not in on:
        return lines
    cols = [
        ("point", "point", ""), ("V", "airspeed_mps", ".2f"),
        ("ρ (kg/m³)", "density_kgpm3", ".5f"), ("ρ from", "density_source", ""),
        ("RH", "relative_humidity", ".3f"), ("Re", "reynolds", ".3g"),
        ("Mach", "mach", ".4f"), ("drift max (N)", "zero_drift_max_abs_N", ".4f"),
        ("windage", "windage_source", ""), ("windage Fx (N)", "windage_fx_N", ".4f"),
        ("CL", "CL", ".4f"), ("CL corr.", "CL_corrected", ".4f"), ("CD", "CD", ".5f"),
        ("CD corr.", "CD_corrected", ".5f"), ("Cm", "Cm", ".5f"), ("Cm corr.", "Cm_corrected", ".5f"),
        ("σ CL", "sd_CL", ".2g"), ("σ_repeat CL", "sd_repeat_CL", ".2g"),
    ]  # fmt: skip
    cols = [c for c in cols if c[1] in on]
    lines += ["", "| " + " | ".join(c[0] for c in cols) + " |", "|" + "---|" * len(cols)]
    for _, r in on.iterrows():
        cells = []
        for _, key, f in cols:
            v = r[key]
            cells.append(
                str(v) if not f else ("–" if not np.isfinite(float(v)) else format(float(v), f))
            )
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Per point, what was applied and its source (the `corrections` column):", ""]
    lines += [f"- {r.point}: {r.corrections or 'none'}" for r in on.itertuples()]
    return lines


# ------------------------------------------------------------------------------------------------
# dynamic (forced-oscillation) points
# ------------------------------------------------------------------------------------------------
LOOPS_PER_FIGURE = 12
"""Points per hysteresis figure (``hysteresis.png``, ``hysteresis_1.png``, ...): 4 a row."""


def dynamic_outputs(df: pd.DataFrame, red: dict[str, Any], folder: Path) -> dict[str, Any]:
    """The files of a run's oscillation points: ``harmonics.csv`` (the harmonic table,
    :func:`cdpr.pipelines.dynamic.harmonics_table`) and the hysteresis loops
    (:func:`hysteresis_figures`).  Returns their names (nothing when the run has none)."""
    h = red.get("_harmonics")
    if h is None:
        return {}
    h.to_csv(folder / "harmonics.csv", index=False)
    figs = hysteresis_figures(red.get("_loops") or [], folder)
    return {"harmonics": "harmonics.csv", "hysteresis_figures": figs}


def _loop_coefficients(axis: str) -> tuple[str, ...]:
    from cdpr.analysis.oscillation import PRIMARY_COEFFICIENTS

    return PRIMARY_COEFFICIENTS.get(axis, ("CL", "Cm"))[:2]


def hysteresis_figures(loops: list[dict[str, Any]], folder: Path) -> list[str]:
    """Per wind-on oscillation point, its primary coefficients (Cm and CL in pitch, Cn and Cl in
    yaw, ...) against the instantaneous angle (deg; m for a translation) along the motion: every
    cycle faint behind (the cycle's phase bins), the cycle average bold (mean over the cycles per
    bin) and the fitted series dashed.  Small multiples: each point a column of two panels, four
    points a row, ``LOOPS_PER_FIGURE`` points a file.  Returns the file names."""
    from cdpr.analysis.motion import ANGULAR_AXES

    from .plotting import png_figure

    names = []
    for k in range(0, len(loops), LOOPS_PER_FIGURE):
        part = loops[k : k + LOOPS_PER_FIGURE]
        name = "hysteresis.png" if k == 0 else f"hysteresis_{k // LOOPS_PER_FIGURE}.png"
        ncol = min(4, len(part))
        nrow = -(-len(part) // ncol)
        size = (3.0 * ncol + 0.5, 4.6 * nrow + 0.6)
        with png_figure(folder / name, 2 * nrow, ncol, size, dpi=90, tight=False) as (fig, axes):
            for j in range(len(part), nrow * ncol):  # the empty places of the last row
                for r in (0, 1):
                    axes[2 * (j // ncol) + r, j % ncol].set_visible(False)
            for j, d in enumerate(part):
                ang = d["axis"] in ANGULAR_AXES
                scale = np.degrees(1.0) if ang else 1.0
                x = np.append(d["loop_angle"], d["loop_angle"][:1]) * scale
                xm = np.append(d["mean_angle"], d["mean_angle"][:1]) * scale
                for r, c in enumerate(_loop_coefficients(d["axis"])):
                    ax = axes[2 * (j // ncol) + r, j % ncol]
                    i = d["coefficients"].index(c)
                    L = d["loops"][:, :, i]
                    # every cycle, closed, NaN between them: one line for all (cheap to draw)
                    cyc = np.concatenate([L, L[:, :1], np.full((L.shape[0], 1), np.nan)], axis=1)
                    xs = np.tile(np.append(x, np.nan), L.shape[0])
                    ax.plot(xs, cyc.reshape(-1), color="C0", lw=0.5, alpha=0.2)
                    n_ok = np.isfinite(L).sum(axis=0)
                    avg = np.where(n_ok > 0, np.nansum(L, axis=0) / np.maximum(n_ok, 1), np.nan)
                    ax.plot(x, np.append(avg, avg[:1]), color="navy", lw=1.8, label="cycle average")
                    ym = d["mean_loop"][:, i]
                    ax.plot(
                        xm, np.append(ym, ym[:1]), "--", color="C3", lw=1.2, label="harmonic fit"
                    )
                    ax.set_ylabel(c, fontsize=8, labelpad=1)
                    ax.tick_params(labelsize=7)
                    ax.grid(alpha=0.3)
                    if r == 0:
                        ax.set_title(f"{d['point']}", fontsize=8)
                    else:
                        ax.set_xlabel(f"{d['axis']} ({'deg' if ang else 'm'})", fontsize=8)
            axes[0, 0].legend(fontsize=7, loc="best")
            fig.suptitle(
                "Hysteresis loops: coefficient against the instantaneous angle "
                f"({len(part)} point(s); each cycle faint, the cycle average bold, the fit dashed)",
                fontsize=9,
            )
            fig.subplots_adjust(left=0.08, right=0.98, bottom=0.06, top=1 - 0.8 / size[1],
                                wspace=0.38, hspace=0.42)  # fmt: skip
        names.append(name)
    return names


def dynamic_section(df: pd.DataFrame, summary: dict[str, Any], harmonics: Any = None) -> list[str]:
    """The report's section on the oscillation points: the load cells' clock and the camera's
    clock offset, the derivatives per point (± σ, the model's inertia beside the tare's, the
    dwell that reaches the goals), the harmonic table of the moments' fundamentals (the inertia
    measured by the tare, the rig file's and their difference), the hysteresis figures."""
    from cdpr.analysis.conventions import OSCILLATION_POINT_KINDS
    from cdpr.analysis.oscillation import NAMED_DERIVATIVES

    osc = df[df["kind"].isin(OSCILLATION_POINT_KINDS)]
    if osc.empty:
        return []
    red = summary["reduction"]
    lines = ["", "## Dynamic points (forced oscillation)", ""]
    clk = red.get("load_cell_clock") or {}
    if clk:
        lines.append(f"- load cells' clock: {clk['source']}")
    co = red.get("clock_offset")
    if co:
        per = ", ".join(
            f"{v:.4f} ± {s:.4f}"
            for v, s in zip(co["per_tare_ms"], co["sd_per_tare_ms"], strict=True)
        )
        lines.append(
            f"- camera clock offset: **{co['offset_ms']:.4f} ms ± {co['sd_ms']:.4f} ms** "
            f"({'identified' if co['identified'] else 'NOT identified: none removed'}; per wind-off "
            f"oscillation: {per or 'none'} ms; {co['note']})"
        )
    on = osc[osc["kind"] == "oscillation"]
    for axis, named in NAMED_DERIVATIVES.items():
        d = on[on["motion_axis"] == axis]
        if d.empty:
            continue
        cols = [n for n, *_ in named if n in d]
        lines += [
            "",
            f"**{axis}**: derivatives ± σ (inertia by the tare; [the rig file's inertia]; dwell "
            "for the goals: 95 % within 2 % in phase, 5 % or 0.3 /rad out of phase)",
            "",
            "| point | V (m/s) | A | f (Hz) | k | " + " | ".join(cols) + " | flags |",
            "|" + "---|" * (6 + len(cols)),
        ]
        ang = axis in ("roll", "pitch", "yaw")
        for _, r in d.iterrows():
            A = np.degrees(r["motion_amplitude"]) if ang else r["motion_amplitude"]
            cells = [
                f"{r[n]:.4g} ± {r['sd_' + n]:.2g} [{r[n + '_model']:.4g}] ({r['dwell_s_' + n]:.0f} s)"
                if np.isfinite(r[n])
                else "–"
                for n in cols
            ]
            lines.append(
                f"| {r['point']} | {r['airspeed_mps']:.2f} | {A:.3f}{'°' if ang else ' m'} | "
                f"{r['motion_frequency_Hz']:.4f} | {r['reduced_frequency']:.4f} | "
                + " | ".join(cells)
                + f" | {r['flags']} |"
            )
    if harmonics is not None and len(harmonics):
        h = harmonics[
            (harmonics["harmonic"] == 1) & harmonics["quantity"].isin(("mx_Nm", "my_Nm", "mz_Nm"))
        ]
        h = h[
            h["source"].isin(
                ("measured", "inertia_tare", "inertia_model", "inertia_model_minus_tare", "aero")
            )
        ]
        if len(h):
            lines += [
                "",
                "Fundamentals of the moments (N m, in phase / quadrature with the motion; σ where "
                "known): the measured cable wrench, the inertia the wind-off tare measured, the rig "
                "file's, their difference, the aerodynamic moment about the MRP (every harmonic "
                "and component: `harmonics.csv`)",
                "",
                "| point | source | Mx | My | Mz |",
                "|---|---|---|---|---|",
            ]
            for (pt, src), g in h.groupby(["point", "source"], sort=False):
                cells = []
                for q in ("mx_Nm", "my_Nm", "mz_Nm"):
                    r = g[g["quantity"] == q]
                    if r.empty:
                        cells.append("–")
                        continue
                    r0 = r.iloc[0]
                    sd = (
                        f" ± {r0['sd_inphase']:.1e}/{r0['sd_quadrature']:.1e}"
                        if np.isfinite(r0["sd_inphase"])
                        else ""
                    )
                    cells.append(f"{r0['mean_or_inphase']:+.5f} / {r0['quadrature']:+.5f}{sd}")
                lines.append(f"| {pt} | {src} | " + " | ".join(cells) + " |")
    figs = (summary.get("dynamic_outputs") or {}).get("hysteresis_figures", [])
    if figs:
        lines += [
            "",
            "Hysteresis loops (each cycle faint, the cycle average bold, the harmonic fit dashed):",
            "",
        ]
        lines += [f"![hysteresis]({f})\n" for f in figs]
    if red.get("dynamic_stages"):
        lines += ["", "Stages of the dynamic reduction:", ""]
        for st in red["dynamic_stages"]:
            note = f": {st['note']}" if st["note"] else ""
            lines.append(f"1. `{st['stage']}` — {st['points_flagged']} points flagged{note}")
    return lines
