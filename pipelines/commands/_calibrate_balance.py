"""``cdpr calibrate loadcells`` and ``cdpr calibrate balance`` (actions added to ``calibrate``).

``cdpr calibrate loadcells POINTS.csv --out loadcells.toml [--rig R]``: POINTS.csv has columns
``channel`` (cable name), ``load_N`` (known tension applied through that cable, e.g. dead weights)
and ``counts`` (the amplifier's reading); >= 3 distinct loads per channel.  Writes a calibration
file with an id: ``offset_counts`` and ``gain_N_per_count`` per cable (the keys a load-cell source
takes, see ``calibration_file`` in docs/recording.md), their standard deviations and correlation
(the fit's parameter covariance, used by the reduction's systematic term), the residual RMS and the
non-linearity; and ``<out>.png`` with the residuals.

``cdpr calibrate balance CHECKLOADS.csv --rig R --out balance.json``: CHECKLOADS.csv has the pose
columns, one ``T_<cable>_N`` column per cable (measured) and the applied wrench
``fx_N .. mz_Nm`` (at P, {O} axes); rows whose applied wrench is zero are wind-off tares, used by the
tare method for the loaded rows at the same pose (else the absolute method).  Writes the check-load
errors, the 6x6 interaction matrix with its fit covariance (``interaction_matrix_fit``; the
second-order model's under ``second_order.fit``), ``<out>.png`` (recovered vs applied) and an id.
"""

from __future__ import annotations

import argparse


