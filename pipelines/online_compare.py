"""On-line against final values: the ``online_result`` events a recording kept (the on-line
reduction of each test point when it ended, :mod:`cdpr.pipelines.online`) beside ``cdpr
analyze``'s final values of the same points.

:func:`compare_online` adds per point ``online_<value>``, ``online_minus_final_<value>`` (for the
wrench and the coefficients), ``online_flags`` and ``online_agrees`` (``yes``, ``no``, empty
without an on-line result and for the wind-off points, whose wrench is a residual against the
weight model that later wind-off points refine) to the per-point table, and returns one line
per point plus a summary.  The two should agree to the σ of the point's steady window (the final
``sd_<value>``); where they do not, the line says so and names what the live session could not
know (a closing zero, later tares, dropped live batches, corrections the
on-line reduction did not run).  :func:`online_section` is the report's table of them.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.conventions import COEFFICIENTS, WIND_OFF_KINDS, WRENCH_COLUMNS

COMPARED: tuple[str, ...] = (*WRENCH_COLUMNS, *COEFFICIENTS)
"""The values compared (names of ``points.csv``)."""
K_SIGMA = 1.0
"""On-line and final agree when every compared difference is within this many final σ."""
EVENT_NAME = "online_result"

_REASONS = {
    "no_closing_zero": "the zero drift was held from the last zero on-line (no closing zero yet)",
    "live_dropped_batches": "the live path dropped batches (a busy machine): samples missing",
    "online_samples_capped": "the session's samples were capped on-line",
    "no_pose_stream": "no camera on-line: reduced at the rig's reference pose",
}


def online_results(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """The ``online_result`` events of a run (``/events`` or ``/event``), in time order."""
    from cdpr.daq.run_reader import open_run

    out: list[dict[str, Any]] = []
    with open_run(path) as run:
        for topic in ("/events", "/event"):
            info = run.streams.get(topic)
            if info is None or not info.count or "name" not in info.fields:
                continue
            df = run.table(topic)
            rows = df[df["name"] == EVENT_NAME]
            for rec in rows.to_dict("records"):
                out.append({k: v for k, v in rec.items() if v is not None and v == v})
    return sorted(out, key=lambda r: int(r.get("t_ns", 0)))


def _match(res: list[dict[str, Any]], label: str, start_ns: float) -> dict[str, Any] | None:
    mine = [r for r in res if str(r.get("point", "")) == label]
    if not mine:
        return None
    if len(mine) == 1 or not math.isfinite(start_ns):
        return mine[-1]
    return min(mine, key=lambda r: abs(float(r.get("start_ns", 0)) - start_ns))


def compare_online(
    path: str | os.PathLike[str], df: pd.DataFrame
) -> tuple[pd.DataFrame, list[str]]:
    """``df`` (the per-point table of ``cdpr analyze``) with the on-line columns added, and the
    lines that say, per point, on-line minus final against σ.  A run without ``online_result``
    events gives ``df`` unchanged and no line."""
    res = online_results(path)
    if not res:
        return df, []
    df = df.copy()
    n = len(df)
    on = {c: np.full(n, np.nan) for c in COMPARED}
    flags = [""] * n
    agrees: list[Any] = [""] * n
    lines: list[str] = []
    bad: list[str] = []
    corrected_final = "corrections" in df.columns
    for i, row in enumerate(df.itertuples(index=False)):
        r = _match(res, str(row.point), float(getattr(row, "start_ns", math.nan)))
        if r is None:
            continue
        worst = 0.0
        parts = []
        for c in COMPARED:
            v = r.get(c)
            on[c][i] = float(v) if isinstance(v, int | float) else math.nan
            final, sd = float(getattr(row, c)), float(getattr(row, f"sd_{c}"))
            d = on[c][i] - final
            if math.isfinite(d) and math.isfinite(sd) and sd > 0:
                worst = max(worst, abs(d) / sd)
        for c in ("CL", "CD", "Cm", "fx_N", "fz_N"):
            d = on[c][i] - float(getattr(row, c))
            if math.isfinite(d):
                sd = float(getattr(row, f"sd_{c}"))
                parts.append(f"d{c} {d:+.2g} (σ {sd:.2g})")
        flags[i] = str(r.get("flags", ""))
        comparable = any(math.isfinite(on[c][i]) and math.isfinite(float(getattr(row, c)))
                         for c in COMPARED)  # fmt: skip
        if not comparable:
            agrees[i] = ""
            lines.append(f"{row.point}: on-line result without values to compare ({flags[i]})")
            continue
        if str(row.kind) in WIND_OFF_KINDS:
            # a wind-off point's wrench is its residual against the weight model, which every
            # later wind-off point refines: shown, not judged
            lines.append(
                f"{row.point}: on-line - final {', '.join(parts)} (wind-off: its residual "
                "against the weight model, which later wind-off points refine; not judged)"
            )
            continue
        ok = worst <= K_SIGMA
        agrees[i] = "yes" if ok else "no"
        verdict = "agree" if ok else f"DIFFER by up to {worst:.1f} σ"
        why = ""
        if not ok:
            words = [w for w in flags[i].split(";") if w in _REASONS]
            reasons = [_REASONS[w] for w in words]
            online_corr = str(r.get("corrections", ""))
            if corrected_final and online_corr.startswith("none"):
                reasons.append(
                    "the final values carry corrections the on-line reduction did not run"
                )
            if not reasons:
                reasons.append("later wind-off points changed the weight model or the tares")
            why = ": " + "; ".join(reasons)
            bad.append(str(row.point))
        lines.append(f"{row.point}: on-line - final {', '.join(parts)} -> {verdict}{why}")
    for c in COMPARED:
        df[f"online_{c}"] = on[c]
        df[f"online_minus_final_{c}"] = on[c] - df[c].to_numpy(np.float64)
    df["online_flags"] = flags
    df["online_agrees"] = agrees
    n_cmp = sum(1 for a in agrees if a != "")
    head = (
        f"on-line against final: {n_cmp - len(bad)} of {n_cmp} point(s) agree within "
        f"{K_SIGMA:g} σ (wind-off points shown, not judged)"
        + (f"; differ: {', '.join(bad)}" if bad else "")
    )
    return df, [head, *lines]


def online_section(df: pd.DataFrame) -> tuple[str, pd.DataFrame] | None:
    """The report's table: per wind-on point with an on-line result, the final and on-line value
    of CL, CD, Cm, their difference and σ, the largest difference in σ over the wrench and the
    coefficients, and whether they agree; None without any."""
    if "online_agrees" not in df.columns:
        return None
    d = df[df["online_agrees"].isin(("yes", "no"))]
    if d.empty:
        return None
    cols: dict[str, Any] = {"run": d["run"], "point": d["point"]}
    for c in ("CL", "CD", "Cm"):
        cols[f"{c} final"] = d[c]
        cols[f"{c} on-line"] = d[f"online_{c}"]
        cols[f"Δ{c}"] = d[f"online_minus_final_{c}"]
        cols[f"σ {c}"] = d[f"sd_{c}"]
    ratio = np.column_stack(
        [np.abs(d[f"online_minus_final_{c}"].to_numpy(np.float64)) / d[f"sd_{c}"].to_numpy(np.float64)
         for c in COMPARED]
    )  # fmt: skip
    ratio[~np.isfinite(ratio)] = np.nan
    cols["max |Δ|/σ (wrench, coefficients)"] = (
        np.nanmax(np.where(np.isnan(ratio), -np.inf, ratio), axis=1) if ratio.size else np.zeros(0)
    )
    cols["agree (1σ)"] = d["online_agrees"]
    cols["on-line flags"] = d["online_flags"].fillna("")
    return "On-line against final values", pd.DataFrame(cols).reset_index(drop=True)
