"""The campaign's dynamic outputs (``cdpr campaign``): the table of the oscillation points' derivatives
beside the static table (``campaign_dynamic.csv``, group ``dynamic`` of ``campaign.h5``) and the
plots of each named derivative against the mean angle of attack, the reduced frequency and the
amplitude, with their 95 % intervals, repeats apart.  Input: the campaign table (the runs'
``points.csv`` stacked, :func:`cdpr.pipelines.report.campaign_table`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.motion import ANGULAR_AXES
from cdpr.analysis.oscillation import NAMED_DERIVATIVES

from .plotting import png_figure

DYNAMIC_COLUMNS: tuple[str, ...] = (
    "run", "point", "kind", "motion_axis", "amplitude_plan_deg_or_m", "amplitude_deg_or_m",
    "motion_frequency_Hz",
    "target_aoa_deg", "aoa_deg", "target_sideslip_deg", "airspeed_mps", "q_Pa",
    "reduced_frequency", "cycles_analysed", "window_s", "clock_offset_ms", "inertia_method",
    "repeat_of", "flags",
)  # fmt: skip
"""The identifying columns of the dynamic table; the named derivatives follow with ``sd_``,
``U95_``, ``dwell_s_`` and ``_model``."""


def _named() -> list[str]:
    return [n for v in NAMED_DERIVATIVES.values() for n, *_ in v]


def dynamic_table(df: pd.DataFrame) -> pd.DataFrame | None:
    """One row per wind-on oscillation point of the campaign table, the derivatives' columns that
    any row has; None when the campaign has none."""
    if "motion_axis" not in df.columns:
        return None
    d = df[df["kind"] == "oscillation"].copy()
    if d.empty:
        return None
    ang = d["motion_axis"].isin(ANGULAR_AXES).to_numpy()
    amp = pd.to_numeric(d["motion_amplitude"], errors="coerce").to_numpy()
    d["amplitude_deg_or_m"] = np.where(ang, np.degrees(amp), amp)
    plan = pd.to_numeric(d["motion_amplitude_plan"], errors="coerce").to_numpy()
    d["amplitude_plan_deg_or_m"] = np.where(ang, np.degrees(plan), plan)
    if "aoa_deg" not in d.columns:
        d["aoa_deg"] = np.degrees(d["aoa_rad"])
    cols = [c for c in DYNAMIC_COLUMNS if c in d.columns]
    for n in _named():
        if n in d.columns and d[n].notna().any():
            cols += [c for c in (n, f"sd_{n}", f"U95_{n}", f"dwell_s_{n}", f"{n}_model") if c in d]
    return d[cols].reset_index(drop=True)


X_AXES: tuple[tuple[str, str], ...] = (
    ("target_aoa_deg", "mean aoa (deg, planned)"),
    ("reduced_frequency", "reduced frequency k"),
    ("amplitude_plan_deg_or_m", "amplitude (deg or m, planned)"),
)


def dynamic_figures(table: pd.DataFrame | None, out_dir: str | os.PathLike[str]) -> list[Any]:
    """Per axis a figure ``dynamic_<axis>.png``: each named derivative (rows) against the mean
    aoa, k and the amplitude (columns), ±U95 bars, one colour per airspeed, repeats as open
    squares, the model's inertia removal as small grey crosses.  Returns
    :class:`cdpr.pipelines.report.Figure` objects."""
    from .report import Figure

    if table is None:
        return []
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = []
    for axis, named in NAMED_DERIVATIVES.items():
        d = table[table["motion_axis"] == axis]
        names = [n for n, *_ in named if n in d.columns and d[n].notna().any()]
        if d.empty or not names:
            continue
        speeds = sorted(d["airspeed_mps"].round(2).unique())
        path = out / f"dynamic_{axis}.png"
        rep = d["repeat_of"].fillna("").astype(str) != "" if "repeat_of" in d else False
        with png_figure(path, len(names), 3, (11.0, 2.6 * len(names) + 0.8)) as (fig, axes):
            for r, n in enumerate(names):
                for c, (x, xl) in enumerate(X_AXES):
                    ax = axes[r, c]
                    for k, v in enumerate(speeds):
                        sel = d["airspeed_mps"].round(2) == v
                        for sub, kw in ((sel & ~rep, {"fmt": "o"}),
                                        (sel & rep, {"fmt": "s", "mfc": "none", "ms": 8})):  # fmt: skip
                            e = d[sub]
                            if e.empty:
                                continue
                            first = (r, c) == (0, 0) and kw["fmt"] == "o"
                            ax.errorbar(
                                e[x], e[n], yerr=e.get(f"U95_{n}", 2 * e[f"sd_{n}"]), capsize=3,
                                color=f"C{k}", label=f"{v:g} m/s" if first else None, **kw,
                            )  # fmt: skip
                    if f"{n}_model" in d:
                        ax.plot(d[x], d[f"{n}_model"], "x", color="0.5", ms=5,
                                label="model inertia" if (r, c) == (0, 0) else None)  # fmt: skip
                    ax.grid(alpha=0.3)
                    ax.ticklabel_format(useOffset=False)
                    if c == 0:
                        ax.set_ylabel(n, fontsize=8)
                    if r == len(names) - 1:
                        ax.set_xlabel(xl)
            axes[0, 0].legend(fontsize=7)
            fig.suptitle(
                f"{axis} oscillations: derivatives ±U95 against the mean aoa, k and the amplitude "
                "(open squares: repeats; grey x: inertia by the rig file's mass)",
                fontsize=9,
            )
        figs.append(Figure(path.name, f"Dynamic derivatives, {axis}", path.read_bytes()))
    return figs


def dynamic_summary(table: pd.DataFrame | None) -> pd.DataFrame | None:
    """The report's table: per point its motion, k and each named derivative ± U95."""
    if table is None:
        return None
    rows = []
    for _, r in table.iterrows():
        row: dict[str, Any] = {
            "run": r["run"], "point": r["point"], "axis": r["motion_axis"],
            "A": r["amplitude_deg_or_m"], "f (Hz)": r.get("motion_frequency_Hz"),
            "V": r.get("airspeed_mps"), "k": r.get("reduced_frequency"),
        }  # fmt: skip
        for n, *_ in NAMED_DERIVATIVES.get(str(r["motion_axis"]), ()):
            if n in r and np.isfinite(r[n]):
                u = r.get(f"U95_{n}", np.nan)
                row[n] = f"{r[n]:.4g} ± {u:.2g}"
        row["flags"] = r.get("flags", "")
        rows.append(row)
    return pd.DataFrame(rows)
