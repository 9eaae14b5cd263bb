"""The stages of the systematic uncertainty and the expanded U95 (issue 21 item 5), for the core.

Each is a thin ``@stage`` wrapper around one public function of :mod:`cdpr.analysis.systematic`.
Their places in :data:`cdpr.analysis.stages.STEADY_STAGES`:

- ``systematic`` right after ``inertia`` (before ``balance_interaction``): it adds the σ terms
  ``loadcell_calibration``, ``rig_geometry`` and ``interaction_matrix`` of the *uncorrected* wrench
  (the one the balance calibration multiplies; the interaction term as its equivalent error there),
  so ``balance_interaction`` carries them with every other term.  Bind ``rig``, the load-cell
  calibration's :class:`~cdpr.analysis.systematic.LoadCellCalibrationSd` (from
  ``LoadCellCalibrationFile.sd_for_cables``; None flags ``loadcell_calibration_sd_not_given``), the
  balance calibration (``interaction``, ``second_order`` as ``balance_interaction`` gets them) and
  its fit covariance (``cdpr.pipelines.config.read_balance_fit``).
- ``flow_uncertainty`` right after ``coefficients``: the instruments' part of the coefficients
  (``coefficient_cov_flow``, ``q_rel_sd``).  Bind the test matrix's ``instruments``
  (``TestMatrix.instruments``; without a matrix the defaults, flagged).
- ``expanded_uncertainty`` last: ``u_random_*``, ``u_systematic_*``, ``U95_*``, ``k95_*`` and
  ``nu_eff_*`` for the reported wrench (at the MRP with a model geometry, else at P) and the
  coefficients.  Bind ``geometry``.  The random part's degrees of freedom per output come from
  the arrays ``dof_random_wrench`` and ``dof_random_coefficients`` (s, 6) when an earlier stage
  (the long-run estimate) put them there; without them ``inf`` and the flag
  ``random_dof_not_given``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .aero import ModelGeometry, coefficient_matrix, transfer_moment
from .conventions import COEFFICIENTS
from .reduction import POSE, WRENCH, Points, stage, with_updates
from .rig import Rig
from .rotations import rotation_from_euler
from .systematic import (
    BalanceFitCovariance,
    InstrumentAccuracy,
    LoadCellCalibrationSd,
    flow_coefficient_covariance,
    point_uncertainty,
    systematic_wrench_covariance,
)

FloatArray = NDArray[np.float64]


@stage("systematic", wraps=systematic_wrench_covariance)
def systematic_stage(
    p: Points,
    *,
    rig: Rig,
    loadcell: LoadCellCalibrationSd | None = None,
    balance_fit: BalanceFitCovariance | None = None,
    interaction: Any = None,
    second_order: Any = None,
) -> Points:
    """The systematic σ terms of each point's wrench
    (:func:`cdpr.analysis.systematic.systematic_wrench_covariance`): ``loadcell_calibration``,
    ``rig_geometry``, ``interaction_matrix`` (each (s, 6, 6)), their degrees of freedom in
    ``meta["systematic_dof"]``, and the flags ``rig_geometry_sd_default``,
    ``loadcell_calibration_sd_not_given``, ``loadcell_calibration_correlation_not_given``,
    ``interaction_matrix_sd_not_given``.  Runs before ``balance_interaction``."""
    tare = np.asarray(p.arrays.get("tare_index", np.full(p.n, -1)), dtype=np.int64)
    sw = systematic_wrench_covariance(
        rig,
        p[POSE],
        p["tension_N"],
        tare,
        p[WRENCH],
        loadcell,
        balance_fit,
        interaction,
        second_order,
    )
    dof = {**p.meta.get("systematic_dof", {}), **sw.dof}
    note = ", ".join(sw.terms) + (
        "; " + ", ".join(w for w, m in sw.flags.items() if m.any())
        if any(m.any() for m in sw.flags.values())
        else ""
    )
    return with_updates(
        p, terms=sw.terms, flag=sw.flags, meta={"systematic_dof": dof, "_note": note}
    )


@stage("flow_uncertainty", wraps=flow_coefficient_covariance)
def flow_uncertainty_stage(p: Points, *, instruments: InstrumentAccuracy) -> Points:
    """The tunnel instruments' part of the coefficients
    (:func:`cdpr.analysis.systematic.flow_coefficient_covariance`): ``coefficient_cov_flow``
    (s, 6, 6), ``q_rel_sd``, ``density_rel_sd``, ``airspeed_rel_sd`` (s,); flag
    ``tunnel_instrument_sd_default`` on the points with coefficients when a stated accuracy took
    its default (the note names which)."""
    s = p.n
    nan = np.full(s, np.nan)
    C = np.stack([p.arrays.get(c, nan) for c in COEFFICIENTS], axis=1)
    fu = flow_coefficient_covariance(
        C,
        p["airspeed_mps"],
        p["density_kgpm3"],
        np.asarray(p.arrays.get("static_pressure_Pa", nan), dtype=np.float64),
        np.asarray(p.arrays.get("temperature_K", nan), dtype=np.float64),
        np.asarray(p.arrays.get("relative_humidity", nan), dtype=np.float64),
        instruments,
    )
    have = np.isfinite(C).all(axis=1)
    defaulted = instruments.defaulted
    return with_updates(
        p,
        arrays={
            "coefficient_cov_flow": fu.cov,
            "q_rel_sd": np.where(have, fu.q_rel_sd, np.nan),
            "density_rel_sd": np.where(have, fu.density_rel_sd, np.nan),
            "airspeed_rel_sd": np.where(have, fu.airspeed_rel_sd, np.nan),
        },
        flag={"tunnel_instrument_sd_default": have & bool(defaulted)},
        meta={"_note": "defaults: " + ", ".join(defaulted) if defaulted else "all stated"},
    )


WRENCH_OUTPUTS = ("fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")


@stage("expanded_uncertainty", wraps=point_uncertainty)
def expanded_uncertainty_stage(
    p: Points, *, geometry: ModelGeometry | None, level: float = 0.95
) -> Points:
    """Random and systematic parts and the expanded uncertainty
    (:func:`cdpr.analysis.systematic.point_uncertainty`) of the reported wrench (at the MRP when
    ``wrench_mrp_O_N_Nm`` is there, else at P) and of the coefficients: arrays
    ``u_random_wrench``, ``u_systematic_wrench``, ``U95_wrench``, ``k95_wrench``,
    ``nu_eff_wrench`` and the same with ``_coefficients`` (s, 6) each (``95``: the level in %)."""
    s = p.n
    tag = f"{100 * level:g}"
    q = np.nan_to_num(p[POSE])
    R = rotation_from_euler(q[:, 3:])
    transfer = None
    if geometry is not None and "wrench_mrp_O_N_Nm" in p.arrays:
        r = R @ np.asarray(geometry.mrp_P_m, dtype=np.float64)  # (s, 3) P -> MRP in {O}
        transfer = np.swapaxes(transfer_moment(np.eye(6)[None], r[:, None, :]), 1, 2)
    nu_w = p.arrays.get("dof_random_wrench")
    nu_c = p.arrays.get("dof_random_coefficients")
    dof = p.meta.get("systematic_dof", {})
    bw = point_uncertainty(p.cov_terms, dof, nu_w, transfer, None, level)
    out: dict[str, Any] = {
        "u_random_wrench": bw.u_random,
        "u_systematic_wrench": bw.u_systematic,
        f"U{tag}_wrench": bw.U,
        f"k{tag}_wrench": bw.k,
        "nu_eff_wrench": bw.nu_eff,
    }
    nan6 = np.full((s, 6), np.nan)
    cols = {k: nan6.copy() for k in ("u_r", "u_s", "U", "k", "nu")}
    C = np.stack([p.arrays.get(c, np.full(s, np.nan)) for c in COEFFICIENTS], axis=1)
    qPa = np.asarray(p.arrays.get("q_Pa", np.full(s, np.nan)), dtype=np.float64)
    use = np.isfinite(C).all(axis=1) & np.isfinite(qPa) & (qPa > 0)
    if geometry is not None and use.any():
        g = geometry
        Kc = coefficient_matrix(
            R[use], qPa[use], g.area_m2, g.span_m, g.chord_m, g.mrp_P_m, g.nose_P, g.up_P
        )
        flow = p.arrays.get("coefficient_cov_flow")
        bc = point_uncertainty(
            {k: v[use] for k, v in p.cov_terms.items()},
            dof,
            None if nu_c is None else np.asarray(nu_c)[use],
            Kc,
            None if flow is None else np.asarray(flow)[use],
            level,
        )
        for key, v in zip(cols, (bc.u_random, bc.u_systematic, bc.U, bc.k, bc.nu_eff), strict=True):
            cols[key][use] = v
    out.update(
        {
            "u_random_coefficients": cols["u_r"],
            "u_systematic_coefficients": cols["u_s"],
            f"U{tag}_coefficients": cols["U"],
            f"k{tag}_coefficients": cols["k"],
            "nu_eff_coefficients": cols["nu"],
        }
    )
    has_w = np.isfinite(p[WRENCH]).all(axis=1)
    missing = (nu_w is None) or (use.any() and nu_c is None)
    return with_updates(
        p,
        arrays=out,
        flag={"random_dof_not_given": has_w & missing},
        meta={"_note": f"level {level:g}" + ("; random dof not given: inf" if missing else "")},
    )
