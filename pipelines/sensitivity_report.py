"""The paper's force-sensitivity study (Figs. 6-15, Table 3), its CSV tables, plots and report.

Everything the paper leaves open is an option of :class:`StudyOptions` with a documented default
(``OPTION_DOCS``); a TOML file with the sections ``[cubic]``, ``[flat]``, ``[aero]`` and ``[study]``
overrides any of them (:func:`options_from_toml`).  :func:`run_study` computes every sweep with the
batched :mod:`cdpr.analysis.sensitivity` and writes into one folder:

- ``cubic_k_grid.csv`` (the 960-case study), ``cubic_Z.csv``, ``cubic_deflection.csv``,
  ``flat_table3_sweeps.csv``, ``flat_table3_grid.csv``, ``singular_scan.csv``;
- ``fig06..fig15_*.png`` in the paper's style and ``singular_*.png``;
- ``report.md``: each of the paper's conclusions next to ours, agrees / differs and why.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import pandas as pd
from pydantic import Field

from cdpr.analysis import sensitivity as sens
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.tension import METHODS
from cdpr.daq.schema import (
    MAX_FORCE_N,
    MAX_LENGTH_M,
    Mass_kg,
    Position_m,
    Schema,
    Tension_N,
    Text,
    parse,
)

from .config import atomic_output, load_toml, write_table
from .plotting import png_figure as _figure

PAPER_FORCES_N = (19.041, 32.183, 48.327, 60.949, 70.043, 75.706)
PAPER_SPEEDS_MPS = (17.27, 25.51, 41.42)


def _arange(a: float, b: float, step: float) -> tuple[float, ...]:
    n = int(round((b - a) / step))
    return tuple(float(round(a + i * step, 6)) for i in range(n + 1))


@dataclass
class CubicOptions:
    """Cubic rig (paper Fig. 3) and its studies (Figs. 6-11)."""

    L_m: float = 2.0
    W_m: float = 1.2
    H_m: float = 1.4
    mass_kg: float = 5.0
    t_min_N: float = 35.0
    t_max_N: float = 1000.0
    layout: str = "crossed"
    k1_values: tuple[float, ...] = (0.1, 0.15, 0.2, 0.3, 0.4)
    k2_values: tuple[float, ...] = (0.075, 0.1, 0.15, 0.2, 0.3)
    k3_values: tuple[float, ...] = (0.025, 0.05, 0.075, 0.1, 0.15)
    forces_N: tuple[float, ...] = PAPER_FORCES_N
    baseline_k: tuple[float, float, float] = (0.15, 0.075, 0.075)
    Z_values_m: tuple[float, ...] = _arange(0.3, 1.1, 0.05)
    deflection_values_m: tuple[float, ...] = _arange(-0.3, 0.3, 0.025)
    methods: tuple[str, ...] = ("penalty", "exact")


@dataclass
class FlatOptions:
    """Flat rig (paper Fig. 4) and its Table 3 study (Figs. 12-15)."""

    L_m: float = 1.0
    l_m: float = 0.03
    w1_m: float = 0.01
    w2_m: float = 0.04
    mass_kg: float = 0.64
    t_min_N: float = 35.0
    t_max_N: float = 300.0
    K21_values: tuple[float, ...] = _arange(46, 96, 5)
    K22_values: tuple[float, ...] = _arange(25, 55, 3)
    H_values_m: tuple[float, ...] = _arange(0.52, 0.92, 0.05)
    X_values_m: tuple[float, ...] = _arange(0.5, 0.95, 0.05)
    baseline: tuple[float, float, float, float] = (51.0, 28.0, 0.67, 0.5)
    methods: tuple[str, ...] = ("penalty", "improved-closed-form")
    full_grid: bool = True


@dataclass
class AeroOptions:
    """The flat study's external wrench: an SDM-like model, coefficients in {O} axes."""

    speeds_mps: tuple[float, ...] = PAPER_SPEEDS_MPS
    max_speed_mps: float = 51.0
    rho_kgpm3: float = 1.225
    S_ref_m2: float = 0.0199
    span_m: float = 0.2441
    chord_m: float = 0.0815
    coefficients: tuple[float, ...] = (0.08, 0.02, 0.45, 0.01, -0.05, 0.01)


@dataclass
class MetricOptions:
    """Metrics beyond the paper."""

    sigma_T_N: float = 0.2
    margin_method: str = "exact"
    near_singular_condition: float = 1e3


@dataclass
class StudyOptions:
    """All options of the study; see ``OPTION_DOCS`` for what each one means and why."""

    cubic: CubicOptions = field(default_factory=CubicOptions)
    flat: FlatOptions = field(default_factory=FlatOptions)
    aero: AeroOptions = field(default_factory=AeroOptions)
    study: MetricOptions = field(default_factory=MetricOptions)


