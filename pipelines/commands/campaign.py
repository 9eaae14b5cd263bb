"""``cdpr campaign``: the campaign outputs from the per-point tables of ``cdpr analyze``.

``cdpr campaign ANALYSIS_DIR... --out DIR [--matrix campaign.toml] [--runs RUNS_DIR]`` finds every
``points.csv`` under the analysis folders and writes into ``DIR``: ``campaign.csv`` and
``campaign.h5`` (one row per test point), the sweep plots, ``campaign.html`` (self-contained) and
``campaign.md``, and per run ``run_<run>.html`` / ``.md`` (its points, plots and, with ``--runs``,
its cable tensions from the run file).  Exit code 0 when every matrix point has data and no point is
flagged or masked; 1 when the reports carry flags (each said in the report and on one line here);
2 on bad input.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "campaign",
        help="campaign table, sweep plots and HTML/Markdown reports from analyze's points.csv",
    )
    p.add_argument(
        "analysis", nargs="+", help="analysis folders (cdpr analyze --out) or points.csv"
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--matrix", help="test matrix (TOML): point order and missing points")
    p.add_argument("--runs", help="folder of the run files (.mcap): tension plots per run")
    p.add_argument(
        "--reference",
        help="reference polars (CSV: aoa_deg, CL/CD/Cm, optional airspeed_mps and source) drawn "
        "beside the measured ones, with a difference table",
    )
    p.set_defaults(func=run)


def _points_files(args: argparse.Namespace) -> list[Path]:
    from cdpr.analysis.errors import ConfigError

    files: list[Path] = []
    for a in args.analysis:
        p = Path(a)
        if p.is_file():
            files.append(p)
        elif p.is_dir():
            files += sorted(p.rglob("points.csv"))
        else:
            raise ConfigError(a, "", "not found (an analysis folder or a points.csv)")
    if not files:
        raise ConfigError(
            ", ".join(args.analysis), "points.csv", "no per-point table found (run cdpr analyze)"
        )
    return files


def _run_tensions(path: Path) -> tuple[Any, Any, list[str]] | None:
    """(t_ns, tensions (n, m), cable names) of a run file's ``/tensions`` stream, or None."""
    import numpy as np

    from cdpr.daq.run_reader import open_run

    with open_run(path) as run:
        info = run.streams.get("/tensions")
        if info is None or not info.count:
            return None
        cols = [k for k in info.fields if k.startswith("T_") and k.endswith("_N")]
        df = run.table("/tensions", columns=cols)
    names = [k[2:-2] for k in cols]
    return df["t_ns"].to_numpy(np.int64), df[cols].to_numpy(np.float64), names


def dynamic_campaign(table: Any) -> Any:
    """The campaign's dynamic table (the oscillation points' derivatives), or None."""
    from ..dynamic_report import dynamic_table

    return dynamic_table(table.df)


def copied_hysteresis(d: Any, dst_dir: Path) -> list[Any]:
    """The hysteresis figures ``cdpr analyze`` drew for a run, copied beside the run's report."""
    import shutil

    from ..report import Figure

    figs = []
    for pf in sorted(set(d["points_file"])):
        for src in sorted(Path(pf).parent.glob("hysteresis*.png")):
            dst_dir.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst_dir / src.name)
            figs.append(Figure(src.name, "Hysteresis loops (each cycle faint, the cycle average "
                               "bold, the harmonic fit dashed)", src.read_bytes()))  # fmt: skip
    return figs