def register_actions(cs: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    lc = cs.add_parser("loadcells", help="load-cell zero and gain from known loads")
    lc.add_argument("points", help="CSV: channel, load_N, counts")
    lc.add_argument(
        "--rig", help="rig file: channel order = its cables (default: order of appearance)"
    )
    lc.add_argument("--out", required=True, help="output calibration file (TOML)")
    lc.set_defaults(func=run_loadcells)

    bal = cs.add_parser(
        "balance", help="check loads on the whole balance: errors, interaction matrix"
    )
    bal.add_argument("checkloads", help="CSV: pose, T_<cable>_N, applied fx_N..mz_Nm")
    bal.add_argument("--rig", required=True, help="rig file (TOML)")
    bal.add_argument("--out", required=True, help="output (JSON)")
    bal.set_defaults(func=run_balance)


def _stamp() -> str:
    import time

    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def run_loadcells(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from cdpr.analysis.errors import ConfigError, InputError
    from cdpr.calibration.balance_fit import fit_load_cell
    from cdpr.daq.loadcell import Calibration, calibration_file_text

    from .. import __version__
    from ..config import atomic_output, file_sha256, load_rig, read_table

    df = read_table(
        args.points,
        ["load_N", "counts"],
        "load-cell calibration table",
        {"load_N": (1e7, "N"), "counts": (1e15, "counts")},
    )
    if "channel" not in df.columns:
        raise ConfigError(args.points, "column channel", "missing (the cable name of each point)")
    df["channel"] = df["channel"].astype(str).str.strip()
    names = list(load_rig(args.rig).cable_names) if args.rig else list(dict.fromkeys(df["channel"]))
    unknown = sorted(set(df["channel"]) - set(names))
    if unknown:
        row = int(np.flatnonzero(df["channel"] == unknown[0])[0]) + 2
        raise ConfigError(
            args.points, f"row {row}, column channel", f"unknown cable {unknown[0]!r}"
        )
    fits = []
    for name in names:
        sel = df[df["channel"] == name]
        try:
            fits.append(fit_load_cell(sel["load_N"], sel["counts"]))
        except InputError as exc:
            raise ConfigError(args.points, f"channel {name}", str(exc)) from None
    sha = file_sha256(args.points)
    text = calibration_file_text(
        names,
        Calibration(
            np.array([f.offset_counts for f in fits]), np.array([f.gain_N_per_count for f in fits])
        ),
        f"loadcells@{sha[:12]}",
        {
            "source": f"{Path(args.points).name} sha256={sha}",
            "created_utc": _stamp(),
            "software_version": __version__,
            "sd_offset_counts": [f.sd_offset_counts for f in fits],
            "sd_gain_N_per_count": [f.sd_gain_N_per_count for f in fits],
            "corr_offset_gain": [f.corr_offset_gain for f in fits],
            "residual_rms_N": [f.residual_rms_N for f in fits],
            "nonlinearity_pct": [f.nonlinearity_pct for f in fits],
            "n_points": [f.n_points for f in fits],
        },
    )
    _residual_plot(df, names, fits, Path(args.out).with_suffix(".png"))
    with atomic_output(args.out) as fh:
        fh.write(text)
    worst = max(fits, key=lambda f: f.nonlinearity_pct)
    print(
        f"cdpr calibrate loadcells: {len(names)} channels, residual RMS <= "
        f"{max(f.residual_rms_N for f in fits):.4g} N, non-linearity <= {worst.nonlinearity_pct:.3g} % "
        f"-> {args.out}"
    )
    return 0


def _residual_plot(df, names, fits, path) -> None:  # type: ignore[no-untyped-def]
    from ..plotting import png_figure

    with png_figure(path, size=(8, 4)) as (fig, axes):
        ax = axes[0, 0]
        for name, f in zip(names, fits, strict=True):
            sel = df[df["channel"] == name]
            pred = (sel["counts"] - f.offset_counts) * f.gain_N_per_count
            ax.plot(sel["load_N"], sel["load_N"] - pred, "o-", ms=3, label=name)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel("applied load (N)")
        ax.set_ylabel("residual (N)")
        ax.set_title("Load-cell calibration residuals (straight-line fit)")
        ax.legend(fontsize=7, ncol=4)


def run_balance(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    import numpy as np

    from cdpr.analysis.balance import nearest_tare
    from cdpr.analysis.balance_model import fit_second_order
    from cdpr.analysis.conventions import POSE_COLUMNS, WRENCH_COLUMNS, WRENCH_NAMES
    from cdpr.analysis.dynamics import gravity_wrench
    from cdpr.analysis.errors import ConfigError, InputError
    from cdpr.analysis.kinematics import structure_matrix
    from cdpr.analysis.rotations import rotation_from_euler
    from cdpr.analysis.wrench import wrench_absolute, wrench_tare
    from cdpr.calibration.balance_fit import check_loads

    from .. import __version__
    from ..config import atomic_output, file_sha256, load_rig, read_table, tension_columns

    rig = load_rig(args.rig)
    cols = [*POSE_COLUMNS, *tension_columns(rig), *WRENCH_COLUMNS]
    df = read_table(args.checkloads, cols, "check-load table")
    q = df[list(POSE_COLUMNS)].to_numpy(dtype=np.float64)
    T = df[tension_columns(rig)].to_numpy(dtype=np.float64)
    W = df[list(WRENCH_COLUMNS)].to_numpy(dtype=np.float64)
    is_tare = np.all(W == 0, axis=1)
    R = rotation_from_euler(q[:, 3:])
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, q[:, :3], R)
    tare = nearest_tare(q, is_tare, np.arange(len(q)), 1e-3, np.deg2rad(0.1))
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    rec = np.where(
        (tare >= 0)[:, None],
        wrench_tare(A, tensions_wind_on_N=T, tensions_wind_off_N=T[np.maximum(tare, 0)]),
        wrench_absolute(A, T, G),
    )
    loaded = ~is_tare
    try:
        res = check_loads(rec[loaded], W[loaded])
    except InputError as exc:
        raise ConfigError(args.checkloads, "rows", str(exc)) from None
    sha = file_sha256(args.checkloads)
    loaded_fs = res.full_scale > 0  # a component never loaded has no full scale
    pct_fs = [
        float(100 * e / f) if ok else None
        for e, f, ok in zip(res.max_abs_error, res.full_scale, loaded_fs, strict=True)
    ]
    doc = {
        "id": f"balance@{sha[:12]}",
        "kind": "balance-check-loads",
        "source": f"{Path(args.checkloads).name} sha256={sha}",
        "rig": f"{Path(args.rig).name} sha256={file_sha256(args.rig)}",
        "created_utc": _stamp(),
        "software_version": __version__,
        "n_check_loads": int(loaded.sum()),
        "n_tares": int(is_tare.sum()),
        "method": "tare where a wind-off row exists at the same pose, else absolute",
        "components": list(WRENCH_NAMES),
        "full_scale": res.full_scale.tolist(),
        "rms_error": res.rms_error.tolist(),
        "max_abs_error": res.max_abs_error.tolist(),
        "max_abs_error_pct_fs": pct_fs,
        "interaction_matrix": res.interaction.tolist(),
        "corrected_rms_error": res.corrected_rms_error.tolist(),
        "interaction_matrix_fit": fit_json(res.fit),
    }
    second, why = fit_second_order(rec[loaded], W[loaded])
    doc["second_order"] = (
        None
        if second is None
        else {
            "K1": second.K1.tolist(),
            "K2": second.K2.tolist(),
            "quadratic_terms": "W_i W_j, i <= j, row-major upper triangle (21)",
            "rms_error_first_order": second.rms_first.tolist(),
            "rms_error_second_order": second.rms_second.tolist(),
            "p_value": second.p_value.tolist(),
            "fit": fit_json(second.fit),
        }
    )
    doc["second_order_note"] = why
    _check_plot(res, Path(args.out).with_suffix(".png"))
    with atomic_output(args.out) as fh:
        fh.write(json.dumps(doc, indent=2) + "\n")
    worst = max((k for k in range(6) if pct_fs[k] is not None), key=lambda k: pct_fs[k] or 0.0)
    never = [WRENCH_NAMES[k] for k in range(6) if pct_fs[k] is None]
    print(
        f"cdpr calibrate balance: {doc['n_check_loads']} check loads, worst {WRENCH_NAMES[worst]} "
        f"{pct_fs[worst]:.3g} % of full scale"
        + (f" (never loaded: {', '.join(never)})" if never else "")
        + f" -> {args.out}"
    )
    print(f"  {why}")
    return 0


def fit_json(fit) -> dict | None:  # type: ignore[no-untyped-def,type-arg]
    """The balance fit's covariance as JSON (read back by
    :func:`cdpr.pipelines.config.read_balance_fit`); None without one."""
    if fit is None:
        return None
    return {
        "residual_cov": fit.residual_cov.tolist(),
        "inverse_gram": fit.inverse_gram.tolist(),
        "dof": fit.dof,
        "covariance": "cov(K[i, j], K[k, l]) = residual_cov[i, k] * inverse_gram[j, l] "
        "(K: the model's coefficients, rows per component, columns per regressor)",
    }


def _check_plot(res, path) -> None:  # type: ignore[no-untyped-def]
    from cdpr.analysis.conventions import WRENCH_NAMES

    from ..plotting import png_figure

    with png_figure(path, 2, 3, (10, 6)) as (fig, axes):
        for k, a in enumerate(axes.flat):
            a.plot(res.applied[:, k], res.error[:, k], "o", ms=4)
            a.axhline(0, color="k", lw=0.8)
            a.set_title(f"{WRENCH_NAMES[k]}: recovered - applied")
            a.set_xlabel("applied")
        fig.suptitle("Balance check loads")
