"""``cdpr analyze``: batch post-processing of recorded runs (see :mod:`cdpr.pipelines.analyze`).

Exit codes: 0 every run reduced without a warning; 1 reduced, but some point carries a warning flag
(masked samples, no tare, no airspeed, a nominal fallback, ... — one line each on stdout, all in the
reports); 2 a run could not be analysed (one line on stderr naming the file and the problem).

A run whose results in OUT record the fingerprint of its inputs now (the SHA-256 of the run, the
balance calibration, the load-cell calibration, the truth file beside it, the options, the
software version) is not recomputed: it is listed as "current, skipped" (its recorded warnings
still count); --force recomputes it.

--loadcell-calibration FILE (or the test matrix's campaign.loadcell_calibration; the option wins)
re-derives every tension from the run's recorded raw counts with FILE before the reduction; a run
without raw counts, or whose cables FILE does not calibrate, is refused before any output (exit 2).
"""

from __future__ import annotations

import argparse
import sys

from cdpr.analysis.conventions import TENSION_METHODS


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "analyze",
        help="post-process runs: test points, weight tares, wrench ± σ, coefficients, reports",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("runs", nargs="+", help="run files (.mcap) or folders holding them")
    p.add_argument("--out", required=True, help="output folder (one sub-folder per run + index.md)")
    p.add_argument("--method", default="exact", choices=TENSION_METHODS, help="controller's method")
    p.add_argument("--scheduler", help="Dask scheduler address (default: a local cluster)")
    p.add_argument("--workers", type=int, default=2, help="local Dask workers (default 2)")
    p.add_argument(
        "--force",
        action="store_true",
        help="recompute runs whose results are current (same input fingerprint)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument(
        "--check-limit-N", type=float, default=1.0, help="pass mark of the tension check"
    )
    p.add_argument("--balance", help="balance calibration (cdpr calibrate balance output, JSON)")
    p.add_argument(
        "--pose-sd",
        nargs=6,
        type=float,
        metavar=("X_M", "Y_M", "Z_M", "ROLL_RAD", "PITCH_RAD", "YAW_RAD"),
        help="the camera's precision per frame, for runs whose pose stream carries no covariance "
        "(wins over the test matrix's campaign.pose_sd; without either: the paper's 0.5 mm / "
        "0.1 deg, flagged pose_cov_nominal)",
    )
    p.add_argument(
        "--loadcell-calibration",
        help="load-cell calibration file (cdpr calibrate loadcells): re-derive every tension from "
        "the run's recorded raw counts, T = (counts - offset) * gain, before the reduction "
        "(re-calibration after the run; wins over the test matrix's "
        "campaign.loadcell_calibration)",
    )
    p.add_argument(
        "--matrix",
        help="test matrix (TOML, docs/campaign.md): the model geometry from [model] and the "
        "corrections (zero drift, flow conditions, windage, [tunnel] wall corrections, "
        "repeatability; docs/corrections.md)",
    )
    geo = p.add_argument_group(
        "model geometry (for runs without a test matrix; the points are flagged geometry_from_options)"
    )
    add_geometry_arguments(geo)
    p.set_defaults(func=run)


def add_geometry_arguments(group: argparse._ArgumentGroup) -> None:
    """``--area-m2 --span-m --chord-m --mrp-P-m``: the model geometry given as options (read back
    by :func:`geometry_from_args`; ``cdpr analyze`` and ``cdpr wrench``)."""
    group.add_argument("--area-m2", dest="area_m2", type=float, help="reference area S")
    group.add_argument("--span-m", dest="span_m", type=float, help="reference span b")
    group.add_argument("--chord-m", dest="chord_m", type=float, help="reference chord c")
    group.add_argument(
        "--mrp-P-m",
        dest="mrp_P_m",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 0.0),
        metavar=("X", "Y", "Z"),
        help="moment reference point in {P} (m, default P)",
    )


def geometry_from_args(args: argparse.Namespace, need: bool) -> object | None:
    """A ``ModelGeometry`` (source "options") from ``--area-m2 --span-m --chord-m --mrp-P-m``
    (and ``--nose-P --up-P`` where the command has them); None when none is given and not needed."""
    import math

    from cdpr.analysis.aero import ModelGeometry
    from cdpr.analysis.errors import ConfigError, InputError

    vals = {f: getattr(args, f) for f in ("area_m2", "span_m", "chord_m")}
    if all(v is None for v in vals.values()) and not need:
        return None
    for f, v in vals.items():
        flag = "--" + f.replace("_", "-")
        if v is None:
            raise ConfigError("command line", flag, "required for the aerodynamic coefficients")
        if not (math.isfinite(v) and v > 0):
            raise ConfigError("command line", flag, f"expected a finite value > 0, got {v}")
    try:
        return ModelGeometry(
            area_m2=vals["area_m2"],
            span_m=vals["span_m"],
            chord_m=vals["chord_m"],
            mrp_P_m=tuple(args.mrp_P_m),
            nose_P=tuple(getattr(args, "nose_P", (-1.0, 0.0, 0.0))),
            up_P=tuple(getattr(args, "up_P", (0.0, 0.0, 1.0))),
            source="options",
        )
    except InputError as exc:
        flag = "--mrp-P-m" if "mrp_P_m" in str(exc) else "--nose-P/--up-P"
        raise ConfigError("command line", flag, str(exc)) from None