OPTION_DOCS: dict[str, str] = {
    "cubic.L_m, W_m, H_m": "frame 2 x 1.2 x 1.4 m (paper)",
    "cubic.mass_kg, t_min_N, t_max_N": "5 kg, 35 N, 1000 N (paper)",
    "cubic.layout": "cable layout of Fig. 3 (not given by the paper): 'crossed' (default, bottom "
    "cables to the opposite y side) or 'cube' (every corner to its own frame corner); see "
    "cdpr.analysis.rigs",
    "cubic.k1_values, k2_values, k3_values": "the grid standing in for the missing Tables 1-2: "
    "k1 in {0.1, 0.15, 0.2, 0.3, 0.4}, k2 in {0.075, 0.1, 0.15, 0.2, 0.3}, k3 in {0.025, 0.05, "
    "0.075, 0.1, 0.15} with 0.025 <= k3 <= k2 <= k1 <= 0.4 (eq. 13): 80 geometries x 6 forces x 2 "
    "directions = 960 cases; it contains every value the paper names",
    "cubic.forces_N": "19.041 ... 75.706 N (paper), applied at P along x and along y",
    "cubic.baseline_k": "(0.15, 0.075, 0.075), the paper's optimum, used by the Z and deflection "
    "studies",
    "cubic.Z_values_m": "0.3 ... 1.1 m step 0.05 (Figs. 8-9)",
    "cubic.deflection_values_m": "-0.3 ... 0.3 m step 0.025 (Figs. 10-11): Fig. 10 a force along "
    "y applied at (d, 0, 0) from P (moment Mz = d Fy), Fig. 11 a force along x applied at "
    "(0, d, 0) (Mz = -d Fx)",
    "cubic.methods": "tension distribution methods (the paper does not say which one the cubic "
    "study used): 'penalty' (the paper's, min |T - Tmin|) and 'exact' (min |T - Tmid|)",
    "flat.*": "L = 1 m, l = 0.03 m, w1 = 0.01 m, w2 = 0.04 m, 0.64 kg, 35-300 N, Table 3 values "
    "(paper); baseline (K21, K22, H, X) = (51, 28, 0.67 m, 0.5 m) for the one-at-a-time sweeps; "
    "full_grid also evaluates all 11 x 11 x 9 x 10 Table 3 combinations",
    "flat.methods": "'penalty' and 'improved-closed-form', as the paper compares them",
    "aero.*": "the flat study's wrench (not given by the paper): W = q S_ref [C_Fx, C_Fy, C_Fz, "
    "b C_Mx, c C_My, b C_Mz] with q = rho V^2 / 2, rho = 1.225 kg/m^3, S_ref = 0.0199 m^2 (span "
    "0.2441 m squared over an aspect ratio of 3), chord 0.0815 m = S_ref / span, coefficients in "
    "{O} axes (drag +x, lift +z) typical of the SDM at about 8 deg angle of attack and 2 deg "
    "sideslip: (0.08, 0.02, 0.45, 0.01, -0.05, 0.01); speeds 17.27, 25.51, 41.42 m/s (paper); the "
    "feasibility margin covers 0 ... 51 m/s (the tunnel's range) and the mirrored sideslip",
    "study.sigma_T_N": "load-cell noise (1 sigma per reading, N) for the wrench uncertainty; the "
    "tare method reads twice, so the covariance is A (2 sigma^2 I) A^T",
    "study.margin_method": "method whose tensions define the feasibility margin",
    "study.near_singular_condition": "condition number above which a configuration is reported "
    "as near-singular",
}


# ------------------------------------------------------------------------------------ options


_Len_m = Annotated[float, Field(gt=0.0, le=MAX_LENGTH_M)]
_K = Annotated[float, Field(ge=0.025, le=0.4)]  # paper eq. 13
_Gain = Annotated[float, Field(gt=1.0, le=1e6)]  # K21, K22: cable length ratios
_Speed_mps = Annotated[float, Field(gt=0.0, le=1e3)]


def _some(item: Any) -> Any:
    """A non-empty list of ``item`` (at most 10,000: each value is a sweep point)."""
    return Annotated[list[item], Field(min_length=1, max_length=10_000)]


def _exactly(item: Any, n: int) -> Any:
    return Annotated[list[item], Field(min_length=n, max_length=n)]


class _CubicSection(Schema):
    L_m: _Len_m | None = None
    W_m: _Len_m | None = None
    H_m: _Len_m | None = None
    mass_kg: Mass_kg | None = None
    t_min_N: Tension_N | None = None
    t_max_N: Tension_N | None = None
    layout: Text | None = None
    k1_values: _some(_K) | None = None
    k2_values: _some(_K) | None = None
    k3_values: _some(_K) | None = None
    forces_N: _some(Annotated[float, Field(gt=0.0, le=MAX_FORCE_N)]) | None = None
    baseline_k: _exactly(_K, 3) | None = None
    Z_values_m: _some(_Len_m) | None = None
    deflection_values_m: _some(Position_m) | None = None
    methods: _some(Text) | None = None


class _FlatSection(Schema):
    L_m: _Len_m | None = None
    l_m: _Len_m | None = None
    w1_m: _Len_m | None = None
    w2_m: _Len_m | None = None
    mass_kg: Mass_kg | None = None
    t_min_N: Tension_N | None = None
    t_max_N: Tension_N | None = None
    K21_values: _some(_Gain) | None = None
    K22_values: _some(_Gain) | None = None
    H_values_m: _some(_Len_m) | None = None
    X_values_m: _some(_Len_m) | None = None
    baseline: _exactly(Annotated[float, Field(gt=0.0, le=1e6)], 4) | None = None
    methods: _some(Text) | None = None
    full_grid: bool | None = None


