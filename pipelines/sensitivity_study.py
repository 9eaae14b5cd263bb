"""The computations of the force-sensitivity study: the paper's loads, the cubic and flat sweeps
(Figs. 6-15, Table 3) and the scan towards singular configurations, batched over
:mod:`cdpr.analysis.sensitivity`; data frames out, no files.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis import sensitivity as sens
from cdpr.analysis.errors import ConfigError

from .sensitivity_options import AeroOptions, StudyOptions, _cubic_grid

# ------------------------------------------------------------------------------------ studies


Progress = Callable[[str, int], Callable[[int], None]]


def _no_progress(label: str, total: int) -> Callable[[int], None]:
    return lambda n: None


def cubic_loads(forces_N: Sequence[float]) -> tuple[np.ndarray, list[str], np.ndarray]:
    """The cubic study's load cases (12, 6): each force along x, then along y; labels; magnitudes."""
    F = np.asarray(forces_N, dtype=np.float64)
    W = np.zeros((2, len(F), 6))
    W[0, :, 0] = F
    W[1, :, 1] = F
    return W.reshape(-1, 6), ["x"] * len(F) + ["y"] * len(F), np.concatenate([F, F])


def flat_loads(a: AeroOptions, speeds: Sequence[float]) -> np.ndarray:
    """The flat study's aerodynamic wrenches (k, 6) at the given airspeeds."""
    return sens.aero_wrench(
        np.asarray(speeds, dtype=np.float64),
        np.asarray(a.coefficients),
        rho_kgpm3=a.rho_kgpm3,
        S_ref_m2=a.S_ref_m2,
        span_m=a.span_m,
        chord_m=a.chord_m,
    )


def flat_margin_loads(a: AeroOptions) -> np.ndarray:
    """Load cases of the flat feasibility margin: 0 ... max speed, both sideslip signs."""
    V = np.linspace(0.0, a.max_speed_mps, 7)[1:]
    C = np.asarray(a.coefficients)
    mirror = C * np.array([1, -1, 1, -1, 1, -1])
    kw = {"rho_kgpm3": a.rho_kgpm3, "S_ref_m2": a.S_ref_m2, "span_m": a.span_m}
    return np.concatenate(
        [
            sens.aero_wrench(V, C, chord_m=a.chord_m, **kw),
            sens.aero_wrench(V, mirror, chord_m=a.chord_m, **kw),
        ]
    )


def _metrics_frame(
    A: np.ndarray,
    G: np.ndarray,
    loads: np.ndarray,
    t_min: float,
    t_max: float,
    o: StudyOptions,
) -> pd.DataFrame:
    """Per-configuration metrics the paper lacks, for A (n, 6, m)."""
    sv = sens.singular_value_metrics(A)
    std = sens.wrench_std(A, o.study.sigma_T_N, tare=True)
    margin = sens.feasibility_margin(A, G, loads, t_min, t_max, o.study.margin_method)
    df = pd.DataFrame(
        {
            "condition": sv.condition,
            "sigma_min": sv.sigma_min,
            "sigma_max": sv.sigma_max,
            "dW_per_dT_min": sv.sigma_min,
            "dW_per_dT_max": sv.sigma_max,
            "margin_N": margin,
        }
    )
    for j, name in enumerate(("fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")):
        df[f"std_{name}"] = std[:, j]
    return df


def _require_holdable(
    res: sens.SensitivityResult,
    sweep: str,
    keys: str,
    source: str,
    method: str,
    singular_keys: str | None = None,
) -> None:
    ok = res.feasible_wind_off & ~res.singular
    if np.all(res.singular):
        raise ConfigError(
            source,
            singular_keys or keys,
            f"{sweep}: the structure matrix is singular at every configuration of the sweep "
            "(for instance the 'cube' layout with two equal ratios at mid-height, or k1 = k3 in "
            "the 'crossed' layout); choose other ratios or another cubic.layout",
        )
    if not np.any(ok):
        n_sing = int(np.sum(res.singular))
        raise ConfigError(
            source,
            keys,
            f"{sweep}: the rig cannot hold its platform against gravity ({method}) at any "
            f"configuration of the sweep ({n_sing} of {res.singular.size} singular); check the "
            "mass, the tension limits and the geometry",
        )


def _require_loaded_holdable(grid: pd.DataFrame, o: StudyOptions, source: str) -> None:
    """The report compares optima at the largest cubic force: some non-singular configuration
    must hold it (per method and direction), else a one-line error naming ``cubic.forces_N``."""
    Fmax = max(o.cubic.forces_N)
    for method in o.cubic.methods:
        for d in ("x", "y"):
            g = grid[(grid.method == method) & (grid.direction == d) & (grid.force_N == Fmax)]
            if not ((g.singular == 0) & (g.feasible == 1)).any():
                raise ConfigError(
                    source,
                    "cubic.forces_N",
                    f"no configuration of the cubic k grid holds the largest load, {Fmax:g} N "
                    f"along {d} ({method}), within [{o.cubic.t_min_N:g}, {o.cubic.t_max_N:g}] N; "
                    "lower the force or widen the tension limits",
                )


