"""Batch post-processing of recorded runs (``cdpr analyze`` / ``make analyze``).

For every run (an MCAP file written by the recorder): the embedded rig, the tension, tunnel and pose
streams; steady segments (test points and wind-off tares, :mod:`cdpr.analysis.balance`); per segment
the structure matrix at the measured pose, the recovered wrench (absolute method, and the tare method
when a wind-off segment at the same pose exists) with its covariance, the aerodynamic coefficients,
and the paper's check: the tensions the distribution method would command for that wrench against
the measured ones.  When the virtual rig's truth file sits beside the run, the true wrench is
compared too.  Runs are processed in parallel on a Dask cluster (local by default, or an address).

Outputs per run, in ``OUT/<run stem>/`` (written to a temporary folder, then renamed):
``segments.csv``, ``summary.json`` (inputs with SHA-256, options, software version), ``report.md``,
``tensions.png``, ``wrench.png``, ``check.png``.  ``OUT/index.md`` lists every run.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import tomllib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.aero import aero_coefficients, air_density, dynamic_pressure
from cdpr.analysis.balance import (
    SegmentRule,
    interpolate_at,
    nearest_tare,
    segment_stats,
    steady_segments,
)
from cdpr.analysis.conventions import WRENCH_COLUMNS
from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.errors import CdprError, ConfigError
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import euler_from_quaternion, rotation_from_euler
from cdpr.analysis.tension import distribute
from cdpr.analysis.uncertainty import wrench_covariance
from cdpr.analysis.wrench import wrench_absolute, wrench_tare
from cdpr.daq.schema import rig_from_mapping

from . import __version__
from .config import file_sha256


@dataclass(frozen=True)
class AnalyzeOptions:
    """Settings of the analysis (all recorded in every summary).

    method: tension distribution the controller used (for the expected tensions).
    pose_sd: camera pose standard deviations (m, m, m, rad, rad, rad) -- the paper's 0.5 mm, 0.1 deg.
    area_m2, span_m, chord_m: reference area, span and chord for the coefficients (SDM-like model).
    check_limit_N: the pass mark of the measured-vs-simulated tension check (the paper's ~1 N).
    """

    method: str = "exact"
    pose_sd: tuple[float, ...] = (5e-4, 5e-4, 5e-4, *(float(np.deg2rad(0.1)),) * 3)
    area_m2: float = 0.2441 * 0.060
    span_m: float = 0.2441
    chord_m: float = 0.060
    check_limit_N: float = 1.0
    rule: SegmentRule = field(default_factory=SegmentRule)


@dataclass
class RunData:
    """The arrays of one run that the analysis needs."""

    path: Path
    rig: Rig
    t_ns: np.ndarray  # (n,) tension sample times
    tensions_N: np.ndarray  # (n, m)
    poses: np.ndarray  # (n, 6) interpolated at t_ns
    pose_source: str
    airspeed_mps: np.ndarray  # (n,)
    density_kgpm3: np.ndarray  # (n,)
    truth: dict[str, np.ndarray] | None
    camera_t_ns: np.ndarray | None = None  # (k,) camera pose times, when the pose is the camera's
    camera_poses: np.ndarray | None = None  # (k, 6) camera poses


def _topic(run: Any, suffix: str) -> str | None:
    """The first topic of ``run`` whose last name is ``suffix`` and that has messages."""
    hits = [t for t, i in run.streams.items() if t.rstrip("/").split("/")[-1] == suffix and i.count]
    return hits[0] if hits else None


def load_run(path: str | os.PathLike[str]) -> RunData:
    """Read a run file: rig attachment, tensions, tunnel conditions, pose (camera, else the truth
    file beside the run, else the rig's reference pose)."""
    from cdpr.daq.run_reader import open_run

    p = Path(path)
    with open_run(p) as run:
        rigs = [k for k in run.attachments if k.startswith("rig/")]
        if not rigs:
            raise ConfigError(str(p), "attachments", "no rig file attached to the run")
        rig_text = run.attachments[rigs[0]][1].decode()
        try:
            rig = rig_from_mapping(tomllib.loads(rig_text), f"{p}:{rigs[0]}")
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}:{rigs[0]}", "", f"invalid TOML: {exc}") from None
        cols = [f"T_{n}_N" for n in rig.cable_names]
        topic = _topic(run, "tensions")
        n_tens = run.streams[topic].count if topic else 0
        if topic is None or n_tens < 3:
            raise ConfigError(
                str(p), "/tensions", f"expected a tension stream, got {n_tens} messages"
            )
        tens = run.table(topic)
        missing = [c for c in cols if c not in tens.columns]
        if missing:
            raise ConfigError(
                str(p), "/tensions", f"field {missing[0]} missing for rig {rig.name!r}"
            )
        tun_topic = _topic(run, "tunnel")
        tun = run.table(tun_topic) if tun_topic else None
        pose_topic = _topic(run, "pose")
        pose_df = run.table(pose_topic) if pose_topic else None
    t_ns = tens["t_ns"].to_numpy(np.int64)
    T = tens[cols].to_numpy(dtype=np.float64)
    order = np.argsort(t_ns, kind="stable")
    t_ns, T = t_ns[order], T[order]
    keep = np.concatenate([[True], np.diff(t_ns) > 0])
    t_ns, T = t_ns[keep], T[keep]

    if tun is not None and len(tun):
        tt = tun["t_ns"].to_numpy(np.int64)
        nan = np.full(len(tun), np.nan)
        v = interpolate_at(
            t_ns,
            tt,
            tun["airspeed_mps"].fillna(0.0).to_numpy(np.float64)
            if "airspeed_mps" in tun
            else np.zeros(len(tun)),
        )
        rho_src = tun["density_kgpm3"].to_numpy(np.float64) if "density_kgpm3" in tun else nan
        need = ~(rho_src > 0)
        if need.any():
            if "static_pressure_Pa" not in tun or "temperature_K" not in tun:
                raise ConfigError(
                    str(p), tun_topic or "/tunnel",
                    "no density_kgpm3, static_pressure_Pa or temperature_K for the air density",
                )  # fmt: skip
            rho_src = rho_src.copy()
            rho_src[need] = air_density(
                tun["static_pressure_Pa"].to_numpy(np.float64)[need],
                tun["temperature_K"].to_numpy(np.float64)[need],
            )
        rho = interpolate_at(t_ns, tt, rho_src)
    else:
        v, rho = np.zeros(len(t_ns)), np.full(len(t_ns), 1.204)

    truth = None
    truth_path = p.with_name(p.name.removesuffix(".mcap") + ".truth.npz")
    if truth_path.exists():
        with np.load(truth_path) as z:
            truth = {k: z[k] for k in z.files}

    pose_msgs = pose_df is not None and len(pose_df) > 0
    cam_t = cam_q = None
    if pose_df is not None and pose_msgs:
        tp = pose_df["t_ns"].to_numpy(np.int64)
        pos = pose_df[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
        quat = pose_df[["qw", "qx", "qy", "qz"]].to_numpy(np.float64)
        good = np.isfinite(pos).all(axis=1) & np.isfinite(quat).all(axis=1)
        if good.sum() >= 2:
            q6 = np.concatenate([pos[good], euler_from_quaternion(quat[good])], axis=1)
            poses, src = interpolate_at(t_ns, tp[good], q6), "camera (/pose stream)"
            cam_t, cam_q = tp[good], q6
        else:
            pose_msgs = False
    if not pose_msgs and truth is not None and "position_O_m" in truth:
        q6 = np.concatenate([truth["position_O_m"], truth["euler_rad"]], axis=1)
        poses = interpolate_at(t_ns, truth["t_ns"], q6)
        src = f"virtual-rig truth ({truth_path.name}); no camera stream in the run"
    elif not pose_msgs:
        ref = np.concatenate([rig.reference_position_O_m, rig.reference_euler_rad])
        poses, src = np.tile(ref, (len(t_ns), 1)), "rig reference pose (no pose stream)"
    return RunData(p, rig, t_ns, T, poses, src, v, rho, truth, cam_t, cam_q)


def _diag_cov(sd: np.ndarray) -> np.ndarray:
    """(n_seg, n) standard deviations -> (n_seg, n, n) diagonal covariances (independent cables)."""
    return sd[..., None] * np.eye(sd.shape[-1]) * sd[:, None, :]


def analyze_arrays(run: RunData, opts: AnalyzeOptions) -> pd.DataFrame:
    """One row per steady segment with the recovered wrench, its standard deviations, the
    coefficients and the tension check."""
    rig = run.rig
    segs = steady_segments(run.t_ns, run.airspeed_mps, run.poses, opts.rule)
    if not segs:
        raise ConfigError(str(run.path), "/tensions", "no steady segment found (run too short?)")
    st = segment_stats(run.t_ns, run.tensions_N, run.poses, run.airspeed_mps, segs)
    s = len(segs)
    rho = np.array([run.density_kgpm3[a:b].mean() for a, b in segs])
    is_tare = st.airspeed_mps < opts.rule.wind_off_mps
    tare_idx = nearest_tare(
        st.pose_mean, is_tare, st.start_ns, opts.rule.position_tol_m, opts.rule.angle_tol_rad
    )
    R = rotation_from_euler(st.pose_mean[:, 3:])
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, st.pose_mean[:, :3], R)
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    W_abs = wrench_absolute(A, st.tension_mean_N, G)
    sem = st.tension_sd_N / np.sqrt(st.n)[:, None]
    cov_abs = wrench_covariance(
        rig,
        st.pose_mean,
        st.tension_mean_N,
        _diag_cov(sem),
        np.array(opts.pose_sd),
    )
    has_tare = tare_idx >= 0
    T0 = np.where(has_tare[:, None], st.tension_mean_N[np.maximum(tare_idx, 0)], np.nan)
    W_tare = np.where(
        has_tare[:, None],
        wrench_tare(A, tensions_wind_on_N=st.tension_mean_N, tensions_wind_off_N=np.nan_to_num(T0)),
        np.nan,
    )
    sem0 = np.where(has_tare[:, None], sem[np.maximum(tare_idx, 0)], 0.0)
    cov_tare = wrench_covariance(
        rig,
        st.pose_mean,
        st.tension_mean_N,
        _diag_cov(sem),
        np.array(opts.pose_sd),
        tare_tensions_N=np.nan_to_num(T0),
        tare_tension_cov=_diag_cov(sem0),
    )
    W_best = np.where(has_tare[:, None], W_tare, W_abs)
    # The paper's check: tensions the method commands for the recovered wrench vs the measured ones.
    expected = distribute(opts.method, A, -(G + W_best), rig.t_min_N, rig.t_max_N)
    err = st.tension_mean_N - expected.tensions_N

    rows: dict[str, Any] = {
        "segment": np.arange(s),
        "start_ns": st.start_ns,
        "stop_ns": st.stop_ns,
        "n_samples": st.n,
        "airspeed_mps": st.airspeed_mps,
        "density_kgpm3": rho,
        "wind_off": is_tare.astype(int),
        "tare_segment": tare_idx,
    }
    for k, c in enumerate(("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")):
        rows[c] = st.pose_mean[:, k]
    for k, name in enumerate(rig.cable_names):
        rows[f"T_{name}_N"] = st.tension_mean_N[:, k]
        rows[f"sd_T_{name}_N"] = st.tension_sd_N[:, k]
        rows[f"dT_{name}_N"] = err[:, k]
    for k, c in enumerate(WRENCH_COLUMNS):
        rows[f"abs_{c}"] = W_abs[:, k]
        rows[f"abs_sd_{c}"] = cov_abs.std[:, k]
        rows[f"tare_{c}"] = W_tare[:, k]
        rows[f"tare_sd_{c}"] = np.where(has_tare, cov_tare.std[:, k], np.nan)
    rows["check_max_abs_dT_N"] = np.abs(err).max(axis=1)
    rows["check_pass"] = (rows["check_max_abs_dT_N"] <= opts.check_limit_N).astype(int)
    rows["expected_feasible"] = expected.feasible.astype(int)
    wind_on = ~is_tare
    coef = {
        k: np.full(s, np.nan) for k in ("alpha_rad", "beta_rad", "CD", "CY", "CL", "Cl", "Cm", "Cn")
    }
    if wind_on.any():
        qd = dynamic_pressure(rho[wind_on], st.airspeed_mps[wind_on])
        res = aero_coefficients(
            W_best[wind_on], R[wind_on], qd, opts.area_m2, opts.span_m, opts.chord_m
        )
        for k in coef:
            coef[k][wind_on] = getattr(res, k)
    rows.update(coef)
    if run.truth is not None and "wrench_aero_O" in run.truth:
        mid = (st.start_ns + st.stop_ns) // 2
        W_true = interpolate_at(mid, run.truth["t_ns"], run.truth["wrench_aero_O"])
        for k, c in enumerate(WRENCH_COLUMNS):
            rows[f"true_{c}"] = W_true[:, k]
            rows[f"err_{c}"] = W_best[:, k] - W_true[:, k]
    return pd.DataFrame(rows)


def camera_pose_error(run: RunData) -> dict[str, float] | None:
    """RMS position (mm) and rotation (deg) error of the camera poses against the virtual rig's
    truth, when the run has both."""
    if run.camera_t_ns is None or run.camera_poses is None or run.truth is None:
        return None
    if "position_O_m" not in run.truth:
        return None
    q_true = np.concatenate([run.truth["position_O_m"], run.truth["euler_rad"]], axis=1)
    tq = interpolate_at(run.camera_t_ns, run.truth["t_ns"], q_true)
    pos_err = np.linalg.norm(run.camera_poses[:, :3] - tq[:, :3], axis=1)
    R_rel = np.swapaxes(rotation_from_euler(tq[:, 3:]), -1, -2) @ rotation_from_euler(
        run.camera_poses[:, 3:]
    )
    cos = np.clip((np.trace(R_rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    return {
        "n_poses": int(len(pos_err)),
        "position_rms_mm": float(1e3 * np.sqrt(np.mean(pos_err**2))),
        "position_max_mm": float(1e3 * pos_err.max()),
        "rotation_rms_deg": float(np.sqrt(np.mean(ang**2))),
        "rotation_max_deg": float(ang.max()),
    }


def _plots(run: RunData, df: pd.DataFrame, folder: Path) -> None:
    from .plotting import png_figure

    t0 = run.t_ns[0]
    ts = (run.t_ns - t0) * 1e-9
    with png_figure(folder / "tensions.png", 2, 1, (10, 6), sharex=True, height_ratios=[3, 1]) as (
        fig,
        axes,
    ):
        ax = axes[:, 0]
        for k, name in enumerate(run.rig.cable_names):
            ax[0].plot(ts, run.tensions_N[:, k], lw=0.8, label=name)
        for _, r in df.iterrows():
            for a in ax:
                a.axvspan(
                    (r.start_ns - t0) * 1e-9,
                    (r.stop_ns - t0) * 1e-9,
                    color="0.9" if r.wind_off else "#dde8f7",
                    zorder=0,
                )
        ax[0].set_ylabel("tension (N)")
        ax[0].legend(fontsize=7, ncol=4, loc="upper left")
        ax[0].set_title(
            f"{run.path.name}: tensions; shaded = steady segments (grey: wind-off tares)"
        )
        ax[1].plot(ts, run.airspeed_mps, color="k", lw=1)
        ax[1].set_ylabel("airspeed (m/s)")
        ax[1].set_xlabel("time (s)")

    on = df[df.wind_off == 0]
    with png_figure(folder / "wrench.png", 2, 3, (11, 6)) as (fig, axes):
        for k, c in enumerate(WRENCH_COLUMNS):
            a = axes.flat[k]
            use_tare = on["tare_segment"] >= 0
            y = np.where(use_tare, on[f"tare_{c}"], on[f"abs_{c}"])
            e = np.where(use_tare, on[f"tare_sd_{c}"], on[f"abs_sd_{c}"])
            a.errorbar(
                on["airspeed_mps"], y, yerr=2 * e, fmt="o", capsize=3, label="recovered (±2σ)"
            )
            if f"true_{c}" in on:
                a.plot(
                    on["airspeed_mps"], on[f"true_{c}"], "x", color="C3", label="virtual-rig truth"
                )
            a.set_title(c)
            a.set_xlabel("airspeed (m/s)")
            a.grid(alpha=0.3)
        axes.flat[0].legend(fontsize=7)
        fig.suptitle(
            "Recovered aerodynamic wrench per test point (tare method where a tare exists)"
        )

    dcols = [f"dT_{n}_N" for n in run.rig.cable_names]
    with png_figure(folder / "check.png", size=(10, 4)) as (fig, axes):
        ax = axes[0, 0]
        width = 0.8 / len(dcols)
        for k, c in enumerate(dcols):
            ax.bar(df["segment"] + (k - len(dcols) / 2) * width, df[c], width, label=c[3:-2])
        ax.axhline(1.0, color="r", ls="--", lw=1)
        ax.axhline(-1.0, color="r", ls="--", lw=1, label="±1 N (paper)")
        ax.set_xlabel("segment")
        ax.set_ylabel("measured − expected tension (N)")
        ax.set_title("Measured vs simulated tensions (the paper's ≈1 N check)")
        ax.legend(fontsize=7, ncol=5)


def _report(run: RunData, df: pd.DataFrame, summary: dict[str, Any]) -> str:
    lines = [
        f"# Analysis of `{run.path.name}`",
        "",
        f"- rig: **{run.rig.name}** ({run.rig.n_cables} cables); pose from: {run.pose_source}",
        f"- {len(df)} steady segments, {int(df.wind_off.sum())} wind-off tares; method for the "
        f"expected tensions: `{summary['options']['method']}`",
        f"- measured vs simulated tensions: max |ΔT| = {summary['check_max_abs_dT_N']:.3f} N "
        f"(paper: about 1 N) → **{'pass' if summary['check_pass'] else 'FAIL'}**",
        "",
        "| seg | V (m/s) | tare | Fx (N) | Fy (N) | Fz (N) | Mx (N m) | My (N m) | Mz (N m) "
        "| CL | CD | max ΔT (N) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for _, r in df.iterrows():
        pre = "tare_" if r.tare_segment >= 0 else "abs_"
        w = [f"{r[pre + c]:.3f} ± {r[pre + 'sd_' + c]:.3f}" for c in WRENCH_COLUMNS]
        tare = int(r.tare_segment) if r.tare_segment >= 0 else "-"
        lines.append(
            f"| {int(r.segment)} | {r.airspeed_mps:.2f} | {tare} | "
            + " | ".join(w)
            + " | "
            + " | ".join("-" if np.isnan(r[c]) else f"{r[c]:.3f}" for c in ("CL", "CD"))
            + f" | {r.check_max_abs_dT_N:.3f} |"
        )
    pe = summary.get("camera_pose_error_vs_truth")
    if pe:
        lines += [
            "",
            f"Camera pose against the virtual rig's truth ({pe['n_poses']} poses): position RMS "
            f"{pe['position_rms_mm']:.3f} mm (max {pe['position_max_mm']:.3f}), rotation RMS "
            f"{pe['rotation_rms_deg']:.4f}° (max {pe['rotation_max_deg']:.4f}°); the paper's camera: "
            "0.5 mm and 0.1°.",
        ]
    if "true_fx_N" in df:
        on = df[df.wind_off == 0]
        errs = ", ".join(f"{c} {np.abs(on['err_' + c]).max():.3g}" for c in WRENCH_COLUMNS)
        lines += ["", f"Against the virtual rig's true aerodynamic wrench, max |error|: {errs}."]
    lines += [
        "",
        "Uncertainty: ±1σ from load-cell noise (segment standard error) and the camera pose "
        "precision (0.5 mm, 0.1°) through the structure matrix (`cdpr.analysis.uncertainty`).",
        "",
        "![tensions](tensions.png)",
        "",
        "![wrench](wrench.png)",
        "",
        "![check](check.png)",
        "",
    ]
    return "\n".join(lines)


def analyze_run(path: str, out_dir: str, opts: AnalyzeOptions) -> dict[str, Any]:
    """Analyse one run and write its folder atomically; returns the summary."""
    run = load_run(path)
    df = analyze_arrays(run, opts)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    final = out / run.path.name.removesuffix(".mcap")
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=out))
    try:
        summary = {
            "run": str(run.path),
            "run_sha256": file_sha256(run.path),
            "software_version": __version__,
            "rig": run.rig.name,
            "pose_source": run.pose_source,
            "options": json.loads(json.dumps(asdict(opts), default=float)),
            "segments": len(df),
            "check_max_abs_dT_N": float(df["check_max_abs_dT_N"].max()),
            "check_pass": bool((df["check_max_abs_dT_N"] <= opts.check_limit_N).all()),
        }
        pose_err = camera_pose_error(run)
        if pose_err is not None:
            summary["camera_pose_error_vs_truth"] = pose_err
        if "err_fx_N" in df:
            on = df[df.wind_off == 0]
            summary["max_abs_error_vs_truth"] = {
                c: float(np.abs(on[f"err_{c}"]).max()) for c in WRENCH_COLUMNS
            }
        df.to_csv(tmp / "segments.csv", index=False)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        _plots(run, df, tmp)
        (tmp / "report.md").write_text(_report(run, df, summary))
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    summary["folder"] = str(final)
    return summary


def _safe(path: str, out_dir: str, opts: AnalyzeOptions) -> dict[str, Any]:
    try:
        return analyze_run(path, out_dir, opts)
    except CdprError as exc:
        return {"run": path, "error": str(exc)}


def analyze_runs(
    paths: Sequence[str],
    out_dir: str,
    opts: AnalyzeOptions,
    scheduler: str | None = None,
    workers: int = 2,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Analyse runs in parallel on Dask (a local cluster unless ``scheduler`` is an address); a bad
    run is reported in its summary (``error``) without stopping the others."""
    if not paths:
        raise ConfigError("runs", "", "no run files given")
    if len(paths) == 1 and scheduler is None:
        results = [_safe(paths[0], out_dir, opts)]
    else:
        from dask.distributed import Client, LocalCluster, as_completed

        cluster = None
        if scheduler is None:
            cluster = LocalCluster(
                n_workers=max(1, min(workers, len(paths))),
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
            )
        client = Client(scheduler or cluster)
        try:
            futures = [client.submit(_safe, p, out_dir, opts, pure=False) for p in paths]
            done = 0
            for _ in as_completed(futures):
                done += 1
                if progress:
                    print(f"  analysed {done}/{len(paths)} runs", flush=True)
            results = client.gather(futures)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    lines = [
        "# Analysed runs",
        "",
        "| run | segments | max ΔT (N) | check | report |",
        "|---|---|---|---|---|",
    ]
    for r in results:
        if "error" in r:
            lines.append(f"| {Path(r['run']).name} | - | - | error: {r['error']} | - |")
        else:
            rel = Path(r["folder"]).name
            lines.append(
                f"| {Path(r['run']).name} | {r['segments']} | {r['check_max_abs_dT_N']:.3f} | "
                f"{'pass' if r['check_pass'] else 'FAIL'} | [{rel}/report.md]({rel}/report.md) |"
            )
    index = Path(out_dir) / "index.md"
    index.parent.mkdir(parents=True, exist_ok=True)
    tmp = index.with_suffix(".md.part")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, index)
    return results