class _AeroSection(Schema):
    speeds_mps: _some(_Speed_mps) | None = None
    max_speed_mps: _Speed_mps | None = None
    rho_kgpm3: Annotated[float, Field(gt=0.0, le=1e3)] | None = None
    S_ref_m2: Annotated[float, Field(gt=0.0, le=1e4)] | None = None
    span_m: _Len_m | None = None
    chord_m: _Len_m | None = None
    coefficients: _exactly(Annotated[float, Field(ge=-1e3, le=1e3)], 6) | None = None


class _MetricSection(Schema):
    sigma_T_N: Tension_N | None = None
    margin_method: Text | None = None
    near_singular_condition: Annotated[float, Field(gt=1.0)] | None = None


class OptionsFile(Schema):
    """A study options file: ``[cubic]``, ``[flat]``, ``[aero]``, ``[study]``, each key optional
    (the default of :class:`StudyOptions` otherwise), typed and in a plausible range; how options
    relate (``t_min_N < t_max_N``, the baseline inside the frame) is :func:`validate_options`."""

    cubic: _CubicSection = Field(default_factory=_CubicSection)
    flat: _FlatSection = Field(default_factory=_FlatSection)
    aero: _AeroSection = Field(default_factory=_AeroSection)
    study: _MetricSection = Field(default_factory=_MetricSection)


def options_from_mapping(data: Mapping[str, Any], source: str = "<options>") -> StudyOptions:
    """Defaults overridden by a mapping ``{section: {key: value}}`` checked by
    :class:`OptionsFile` (unknown keys, types, ranges) and :func:`validate_options`."""
    f = parse(OptionsFile, data, source)
    opts = StudyOptions()
    for sec in ("cubic", "flat", "aero", "study"):
        target = getattr(opts, sec)
        for key, value in getattr(f, sec).model_dump(exclude_none=True).items():
            setattr(target, key, tuple(value) if isinstance(value, list) else value)
    validate_options(opts, source)
    return opts


def options_from_toml(path: str) -> StudyOptions:
    """Load study options from a TOML file (sections cubic, flat, aero, study)."""
    return options_from_mapping(load_toml(path), source=str(path))


def validate_options(o: StudyOptions, source: str = "<options>") -> None:
    """Check how the options relate (each option's type and range is :class:`OptionsFile`'s);
    a :class:`ConfigError` names the option and the problem."""

    def need(ok: bool, key: str, problem: str) -> None:
        if not ok:
            raise ConfigError(source, key, problem)

    c, f, s = o.cubic, o.flat, o.study
    need(0 <= c.t_min_N < c.t_max_N, "cubic.t_min_N", "expected 0 <= t_min_N < t_max_N")
    need(c.layout in sens.CUBIC_LAYOUTS, "cubic.layout", f"expected one of {sens.CUBIC_LAYOUTS}")
    need(
        len(tuple(_cubic_grid(c))) > 0,
        "cubic.k1_values",
        "no (k1, k2, k3) of the grids satisfies k3 <= k2 <= k1",
    )
    k1, k2, k3 = c.baseline_k
    need(
        0.025 <= k3 <= k2 <= k1 <= 0.4,
        "cubic.baseline_k",
        f"expected 0.025 <= k3 <= k2 <= k1 <= 0.4, got {tuple(c.baseline_k)}",
    )
    half = 0.5 * k3 * c.H_m
    need(
        all(half < z < c.H_m - half for z in c.Z_values_m),
        "cubic.Z_values_m",
        f"expected {half:g} < Z < {c.H_m - half:g} m (platform inside the frame)",
    )
    need(
        all(abs(d) <= 0.5 * min(c.L_m, c.W_m) for d in c.deflection_values_m),
        "cubic.deflection_values_m",
        f"expected |d| <= {0.5 * min(c.L_m, c.W_m):g} m (inside the frame)",
    )
    need(0 <= f.t_min_N < f.t_max_N, "flat.t_min_N", "expected 0 <= t_min_N < t_max_N")
    need(
        all(f.l_m / 2 < x < f.L_m - f.l_m / 2 for x in f.X_values_m),
        "flat.X_values_m",
        f"expected {f.l_m / 2:g} < X < {f.L_m - f.l_m / 2:g} m (inside the frame)",
    )
    b21, b22, bH, bX = f.baseline
    need(b21 > 1 and b22 > 1, "flat.baseline", "expected K21, K22 > 1")
    need(f.l_m / 2 < bX < f.L_m - f.l_m / 2, "flat.baseline", "expected X inside the frame")
    for key, methods in (("cubic.methods", c.methods), ("flat.methods", f.methods)):
        bad = [m for m in methods if m not in METHODS]
        need(not bad, key, f"unknown method {bad} (known: {sorted(METHODS)})")
    need(s.margin_method in METHODS, "study.margin_method", f"expected one of {sorted(METHODS)}")


def _cubic_grid(c: CubicOptions) -> Iterator[tuple[float, float, float]]:
    for k1 in c.k1_values:
        for k2 in c.k2_values:
            for k3 in c.k3_values:
                if k3 <= k2 <= k1:
                    yield (k1, k2, k3)


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


