"""``cdpr recover RUN``: salvage a truncated or damaged run file into ``<run>.recovered.mcap``."""

from __future__ import annotations

import argparse
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "recover",
        help="salvage a truncated or damaged run file (every readable chunk) into "
        "<run>.recovered.mcap",
        description="Copy every readable chunk of a run file, before and after damage, into a new "
        "finished file. Exit codes: 0 salvaged (the file was only cut short, or complete); 3 "
        "salvaged, but damaged parts were skipped (listed on stderr); 2 nothing to salvage or "
        "bad input (no file written).",
    )
    p.add_argument("run", help="run file (.mcap), possibly truncated or damaged")
    p.add_argument("--out", help="output file (default: <run>.recovered.mcap; never overwritten)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cdpr.analysis.errors import ConfigError

    if Path(args.run).is_dir():
        raise ConfigError(args.run, "", "a folder, not a run file (.mcap)")
    from cdpr.daq.recover import recover_run

    out, contents = recover_run(args.run, args.out)
    n = {t: len(m) for t, m in contents.messages.items()}
    state = "complete file" if contents.complete else "truncated file"
    rec = contents.metadata["recovery"]
    skipped = json.loads(rec["skipped"])
    if skipped:
        state = "damaged " + state
    print(f"recovered {sum(n.values())} messages from a {state} into {out}")
    print(f"  stopped at: {rec['stopped_at']}")
    for topic, count in n.items():
        print(f"  {topic:24s} {count:9d}")
    if skipped:
        print(f"cdpr recover: {args.run}: {len(skipped)} damaged part(s) skipped:", file=sys.stderr)
        for line in skipped:
            print(f"  {line}", file=sys.stderr)
        return 3
    return 0