def run(args: argparse.Namespace) -> int:
    import math
    from pathlib import Path

    from cdpr.analysis.errors import ConfigError, InputError
    from cdpr.analysis.stages import ReduceSettings

    from ..analyze import AnalyzeOptions
    from ..batch import analyze_runs

    if args.workers < 1:
        raise InputError(f"--workers: expected >= 1, got {args.workers}")
    if not (math.isfinite(args.check_limit_N) and args.check_limit_N > 0):
        raise InputError(
            f"--check-limit-N: expected a finite number > 0 N, got {args.check_limit_N}"
        )
    if args.balance is not None and not Path(args.balance).is_file():
        raise ConfigError(args.balance, "", "no such balance calibration file")
    geometry = geometry_from_args(args, need=False)
    pose_sd: tuple[float, ...] | None = None
    pose_sd_from = "paper"
    if args.pose_sd is not None:
        if not all(math.isfinite(v) and v > 0 for v in args.pose_sd):
            raise InputError(f"--pose-sd: expected 6 finite values > 0, got {args.pose_sd}")
        pose_sd, pose_sd_from = tuple(args.pose_sd), "--pose-sd"
    tunnel = instruments = None
    lc_file: str | None = args.loadcell_calibration
    lc_from = "--loadcell-calibration"
    if args.matrix is not None:
        from ..campaign import load_test_matrix

        if geometry is not None:
            raise InputError("--matrix gives the model geometry: drop --area-m2/--span-m/--chord-m")
        m = load_test_matrix(args.matrix)
        geometry = m.model
        if pose_sd is None and m.pose_sd is not None:
            pose_sd, pose_sd_from = m.pose_sd, f"the test matrix {args.matrix} (campaign.pose_sd)"
        tunnel = m.tunnel
        instruments = m.instruments
        if m.loadcell_calibration is not None:
            if lc_file is None:
                lc_file = str(m.loadcell_calibration)
                lc_from = f"the test matrix {args.matrix} (campaign.loadcell_calibration)"
            else:
                lc_from += f" (over the test matrix's {m.loadcell_calibration})"
    if lc_file is not None:
        from cdpr.daq.loadcell import read_calibration_file

        if not Path(lc_file).is_file():
            raise ConfigError(lc_file, "", "no such load-cell calibration file")
        read_calibration_file(lc_file)  # its schema, before any output
    paths: list[str] = []
    for r in args.runs:
        p = Path(r)
        if p.is_dir():
            paths += sorted(
                str(f) for f in p.glob("*.mcap") if not f.name.endswith(".recovered.mcap")
            )
        elif p.is_file():
            paths.append(str(p))
        else:
            raise ConfigError(r, "", "no such run file or folder")
    if not paths:
        raise ConfigError(" ".join(args.runs), "", "no .mcap run files found")
    opts = AnalyzeOptions(
        geometry=geometry,  # type: ignore[arg-type]
        balance_file=args.balance,
        corrections=args.matrix is not None,
        tunnel=tunnel,
        matrix_file=args.matrix,
        loadcell_calibration_file=lc_file,
        loadcell_calibration_from=lc_from if lc_file is not None else None,
        instruments=instruments,
        reduce=ReduceSettings(method=args.method, check_limit_N=args.check_limit_N),
        **({} if pose_sd is None else {"pose_sd_fallback": pose_sd, "pose_sd_from": pose_sd_from}),
    )
    results = analyze_runs(
        paths,
        args.out,
        opts,
        scheduler=args.scheduler,
        workers=args.workers,
        progress=not args.no_progress,
        force=args.force,
    )
    bad = [r for r in results if "error" in r]
    if lc_file is not None:
        print(
            f"load-cell calibration {lc_file} (given by {lc_from}): tensions re-derived from the "
            "recorded raw counts"
        )
    warned = False
    for r in results:
        if "error" in r:
            print(f"cdpr analyze: error: {r['error']}", file=sys.stderr)
            continue
        red = r["reduction"]
        verdict = "pass" if r["check_pass"] else "FAIL"
        if r.get("skipped"):
            print(
                f"{Path(r['run']).name}: current, skipped (inputs unchanged; --force recomputes)"
                f" -> {r['folder']}/report.md"
            )
            for line in red["lines"]:
                print(f"  warning: {line}")
            for line in r.get("online", []):
                print(f"  {line}")
            warned |= bool(red["warnings"])
            continue
        print(
            f"{Path(r['run']).name}: {r['points']} points ({red['point_source']}), "
            f"{red['points_with_warnings']} with warnings, max |dT| "
            f"{r['check_max_abs_dT_N']:.3f} N ({verdict}) -> {r['folder']}/report.md"
        )
        for line in red["lines"]:
            print(f"  warning: {line}")
        for line in r.get("online", []):  # on-line against final values, per point
            print(f"  {line}")
        warned |= bool(red["warnings"])
    print(f"index: {Path(args.out) / 'index.md'}")
    return 2 if bad else (1 if warned else 0)