# ------------------------------------------------------------------------------------ report


def _fmt_k(k: Sequence[float]) -> str:
    return "(" + ", ".join(f"{float(v):g}" for v in k) + ")"


def _verdict(ok: bool) -> str:
    return "**agrees**" if ok else "**differs**"


def _argmax_row(df: pd.DataFrame, col: str = "S_N") -> pd.Series:
    return df.loc[df[col].idxmax()]


def _why_k(d: str, best: pd.Series, g: pd.DataFrame, o: StudyOptions) -> str:
    on_edge = [
        key
        for key, vals in (("k1", o.cubic.k1_values), ("k2", o.cubic.k2_values), ("k3", o.cubic.k3_values))
        if best[key] in (min(vals), max(vals))
    ]  # fmt: skip
    cond_med = float(g.condition.median())
    near = best.condition > 5 * cond_med
    return (
        "with no bound active dT = A^+ W, so S grows as the cables turn away from W "
        + (
            "and, here, as A nears a singular configuration (condition "
            f"{best.condition:.3g} against a median of {cond_med:.3g})"
            if near
            else f"(a long, flat platform makes the cables steeper; condition {best.condition:.3g}, "
            f"median {cond_med:.3g})"
        )
        + (f"; the maximum sits on the edge of the grid in {', '.join(on_edge)}" if on_edge else "")
        + ", not at the paper's interior optimum. Tables 1-2 and the layout of Fig. 3 are "
        "unpublished, and the paper's k3 = 0.1 > k2 = 0.075 violates its own eq. 13"
    )


def _why_z_side(o: StudyOptions, z_lo: float, z_hi: float) -> str:
    """Why S of a side force falls with Z, with the numbers of the baseline geometry."""
    c = o.cubic
    Z = np.array([z_lo, z_hi])
    A = sens.structure_matrices(
        sens.cubic_geometry(*c.baseline_k, Z_m=Z, L_m=c.L_m, W_m=c.W_m, H_m=c.H_m, layout=c.layout)
    )
    uy_top = np.abs(A[:, 1, :4]).mean(axis=1)
    share = np.linalg.norm(np.linalg.pinv(A)[:, :4, 1], axis=1) / np.linalg.norm(
        np.linalg.pinv(A)[:, :, 1], axis=1
    )
    return (
        f"a side force at P is carried mostly by the four top cables ({100 * share[0]:.0f} % of "
        f"|dT| at Z = {z_lo:g} m, {100 * share[1]:.0f} % at {z_hi:g} m; the bottom ones mainly "
        f"cancel the roll moment); as P goes down the top cables get steeper (mean |u_y| "
        f"{uy_top[1]:.2f} at Z = {z_hi:g} m, {uy_top[0]:.2f} at {z_lo:g} m), so their tensions "
        "must change more per newton"
    )


def _flat_singular_text(o: StudyOptions, flat: dict) -> str:
    """The flat rig's yaw singularity and how it shapes Figs. 12-13."""
    f = o.flat
    K21b, K22b, _, Xb = f.baseline
    kw = {"L_m": f.L_m, "l_m": f.l_m}
    k22s = float(sens.flat_yaw_singular_K22(K21b, Xb, **kw))
    K21 = np.linspace(1.5, 300.0, 200_000)
    d = sens.flat_yaw_singular_K22(K21, Xb, **kw) - K22b
    cross = np.flatnonzero(np.diff(np.sign(d)) != 0)
    k21s = float(K21[cross[0]]) if len(cross) else float("nan")
    A_b = sens.structure_matrices(sens.flat_geometry(*f.baseline, w1_m=f.w1_m, w2_m=f.w2_m, **kw))
    cond_b = float(sens.singular_value_metrics(A_b).condition)
    text = (
        "- Flat rig: A loses the yaw direction when, seen from above, the front and the back "
        "cable pairs point at the same spot of the x axis: `(X - l/2) K21 / (K21 - 1) = (X + l/2) "
        "- (L - X - l/2) / (K22 - 1)` (independent of H, w1, w2; `flat_yaw_singular_K22` in "
        f"`cdpr.analysis.sensitivity`). With X = {Xb:g} m that is K22* = {k22s:.2f} for K21 = "
        f"{K21b:g}, and K21* = {k21s:.2f} for K22 = {K22b:g}. Table 3 runs right up to this "
        "surface: the steep rise of S towards small K21 and K22 in Figs. 12-13 (and the failed or "
        "infeasible points there) is the approach to it, and the paper's optimum "
        f"({K21b:g}, {K22b:g}) sits next to it (condition number {cond_b:.3g})."
    )
    if "grid" in flat:
        fg = flat["grid"]
        near = int((fg.condition > o.study.near_singular_condition).sum())
        text += (
            f" In the full Table 3 grid {near} of {len(fg)} configurations have a condition number "
            f"above {o.study.near_singular_condition:g}."
        )
    return text


def _at(e: pd.DataFrame, value: float) -> str:
    hit = e[np.isclose(e.value, value)]
    return f"{hit.S_N.iloc[0]:.3g} N" if len(hit) else "not in the sweep"


