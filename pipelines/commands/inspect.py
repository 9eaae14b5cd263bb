"""``cdpr inspect RUN``: streams, counts, rates, gaps, drops, duration and metadata of a run file.

Exit codes (as ``cdpr export``): 0 the file is whole; 3 it is cut short or damaged (the first line
says ``TRUNCATED (...)`` or ``DAMAGED (...)``, and the summary is of what the recovery path reads);
2 bad input or nothing readable (one line on stderr).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

EXIT_DAMAGED = 3
"""The file is cut short or damaged: the code ``cdpr export`` and ``cdpr recover`` give too."""


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "inspect",
        help="summarise a run file (streams, counts, rates, gaps, drops)",
        description="Summarise a run file. Exit codes: 0 the file is whole; 3 it is cut short or "
        "damaged (said in the first line; the summary is of what recovery reads); 2 bad input.",
    )
    p.add_argument("run", help="run file (.mcap)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def inspect_run(path: str, recover: bool = False) -> dict[str, Any]:
    """The summary ``cdpr inspect`` prints, as a dict (``recover``: read through the recovery
    path, for a file with a damaged chunk inside)."""
    from cdpr.daq.run_reader import open_run, summarize

    with open_run(path, recover=recover) as rc:
        streams = summarize(rc)
        rc.verify()  # every chunk, also those of streams whose values the summary does not read
        metadata = rc.metadata
        attachments = {
            k: {"media_type": v[0], "bytes": len(v[1])} for k, v in rc.attachments.items()
        }
        drops: dict[str, dict[str, int]] = {}
        if "/recorder" in rc.streams and rc.streams["/recorder"].count:
            stats = rc.table("/recorder")
            last_stats = stats.iloc[-1]
            for k, v in last_stats.items():
                if k in ("t_ns", "status") or "_" not in str(k) or v != v:
                    continue
                src, _, what = str(k).rpartition("_")
                drops.setdefault(src, {})[what] = int(v)
        elif "source_stats" in metadata.get("run_end", {}):  # `cdpr import`: the log's counters
            stats = json.loads(metadata["run_end"]["source_stats"])
            drops["can_log"] = {k: int(v) for k, v in stats.items() if isinstance(v, int)}
        recovered, warning = rc.recovered, rc.warning
    first = [s.first_ns for s in streams if s.first_ns is not None]
    last = [s.last_ns for s in streams if s.last_ns is not None]
    run_md = metadata.get("run", {})
    end_md = metadata.get("run_end", {})
    return {
        "file": str(path),
        "complete": not recovered,
        "read_error": warning,
        "duration_s": (max(last) - min(first)) / 1e9 if first else 0.0,
        "streams": [
            {
                "topic": s.topic,
                "schema": s.schema,
                "count": s.count,
                "rate_hz": round(float(s.rate_hz), 3),
                "nominal_rate_hz": s.nominal_rate_hz,
                "gaps": s.gaps,
                "max_gap_s": round(s.max_gap_s, 6),
                "bad_status": s.bad_status,
            }
            for s in streams
        ],
        "sources": drops,
        "metadata": {
            k: v
            for k, v in run_md.items()
            if k not in ("config",)  # the full snapshot is long: see `--json` of the record
        },
        "run_end": {
            k: v
            for k, v in end_md.items()
            if k in ("stop_time_utc", "duration_s", "stop_reason", "dropped_total")
        },
        "other_metadata": sorted(k for k in metadata if k not in ("run", "run_end")),
        "attachments": attachments,
    }


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cdpr.analysis.errors import CdprError, ConfigError, InputError

    if Path(args.run).is_dir():
        raise ConfigError(args.run, "", "a folder, not a run file (.mcap)")
    from cdpr.daq.run_reader import DamagedRunError

    try:
        try:
            info = inspect_run(args.run)
        except DamagedRunError:  # a damaged part inside: summarise what recovery salvages
            info = inspect_run(args.run, recover=True)
    except CdprError:
        raise
    except Exception as exc:  # a reader failing on damage: one line, never a traceback
        raise InputError(
            f"{args.run}: damaged run file ({type(exc).__name__}: {exc}); "
            "`cdpr recover` salvages every readable chunk"
        ) from None
    damage = _damage_line(args.run, info["complete"])
    whole = info["complete"] and not damage
    if args.json:
        info["damage"] = damage
        print(json.dumps(info, indent=2))
        return 0 if whole else EXIT_DAMAGED
    md = info["metadata"]
    state = "complete" if info["complete"] else f"TRUNCATED ({info['read_error'] or 'no footer'})"
    if damage:
        state = damage
    print(f"run {info['file']}: {state}, {info['duration_s']:.3f} s of data")
    for k in ("label", "rig", "rig_sha256", "software_version", "host", "start_time_utc",
              "operator", "notes", "calibration_ids", "command"):  # fmt: skip
        if md.get(k):
            print(f"  {k:17s} {md[k]}")
    for k, v in info["run_end"].items():
        print(f"  {k:17s} {v}")
    if info["attachments"]:
        att = ", ".join(f"{k} ({v['bytes']} B)" for k, v in info["attachments"].items())
        print(f"  attachments       {att}")
    if info["other_metadata"]:
        print(f"  other metadata    {', '.join(info['other_metadata'])}")
    print()
    print(
        f"  {'topic':24s} {'schema':26s} {'messages':>9s} {'rate/s':>9s} {'nominal':>8s} "
        f"{'gaps':>5s} {'max gap s':>9s} {'bad':>6s}"
    )
    for s in info["streams"]:
        print(
            f"  {s['topic']:24s} {s['schema']:26s} {s['count']:9d} {s['rate_hz']:9.1f} "
            f"{s['nominal_rate_hz']:8.1f} {s['gaps']:5d} {s['max_gap_s']:9.3f} {s['bad_status']:6d}"
        )
    if info["sources"]:
        print()
        print(
            f"  {'source':16s} {'read':>9s} {'dropped':>8s} {'lost':>6s} {'bad':>6s} {'errors':>6s}"
        )
        for name, c in info["sources"].items():
            print(
                f"  {name:16s} {c.get('read', 0):9d} {c.get('dropped', 0):8d} "
                f"{c.get('lost', 0):6d} {c.get('bad', 0):6d} {c.get('errors', 0):6d}"
            )
    return 0 if whole else EXIT_DAMAGED


def _damage_line(path: str, read_whole: bool) -> str:
    """``DAMAGED (...)`` when parts inside the file are unreadable (not only its end cut off):
    :func:`cdpr.daq.recover.check_mcap`, the check ``cdpr recover`` makes.  ``read_whole``: the
    summary's chunks all read (the damage is in a part the summary holds again)."""
    from cdpr.daq.recover import check_mcap

    scan = check_mcap(path)
    if not scan.skipped:
        return ""
    counts = (
        "every chunk the summary lists reads: the counts below are whole"
        if read_whole
        else "the counts below are of what recovery reads: every readable chunk before and "
        "after the damage"
    )
    return f"DAMAGED ({len(scan.skipped)} unreadable part(s), first {scan.skipped[0]}; {counts})"
