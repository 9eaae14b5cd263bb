"""``cdpr analyze``: batch post-processing of recorded runs (see :mod:`cdpr.pipelines.analyze`)."""

from __future__ import annotations

import argparse
import sys

METHOD_NAMES = ("closed-form", "improved-closed-form", "penalty", "exact")


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "analyze",
        help="post-process runs: wrench, coefficients, uncertainty, the 1 N check, reports",
        description=__doc__,
    )
    p.add_argument("runs", nargs="+", help="run files (.mcap) or folders holding them")
    p.add_argument("--out", required=True, help="output folder (one sub-folder per run + index.md)")
    p.add_argument("--method", default="exact", choices=METHOD_NAMES, help="controller's method")
    p.add_argument("--scheduler", help="Dask scheduler address (default: a local cluster)")
    p.add_argument("--workers", type=int, default=2, help="local Dask workers (default 2)")
    p.add_argument(
        "--check-limit-N", type=float, default=1.0, help="pass mark of the tension check"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import math
    from pathlib import Path

    from cdpr.analysis.errors import ConfigError, InputError

    from ..analyze import AnalyzeOptions, analyze_runs

    if args.workers < 1:
        raise InputError(f"--workers: expected >= 1, got {args.workers}")
    if not (math.isfinite(args.check_limit_N) and args.check_limit_N > 0):
        raise InputError(
            f"--check-limit-N: expected a finite number > 0 N, got {args.check_limit_N}"
        )
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
    opts = AnalyzeOptions(method=args.method, check_limit_N=args.check_limit_N)
    results = analyze_runs(paths, args.out, opts, scheduler=args.scheduler, workers=args.workers)
    bad = [r for r in results if "error" in r]
    for r in results:
        if "error" in r:
            print(f"cdpr analyze: error: {r['error']}", file=sys.stderr)
        else:
            verdict = "pass" if r["check_pass"] else "FAIL"
            print(
                f"{Path(r['run']).name}: {r['segments']} segments, max |dT| "
                f"{r['check_max_abs_dT_N']:.3f} N ({verdict}) -> {r['folder']}/report.md"
            )
    print(f"index: {Path(args.out) / 'index.md'}")
    return 2 if bad else 0