def _why_flat(p: str, e: pd.DataFrame, ok: bool) -> str:
    if ok:
        return (
            "same location; S follows the weakest direction of A along the wrench (the platform "
            "is 3 cm long, so the moment rows of A are small)"
            + ("; the maximum is next to the yaw-singular surface" if p in ("K21", "K22") else "")
        )
    vals = e.value.to_numpy()
    best = float(e.loc[e.S_N.idxmax(), "value"])
    where = (
        "smallest" if best == vals.min() else ("largest" if best == vals.max() else "an interior")
    )
    near = (
        "; S rises towards the yaw-singular surface just below the range (see the singular "
        "configurations section)"
        if p in ("K21", "K22")
        else ""
    )
    d = np.diff(e.sort_values("value").S_N.to_numpy())
    d = d[np.isfinite(d)]
    shape = (
        "decreases monotonically"
        if np.all(d < 0)
        else ("increases monotonically" if np.all(d > 0) else "is not monotone")
    )
    return (
        f"S {shape} over the range and is highest at its {where} value. With a 3 cm platform "
        "the moment rows of A are small and S follows the weakest directions of A along the "
        "wrench; the paper's wrench values are not published (ours: the SDM-like model of the "
        "assumptions), and an interior maximum depends on them and on the layout" + near
    )


