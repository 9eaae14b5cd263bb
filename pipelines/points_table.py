"""The per-point table of a reduced run: one row per test point, the columns docs/analysis.md
lists (the pose, the wrench at the MRP with σ by source, axes, coefficients, tensions and the tension
check, and the corrections' sizes), from the :class:`~cdpr.analysis.reduction.Points` the core gives.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.conventions import COEFFICIENTS, POSE_COLUMNS, WRENCH_COLUMNS
from cdpr.analysis.errors import InputError
from cdpr.analysis.reduction import POSE, POSE_COV, WRENCH, Points
from cdpr.analysis.rig import Rig
from cdpr.analysis.stages import UNCERTAINTY_COLUMNS


def _sd(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0.0, None))


def points_table(
    p: Points,
    rig: Rig,
    labels: Sequence[str],
    columns_before: Mapping[str, Any] | None = None,
    columns_after: Mapping[str, Any] | None = None,
) -> pd.DataFrame:
    """The per-point table: one row per test point (see docs/analysis.md for every column)."""
    s = p.n
    if len(labels) != s:
        raise InputError(f"labels: expected {s}, got {len(labels)}")
    cols: dict[str, Any] = dict(columns_before or {})
    cols["point"] = list(labels)
    cols["kind"] = p["kind"]
    cols["flags"] = p.flag_text()
    for k, c in enumerate(POSE_COLUMNS):
        cols[c] = p[POSE][:, k]
    for k, c in enumerate(POSE_COLUMNS):
        cols[f"sd_{c}"] = _sd(p[POSE_COV])[:, k]
    cols["airspeed_mps"] = p["airspeed_mps"]
    cols["density_kgpm3"] = p["density_kgpm3"]
    cols["q_Pa"] = p.arrays.get("q_Pa", np.full(s, np.nan))
    cols["aoa_rad"] = p.arrays.get("aoa_rad", np.full(s, np.nan))
    cols["sideslip_rad"] = p.arrays.get("sideslip_rad", np.full(s, np.nan))
    cols["tare_point"] = [labels[j] if j >= 0 else "" for j in p["tare_index"]]
    at_mrp = "wrench_mrp_O_N_Nm" in p.arrays
    W = p["wrench_mrp_O_N_Nm"] if at_mrp else p[WRENCH]
    sd = _sd(p["wrench_mrp_cov_O"] if at_mrp else p.wrench_cov)
    for k, c in enumerate(WRENCH_COLUMNS):
        cols[c] = W[:, k]
        cols[f"sd_{c}"] = sd[:, k]
    for name, term in p.cov_terms.items():
        for k, c in enumerate(WRENCH_COLUMNS):
            cols[f"sd_{name}_{c}"] = _sd(term)[:, k]
    if "force_B_N" in p.arrays:
        for k, c in enumerate(("fx_B_N", "fy_B_N", "fz_B_N")):
            cols[c] = p["force_B_N"][:, k]
        for k, c in enumerate(("mx_B_Nm", "my_B_Nm", "mz_B_Nm")):
            cols[c] = p["moment_B_Nm"][:, k]
        for c in ("drag_N", "side_N", "lift_N"):
            cols[c] = p[c]
    for c in COEFFICIENTS:
        cols[c] = p.arrays.get(c, np.full(s, np.nan))
        cols[f"sd_{c}"] = p.arrays.get(f"sd_{c}", np.full(s, np.nan))
    m = rig.n_cables
    dT = p.arrays.get("check_dT_N", np.full((s, m), np.nan))  # the dynamic order has no check
    for k, name in enumerate(rig.cable_names):
        cols[f"T_{name}_N"] = p["tension_N"][:, k]
        cols[f"sd_T_{name}_N"] = np.sqrt(np.clip(p["tension_cov_N2"][:, k, k], 0.0, None))
        cols[f"dT_{name}_N"] = dT[:, k]
    cols["check_max_abs_dT_N"] = p.arrays.get("check_max_abs_dT_N", np.full(s, np.nan))
    cols.update(uncertainty_columns(p))
    cols.update(correction_columns(p, rig))
    cols.update(columns_after or {})
    return pd.DataFrame(cols)


def uncertainty_columns(p: Points) -> dict[str, Any]:
    """The uncertainty stage's columns (random and systematic σ, degrees of freedom, U95 of each
    wrench component and coefficient), the effective load-cell sample count of each point's window
    and the dwell it would need, and a tared point's pose difference to its tare (used and
    measured)."""
    a = p.arrays
    cols: dict[str, Any] = {}
    for key in ("n_eff_min", "dwell_needed_s"):
        if key in a:
            cols[key] = a[key]
    for prefix in UNCERTAINTY_COLUMNS:
        for c in (*WRENCH_COLUMNS, *COEFFICIENTS):
            if f"{prefix}_{c}" in a:
                cols[f"{prefix}_{c}"] = a[f"{prefix}_{c}"]
    for key, prefix in (
        ("deflection_O_m_rad", "deflection"), ("deflection_measured_O_m_rad", "deflection_measured")
    ):  # fmt: skip
        if key in a:
            for k, c in enumerate(POSE_COLUMNS):
                cols[f"{prefix}_{c}"] = a[key][:, k]
    return cols


def _correction_text(p: Points, i: int) -> str:
    """The corrections applied to point i, their sizes and sources, one ``; ``-joined string."""
    a = p.arrays
    out = []
    if "zero_drift_N" in a and np.isfinite(a["zero_drift_N"][i]).all():
        out.append(
            f"zero drift max {np.max(np.abs(a['zero_drift_N'][i])):.4f} N "
            "(linear in time between wind-off zeros)"
        )
    src = str(a["windage_source"][i]) if "windage_source" in a else ""
    if src in ("measured", "model"):
        w = a["windage_N"][i]
        how = (
            "measured tare, fit per speed in aoa/sideslip"
            if src == "measured"
            else ("model: cable drag CD(Re), taut-string end share, from the rig file and [tunnel]")
        )
        out.append(f"windage Fx {w[0]:.4f} N, |F| {np.linalg.norm(w[:3]):.4f} N ({how})")
    if "wall_q_ratio" in a and np.isfinite(a["wall_q_ratio"][i]):
        out.append(
            f"walls q x{a['wall_q_ratio'][i]:.5f}, d_aoa {np.degrees(a['wall_delta_aoa_rad'][i]):.4f}"
            f" deg, dCD_i {a['wall_delta_CD_induced'][i]:.2e} (Barlow, Rae & Pope ch. 10)"
        )
    return "; ".join(out)


def correction_columns(p: Points, rig: Rig) -> dict[str, Any]:
    """The per-point columns of the correction stages that ran (docs/analysis.md): each
    correction's size, the corrected beside the uncorrected coefficients, q/Re/Mach, the
    repeatability σ and the ``corrections`` text (what was applied, its size, its source)."""
    a = p.arrays
    cols: dict[str, Any] = {}
    if "zero_drift_N" in a:
        d = a["zero_drift_N"]
        cols["zero_drift_max_abs_N"] = np.abs(d).max(axis=1) if d.size else np.zeros(p.n)
        for k, name in enumerate(rig.cable_names):
            cols[f"zero_drift_{name}_N"] = d[:, k]
            cols[f"sd_zero_drift_{name}_N"] = a["sd_zero_drift_N"][:, k]
    for key in (
        "relative_humidity", "density_source", "reynolds", "mach", "viscosity_Pas",
        "lowest_mode_Hz",
    ):  # fmt: skip
        if key in a:
            cols[key] = a[key]
    if "windage_N" in a:
        cols["windage_source"] = a["windage_source"]
        for prefix, key in (
            ("windage", "windage_N"),
            ("windage_tare", "windage_tare_N"),
            ("sd_windage_tare", "sd_windage_tare_N"),
            ("windage_model", "windage_model_N"),
        ):
            for k, c in enumerate(WRENCH_COLUMNS):
                cols[f"{prefix}_{c}"] = a[key][:, k]
    for key in (
        "aoa_corrected_rad", "q_corrected_Pa", "wall_eps_solid", "wall_eps_wake", "wall_q_ratio",
        "wall_delta_aoa_rad", "wall_delta_CD_induced", "wall_delta_CL_curvature",
        "wall_delta_Cm_curvature",
        *(f"{c}_corrected" for c in COEFFICIENTS), *(f"sd_{c}_corrected" for c in COEFFICIENTS),
        *(f"sd_repeat_{c}" for c in COEFFICIENTS), *(f"sd_propagated_{c}" for c in COEFFICIENTS),
    ):  # fmt: skip
        if key in a:
            cols[key] = a[key]
    if "corrections" in p.meta:
        cols["corrections"] = [_correction_text(p, i) for i in range(p.n)]
    return cols


def steps_log(p: Points) -> list[dict[str, Any]]:
    """The stage log as plain dicts (for summary.json and the report)."""
    return [
        {
            "stage": st.name,
            "settings": dict(st.settings),
            "points_flagged": st.flagged,
            "note": st.note,
        }
        for st in p.steps
    ]