def run_cubic(o: StudyOptions, progress: Progress = _no_progress, source: str = "options") -> dict:
    """The cubic-rig studies: the 960-case k grid (Figs. 6-7), Z (Figs. 8-9), deflection (10-11)."""
    c = o.cubic
    G = sens.gravity_load(c.mass_kg)
    W, dirs, mags = cubic_loads(c.forces_N)
    geo_kw = {"L_m": c.L_m, "W_m": c.W_m, "H_m": c.H_m, "layout": c.layout}
    grid = np.array(list(_cubic_grid(c)))
    A = sens.structure_matrices(sens.cubic_geometry(grid[:, 0], grid[:, 1], grid[:, 2], **geo_kw))
    margin_loads = np.concatenate([W, -W])
    metrics = _metrics_frame(A, G, margin_loads, c.t_min_N, c.t_max_N, o)
    out: dict[str, Any] = {"grid": [], "Z": [], "deflection": []}
    tick = progress("cubic rig: k grid, Z, deflection", 3 * len(c.methods))
    timings = {}
    for method in c.methods:
        t0 = time.perf_counter()
        res = sens.sensitivity(A[:, None], W, G, c.t_min_N, c.t_max_N, method)
        timings[method] = time.perf_counter() - t0
        _require_holdable(res, "cubic k grid", "cubic.mass_kg", source, method, "cubic.k1_values")
        n, k = res.S_N.shape
        df = pd.DataFrame(
            {
                "method": method,
                "k1": np.repeat(grid[:, 0], k),
                "k2": np.repeat(grid[:, 1], k),
                "k3": np.repeat(grid[:, 2], k),
                "Z_m": 0.5 * c.H_m,
                "direction": np.tile(dirs, n),
                "force_N": np.tile(mags, n),
                "S_N": res.S_N.ravel(),
                "feasible": res.feasible.ravel().astype(int),
                "singular": res.singular.ravel().astype(int),
            }
        )
        df = pd.concat([df, metrics.loc[np.repeat(np.arange(n), k)].reset_index(drop=True)], axis=1)
        out["grid"].append(df)
        tick(1)
        # Z study at the baseline k.
        Z = np.asarray(c.Z_values_m)
        k1, k2, k3 = c.baseline_k
        AZ = sens.structure_matrices(sens.cubic_geometry(k1, k2, k3, Z_m=Z, **geo_kw))
        rz = sens.sensitivity(AZ[:, None], W, G, c.t_min_N, c.t_max_N, method)
        _require_holdable(
            rz, "cubic Z sweep", "cubic.Z_values_m", source, method, "cubic.baseline_k"
        )
        out["Z"].append(
            pd.DataFrame(
                {
                    "method": method,
                    "Z_m": np.repeat(Z, len(W)),
                    "direction": np.tile(dirs, len(Z)),
                    "force_N": np.tile(mags, len(Z)),
                    "S_N": rz.S_N.ravel(),
                    "feasible": rz.feasible.ravel().astype(int),
                    "singular": rz.singular.ravel().astype(int),
                }
            )
        )
        tick(1)
        # Deflection study: Fig. 10 force along y applied at (d, 0, 0); Fig. 11 along x at (0, d, 0).
        d = np.asarray(c.deflection_values_m)
        F = np.asarray(c.forces_N)
        Wd = np.zeros((2, len(d), len(F), 6))
        Wd[0, :, :, 1] = F
        Wd[0, :, :, 5] = d[:, None] * F
        Wd[1, :, :, 0] = F
        Wd[1, :, :, 5] = -d[:, None] * F
        A0 = sens.structure_matrices(sens.cubic_geometry(k1, k2, k3, **geo_kw))
        rd = sens.sensitivity(A0, Wd, G, c.t_min_N, c.t_max_N, method)
        _require_holdable(rd, "cubic deflection sweep", "cubic.baseline_k", source, method)
        fig = np.array(["fig10_force_y_offset_x", "fig11_force_x_offset_y"])
        out["deflection"].append(
            pd.DataFrame(
                {
                    "method": method,
                    "case": np.repeat(fig, len(d) * len(F)),
                    "direction": np.repeat(np.array(["y", "x"]), len(d) * len(F)),
                    "deflection_m": np.tile(np.repeat(d, len(F)), 2),
                    "force_N": np.tile(F, 2 * len(d)),
                    "S_N": rd.S_N.ravel(),
                    "feasible": rd.feasible.ravel().astype(int),
                }
            )
        )
        tick(1)
    return {
        "grid": pd.concat(out["grid"], ignore_index=True),
        "Z": pd.concat(out["Z"], ignore_index=True),
        "deflection": pd.concat(out["deflection"], ignore_index=True),
        "timings_s": timings,
        "n_geometries": len(grid),
    }


