"""The force-sensitivity study's figures (``fig06..fig15_*.png`` in the paper's style,
``singular_*.png``, ``stiffness_*.png``) from the study's data frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis import sensitivity as sens

from .plotting import png_figure as _figure
from .sensitivity_options import StudyOptions

# ------------------------------------------------------------------------------------ plots


_MARKERS = "os^vD<>ph*"


def _plot_lines(ax: Any, x: Sequence[float], series: dict[str, np.ndarray], **kw: Any) -> None:
    for i, (label, y) in enumerate(series.items()):
        ax.plot(x, y, marker=_MARKERS[i % len(_MARKERS)], ms=4, lw=1.2, label=label, **kw)


def _by_force(piv: pd.DataFrame) -> dict[str, np.ndarray]:
    """The columns of a pivot table whose columns are forces (N), labelled ``"<F> N"``."""
    return {f"{F:g} N": piv[F].values for F in piv.columns}


def _force_lines_figure(path: Path, piv: pd.DataFrame, xlabel: str, title: str) -> None:
    """One panel: S (N) against the pivot's index, one line per force column."""
    with _figure(path) as (fig, axes):
        ax = axes[0, 0]
        _plot_lines(ax, piv.index, _by_force(piv))
        ax.set_xlabel(xlabel)
        ax.set_ylabel("S (N)")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)


def plot_cubic(cub: dict, out: Path, o: StudyOptions) -> list[str]:
    """Figs. 6-11 for every cubic method; returns the file names."""
    files = []
    grid, Zdf, Ddf = cub["grid"], cub["Z"], cub["deflection"]
    for method in o.cubic.methods:
        for fig_no, d in (("06", "x"), ("07", "y")):
            name = f"fig{fig_no}_cubic_S_vs_k_force_{d}_{method}.png"
            g = grid[(grid.method == method) & (grid.direction == d) & (grid.singular == 0)]
            # Same geometries on every line: those that hold every force of the study.
            ok = g.groupby(["k1", "k2", "k3"]).feasible.transform("min") == 1
            g = g[ok]
            with _figure(out / name, 1, 3, (13, 4.2)) as (fig, axes):
                for j, key in enumerate(("k1", "k2", "k3")):
                    ax = axes[0, j]
                    piv = g.groupby([key, "force_N"]).S_N.max().unstack()
                    _plot_lines(ax, piv.index, _by_force(piv))
                    ax.set_xlabel(key)
                    ax.set_ylabel("S (N), max over the other ratios")
                    ax.set_title(f"({j + 1}) S vs {key}, force along {d}")
                    ax.grid(alpha=0.3)
                axes[0, 0].legend(fontsize=7, title="force")
                fig.suptitle(
                    f"Cubic rig, {o.cubic.layout} layout, method {method}; geometries that hold "
                    "every force of the study",
                    fontsize=10,
                )
            files.append(name)
        for fig_no, d in (("08", "x"), ("09", "y")):
            name = f"fig{fig_no}_cubic_S_vs_Z_force_{d}_{method}.png"
            z = Zdf[(Zdf.method == method) & (Zdf.direction == d)]
            piv = z.pivot_table(index="Z_m", columns="force_N", values="S_N")
            _force_lines_figure(
                out / name,
                piv,
                "Z of the reference point P (m)",
                f"Force along {d}, k = {o.cubic.baseline_k}, {method}",
            )
            files.append(name)
        for fig_no, case, label in (
            ("10", "fig10_force_y_offset_x", "force along y, offset along x"),
            ("11", "fig11_force_x_offset_y", "force along x, offset along y"),
        ):
            name = f"fig{fig_no}_cubic_S_vs_deflection_{method}.png"
            dd = Ddf[(Ddf.method == method) & (Ddf.case == case)]
            piv = dd.pivot_table(index="deflection_m", columns="force_N", values="S_N")
            _force_lines_figure(
                out / name,
                piv,
                "deflection of the point of application from P (m)",
                f"{label}, {method}",
            )
            files.append(name)
    return files


def plot_flat(flat: dict, out: Path, o: StudyOptions) -> list[str]:
    """Figs. 12-15: S vs K21, K22, H, X for both methods at the three speeds."""
    files = []
    sw = flat["sweeps"]
    labels = {"K21": "K21 (front base width / w1)", "K22": "K22 (back base width / w2)",
              "H_m": "H, height of the base (m)", "X_m": "X of the reference point P (m)"}  # fmt: skip
    for fig_no, p in (("12", "K21"), ("13", "K22"), ("14", "H_m"), ("15", "X_m")):
        name = f"fig{fig_no}_flat_S_vs_{p}.png"
        d = sw[sw.parameter == p]
        with _figure(out / name) as (fig, axes):
            ax = axes[0, 0]
            for mi, method in enumerate(o.flat.methods):
                for si, V in enumerate(o.aero.speeds_mps):
                    e = d[(d.method == method) & (d.speed_mps == V)]
                    ax.plot(
                        e.value,
                        e.S_N,
                        marker=_MARKERS[si],
                        ms=4,
                        ls="-" if mi == 0 else "--",
                        color=f"C{si}",
                        label=f"{V:g} m/s, {method}",
                    )
                    bad = e[e.feasible == 0]
                    ax.plot(bad.value, bad.S_N, ls="none", marker=_MARKERS[si], ms=8,
                            mfc="white", mec=f"C{si}")  # fmt: skip
            ax.set_xlabel(labels[p])
            ax.set_ylabel("S (N)")
            ax.set_yscale("log")
            ax.set_title(
                f"Flat rig, others at {tuple(o.flat.baseline)}; hollow: tensions infeasible",
                fontsize=9,
            )
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
        files.append(name)
    return files


def plot_singular(scan: pd.DataFrame, out: Path) -> list[str]:
    """S and sigma_min as k3 -> k1 = k2 = 0.15 for both layouts."""
    name = "singular_approach.png"
    with _figure(out / name, 1, 2, (12, 4.4)) as (fig, axes):
        for i, layout in enumerate(sens.CUBIC_LAYOUTS):
            ax = axes[0, i]
            d = scan[scan.layout == layout]
            for j, load in enumerate(d.load.unique()):
                e = d[d.load == load]
                (ln,) = ax.loglog(e.gap, e.S_N, marker=_MARKERS[j], ms=3, label=f"S, {load}")
                bad = e[e.feasible == 0]
                ax.plot(bad.gap, bad.S_N, ls="none", marker=_MARKERS[j], ms=6, mfc="white",
                        mec=ln.get_color())  # fmt: skip
            e = d[d.load == d.load.iloc[0]]
            ax.loglog(e.gap, 1.0 / e.sigma_min, "k:", label="1 / sigma_min")
            ax.set_xlabel("distance to the singular configuration (ratio)")
            ax.set_ylabel("S (N)  /  1 / sigma_min")
            ax.set_title(
                f"{layout} layout: {d.approach.iloc[0]} (exact; hollow: tensions infeasible)",
                fontsize=9,
            )
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
    return [name]
