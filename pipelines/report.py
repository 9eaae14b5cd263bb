"""Campaign outputs: the campaign table across runs, plots per sweep, HTML and Markdown reports.

Input: the per-point tables ``points.csv`` that ``cdpr analyze`` writes per run folder (one row per
test point, columns :data:`REQUIRED_COLUMNS`, plus ``true_*`` / ``err_*`` when a truth exists).

- :func:`read_points` checks a table (a missing column or a bad number: ``ConfigError`` naming the
  file, row and column);
- :func:`campaign_table` stacks the runs' tables (one row per test point, provenance columns
  ``points_file``, ``points_sha256``), matches them to the test matrix when given (a matrix point
  with no row is *missing*, said in the report and the exit code);
- :func:`write_campaign_table` writes ``campaign.csv`` and ``campaign.h5`` (h5py: one dataset per
  column, provenance as attributes);
- :func:`sweep_figures` draws CL-aoa, the drag polar CD-CL, Cm-aoa and CY/Cl/Cn-sideslip, one
  series per airspeed, error bars U95 (random + systematic; +-2 sigma where a run gives no
  U95), repeat points and flagged points with their own markers;
- :func:`tension_figure` draws tensions against time with per-cable labels spread so they stay
  readable when cables overlap, from a min/max envelope when the series is long;
- :func:`html_report` / :func:`markdown_report`: a self-contained HTML page (plots inline as
  ``data:`` URIs, tables, flags, provenance) and the Markdown page beside its PNG files.
"""

from __future__ import annotations

import base64
import html
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from cdpr.analysis.errors import ConfigError

from .config import atomic_output, file_sha256, read_table
from .plotting import png_figure

COEFFS = ("CD", "CY", "CL", "Cl", "Cm", "Cn")
WRENCH = ("fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")
POSE = ("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")
TEXT_COLUMNS = ("run", "point", "kind", "source", "flags")
TARGET_COLUMNS = ("target_aoa_deg", "target_sideslip_deg", "target_airspeed_mps")
OPTIONAL_COLUMNS = (*TARGET_COLUMNS, "repeat_of")
"""Only in tables whose points come from test-point events (``source == "events"``); absent for
detected points: filled with NaN / "" (the report says the points have no targets)."""
NUMBER_COLUMNS = (
    "start_ns",
    "stop_ns",
    "n_samples",
    "n_masked",
    *POSE,
    "airspeed_mps",
    "density_kgpm3",
    "q_Pa",
    "aoa_rad",
    "sideslip_rad",
    *WRENCH,
    *(f"sd_{c}" for c in WRENCH),
    *COEFFS,
    *(f"sd_{c}" for c in COEFFS),
    "check_max_abs_dT_N",
)
REQUIRED_COLUMNS = (*TEXT_COLUMNS, *NUMBER_COLUMNS)
"""The per-point columns agreed with ``cdpr analyze`` (``points.csv``)."""
WIND_ON = "wind_on"
SIGMA_BARS = 2.0  # error bars: +-2 sigma (about 95 %)


# --------------------------------------------------------------------------------------------
# the table
# --------------------------------------------------------------------------------------------
def read_points(path: str | os.PathLike[str]) -> pd.DataFrame:
    """A run's per-point table, checked.  Numbers may be empty (NaN: not computed, e.g. the
    coefficients of a wind-off point); text columns are strings (empty when absent)."""
    p = str(path)
    df = read_table(p, (), "per-point table")
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise ConfigError(p, f"column {missing[0]}", f"missing (have: {list(df.columns)})")
    for c in TARGET_COLUMNS:
        if c not in df.columns:
            df[c] = np.nan
    if "repeat_of" not in df.columns:
        df["repeat_of"] = ""
    numbers = (*NUMBER_COLUMNS, *TARGET_COLUMNS)
    for c in (*numbers, *(c for c in df.columns if c.startswith(("true_", "err_")))):
        num = pd.to_numeric(df[c], errors="coerce")
        bad = np.flatnonzero(df[c].notna().to_numpy() & num.isna().to_numpy())
        if bad.size:
            i = int(bad[0])
            raise ConfigError(
                p, f"row {i + 2}, column {c}", f"expected a number, got {df[c].iloc[i]!r}"
            )
        df[c] = num.astype(np.float64)
    for c in (*TEXT_COLUMNS, "repeat_of"):
        df[c] = df[c].astype(object).where(df[c].notna(), "").astype(str).str.strip()
    return df


@dataclass
class CampaignTable:
    """The stacked table (one row per test point) and what the matrix expected but did not get."""

    df: pd.DataFrame
    inputs: list[tuple[str, str]] = field(default_factory=list)  # (points file, sha256)
    missing_points: list[str] = field(default_factory=list)
    info_flags: frozenset[str] = frozenset()

    def warning_words(self) -> pd.Series:
        """Per point, its flag words that are warnings (all but ``info_flags``), ";"-joined."""
        return self.df["flags"].map(
            lambda f: ";".join(w for w in f.split(";") if w and w not in self.info_flags)
        )

    @property
    def flagged(self) -> pd.DataFrame:
        """The points with a warning flag (a point with only informational flags is not)."""
        return self.df[self.warning_words() != ""]


def campaign_table(
    paths: Sequence[str | os.PathLike[str]],
    matrix_labels: Sequence[str] | None = None,
    info_flags: frozenset[str] = frozenset(),
) -> CampaignTable:
    """Stack the per-point tables of ``paths`` (in that order); with ``matrix_labels`` (the test
    matrix's points) the table follows the matrix order and lists the points no run has."""
    if not paths:
        raise ConfigError("<campaign>", "points.csv", "no per-point tables given")
    frames, inputs = [], []
    for p in paths:
        df = read_points(p).copy()  # one block per dtype (the CSV had many columns)
        sha = file_sha256(p)
        frames.append(df.assign(points_file=str(p), points_sha256=sha))
        inputs.append((str(p), sha))
    df = pd.concat(frames, ignore_index=True)
    df = df.assign(
        aoa_deg=np.degrees(df["aoa_rad"].to_numpy()),
        sideslip_deg=np.degrees(df["sideslip_rad"].to_numpy()),
        is_repeat=df["repeat_of"] != "",
    )
    missing: list[str] = []
    if matrix_labels is not None:
        order = {lab: i for i, lab in enumerate(matrix_labels)}
        missing = [lab for lab in matrix_labels if lab not in set(df["point"])]
        df = df.assign(matrix_index=df["point"].map(order).astype("float64"))
        df = df.sort_values(["matrix_index", "start_ns"], kind="stable", na_position="last")
        df = df.reset_index(drop=True)
    return CampaignTable(df, inputs, missing, info_flags)


