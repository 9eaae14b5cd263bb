"""The ordered stage list of the reduction core, and the per-point table it gives.

:func:`reduction_stages` binds the settings of every stage (:mod:`cdpr.analysis.reduction`) in the
order of DESIGN.md; :func:`reduce_points` runs them; :func:`points_table` turns the result into the
per-point table (one row per test point, columns documented in docs/analysis.md).  ``cdpr analyze``,
``cdpr wrench`` and the live view call these.

Slots for later stages (zero drift, cable/platform windage, inertia of a moving platform, wall
corrections): pass them in
``extra`` under the slot's name; each is a :data:`cdpr.analysis.reduction.Stage` (points in, points
out) that adds its correction to ``wrench_N`` and its σ term to ``cov_terms``, flags the points it
cannot treat and is logged by the ``@stage`` decorator.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.aero import ModelGeometry
from cdpr.analysis.conventions import POSE_COLUMNS, WRENCH_COLUMNS
from cdpr.analysis.errors import InputError
from cdpr.analysis.reduction import (
    COEFFICIENTS,
    Points,
    Stage,
    axes_and_moments,
    balance_interaction,
    coefficients,
    run_stages,
    structure_matrix_stage,
    tension_check,
    weight_model_stage,
    weight_tare,
)
from cdpr.analysis.rig import Rig
from cdpr.analysis.weight import WeightModel

SLOTS: tuple[str, ...] = ("zero_drift", "windage", "inertia", "wall_corrections")
"""Names of the slots later stages plug into (see the module docstring)."""


@dataclass(frozen=True)
class ReduceSettings:
    """Settings of the core (recorded in every summary).

    method, check_limit_N: the tension check (controller's distribution method, pass mark).
    tare_position_tol_m, tare_angle_tol_rad: a wind-off point at the same pose within these is the
        point's tare (else the weight model).
    prior_mass_rel_sd, prior_com_sd_m: spread of the rig file's mass / centre of mass as the weight
        model's prior.
    allow_nominal_weight: reduce points without tare or weight model with the rig file's mass
        (flagged ``weight_nominal``); off by default.
    wind_off_mps: below this a point has no coefficients.
    fit_weight_model: fit the weight model from the wind-off points (``cdpr wrench`` pairs each row
        with its own tare and does not); tare_shares_pose: the tare row is at the same measured
        pose (one pose error for both, see :func:`cdpr.analysis.reduction.weight_tare`).
    """

    method: str = "exact"
    check_limit_N: float = 1.0
    tare_position_tol_m: float = 1e-3
    tare_angle_tol_rad: float = float(np.deg2rad(0.1))
    prior_mass_rel_sd: float = 0.05
    prior_com_sd_m: float = 0.01
    allow_nominal_weight: bool = False
    wind_off_mps: float = 1.0
    fit_weight_model: bool = True
    tare_shares_pose: bool = False


def reduction_stages(
    rig: Rig,
    geometry: ModelGeometry | None,
    settings: ReduceSettings = ReduceSettings(),
    interaction: Any = None,
    weight_model: WeightModel | None = None,
    second_order: Any = None,
    extra: Mapping[str, Sequence[Stage]] | None = None,
) -> list[Stage]:
    """The ordered stages with their settings bound."""
    extra = dict(extra or {})
    unknown = sorted(set(extra) - set(SLOTS))
    if unknown:
        raise InputError(f"extra: unknown slot {unknown[0]!r}, expected one of {SLOTS}")
    s = settings
    stages: list[Stage] = [*extra.get("zero_drift", ())]
    stages.append(functools.partial(structure_matrix_stage, rig=rig))
    stages.append(
        functools.partial(
            weight_model_stage,
            rig=rig,
            prior_mass_rel_sd=s.prior_mass_rel_sd,
            prior_com_sd_m=s.prior_com_sd_m,
            model=weight_model,
            fit=s.fit_weight_model,
        )
    )
    stages.append(
        functools.partial(
            weight_tare,
            rig=rig,
            position_tol_m=s.tare_position_tol_m,
            angle_tol_rad=s.tare_angle_tol_rad,
            allow_nominal_weight=s.allow_nominal_weight,
            prior_mass_rel_sd=s.prior_mass_rel_sd,
            prior_com_sd_m=s.prior_com_sd_m,
            tare_shares_pose=s.tare_shares_pose,
        )
    )
    stages += extra.get("windage", ())
    stages += extra.get("inertia", ())
    stages.append(
        functools.partial(balance_interaction, interaction=interaction, second_order=second_order)
    )
    if geometry is not None:
        stages.append(functools.partial(axes_and_moments, geometry=geometry))
        stages += extra.get("wall_corrections", ())
        stages.append(
            functools.partial(coefficients, geometry=geometry, wind_off_mps=s.wind_off_mps)
        )
    stages.append(
        functools.partial(tension_check, rig=rig, method=s.method, limit_N=s.check_limit_N)
    )
    return stages


def reduce_points(points: Points, stages: list[Stage]) -> Points:
    """Run the stages (see :func:`cdpr.analysis.reduction.run_stages`)."""
    return run_stages(points, stages)


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
        cols[c] = p["pose"][:, k]
    for k, c in enumerate(POSE_COLUMNS):
        cols[f"sd_{c}"] = _sd(p["pose_cov"])[:, k]
    cols["airspeed_mps"] = p["airspeed_mps"]
    cols["density_kgpm3"] = p["density_kgpm3"]
    cols["q_Pa"] = p.arrays.get("q_Pa", np.full(s, np.nan))
    cols["aoa_rad"] = p.arrays.get("aoa_rad", np.full(s, np.nan))
    cols["sideslip_rad"] = p.arrays.get("sideslip_rad", np.full(s, np.nan))
    cols["tare_point"] = [labels[j] if j >= 0 else "" for j in p["tare_index"]]
    at_mrp = "wrench_mrp_N" in p.arrays
    W = p["wrench_mrp_N"] if at_mrp else p["wrench_N"]
    sd = _sd(p["wrench_mrp_cov"] if at_mrp else p.wrench_cov)
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
    for k, name in enumerate(rig.cable_names):
        cols[f"T_{name}_N"] = p["tension_N"][:, k]
        cols[f"sd_T_{name}_N"] = np.sqrt(np.clip(p["tension_cov_N2"][:, k, k], 0.0, None))
        cols[f"dT_{name}_N"] = p["check_dT_N"][:, k]
    cols["check_max_abs_dT_N"] = p["check_max_abs_dT_N"]
    cols.update(columns_after or {})
    return pd.DataFrame(cols)


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
