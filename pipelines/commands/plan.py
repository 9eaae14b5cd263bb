"""``cdpr plan``: plan the motion of a test matrix's oscillation points before the tunnel.

Per oscillation point (docs/dynamic_tests.md): the controller's table (``<point>.csv``: time,
pose, each cable's length, speed and acceleration, the feed-forward tensions at ``--rate-hz``),
a figure (``<point>.png``: tensions over a cycle against the limits, harmonics against the modes),
and ``summary.csv`` / ``summary.md`` (margins, limits, modes against the frequency and its
harmonics).  A refused point gets one line on stderr naming it and the reason, and no table.
Exit 0: every point ok; 1: a point flagged; 3: a point refused; 2: bad input (one line).
"""

from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from ..motion_plan import DEFAULT_HARMONICS, DEFAULT_MODE_BAND, DEFAULT_RATE_HZ

    p = sub.add_parser(
        "plan",
        help="plan the oscillation points of a test matrix: cable tables, tension margins, modes",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("matrix", help="test matrix (TOML, docs/campaign.md)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--rate-hz",
        type=float,
        default=DEFAULT_RATE_HZ,
        help=f"rows per second of the controller's table (default {DEFAULT_RATE_HZ:g})",
    )
    p.add_argument(
        "--method",
        default="exact",
        choices=("closed-form", "improved-closed-form", "penalty", "exact"),
        help="the controller's tension distribution (default exact)",
    )
    p.add_argument(
        "--harmonics",
        type=int,
        default=DEFAULT_HARMONICS,
        help=f"harmonics of the frequency checked against the modes (default {DEFAULT_HARMONICS})",
    )
    p.add_argument(
        "--mode-band",
        type=float,
        default=DEFAULT_MODE_BAND,
        help="a harmonic within this fraction of a mode meets it: the fundamental is refused, "
        f"a harmonic flagged (default {DEFAULT_MODE_BAND:g})",
    )
    p.add_argument("--point", action="append", help="plan only this point (repeatable)")
    p.add_argument("--no-plots", action="store_true", help="no figures")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cdpr.analysis.errors import ConfigError, InputError

    from ..campaign import load_test_matrix
    from ..config import load_rig
    from ..motion_plan import plan_matrix, refusal_line, summary_line, write_plan

    if not (args.rate_hz > 0 and args.rate_hz <= 1e5):
        raise InputError(f"--rate-hz: expected a rate in (0, 1e5] Hz, got {args.rate_hz}")
    if args.harmonics < 1 or args.harmonics > 100:
        raise InputError(f"--harmonics: expected 1..100, got {args.harmonics}")
    if not (0 <= args.mode_band < 1):
        raise InputError(f"--mode-band: expected a fraction in [0, 1), got {args.mode_band}")
    matrix = load_test_matrix(args.matrix)
    rig = load_rig(matrix.rig_path)
    labels = {p.label for p in matrix.points}
    for lab in args.point or []:
        if lab not in labels:
            raise ConfigError(args.matrix, "--point", f"no point labelled {lab!r}")
    plans = plan_matrix(
        matrix, rig, args.rate_hz, args.method, args.harmonics, args.mode_band, args.point
    )
    if not plans:
        raise ConfigError(args.matrix, "points", "no oscillation point to plan")
    options = {
        "rate_hz": args.rate_hz,
        "method": args.method,
        "harmonics": args.harmonics,
        "mode_band": args.mode_band,
    }
    write_plan(plans, matrix, rig, args.out, options, args.mode_band, plots=not args.no_plots)
    for p in plans:
        if p.refused:
            print(f"cdpr plan: refused: {refusal_line(p)}", file=sys.stderr)
        else:
            print(f"cdpr plan: {summary_line(p)}")
    n_ref = sum(bool(p.refused) for p in plans)
    n_flag = sum(bool(p.flags) and not p.refused for p in plans)
    print(
        f"cdpr plan: {len(plans)} oscillation points: {len(plans) - n_ref - n_flag} ok, "
        f"{n_flag} flagged, {n_ref} refused; wrote {args.out}/summary.md"
    )
    return 3 if n_ref else (1 if n_flag else 0)