def write_campaign_table(
    table: CampaignTable,
    out_dir: str | os.PathLike[str],
    beside: Mapping[str, pd.DataFrame] | None = None,
) -> list[Path]:
    """``campaign.csv`` and ``campaign.h5`` in ``out_dir`` (atomic); ``beside``: more tables
    (e.g. ``{"dynamic": ...}``, :mod:`cdpr.pipelines.dynamic_report`) written as
    ``campaign_<name>.csv`` and the group ``<name>`` of ``campaign.h5``.  Returns the paths."""
    import h5py

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    csv = out / "campaign.csv"
    with atomic_output(csv) as fh:
        table.df.to_csv(fh, index=False)
    extra = []
    for name, t in (beside or {}).items():
        extra.append(out / f"campaign_{name}.csv")
        with atomic_output(extra[-1]) as fh:
            t.to_csv(fh, index=False)
    h5 = out / "campaign.h5"
    tmp = h5.with_name(f".{h5.name}.part")
    with h5py.File(tmp, "w") as f:
        for gname, t in {"points": table.df, **(beside or {})}.items():
            g = f.create_group(gname)
            for c in t.columns:
                col = t[c]
                if pd.api.types.is_bool_dtype(col) or pd.api.types.is_numeric_dtype(col):
                    g.create_dataset(c, data=col.to_numpy())
                else:  # text (object or pandas' string dtype): UTF-8 strings, NaN as ""
                    text = col.astype(object).where(col.notna(), "").astype(str)
                    g.create_dataset(c, data=text.to_numpy(dtype=object), dtype=h5py.string_dtype())
            g.attrs["columns"] = list(map(str, t.columns))
        f.attrs["inputs"] = [f"{p} sha256={s}" for p, s in table.inputs]
        f.attrs["missing_points"] = list(table.missing_points)
    os.replace(tmp, h5)
    return [csv, h5, *extra]


# --------------------------------------------------------------------------------------------
# plots
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Figure:
    """A written figure: file name (in the report folder), title, PNG bytes."""

    name: str
    title: str
    png: bytes

    def data_uri(self) -> str:
        return "data:image/png;base64," + base64.b64encode(self.png).decode("ascii")


def _figure(path: Path, title: str) -> Figure:
    return Figure(path.name, title, path.read_bytes())


def _bars(e: pd.DataFrame, c: str) -> np.ndarray:
    """The half-length of a point's bar on ``c``: its expanded uncertainty ``U95_<c>`` (random +
    systematic, coverage factor from the effective degrees of freedom) where the table has it,
    else ``SIGMA_BARS`` sigma."""
    two_sd = SIGMA_BARS * e[f"sd_{c}"].to_numpy(float)
    if f"U95_{c}" not in e:
        return two_sd
    u = pd.to_numeric(e[f"U95_{c}"], errors="coerce").to_numpy(float)
    return np.asarray(np.where(np.isfinite(u), u, two_sd))


def _bar_note(d: pd.DataFrame, cols: Sequence[str]) -> str:
    """What the bars of a plot of ``cols`` show (said on the plot)."""
    n = [
        pd.to_numeric(d[f"U95_{c}"], errors="coerce").notna().to_numpy()
        if f"U95_{c}" in d
        else np.zeros(len(d), bool)
        for c in cols
    ]
    if n and all(x.all() for x in n):
        return "bars: U95 (random + systematic, k from the effective dof)"
    if any(x.any() for x in n):
        return f"bars: U95 (random + systematic), +-{SIGMA_BARS:g} sigma where a point has none"
    return f"bars: +-{SIGMA_BARS:g} sigma (random + systematic; the runs give no U95)"


def _series(ax: Any, d: pd.DataFrame, x: str, y: str, label: str, color: Any) -> None:
    """Normal points (filled), repeats (open squares), flagged points (red x), U95 bars
    (:func:`_bars`)."""
    d = d.sort_values(x)
    sx = d.get(f"sd_{x}") if x in COEFFS else None
    normal = ~d["is_repeat"] & ~d["warned"]
    for sel, kw in (
        (normal, {"fmt": "o-", "label": label}),
        (d["is_repeat"], {"fmt": "s", "mfc": "none", "ms": 9, "label": f"{label} repeat"}),
        (d["warned"], {"fmt": "x", "ms": 10, "mew": 2, "ecolor": "red", "label": None}),
    ):
        if not sel.any():
            continue
        e = d[sel]
        xerr = None if sx is None else _bars(e, x)
        color_k = "red" if kw.get("fmt") == "x" else color
        ax.errorbar(
            e[x].to_numpy(), e[y].to_numpy(), yerr=_bars(e, y),
            xerr=xerr, color=color_k, capsize=3, **kw,
        )  # fmt: skip


def _groups(d: pd.DataFrame, keys: list[str]) -> list[tuple[tuple[Any, ...], pd.DataFrame]]:
    groups = d.groupby(keys, sort=True, dropna=False)
    return [((k,) if not isinstance(k, tuple) else k, g) for k, g in groups]