def build_report(
    o: StudyOptions, cub: dict, flat: dict, scan: pd.DataFrame, files: list[str], meta: dict
) -> str:
    """The reproduction report (Markdown): the paper's conclusions next to ours."""
    c, f = o.cubic, o.flat
    Fmax = max(c.forces_N)
    Vmax = max(o.aero.speeds_mps)
    grid = cub["grid"]
    L: list[str] = []
    add = L.append
    add("# Force sensitivity: reproduction of the paper's Figs. 6-15 and Table 3\n")
    add(
        f"Generated by `cdpr sensitivity` ({meta['version']}) in {meta['elapsed_s']:.1f} s. "
        "S is the paper's eq. 12, `S = sqrt(sum((dT_i / m)^2))` with `dT = T0 - Tw` from the same "
        "tension distribution method (T0: gravity only; Tw: gravity and the external wrench). "
        "Every number below is computed by this run; the assumptions are listed at the end.\n"
    )
    add("## Conclusions side by side\n")
    add("| # | Paper | This reproduction | Verdict | Why |")
    add("|---|---|---|---|---|")
    row = 0

    def line(paper: str, ours: str, ok: bool, why: str) -> None:
        nonlocal row
        row += 1
        add(f"| {row} | {paper} | {ours} | {_verdict(ok)} | {why} |")

    bk = tuple(c.baseline_k)
    for method in c.methods:
        for d in ("x", "y"):
            g = grid[
                (grid.method == method)
                & (grid.direction == d)
                & (grid.force_N == Fmax)
                & (grid.singular == 0)
            ]
            n_inf = int((g.feasible == 0).sum())
            g = g[g.feasible == 1]
            best = _argmax_row(g)
            wc = g[(g.condition < o.study.near_singular_condition) & (g.feasible == 1)]
            best_wc = _argmax_row(wc) if len(wc) else best
            at = g[(g.k1 == bk[0]) & (g.k2 == bk[1]) & (g.k3 == bk[2])]
            rank = int((g.S_N > at.S_N.iloc[0]).sum()) + 1 if len(at) else -1
            kb = (best.k1, best.k2, best.k3)
            ok = np.allclose(kb, bk) or np.allclose(kb, (0.15, 0.075, 0.1))
            line(
                f"optimum k1 = 0.15, k2 = 0.075, k3 = 0.075 or 0.1 (force along {d}, {method})",
                f"max S = {best.S_N:.3g} N at k = {_fmt_k(kb)} (cond {best.condition:.3g}); "
                f"among feasible configurations with cond < {o.study.near_singular_condition:g}: "
                f"{_fmt_k((best_wc.k1, best_wc.k2, best_wc.k3))}, S = {best_wc.S_N:.3g} N; "
                f"the paper's optimum ranks {rank} of {len(g)} feasible ({n_inf} infeasible "
                "left out) (S = "
                f"{at.S_N.iloc[0] if len(at) else float('nan'):.3g} N)",
                ok,
                _why_k(d, best, g, o),
            )
    for method in c.methods:
        z = cub["Z"]
        zx = z[(z.method == method) & (z.direction == "x") & (z.force_N == Fmax)]
        zmin = float(zx.loc[zx.S_N.idxmin(), "Z_m"])
        line(
            f"force along x: S falls from Z = 0.3 to 0.6 m, bottoms out at Z = 0.7 m, rises to "
            f"1.1 m (Fig. 8, {method})",
            f"minimum of S at Z = {zmin:g} m (S from {zx.S_N.iloc[0]:.3g} N at {zx.Z_m.iloc[0]:g} m "
            f"to {zx.S_N.min():.3g} N to {zx.S_N.iloc[-1]:.3g} N at {zx.Z_m.iloc[-1]:g} m)",
            abs(zmin - 0.7) <= 0.1 + 1e-9,
            (
                "Z = 0.7 m = H/2 is the symmetric position between the floor and the top anchors: "
                "there the cables share the load most evenly and |A^+ W| is smallest; moving P "
                "towards either frame plane makes some cables steeper and the rest carry more"
            )
            if abs(zmin - 0.7) <= 0.1 + 1e-9
            else (
                "the penalty method (min |T - Tmin|) keeps several cables at Tmin; which ones "
                "changes with Z, so dT is not A^+ W and the minimum moves; with a Tmid-centred "
                "method no bound is active and the minimum is near H/2 (see the other rows)"
            ),
        )
        zy = z[(z.method == method) & (z.direction == "y") & (z.force_N == Fmax)]
        corr = float(np.corrcoef(zy.Z_m, zy.S_N)[0, 1])
        line(
            f"force along y: S grows as Z decreases (Fig. 9, {method}); 'the lower the reference "
            "point, the better the sensitivity'",
            f"S = {zy.S_N.iloc[0]:.3g} N at Z = {zy.Z_m.iloc[0]:g} m, {zy.S_N.iloc[-1]:.3g} N at "
            f"{zy.Z_m.iloc[-1]:g} m; correlation(Z, S) = {corr:.2f}",
            corr < -0.5,
            _why_z_side(o, float(zy.Z_m.iloc[0]), float(zy.Z_m.iloc[-1])),
        )
    dfl = cub["deflection"]
    for method in c.methods:
        for case, label in (
            ("fig10_force_y_offset_x", "Fig. 10"),
            ("fig11_force_x_offset_y", "Fig. 11"),
        ):
            e = dfl[(dfl.method == method) & (dfl.case == case) & (dfl.force_N == Fmax)]
            e = e.sort_values("deflection_m")
            s = e.S_N.to_numpy()
            asym = float(np.max(np.abs(s - s[::-1])) / np.max(s))
            d_max = float(e.deflection_m.iloc[int(np.argmax(s))])
            d_min = float(e.deflection_m.iloc[int(np.argmin(s))])
            line(
                f"{label}: S symmetric in the deflection, peak at zero deflection ({method})",
                f"asymmetry {asym:.1e}; maximum at d = {d_max:g} m, minimum at d = {d_min:g} m "
                f"(S(0) = {e.S_N[e.deflection_m.abs() < 1e-12].iloc[0]:.3g} N, "
                f"S(+-{e.deflection_m.max():g}) = {s[-1]:.3g} N)",
                asym < 0.01 and abs(d_max) < 1e-9,
                "symmetry agrees (the rig is symmetric in x and y); but an offset d adds a moment "
                "d F to W, and while no bound is active dT = A^+ (W_F + d W_M) is affine in d, so "
                "S(d) is convex with its minimum at d = 0 by symmetry: a peak at zero is "
                "impossible for any linear response; only bound switching (penalty method) can "
                "bend it, and here it does not",
            )
    sw = flat["sweeps"]
    for p, target, fig in (
        ("K21", 51.0, "Fig. 12"),
        ("K22", 28.0, "Fig. 13"),
        ("H_m", 0.67, "Fig. 14"),
    ):
        for method in f.methods:
            e_all = sw[(sw.parameter == p) & (sw.method == method) & (sw.speed_mps == Vmax)]
            e = e_all[(e_all.singular == 0) & (e_all.feasible == 1) & np.isfinite(e_all.S_N)]
            missing = sorted(set(e_all.value) - set(e.value))
            if not len(e):
                continue
            best = _argmax_row(e)
            ok = abs(best.value - target) < 1e-9
            gaps = (
                f"; no feasible tensions at {p} = {', '.join(f'{v:g}' for v in missing)}"
                if missing
                else ""
            )
            why = _why_flat(p, e, ok)
            if ok and missing:
                why += (
                    f"; weak agreement: the method finds no feasible tensions at "
                    f"{', '.join(f'{v:g}' for v in missing)}, next to the maximum"
                )
            line(
                f"{fig}: S highest at {p} = {target:g} ({method})",
                f"S highest at {p} = {best.value:g} (S = {best.S_N:.3g} N at {Vmax:g} m/s; "
                f"S at {target:g}: {_at(e, target)}; range "
                f"{e.S_N.min():.3g}-{e.S_N.max():.3g} N{gaps})",
                ok,
                why,
            )
    for method in f.methods:
        e = sw[(sw.parameter == "X_m") & (sw.method == method) & (sw.speed_mps == Vmax)]
        spread = float((e.S_N.max() - e.S_N.min()) / e.S_N.mean())
        line(
            f"Fig. 15: the X coordinate of P has (almost) no effect ({method})",
            f"S varies by {100 * spread:.0f} % over X = {e.value.min():g}-{e.value.max():g} m "
            f"({e.S_N.min():.3g}-{e.S_N.max():.3g} N)",
            spread < 0.1,
            "moving P along x changes the angles of all eight cables (front anchors at x = 0, "
            "back ones at x = L); it leaves S unchanged only if the front and back cables "
            "change in compensating ways, which this geometry does not do near the back plane",
        )
    add("")
    add("## Singular and near-singular configurations\n")
    sing = grid[(grid.singular == 1)][["k1", "k2", "k3"]].drop_duplicates()
    near = grid[(grid.singular == 0) & (grid.condition > o.study.near_singular_condition)][
        ["k1", "k2", "k3", "condition"]
    ].drop_duplicates()
    add(
        f"- Layout `{c.layout}`: {len(sing)} of {cub['n_geometries']} grid geometries are "
        f"singular ({', '.join(_fmt_k(r) for r in sing.to_numpy()) or 'none'}); S is undefined "
        f"there (NaN in the CSV, skipped in the plots). {len(near)} more have a condition number "
        f"above {o.study.near_singular_condition:g}."
    )
    add(
        "- Where the singular sets lie (found by scanning a fine k grid and by the plot "
        "`singular_approach.png`): the `cube` layout (every platform corner to the frame corner "
        "of its own octant) loses rank whenever two ratios are equal (k1 = k2: Mz, k1 = k3: My, "
        "k2 = k3: Mx), so the paper's optimum (0.15, 0.075, 0.075) is singular in it; the "
        "`crossed` layout keeps the x-z projection of the cube, so it is singular at k1 = k3 "
        "(My), which inside eq. 13 (k3 <= k2 <= k1) means k1 = k2 = k3, and it is regular at "
        "k1 = k2."
    )
    for layout in sens.CUBIC_LAYOUTS:
        d = scan[scan.layout == layout]
        parts = []
        for load in d.load.unique():
            e = d[(d.load == load) & (d.singular == 0)].sort_values("gap")
            if len(e) >= 4:
                x, y = np.log(e.gap.to_numpy()), np.log(e.S_N.to_numpy())
                slope = float(np.polyfit(x[:8], y[:8], 1)[0])
                infeas = e[e.feasible == 0]
                lost = (
                    f", tensions outside the limits below gap {infeas.gap.max():.1e}"
                    if len(infeas)
                    else ""
                )
                parts.append(
                    f"{load}: S ~ gap^{slope:.2f} (S = {e.S_N.iloc[0]:.3g} N at gap "
                    f"{e.gap.iloc[0]:.1e}{lost})"
                )
        n_s = int(d[d.load == d.load.iloc[0]].singular.sum())
        add(
            f"- Approaching the singular set ({layout}, {d.approach.iloc[0]}; {n_s} of "
            f"{len(gap_values(d))} steps flagged singular): "
            + "; ".join(parts)
            + ". S grows like 1/sigma_min (slope -1) only for the loads with a component "
            "along the lost direction; the others stay finite, so a sweep can show a huge S next "
            "to a singularity for one load direction and nothing for another. An S that is large "
            "because A is nearly singular is not a good force balance: the tensions needed for "
            "the weak-direction loads leave their limits (the margin collapses, see below), and "
            "the wrench the rig recovers gains no accuracy from it (next section)."
        )
    add(_flat_singular_text(o, flat))
    add("")
    add("## Metrics the paper lacks (per configuration, in the CSV files)\n")
    add(
        "`condition`, `sigma_min`, `sigma_max` of A; `dW_per_dT_min/max` = sigma_min/max, the "
        "bounds of |dW| / |dT| for dT in the row space of A (and m S lies between |W| / sigma_max "
        f"and |W| / sigma_min when no bound is active); `margin_N`, the worst tension slack "
        f"(method `{o.study.margin_method}`) over the full load range (cubic: +-x and +-y forces "
        f"up to {Fmax:g} N; flat: 0-{o.aero.max_speed_mps:g} m/s, both sideslip signs), "
        "negative or -inf when infeasible; `std_*`, the standard deviation of each recovered "
        f"wrench component for load-cell noise sigma = {o.study.sigma_T_N:g} N per reading (tare "
        "method: sqrt(diag(A 2 sigma^2 I A^T))).\n"
    )
    add(
        "What S does not tell: the recovered wrench is `W = A (T0 - Tw)`, so load-cell noise "
        "reaches it through A itself, `Cov(W) = A Sigma_T A^T`: its standard deviation depends on "
        "the row norms of A, not on S or on sigma_min. A larger dT for the same W makes the "
        "tension change easier to see on a load cell, but the absolute accuracy of W is set by "
        "`std_*`; a design should compare `std_*` (or |W| / std) and the margin, with S as a "
        "secondary figure (see `cdpr design` for the trade-off between S and the margin).\n"
    )
    add(
        "| configuration | S (N) | condition | sigma_min | margin (N) | std Fx (N) | std Mz (N m) |"
    )
    add("|---|---|---|---|---|---|---|")
    m0 = c.methods[0]
    for k in (bk, (0.4, 0.3, 0.025), (0.15, 0.15, 0.025)):
        e = grid[
            (grid.method == m0)
            & (grid.direction == "x")
            & (grid.force_N == Fmax)
            & np.isclose(grid.k1, k[0])
            & np.isclose(grid.k2, k[1])
            & np.isclose(grid.k3, k[2])
        ]
        if len(e):
            r = e.iloc[0]
            add(
                f"| cubic {_fmt_k(k)}, Fx {Fmax:g} N, {m0} | {r.S_N:.3g} | {r.condition:.3g} | "
                f"{r.sigma_min:.3g} | {r.margin_N:.3g} | {r.std_fx_N:.3g} | {r.std_mz_Nm:.3g} |"
            )
    if "grid" in flat:
        fg = flat["grid"]
        col = f"S_{f.methods[0]}_{Vmax:g}mps_N"
        for k in (tuple(f.baseline), (61.0, 34.0, 0.72, 0.5)):
            e = fg[
                np.isclose(fg.K21, k[0])
                & np.isclose(fg.K22, k[1])
                & np.isclose(fg.H_m, k[2])
                & np.isclose(fg.X_m, k[3])
            ]
            if len(e):
                r = e.iloc[0]
                add(
                    f"| flat {_fmt_k(k)}, {Vmax:g} m/s, {f.methods[0]} | {r[col]:.3g} | "
                    f"{r.condition:.3g} | {r.sigma_min:.3g} | {r.margin_N:.3g} | "
                    f"{r.std_fx_N:.3g} | {r.std_mz_Nm:.3g} |"
                )
        ok = fg[np.isfinite(fg[col]) & (fg.margin_N > 0)]
        if len(ok):
            b = _argmax_row(ok, col)
            add(
                f"\nFull Table 3 grid ({len(fg)} configurations): the highest S with a positive "
                f"margin over the whole load range is {b[col]:.3g} N at K21 = {b.K21:g}, K22 = "
                f"{b.K22:g}, H = {b.H_m:g} m, X = {b.X_m:g} m (condition {b.condition:.3g}; "
                f"the yaw-singular K22* there is "
                f"{float(sens.flat_yaw_singular_K22(b.K21, b.X_m, L_m=f.L_m, l_m=f.l_m)):.3g}); "
                f"{int((fg.margin_N > 0).sum())} of {len(fg)} configurations keep every cable "
                "within its limits over the whole range."
            )
        corr = np.corrcoef(np.log(fg[col].to_numpy()), -np.log(fg.sigma_min.to_numpy()))[0, 1]
        add(
            f"\nAcross the flat grid, log S correlates with log(1/sigma_min) at r = {corr:.2f}: "
            "S is mostly a measure of how weak A is."
        )
    add("")
    add("## Timing\n")
    for k, v in cub["timings_s"].items():
        add(f"- cubic {cub['n_geometries']}-geometry x {2 * len(c.forces_N)}-load study "
            f"({cub['n_geometries'] * 2 * len(c.forces_N)} cases), method {k}: {v * 1e3:.1f} ms")  # fmt: skip
    add("")
    add("## Assumptions (options, with their defaults)\n")
    for k, v in OPTION_DOCS.items():
        add(f"- `{k}`: {v}")
    add("")
    add("## Files\n")
    for name in files:
        add(f"- [{name}]({name})")
    add("")
    add("## Figures\n")
    for name in files:
        if name.endswith(".png"):
            add(f"### {name}\n\n![{name}]({name})\n")
    return "\n".join(L)


