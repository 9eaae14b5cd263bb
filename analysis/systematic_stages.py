"""The stages of the systematic uncertainty (issue 21 item 5), for the core.

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
- ``flow_uncertainty`` right after ``coefficients`` (before ``uncertainty``): the instruments' part
  of the coefficients (``coefficient_cov_flow`` (s, 6, 6), ``q_rel_sd``).  Bind the test matrix's
  ``instruments`` (``TestMatrix.instruments``; without a matrix ``InstrumentAccuracy(defaulted=
  INSTRUMENT_KEYS)``, flagged).
- the ``uncertainty`` stage (:func:`cdpr.analysis.uncertainty.expanded_uncertainty`) then takes
  ``term_dof=p.meta.get("systematic_dof")`` (the fitted calibrations' degrees of freedom) and
  ``extra_systematic_u2`` = the wrench outputs' zeros beside the diagonal of
  ``coefficient_cov_flow`` (the coefficients' outputs).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .conventions import COEFFICIENTS
from .reduction import POSE, WRENCH, Points, stage, with_updates
from .rig import Rig
from .systematic import (
    BalanceFitCovariance,
    InstrumentAccuracy,
    LoadCellCalibrationSd,
    flow_coefficient_covariance,
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