def _flat_eval(
    o: StudyOptions, K21: np.ndarray, K22: np.ndarray, H: np.ndarray, X: np.ndarray, method: str
) -> sens.SensitivityResult:
    f = o.flat
    A = sens.structure_matrices(
        sens.flat_geometry(K21, K22, H, X, L_m=f.L_m, l_m=f.l_m, w1_m=f.w1_m, w2_m=f.w2_m)
    )
    W = flat_loads(o.aero, o.aero.speeds_mps)
    return sens.sensitivity(
        A[:, None], W, sens.gravity_load(f.mass_kg), f.t_min_N, f.t_max_N, method
    )


def run_flat(o: StudyOptions, progress: Progress = _no_progress, source: str = "options") -> dict:
    """The flat-rig Table 3 study: one-at-a-time sweeps (Figs. 12-15) and the full grid."""
    f = o.flat
    b = np.asarray(f.baseline, dtype=np.float64)
    params = (
        ("K21", f.K21_values, "fig12"),
        ("K22", f.K22_values, "fig13"),
        ("H_m", f.H_values_m, "fig14"),
        ("X_m", f.X_values_m, "fig15"),
    )
    speeds = np.asarray(o.aero.speeds_mps)
    rows = []
    tick = progress("flat rig: Table 3 sweeps", len(params) * len(f.methods))
    for j, (name, values, _fig) in enumerate(params):
        cfg = np.tile(b, (len(values), 1))
        cfg[:, j] = values
        for method in f.methods:
            res = _flat_eval(o, cfg[:, 0], cfg[:, 1], cfg[:, 2], cfg[:, 3], method)
            _require_holdable(res, f"flat {name} sweep", f"flat.{name}_values", source, method)
            for s_i, V in enumerate(speeds):
                rows.append(
                    pd.DataFrame(
                        {
                            "parameter": name,
                            "value": np.asarray(values),
                            "K21": cfg[:, 0],
                            "K22": cfg[:, 1],
                            "H_m": cfg[:, 2],
                            "X_m": cfg[:, 3],
                            "method": method,
                            "speed_mps": V,
                            "S_N": res.S_N[:, s_i],
                            "feasible": res.feasible[:, s_i].astype(int),
                            "singular": res.singular[:, s_i].astype(int),
                        }
                    )
                )
            tick(1)
    out: dict[str, Any] = {"sweeps": pd.concat(rows, ignore_index=True)}
    if f.full_grid:
        g = np.array(
            np.meshgrid(f.K21_values, f.K22_values, f.H_values_m, f.X_values_m, indexing="ij")
        ).reshape(4, -1)
        df = pd.DataFrame({"K21": g[0], "K22": g[1], "H_m": g[2], "X_m": g[3]})
        chunk = 2048
        n = g.shape[1]
        tick = progress("flat rig: full Table 3 grid", n * len(f.methods))
        cols: dict[str, list[np.ndarray]] = {}
        mets = []
        G = sens.gravity_load(f.mass_kg)
        mloads = flat_margin_loads(o.aero)
        for s in range(0, n, chunk):
            sl = slice(s, min(n, s + chunk))
            A = sens.structure_matrices(
                sens.flat_geometry(
                    g[0, sl], g[1, sl], g[2, sl], g[3, sl],
                    L_m=f.L_m, l_m=f.l_m, w1_m=f.w1_m, w2_m=f.w2_m,
                )
            )  # fmt: skip
            mets.append(_metrics_frame(A, G, mloads, f.t_min_N, f.t_max_N, o))
            for method in f.methods:
                res = sens.sensitivity(
                    A[:, None], flat_loads(o.aero, speeds), G, f.t_min_N, f.t_max_N, method
                )
                for s_i, V in enumerate(speeds):
                    cols.setdefault(f"S_{method}_{V:g}mps_N", []).append(res.S_N[:, s_i])
                    cols.setdefault(f"feasible_{method}_{V:g}mps", []).append(
                        res.feasible[:, s_i].astype(int)
                    )
                tick(sl.stop - sl.start)
        for k, v in cols.items():
            df[k] = np.concatenate(v)
        out["grid"] = pd.concat([df, pd.concat(mets, ignore_index=True)], axis=1)
    return out