def gap_values(d: pd.DataFrame) -> np.ndarray:
    """The distinct distances to the singular configuration of a scan."""
    return np.unique(d.gap.to_numpy())


def _write_csv(path: Path, df: pd.DataFrame, what: str, meta: dict) -> None:
    write_table(path, df, {"cdpr": meta["version"], "table": what, "units": "S in N"})


def run_study(
    o: StudyOptions,
    out_dir: str | Path,
    progress: Progress = _no_progress,
    source: str = "options",
    version: str = "",
) -> dict:
    """Run every study, write CSVs, PNGs and ``report.md`` into ``out_dir``; returns a summary."""
    validate_options(o, source)
    t0 = time.perf_counter()
    out = Path(out_dir)
    cub = run_cubic(o, progress, source)
    _require_loaded_holdable(cub["grid"], o, source)
    flat = run_flat(o, progress, source)
    scan = singular_scan(o)
    meta = {"version": f"cdpr {version}".strip()}
    tick = progress("writing tables and figures", 4)
    _write_csv(out / "cubic_k_grid.csv", cub["grid"], "cubic k grid (Figs. 6-7)", meta)
    _write_csv(out / "cubic_Z.csv", cub["Z"], "cubic Z sweep (Figs. 8-9)", meta)
    _write_csv(out / "cubic_deflection.csv", cub["deflection"], "deflection (Figs. 10-11)", meta)
    _write_csv(out / "flat_table3_sweeps.csv", flat["sweeps"], "flat sweeps (Figs. 12-15)", meta)
    if "grid" in flat:
        _write_csv(out / "flat_table3_grid.csv", flat["grid"], "flat Table 3 grid", meta)
    _write_csv(out / "singular_scan.csv", scan, "approach to singular configurations", meta)
    tick(1)
    files = plot_cubic(cub, out, o)
    tick(1)
    files += plot_flat(flat, out, o)
    files += plot_singular(scan, out)
    tick(1)
    files = [
        "cubic_k_grid.csv",
        "cubic_Z.csv",
        "cubic_deflection.csv",
        "flat_table3_sweeps.csv",
        *(["flat_table3_grid.csv"] if "grid" in flat else []),
        "singular_scan.csv",
        *files,
    ]
    meta["elapsed_s"] = time.perf_counter() - t0
    text = build_report(o, cub, flat, scan, files, meta)
    with atomic_output(out / "report.md") as fh:
        fh.write(text)
    tick(1)
    return {"report": str(out / "report.md"), "files": files, "elapsed_s": meta["elapsed_s"]}
