"""``cdpr sensitivity``: the paper's force-sensitivity study (Figs. 6-15, Table 3) and its report.

``cdpr sensitivity --paper --out DIR`` runs every sweep with the documented defaults (see
docs/sensitivity.md and the "Assumptions" section of the report); ``--config FILE.toml`` overrides
any option (sections ``[cubic]``, ``[flat]``, ``[aero]``, ``[study]``).  Writes CSV tables, PNG
figures and ``report.md`` into DIR.  An option out of its range, or a rig that cannot hold its
platform anywhere in a sweep, is a one-line error naming the option (exit 2).
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from cdpr.analysis.errors import ConfigError


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "sensitivity",
        help="force-sensitivity study of the paper (Figs. 6-15) and reproduction report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--paper", action="store_true", help="the paper's studies, default options")
    p.add_argument(
        "--config", help="TOML file overriding options ([cubic], [flat], [aero], [study])"
    )
    p.add_argument("--out", help="output folder (required unless --print-config)")
    p.add_argument(
        "--print-config",
        action="store_true",
        help="print the options (defaults, or --config merged) as TOML and exit",
    )
    p.add_argument("--layout", choices=("crossed", "cube"), help="cubic cable layout (override)")
    p.add_argument(
        "--no-flat-grid",
        action="store_true",
        help="skip the full Table 3 grid (11 x 11 x 9 x 10 configurations)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cdpr.analysis.errors import InputError

    from .. import __version__
    from ..sensitivity_report import StudyOptions, options_from_toml, run_study, validate_options

    opts = options_from_toml(args.config) if args.config else StudyOptions()
    if args.print_config:
        import dataclasses

        import tomli_w

        print(tomli_w.dumps(dataclasses.asdict(opts)), end="")
        return 0
    if not args.paper and not args.config:
        raise InputError("give --paper (the paper's studies) and/or --config FILE.toml")
    if not args.out:
        raise InputError("--out: required (the output folder)")
    source = args.config or "command line"
    if args.layout:
        opts.cubic.layout = args.layout
    if args.no_flat_grid:
        opts.flat.full_grid = False
    validate_options(opts, source)
    with _staged_folder(args.out) as stage:  # nothing lands in --out unless the study succeeds
        if args.no_progress:
            summary = run_study(opts, stage, source=source, version=__version__)
        else:
            summary = _with_progress(opts, stage, source, __version__, run_study)
        summary["report"] = str(Path(args.out) / Path(summary["report"]).name)
    print(
        f"cdpr sensitivity: {len(summary['files'])} files in {args.out} "
        f"({summary['elapsed_s']:.1f} s); report: {summary['report']}"
    )
    return 0


@contextmanager
def _staged_folder(out: str) -> Iterator[Path]:
    """A temporary folder beside ``out``; on success its files move into ``out`` (created if
    needed; same-named files of an earlier run replaced), on any failure it is removed."""
    dest = Path(out)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".part", dir=dest.parent))
    except OSError as exc:
        raise ConfigError(str(dest), "", f"cannot write: {exc.strerror or exc}") from None
    try:
        yield stage
        dest.mkdir(exist_ok=True)
        for f in sorted(stage.iterdir()):
            os.replace(f, dest / f.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _with_progress(opts, out, source, version, run_study):  # type: ignore[no-untyped-def]
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        transient=False,
    ) as bar:

        def progress(label: str, total: int):  # type: ignore[no-untyped-def]
            task = bar.add_task(label, total=total)
            return lambda n: bar.advance(task, n)

        return run_study(opts, out, progress=progress, source=source, version=version)
