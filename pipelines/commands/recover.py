"""``cdpr recover RUN``: salvage a truncated run file into ``<run>.recovered.mcap``."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "recover",
        help="salvage a truncated run file (every complete chunk) into <run>.recovered.mcap",
    )
    p.add_argument("run", help="run file (.mcap), possibly truncated")
    p.add_argument("--out", help="output file (default: <run>.recovered.mcap; never overwritten)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cdpr.analysis.errors import ConfigError

    if Path(args.run).is_dir():
        raise ConfigError(args.run, "", "a folder, not a run file (.mcap)")
    from cdpr.daq.mcap_io import recover_run

    out, contents = recover_run(args.run, args.out)
    n = {t: len(m) for t, m in contents.messages.items()}
    state = "complete file" if contents.complete else "truncated file"
    print(f"recovered {sum(n.values())} messages from a {state} into {out}")
    print(f"  stopped at: {contents.error or 'end of file'}")
    for topic, count in n.items():
        print(f"  {topic:24s} {count:9d}")
    return 0