def singular_scan(o: StudyOptions) -> pd.DataFrame:
    """S, sigma_min and the condition number as a configuration approaches a singular one.

    ``crossed`` layout: k1 = k2 = 0.15, k3 -> k1 from below (singular at k1 = k3).  ``cube``
    layout: k1 = 0.15, k3 = 0.075, k2 -> k3 from above (singular at k2 = k3: the paper's optimum).
    Loads: the largest force along x and along y, and pure moments of 0.1 m times it about x, y, z.
    """
    c = o.cubic
    G = sens.gravity_load(c.mass_kg)
    F = max(c.forces_N)
    loads = {
        "Fx": [F, 0, 0, 0, 0, 0],
        "Fy": [0, F, 0, 0, 0, 0],
        "Mx": [0, 0, 0, F * 0.1, 0, 0],
        "My": [0, 0, 0, 0, F * 0.1, 0],
        "Mz": [0, 0, 0, 0, 0, F * 0.1],
    }
    W = np.array(list(loads.values()), dtype=np.float64)
    gap = np.geomspace(0.05, 1e-7, 25)
    rows = []
    for layout in sens.CUBIC_LAYOUTS:
        if layout == "crossed":
            k1, k2, k3 = 0.15, 0.15, 0.15 - gap
            what = "k3 -> k1 = k2 = 0.15"
        else:
            k1, k2, k3 = 0.15, 0.075 + gap, 0.075
            what = "k2 -> k3 = 0.075 (k1 = 0.15)"
        A = sens.structure_matrices(
            sens.cubic_geometry(k1, k2, k3, L_m=c.L_m, W_m=c.W_m, H_m=c.H_m, layout=layout)
        )
        sv = sens.singular_value_metrics(A)
        res = sens.sensitivity(A[:, None], W, G, c.t_min_N, c.t_max_N, "exact")
        for j, name in enumerate(loads):
            rows.append(
                pd.DataFrame(
                    {
                        "layout": layout,
                        "approach": what,
                        "k1": k1,
                        "k2": np.broadcast_to(k2, gap.shape),
                        "k3": np.broadcast_to(k3, gap.shape),
                        "gap": gap,
                        "load": name,
                        "S_N": res.S_N[:, j],
                        "sigma_min": sv.sigma_min,
                        "condition": sv.condition,
                        "singular": res.singular[:, j].astype(int),
                        "feasible": res.feasible[:, j].astype(int),
                    }
                )
            )
    return pd.concat(rows, ignore_index=True)


def optimum_stiffness(o: StudyOptions) -> pd.DataFrame:
    """Sensitivity beside stiffness at the paper's optima (flat baseline, cubic baseline_k).

    One row per design load: the rig, the load, S (N, eq. 12) with the first method of the rig's
    study, and the six natural frequencies (Hz) at the reference pose under gravity alone
    (:func:`cdpr.analysis.stiffness.rig_modes`, cables E*A = ``study.EA_N``).
    """
    import dataclasses

    from cdpr.analysis import rigs
    from cdpr.analysis.stiffness import rig_modes

    f, c = o.flat, o.cubic
    flat = rigs.flat_rig(
        *f.baseline, L_m=f.L_m, l_m=f.l_m, w1_m=f.w1_m, w2_m=f.w2_m, mass_kg=f.mass_kg,
        t_min_N=f.t_min_N, t_max_N=f.t_max_N, name="flat-paper-optimum",
    )  # fmt: skip
    cubic = rigs.cubic_rig(
        *c.baseline_k, L_m=c.L_m, W_m=c.W_m, H_m=c.H_m, mass_kg=c.mass_kg, t_min_N=c.t_min_N,
        t_max_N=c.t_max_N, layout=c.layout, name="cubic-paper-optimum",
    )  # fmt: skip
    F = max(c.forces_N)
    cases = [
        (flat, f.methods[0], [(f"aero {v:g} m/s", w) for v, w in
                              zip(o.aero.speeds_mps, flat_loads(o.aero, o.aero.speeds_mps), strict=True)]),
        (cubic, c.methods[0], [(f"{F:g} N along {ax}", np.eye(6)[i] * F) for i, ax in ((0, "x"), (1, "y"))]),
    ]  # fmt: skip
    rows = []
    for rig, method, loads in cases:
        rig = dataclasses.replace(rig, cable_EA_N=np.full(rig.n_cables, o.study.EA_N))
        modes = rig_modes(rig, method=method).modes.frequencies_Hz
        for label, W in loads:
            res = sens.sensitivity_of_rig(rig, W, method)
            row = {"rig": rig.name, "load": label, "method": method, "S_N": float(res.S_N)}
            row.update({f"f{k + 1}_Hz": float(modes[k]) for k in range(6)})
            row["EA_N"] = o.study.EA_N
            rows.append(row)
    return pd.DataFrame(rows)