def sweep_figures(
    table: CampaignTable,
    out_dir: str | os.PathLike[str],
    reference: pd.DataFrame | None = None,
) -> list[Figure]:
    """The sweep plots of the wind-on points (PNG files in ``out_dir``); a plot whose sweep does
    not exist in the data (no sideslip sweep) is not drawn.  ``reference``
    (:func:`read_reference_polars`) is drawn beside the measured polars (black, one line per
    source and speed)."""
    import matplotlib

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    d = table.df.assign(warned=table.warning_words() != "")
    d = d[d["kind"] == WIND_ON]
    figs: list[Figure] = []
    if d.empty:
        return figs
    cmap = matplotlib.colormaps["viridis"]
    speeds = sorted(d["target_airspeed_mps"].dropna().unique())
    color = {v: cmap(0.1 + 0.8 * i / max(1, len(speeds) - 1)) for i, v in enumerate(speeds)}
    note = f"{_bar_note(d, [c for c in COEFFS if c in d])}; open squares: repeats; red x: flagged"
    alpha_sweeps = [
        (k, g) for k, g in _groups(d, ["target_sideslip_deg", "target_airspeed_mps"])
        if g["target_aoa_deg"].nunique() > 1
    ]  # fmt: skip
    if alpha_sweeps:
        for name, title, x, y, xl, yl in (
            ("cl_aoa.png", "Lift curve CL - aoa", "aoa_deg", "CL", "aoa (deg)", "CL"),
            ("drag_polar.png", "Drag polar CD - CL", "CL", "CD", "CL", "CD"),
            ("cm_aoa.png", "Pitching moment Cm - aoa", "aoa_deg", "Cm", "aoa (deg)", "Cm"),
        ):
            path = out / name
            with png_figure(path, size=(6.4, 4.6)) as (_, axes):
                ax = axes[0, 0]
                for (beta, v), g in alpha_sweeps:
                    lab = f"{v:g} m/s" + (f", sideslip {beta:g} deg" if beta != 0 else "")
                    _series(ax, g, x, y, lab, color.get(v, "0.4"))
                _reference_lines(ax, reference, x, y)
                ax.set_xlabel(xl)
                ax.set_ylabel(yl)
                ax.set_title(f"{title}\n({note})", fontsize=9)
                ax.grid(True, alpha=0.3)
                ax.legend(fontsize=8)
            figs.append(_figure(path, title))
    beta_sweeps = [
        (k, g) for k, g in _groups(d, ["target_aoa_deg", "target_airspeed_mps"])
        if g["target_sideslip_deg"].nunique() > 1
    ]  # fmt: skip
    if beta_sweeps:
        path = out / "lateral_sideslip.png"
        with png_figure(path, 3, 1, size=(6.4, 8.5), sharex=True) as (_, axes):
            for ax, y in zip(axes[:, 0], ("CY", "Cl", "Cn"), strict=True):
                for (a, v), g in beta_sweeps:
                    lab = f"{v:g} m/s, aoa {a:g} deg"
                    _series(ax, g, "sideslip_deg", y, lab, color.get(v, "0.4"))
                ax.set_ylabel(y)
                ax.grid(True, alpha=0.3)
            axes[0, 0].set_title(f"CY, Cl, Cn - sideslip\n({note})", fontsize=9)
            axes[0, 0].legend(fontsize=8)
            axes[-1, 0].set_xlabel("sideslip (deg)")
        figs.append(_figure(path, "Lateral coefficients CY, Cl, Cn - sideslip"))
    return figs


def _reference_lines(ax: Any, ref: pd.DataFrame | None, x: str, y: str) -> None:
    """Reference polars on an aoa or drag-polar plot (x ``aoa_deg`` or ``CL``)."""
    if ref is None or y not in ref.columns or x not in ref.columns:
        return
    styles = ("-", "--", ":", "-.")
    for k, ((src, v), g) in enumerate(ref.groupby(["source", "airspeed_mps"], dropna=False)):
        g = g.sort_values("aoa_deg")
        lab = f"reference {src}" + ("" if not np.isfinite(v) else f" {v:g} m/s")
        ax.plot(g[x].to_numpy(), g[y].to_numpy(), styles[k % 4], color="k", lw=1.2, label=lab)


