"""``cdpr export RUN --hdf5 OUT``: a run's streams as HDF5 tables, metadata as attributes.

Exit codes: 0 the whole run exported; 2 bad input (one line, nothing written); 3 the run is cut off
or damaged: what could be read is exported and kept, and one line on stderr says what was lost.
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "export",
        help="export a run file to HDF5 (one table per stream)",
        description="Export a run file to HDF5. Exit codes: 0 the whole run exported; 3 the run is "
        "cut off or damaged (what reads is exported, one line on stderr says what was lost); 2 "
        "bad input (one line, nothing written).",
    )
    p.add_argument("run", help="run file (.mcap)")
    p.add_argument("--hdf5", required=True, help="output HDF5 file (never overwritten)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cdpr.analysis.errors import ConfigError

    if Path(args.run).is_dir():
        raise ConfigError(args.run, "", "a folder, not a run file (.mcap)")
    import sys

    from cdpr.daq.hdf5_io import export_hdf5

    res = export_hdf5(args.run, args.hdf5)
    print(f"wrote {args.hdf5}: " + ", ".join(f"{k} {v} rows" for k, v in res.counts.items()))
    if res.partial is not None:
        print(f"cdpr export: PARTIAL export: {res.partial}", file=sys.stderr)
        return 3
    return 0