def run(args: argparse.Namespace) -> int:
    import shutil
    import time

    import numpy as np

    from .. import __version__
    from ..config import file_sha256
    from ..dynamic_report import dynamic_figures, dynamic_summary
    from ..report import (
        CampaignTable,
        Figure,
        campaign_table,
        report_content,
        sweep_figures,
        tension_figure,
        windage_figure,
        write_campaign_table,
        write_report,
    )

    files = _points_files(args)
    ref = None
    if args.reference:
        from ..report import read_reference_polars

        ref = read_reference_polars(args.reference)
    labels = None
    title = "Campaign"
    prov: dict[str, str] = {"software": f"cdpr {__version__}"}
    if args.matrix:
        from ..campaign import load_test_matrix

        m = load_test_matrix(args.matrix)
        labels = [p.label for p in m.points]
        title = f"Campaign {m.name} (model {m.model.name})"
        prov["test matrix"] = f"{args.matrix} sha256={file_sha256(args.matrix)}"
    from .. import analyze as analyze_module

    # flag words that describe what was done, not a problem: defined once, by the analysis
    info = frozenset(getattr(analyze_module, "INFO_FLAGS", frozenset()))
    table = campaign_table(files, labels, info)
    for p, sha in table.inputs:
        prov[f"points {p}"] = f"sha256={sha}"
    if args.reference:
        prov["reference polars"] = f"{args.reference} sha256={file_sha256(args.reference)}"
    prov["written"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    out = Path(args.out)
    dyn = dynamic_campaign(table)
    written = write_campaign_table(table, out, None if dyn is None else {"dynamic": dyn})
    figs = sweep_figures(table, out / "plots", ref)
    wfig = windage_figure(table, out / "plots")
    if wfig is not None:
        figs.append(wfig)
    figs += dynamic_figures(dyn, out / "plots")
    rc = report_content(title, table, figs, prov)
    if dyn is not None:
        rc.sections.insert(0, ("Dynamic derivatives (± U95)", dynamic_summary(dyn)))
    if ref is not None:
        from ..report import reference_differences

        rc.sections.append(
            ("Measured minus reference polars (wall-corrected where available)",
             reference_differences(table.df, ref))
        )  # fmt: skip
    written += write_report(rc, out, "campaign")
    # per run
    runs_dir = Path(args.runs) if args.runs else None
    for run_name, d in table.df.groupby("run", sort=False):
        stem = Path(str(run_name)).stem
        sub = CampaignTable(
            d.reset_index(drop=True),
            [i for i in table.inputs if i[0] in set(d["points_file"])],
            info_flags=info,
        )
        rfigs = sweep_figures(sub, out / "plots" / stem)
        if runs_dir is not None and (runs_dir / f"{stem}.mcap").is_file():
            tens = _run_tensions(runs_dir / f"{stem}.mcap")
            if tens is not None:
                windows = [
                    (str(r.point), int(r.start_ns), int(r.stop_ns))
                    for r in d.itertuples()
                    if np.isfinite(r.start_ns) and np.isfinite(r.stop_ns)
                ]
                rfigs.append(
                    tension_figure(out / "plots" / stem / "tensions.png", *tens, windows=windows)
                )
        rfigs += copied_hysteresis(d, out / "plots" / stem)
        # the tension spectra with the rig's modes (cdpr analyze --matrix drew them per run):
        # the fastest point's, then every point's (small multiples, one panel per point)
        for pf in sorted(set(d["points_file"])):
            src = Path(pf).parent
            grids = sorted(src.glob("spectra*.png"), key=lambda q: (len(q.stem), q.stem))
            specs = [src / "spectrum.png", *grids]
            for spec in specs:
                if not spec.is_file():
                    continue
                dst = out / "plots" / stem / spec.name
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(spec, dst)
                what = (
                    "Tension spectra with the rig's modes"
                    if spec.name == "spectrum.png"
                    else "Tension spectra of every point (label and spectrum flags per panel, "
                    "the rig's modes dashed)" + (f" — {spec.stem}" if "_" in spec.stem else "")
                )
                rfigs.append(Figure(dst.name, what, dst.read_bytes()))
        rprov = {**prov, "run": str(run_name)}
        written += write_report(
            report_content(f"Run {run_name}", sub, rfigs, rprov), out, f"run_{stem}"
        )
    print(
        f"campaign table: {written[0]} ({len(table.df)} points from {len(files)} run(s)), {written[1]}"
    )
    if rc.truth is not None and len(rc.truth):
        t = rc.truth
        print("recovered - true wrench, wind-on points (N, N m):")
        print(t.to_string(index=False, float_format=lambda v: f"{v:+.4f}"))
    print(f"campaign report: {out / 'campaign.html'}")
    for w in rc.warnings:
        print(f"cdpr campaign: {w}")
    return 1 if rc.warnings else 0