def envelope(
    t: NDArray[np.float64], y: NDArray[np.float64], max_bins: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Min/max envelope of ``y`` (n, m) over ``max_bins`` bins of equal sample count
    (:func:`cdpr.pipelines.plotting.minmax_bins`, the one binning of the plots): the bins' mean
    times (b,), minima (b, m), maxima (b, m); NaN samples ignored (an all-NaN bin gives NaN).  With
    ``n <= max_bins`` the samples themselves (min = max = y)."""
    from .plotting import minmax_bins

    n = y.shape[0]
    if n <= max_bins:
        return t, y, y
    starts, lo, hi = minmax_bins(y, max_bins)
    counts = np.diff(np.append(starts, n))
    return np.add.reduceat(np.asarray(t, dtype=np.float64), starts) / counts, lo, hi


def spread_labels(y: NDArray[np.float64], min_gap: float) -> NDArray[np.float64]:
    """Label heights near ``y`` (m,) at least ``min_gap`` apart, order kept, mean shift zero
    (labels of overlapping cables fan out around their common value)."""
    y = np.asarray(y, dtype=np.float64)
    order = np.argsort(y, kind="stable")
    ys = y[order]
    # the lowest placement with gaps >= min_gap: a running maximum of y_k - k gap, plus k gap
    k = np.arange(ys.size) * min_gap
    placed = np.maximum.accumulate(ys - k) + k
    placed -= np.mean(placed - ys)  # centre the fan on the data
    out = np.empty_like(placed)
    out[order] = placed
    return out


def tension_figure(
    path: str | os.PathLike[str],
    t_ns: NDArray[np.int64],
    tensions_N: NDArray[np.float64],
    cable_names: Sequence[str],
    windows: Sequence[tuple[str, int, int]] = (),
    max_bins: int = 2000,
) -> Figure:
    """Tensions against time (s from the first sample), one colour per cable, a label per cable at
    the right end (spread to stay readable when cables overlap), test-point windows shaded;
    drawn as a min/max envelope when longer than ``max_bins`` samples."""
    t0 = int(t_ns[0])
    t = (np.asarray(t_ns, dtype=np.int64) - t0).astype(np.float64) * 1e-9
    T = np.asarray(tensions_N, dtype=np.float64)
    tc, lo, hi = envelope(t, T, max_bins)
    p = Path(path)
    long = T.shape[0] > max_bins
    with png_figure(p, size=(9.0, 4.8)) as (_, axes):
        ax = axes[0, 0]
        import matplotlib

        colors = matplotlib.colormaps["tab10"]
        for j in range(T.shape[1]):
            c = colors(j % 10)
            if long:
                ax.fill_between(tc, lo[:, j], hi[:, j], color=c, alpha=0.35, lw=0)
                ax.plot(tc, 0.5 * (lo[:, j] + hi[:, j]), color=c, lw=0.9)
            else:
                ax.plot(tc, lo[:, j], color=c, lw=0.8)
        for lab, a, b in windows:
            ax.axvspan((a - t0) * 1e-9, (b - t0) * 1e-9, color="0.88", zorder=0)
            ax.text((a - t0) * 1e-9, 1.0, lab, transform=ax.get_xaxis_transform(), rotation=90,
                    va="top", ha="left", fontsize=5, color="0.35")  # fmt: skip
        finite = np.isfinite(T)
        last = np.array([T[np.flatnonzero(finite[:, j])[-1], j] if finite[:, j].any() else np.nan
                         for j in range(T.shape[1])])  # fmt: skip
        ok = np.isfinite(last)
        y0, y1 = np.nanmin(lo), np.nanmax(hi)
        gap = 0.045 * max(y1 - y0, 1e-9)
        ys = np.full_like(last, np.nan)
        ys[ok] = spread_labels(last[ok], gap)
        x_end = t[-1]
        for j, name in enumerate(cable_names):
            if not ok[j]:
                continue
            ax.annotate(
                name, xy=(x_end, last[j]), xytext=(x_end + 0.02 * max(x_end, 1e-9), ys[j]),
                textcoords="data", va="center", fontsize=7, color=colors(j % 10),
                arrowprops={"arrowstyle": "-", "color": colors(j % 10), "lw": 0.6},
                annotation_clip=False,
            )  # fmt: skip
        ax.set_xlim(0, x_end * 1.22 if x_end > 0 else 1)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("tension (N)")
        how = f"min/max envelope of {T.shape[0]} samples" if long else f"{T.shape[0]} samples"
        ax.set_title(f"Cable tensions ({how}; shaded: test points)", fontsize=9)
        ax.grid(True, alpha=0.3)
    return _figure(p, "Cable tensions")


# --------------------------------------------------------------------------------------------
# the corrections (issue 13): windage tare and its fit, corrected beside uncorrected, q/Re/Mach,
# repeatability beside the propagated sigma
# --------------------------------------------------------------------------------------------
CORRECTION_COLUMNS = (
    "run", "point", "target_airspeed_mps", "aoa_deg", "density_kgpm3", "density_source",
    "relative_humidity", "q_Pa", "reynolds", "mach",
    "CL", "CL_corrected", "sd_CL", "sd_repeat_CL", "CD", "CD_corrected", "sd_CD", "sd_repeat_CD",
    "Cm", "Cm_corrected", "sd_Cm", "sd_repeat_Cm", "zero_drift_max_abs_N", "windage_source",
    "windage_fx_N",
)  # fmt: skip
"""The campaign table's correction view: one row per wind-on point (columns that exist)."""
_WINDAGE_SHOWN = (("fx_N", "Fx (N)"), ("fz_N", "Fz (N)"), ("my_Nm", "My (N m)"))


def _windage_points(df: pd.DataFrame) -> pd.DataFrame:
    if "windage_tare_fx_N" not in df.columns:
        return df.iloc[0:0]
    d = df[(df["kind"] == "windage") & np.isfinite(df["windage_tare_fx_N"].astype(float))]
    speed = d["target_airspeed_mps"].where(d["target_airspeed_mps"].notna(), d["airspeed_mps"])
    return d.assign(speed_mps=speed.round(2))


def windage_figure(table: CampaignTable, out_dir: str | os.PathLike[str]) -> Figure | None:
    """The measured windage tare (model-off wind-on points, markers), its fit per speed (line),
    the model beside it (dashed, when the matrix has a [tunnel]) and the fit residuals, against
    aoa; None without windage points."""
    import matplotlib

    d = _windage_points(table.df)
    if d.empty:
        return None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "windage_tare.png"
    speeds = sorted(d["speed_mps"].unique())
    cmap = matplotlib.colormaps["viridis"]
    with png_figure(path, 2, 3, size=(11.0, 6.4), sharex=True, height_ratios=[2, 1]) as (_, ax):
        for j, (c, label) in enumerate(_WINDAGE_SHOWN):
            for i, v in enumerate(speeds):
                g = d[d["speed_mps"] == v].sort_values("aoa_deg")
                col = cmap(0.1 + 0.8 * i / max(1, len(speeds) - 1))
                x = g["aoa_deg"].to_numpy(float)
                ax[0, j].errorbar(
                    x, g[c].to_numpy(float), yerr=SIGMA_BARS * g[f"sd_{c}"].to_numpy(float),
                    fmt="o", color=col, capsize=3, label=f"{v:g} m/s measured",
                )  # fmt: skip
                ax[0, j].plot(x, g[f"windage_tare_{c}"].to_numpy(float), "-", color=col,
                              label=f"{v:g} m/s fit")  # fmt: skip
                if np.isfinite(g[f"windage_model_{c}"].astype(float)).any():
                    ax[0, j].plot(x, g[f"windage_model_{c}"].to_numpy(float), "--", color=col,
                                  lw=0.9, label=f"{v:g} m/s model")  # fmt: skip
                res = (g[c] - g[f"windage_tare_{c}"]).to_numpy(float)
                ax[1, j].plot(x, res, "o-", color=col, ms=4)
            ax[0, j].set_title(f"windage tare {label}", fontsize=9)
            ax[1, j].axhline(0.0, color="0.5", lw=0.8)
            ax[1, j].set_xlabel("aoa (deg)")
            ax[1, j].set_ylabel(f"residual {label}")
            for a in ax[:, j]:
                a.grid(True, alpha=0.3)
        ax[0, 0].legend(fontsize=6, ncol=1)
    return _figure(path, "Windage tare (model-off points), its fit per speed and the residuals")


def windage_fit_table(df: pd.DataFrame) -> pd.DataFrame | None:
    """Per run and speed: the windage points, the largest tare and the RMS fit residual of
    Fx, Fz, My, and the model's Fx beside the measured one (mean over the points)."""
    d = _windage_points(df)
    if d.empty:
        return None
    rows = []
    for (run, v), g in d.groupby(["run", "speed_mps"], sort=True):
        row: dict[str, Any] = {"run": run, "speed_mps": v, "points": len(g)}
        row["max_abs_tare_fx_N"] = float(np.abs(g["windage_tare_fx_N"]).max())
        for c, _ in _WINDAGE_SHOWN:
            row[f"rms_residual_{c}"] = float(np.sqrt(np.mean((g[c] - g[f"windage_tare_{c}"]) ** 2)))
        row["mean_measured_fx_N"] = float(g["fx_N"].mean())
        row["mean_model_fx_N"] = float(g["windage_model_fx_N"].astype(float).mean())
        rows.append(row)
    return pd.DataFrame(rows)


def repeatability_table(df: pd.DataFrame) -> pd.DataFrame | None:
    """Per run: the measured repeatability σ of each coefficient beside the propagated σ (RMS over
    the repeat points) and their ratio; None when no run has repeat points."""
    rows = []
    for run, g in df[df["kind"] == WIND_ON].groupby("run", sort=False):
        for c in COEFFS:
            if f"sd_repeat_{c}" not in g.columns:
                continue
            rep = g[f"sd_repeat_{c}"].astype(float).dropna()
            if rep.empty:
                continue
            prop = float(g[f"sd_propagated_{c}"].astype(float).dropna().iloc[0])
            r = float(rep.iloc[0])
            rows.append(
                {"run": run, "coefficient": c, "sd_repeat": r, "sd_propagated": prop,
                 "ratio": r / prop if prop > 0 else float("nan")}
            )  # fmt: skip
    return pd.DataFrame(rows) if rows else None


def correction_sections(df: pd.DataFrame) -> list[tuple[str, pd.DataFrame]]:
    """The report's correction tables (only those the data has)."""
    out: list[tuple[str, pd.DataFrame]] = []
    on = df[df["kind"] == WIND_ON]
    if "corrections" in on.columns and len(on):
        cols = [c for c in CORRECTION_COLUMNS if c in on.columns]
        shown = on[cols].copy()
        if "windage_source" in shown:
            w = shown["windage_source"]
            shown["windage_source"] = w.astype(object).where(w.notna(), "").astype(str)
        out.append(
            ("Corrections per point: q, Re, Mach, corrected beside uncorrected, "
             "repeatability σ beside the propagated σ", shown)
        )  # fmt: skip
        text = on["corrections"].astype(object).where(on["corrections"].notna(), "none")
        out.append(
            ("Every correction applied per point, its size and its source",
             on[["run", "point"]].assign(corrections=text.astype(str)))
        )  # fmt: skip
    w = windage_fit_table(df)
    if w is not None:
        out.append(("Windage tare fit per speed (residuals of the model-off points)", w))
    r = repeatability_table(df)
    if r is not None:
        out.append(("Repeatability: measured σ beside the propagated σ", r))
    return out


def spectrum_figure(
    path: str | os.PathLike[str],
    freqs_Hz: NDArray[np.float64],
    psd: NDArray[np.float64],
    cable_names: Sequence[str],
    modes_Hz: NDArray[np.float64],
    title: str,
) -> Figure:
    """The power spectrum of every tension of one point (``psd`` (m, nf), N^2/Hz) with the rig's
    natural frequencies at the point's pose marked (dashed lines, labelled in Hz)."""
    import matplotlib

    p = Path(path)
    with png_figure(p, size=(9.0, 4.6)) as (_, axes):
        ax = axes[0, 0]
        colors = matplotlib.colormaps["tab10"]
        for j, name in enumerate(cable_names):
            ax.semilogy(freqs_Hz[1:], psd[j, 1:], lw=0.8, color=colors(j % 10), label=name)
        for k, f in enumerate(np.asarray(modes_Hz, dtype=np.float64)):
            if np.isfinite(f):
                ax.axvline(f, color="k", ls="--", lw=0.8)
                ax.text(f, 0.98 - 0.06 * (k % 2), f" mode {k + 1}: {f:.1f} Hz",
                        transform=ax.get_xaxis_transform(), fontsize=7, va="top")  # fmt: skip
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel("tension PSD (N²/Hz)")
        ax.set_title(title, fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=6, ncol=4, loc="lower left")
    return _figure(p, title)


SPECTRUM_FLAGS = ("too_few_periods", "spectrum_peak_near_mode", "no_modes")
"""The spectrum check's flags (:func:`cdpr.analysis.stages.spectrum_stage`), shown per panel."""
SPECTRA_PER_FIGURE = 24
"""Panels per small-multiples figure of the spectra (6 columns x 4 rows)."""


def decimate_spectrum(
    freqs_Hz: NDArray[np.float64], psd: NDArray[np.float64], max_bins: int = 64
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A Welch spectrum (``psd`` (m, nf)) reduced to at most ``max_bins`` bins for a small panel:
    the zero-frequency bin dropped, then the mean frequency and the mean PSD of blocks of
    ``ceil((nf - 1) / max_bins)`` adjacent bins (the power in a block is kept; a peak stays at
    its block).  Returns ``(f (k,), psd (m, k))``."""
    f = np.asarray(freqs_Hz, dtype=np.float64)[1:]
    P = np.asarray(psd, dtype=np.float64)[:, 1:]
    n = f.size
    if n <= max_bins:
        return f, P
    k = int(np.ceil(n / max_bins))
    starts = np.arange(0, n, k)
    counts = np.diff(np.append(starts, n))
    return np.add.reduceat(f, starts) / counts, np.add.reduceat(P, starts, axis=1) / counts


@dataclass(frozen=True)
class SpectraGrid:
    """The small-multiples figures of the tension spectra: ``figures`` (one PNG each) and
    ``panels`` (how many point panels each figure holds, one per point, in point order)."""

    figures: list[Figure]
    panels: list[int]


def spectra_grid_figures(
    out_dir: str | os.PathLike[str],
    labels: Sequence[str],
    flags: Sequence[str],
    freqs_Hz: Sequence[NDArray[np.float64]],
    psd: Sequence[NDArray[np.float64]],
    modes_Hz: NDArray[np.float64],
    cable_names: Sequence[str] = (),
    per_figure: int = SPECTRA_PER_FIGURE,
    stem: str = "spectra",
) -> SpectraGrid:
    """The tension spectra of every point, one small panel per point: every cable's PSD
    (decimated by :func:`decimate_spectrum`), the rig's modes at the point's pose as dashed
    vertical lines, the point's label and its spectrum flags (``flags``: the point's flag text;
    the words of :data:`SPECTRUM_FLAGS` are shown in red, else ``ok``) as the panel's title.

    All panels share their scales (frequency linear from 0 to the highest, PSD logarithmic over
    at most 8 decades, a faint line at every decade; the scales are written under each figure)
    and are drawn into one axes per figure as a few line collections, so 180 points take about
    a second.  At most ``per_figure`` panels a figure (6 columns): ``<stem>.png``, or
    ``<stem>_1.png``, ``<stem>_2.png``, ... when there are more points.  A point without a
    spectrum (too few samples, no mode) keeps its panel, which says so."""
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    s = len(labels)
    if not (len(flags) == len(freqs_Hz) == len(psd) == len(modes_Hz) == s):
        raise ConfigError("spectra", "", f"expected {s} points in every input")
    out = Path(out_dir)
    dec = [
        decimate_spectrum(freqs_Hz[i], psd[i]) if np.asarray(freqs_Hz[i]).size >= 3 else None
        for i in range(s)
    ]
    pos = [d[1][d[1] > 0] for d in dec if d is not None]
    allp = np.concatenate([p.ravel() for p in pos]) if pos else np.zeros(0)
    allp = allp[np.isfinite(allp)]
    y1 = float(np.ceil(np.log10(allp.max()))) if allp.size else 0.0
    # the lowest 1 % of the bins (near-empty ones) may fall below the panel: clipped at its floor
    y0 = max(float(np.floor(np.log10(np.percentile(allp, 1.0)))), y1 - 8.0) if allp.size else -1.0
    y0 = min(y0, y1 - 1.0)
    fmax = max((float(d[0][-1]) for d in dec if d is not None), default=1.0)
    colors = [f"C{j % 10}" for j in range(max((d[1].shape[0] for d in dec if d), default=0))]
    ncols = 6
    n_fig = int(np.ceil(s / per_figure))
    figs: list[Figure] = []
    panels: list[int] = []
    for c in range(n_fig):
        idx = list(range(c * per_figure, min(s, (c + 1) * per_figure)))
        nrows = int(np.ceil(len(idx) / ncols))
        name = f"{stem}.png" if n_fig == 1 else f"{stem}_{c + 1}.png"
        title = "Tension spectra per point (Welch PSD) with the rig's modes (dashed)"
        if n_fig > 1:
            title += f": points {idx[0] + 1}–{idx[-1] + 1} of {s}"
        size = (13.0, 1.45 * nrows + 1.1)
        with png_figure(out / name, size=size, dpi=72, tight=False) as (fig, axes):
            ax = axes[0, 0]
            ax.set_position((0.005, 0.27 / size[1], 0.99, 1 - 0.8 / size[1] - 0.27 / size[1]))
            ax.set_axis_off()
            ax.set_xlim(0.0, ncols)
            ax.set_ylim(0.0, nrows)
            w, h = 0.9, 0.72  # a panel in its (1 x 1) cell, room for the title above
            lines, lcol, modes, frames, grid = [], [], [], [], []
            drawn = 0
            for k, i in enumerate(idx):
                x0, b0 = (k % ncols) + 0.05, nrows - 1 - (k // ncols) + 0.06
                frames.append([(x0, b0), (x0 + w, b0), (x0 + w, b0 + h), (x0, b0 + h), (x0, b0)])
                words = [wd for wd in str(flags[i]).split(";") if wd in SPECTRUM_FLAGS]
                ax.text(x0 + w / 2, b0 + h + 0.03, f"{labels[i]}: {', '.join(words) or 'ok'}",
                        ha="center", va="bottom", fontsize=7,
                        color="tab:red" if words else "k")  # fmt: skip
                drawn += 1
                di = dec[i]
                if di is None:
                    ax.text(x0 + w / 2, b0 + h / 2, "no spectrum", ha="center", va="center",
                            fontsize=7, color="0.4")  # fmt: skip
                    continue
                f, P = di
                X = x0 + w * f / fmax
                with np.errstate(divide="ignore", invalid="ignore"):
                    Y = b0 + h * np.clip((np.log10(P) - y0) / (y1 - y0), 0.0, 1.0)
                for j in range(P.shape[0]):
                    ok = np.isfinite(Y[j])
                    lines.append(np.column_stack([X[ok], Y[j, ok]]))
                    lcol.append(colors[j])
                grid += [[(x0, b0 + h * (d - y0) / (y1 - y0)), (x0 + w, b0 + h * (d - y0) / (y1 - y0))]
                         for d in np.arange(y0 + 1, y1)]  # fmt: skip
                m = np.asarray(modes_Hz[i], dtype=np.float64)
                for fm in m[np.isfinite(m) & (m <= fmax)]:
                    xm = x0 + w * fm / fmax
                    modes.append([(xm, b0), (xm, b0 + h)])
            ax.add_collection(LineCollection(grid, colors="0.9", linewidths=0.4))
            ax.add_collection(LineCollection(lines, colors=lcol, linewidths=0.6))
            ax.add_collection(LineCollection(modes, colors="k", linewidths=0.7, linestyles="--"))
            ax.add_collection(LineCollection(frames, colors="0.5", linewidths=0.6))
            fig.suptitle(title, fontsize=9, y=1 - 0.08 / size[1], va="top")
            fig.text(0.5, 0.06 / size[1], f"every panel: frequency 0–{fmax:.4g} Hz (linear), "
                     f"PSD 1e{y0:.0f}–1e{y1:.0f} N²/Hz (log, a faint line per decade)",
                     ha="center", va="bottom", fontsize=7)  # fmt: skip
            if cable_names and colors:
                handles = [Line2D([], [], color=colors[j], lw=1.2) for j in range(len(colors))]
                fig.legend(handles, list(cable_names)[: len(colors)], loc="upper center",
                           bbox_to_anchor=(0.5, 1 - 0.32 / size[1]), ncol=len(colors),
                           fontsize=7, frameon=False)  # fmt: skip
        figs.append(_figure(out / name, title))
        panels.append(drawn)
    return SpectraGrid(figs, panels)


# --------------------------------------------------------------------------------------------
# reference polars (CFD or another facility) beside the measured ones
# --------------------------------------------------------------------------------------------
REFERENCE_COEFFS = ("CL", "CD", "Cm")


def read_reference_polars(path: str | os.PathLike[str]) -> pd.DataFrame:
    """A reference polar CSV: ``aoa_deg`` and at least one of ``CL, CD, Cm`` (finite numbers),
    optional ``airspeed_mps`` (one polar per speed; without it one polar for every speed) and
    ``source`` (a label, default the file name).  Errors name the file, the row and the column."""
    p = str(path)
    df = read_table(p, ("aoa_deg",), "reference polar")
    have = [c for c in REFERENCE_COEFFS if c in df.columns]
    if not have:
        raise ConfigError(p, "columns", f"expected at least one of {list(REFERENCE_COEFFS)}")
    for c in (*have, *(["airspeed_mps"] if "airspeed_mps" in df.columns else [])):
        num = pd.to_numeric(df[c], errors="coerce")
        bad = np.flatnonzero(~np.isfinite(num.to_numpy(dtype=np.float64)))
        if bad.size:
            i = int(bad[0])
            raise ConfigError(
                p, f"row {i + 2}, column {c}", f"expected a finite number, got {df[c].iloc[i]!r}"
            )
        df[c] = num.astype(np.float64)
    if "airspeed_mps" not in df.columns:
        df["airspeed_mps"] = np.nan
    src = df["source"].astype(str) if "source" in df.columns else Path(p).stem
    return df.assign(source=src)


def _reference_at(ref: pd.DataFrame, speed: float, aoa_deg: NDArray[np.float64], c: str) -> Any:
    """The reference coefficient ``c`` at ``aoa_deg``, linear in aoa within the polar of the
    speed (within 3 %) or the speed-free polar; NaN outside its aoa range or without a polar."""
    sp = ref["airspeed_mps"].to_numpy(dtype=np.float64)
    sel = np.isfinite(sp) & (np.abs(sp - speed) <= 0.03 * speed)
    if not sel.any():
        sel = ~np.isfinite(sp)
    r = ref[sel & ref[c].notna().to_numpy()].sort_values("aoa_deg") if c in ref else ref.iloc[0:0]
    if len(r) < 2:
        return np.full(np.shape(aoa_deg), np.nan)
    x, y = r["aoa_deg"].to_numpy(dtype=np.float64), r[c].to_numpy(dtype=np.float64)
    return np.interp(aoa_deg, x, y, left=np.nan, right=np.nan)


def reference_differences(df: pd.DataFrame, ref: pd.DataFrame) -> pd.DataFrame:
    """Per wind-on point: measured (wall-corrected where the table has it, else uncorrected),
    reference at the same aoa and speed, and their difference, for each reference coefficient."""
    on = df[df["kind"] == WIND_ON]
    rows = []
    for r in on.itertuples():
        speed = r.target_airspeed_mps if np.isfinite(r.target_airspeed_mps) else r.airspeed_mps
        row: dict[str, Any] = {"run": r.run, "point": r.point, "airspeed_mps": speed}
        corrected = "aoa_corrected_rad" in on.columns and np.isfinite(
            float(getattr(r, "aoa_corrected_rad", np.nan))
        )
        aoa = np.degrees(r.aoa_corrected_rad) if corrected else r.aoa_deg
        row["aoa_deg"] = aoa
        row["measured"] = "corrected" if corrected else "uncorrected"
        for c in REFERENCE_COEFFS:
            if c not in ref.columns:
                continue
            m = float(getattr(r, f"{c}_corrected")) if corrected else float(getattr(r, c))
            v = float(_reference_at(ref, float(speed), np.array(aoa), c))
            row.update({c: m, f"{c}_reference": v, f"d{c}": m - v})
        rows.append(row)
    return pd.DataFrame(rows)


# --------------------------------------------------------------------------------------------
# reports
# --------------------------------------------------------------------------------------------
SUMMARY_COLUMNS = (
    "run", "point", "kind", "target_aoa_deg", "target_airspeed_mps", "aoa_deg", "airspeed_mps",
    "q_Pa", "CL", "sd_CL", "CD", "sd_CD", "Cm", "sd_Cm", "n_masked", "repeat_of", "flags",
)  # fmt: skip


def truth_table(df: pd.DataFrame) -> pd.DataFrame | None:
    """Recovered minus true wrench per wind-on point (``err_*`` columns), or None without truth."""
    cols = [f"err_{c}" for c in WRENCH]
    if not all(c in df.columns for c in cols):
        return None
    d = df[df["kind"] == WIND_ON]
    out = d[["run", "point", *cols]].copy()
    out["max_abs_err_F_N"] = d[cols[:3]].abs().max(axis=1)
    out["max_abs_err_M_Nm"] = d[cols[3:]].abs().max(axis=1)
    return out.reset_index(drop=True)


def _fmt(v: Any) -> str:
    if isinstance(v, float | np.floating):
        if not np.isfinite(v):
            return ""
        return f"{v:.4g}"
    return str(v)


def _html_table(df: pd.DataFrame, flag_col: str | None) -> str:
    """An HTML table; rows with a non-empty ``flag_col`` are highlighted."""
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in df.columns)
    rows = []
    for _, r in df.iterrows():
        cls = ' class="flag"' if flag_col and flag_col in df.columns and r[flag_col] else ""
        cells = "".join(f"<td>{html.escape(_fmt(v))}</td>" for v in r.to_numpy())
        rows.append(f"<tr{cls}>{cells}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


def _md_table(df: pd.DataFrame) -> str:
    lines = ["| " + " | ".join(map(str, df.columns)) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(_fmt(v) for v in r) + " |" for r in df.to_numpy()]
    return "\n".join(lines)


_CSS = """body{font-family:sans-serif;margin:2em;max-width:1200px}
table{border-collapse:collapse;font-size:12px;margin:1em 0}td,th{border:1px solid #bbb;padding:2px 6px}
th{background:#eee}tr.flag td{background:#fdd}.warn{color:#a00;font-weight:bold}
img{max-width:100%;border:1px solid #ddd;margin:0.5em 0}"""


@dataclass(frozen=True)
class ReportContent:
    """What a report says: title, warnings (said first), the tables, figures, provenance."""

    title: str
    warnings: list[str]
    table: pd.DataFrame
    figures: list[Figure]
    provenance: Mapping[str, str]
    truth: pd.DataFrame | None = None
    sections: list[tuple[str, pd.DataFrame]] = field(default_factory=list)


def report_content(
    title: str,
    table: CampaignTable,
    figures: list[Figure],
    provenance: Mapping[str, str],
) -> ReportContent:
    df = table.df
    warnings = []
    if table.missing_points:
        warnings.append(
            f"{len(table.missing_points)} test point(s) of the matrix have no data: "
            + ", ".join(table.missing_points)
        )
    fl = table.flagged
    if len(fl):
        warnings.append(
            f"{len(fl)} point(s) flagged: "
            + "; ".join(
                f"{r.point} [{w}]"
                for r, w in zip(fl.itertuples(), table.warning_words()[fl.index], strict=True)
            )
        )
    detected = df[df["source"] != "events"]
    if len(detected):
        warnings.append(
            f"{len(detected)} point(s) found by steady-point detection, not by test-point "
            "events: no targets, no repeat links (" + ", ".join(map(str, detected["point"])) + ")"
        )
    masked = df[df["n_masked"] > 0]
    if len(masked):
        warnings.append(
            f"{len(masked)} point(s) with masked samples: "
            + ", ".join(f"{r.point} ({int(r.n_masked)})" for r in masked.itertuples())
        )
    cols = [c for c in SUMMARY_COLUMNS if c in df.columns]
    shown = df[cols].assign(warnings=table.warning_words())
    from .online_compare import online_section

    online = online_section(df)
    return ReportContent(
        title, warnings, shown, figures, dict(provenance), truth_table(df),
        correction_sections(df) + ([online] if online is not None else []),
    )  # fmt: skip


def html_report(rc: ReportContent) -> str:
    """A self-contained HTML page: warnings, figures inline (data URIs), tables, provenance."""
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(rc.title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(rc.title)}</h1>",
    ]
    if rc.warnings:
        parts.append("<h2>Flags</h2><ul>")
        parts += [f"<li class='warn'>{html.escape(w)}</li>" for w in rc.warnings]
        parts.append("</ul>")
    else:
        parts.append("<p>No flags: every point has data, none masked or flagged.</p>")
    parts.append("<h2>Plots</h2>")
    for f in rc.figures:
        parts.append(
            f"<figure><img alt='{html.escape(f.title)}' src='{f.data_uri()}'>"
            f"<figcaption>{html.escape(f.title)}</figcaption></figure>"
        )
    if rc.truth is not None:
        parts.append("<h2>Recovered minus true wrench (virtual rig truth)</h2>")
        parts.append(_html_table(rc.truth, None))
    for head, t in rc.sections:
        parts.append(f"<h2>{html.escape(head)}</h2>")
        parts.append(_html_table(t, None))
    parts.append("<h2>Test points</h2>")
    parts.append(_html_table(rc.table, "warnings"))
    parts.append("<h2>Provenance</h2><ul>")
    parts += [
        f"<li>{html.escape(k)}: <code>{html.escape(v)}</code></li>"
        for k, v in rc.provenance.items()
    ]
    parts.append("</ul></body></html>")
    return "\n".join(parts)


def markdown_report(rc: ReportContent) -> str:
    """The Markdown page (figures as links to the PNG files beside it)."""
    out = [f"# {rc.title}", ""]
    if rc.warnings:
        out += ["## Flags", ""] + [f"- **{w}**" for w in rc.warnings] + [""]
    else:
        out += ["No flags: every point has data, none masked or flagged.", ""]
    out += [f"![{f.title}]({f.name})" for f in rc.figures] + [""]
    if rc.truth is not None:
        out += ["## Recovered minus true wrench", "", _md_table(rc.truth), ""]
    for head, t in rc.sections:
        out += [f"## {head}", "", _md_table(t), ""]
    out += ["## Test points", "", _md_table(rc.table), "", "## Provenance", ""]
    out += [f"- {k}: `{v}`" for k, v in rc.provenance.items()]
    return "\n".join(out) + "\n"


def write_report(rc: ReportContent, out_dir: str | os.PathLike[str], stem: str) -> list[Path]:
    """``<stem>.html`` and ``<stem>.md`` in ``out_dir`` (atomic); returns their paths."""
    out = Path(out_dir)
    paths = [out / f"{stem}.html", out / f"{stem}.md"]
    for p, text in zip(paths, (html_report(rc), markdown_report(rc)), strict=True):
        with atomic_output(p) as fh:
            fh.write(text)
    return paths
