"""The dynamic order's inputs straight from a lab case's files (no ``cdpr import``): the decoded
candump, the pose CSV, the tunnel and events CSVs, as :class:`cdpr.analysis.reduction.Points` and
:class:`cdpr.analysis.dynamic_stages.DynamicSamples` (for the core's own tests)."""

from __future__ import annotations

import tomllib
from typing import Any

import lab_generator as lg
import numpy as np
import pandas as pd

from cdpr.analysis.balance import points_from_events, sample_mask
from cdpr.analysis.dynamic_stages import DynamicSamples
from cdpr.analysis.flow import air_density
from cdpr.analysis.point_inputs import points_from_samples
from cdpr.analysis.reduction import Points, with_updates


def lab_samples(case: lg.LabCase) -> tuple[np.ndarray, ...]:
    """The case's load cells (times, tensions by its calibration) and camera (times, poses,
    covariance (k, 6, 6)), decoded by the generator's own reader."""
    f = case.files
    cal = tomllib.loads(f["calibration"].read_text())["calibration"]
    t_ns, counts = lg.read_candump(f["can_log"])
    T = (counts - np.array(cal["offset_counts"])) * np.array(cal["gain_N_per_count"])
    poses = pd.read_csv(f["poses"])
    tp = poses["t_ns"].to_numpy(np.int64)
    q = poses[list(lg.POSE_COLUMNS)].to_numpy()
    cov = poses[list(lg.COV_COLUMNS)].to_numpy().reshape(-1, 6, 6)
    return t_ns, T, tp, q, cov


def dynamic_inputs(case: lg.LabCase) -> tuple[Points, DynamicSamples, list[str]]:
    """Points (every point of the case, zeros included), the samples, the labels."""
    f = case.files
    t_ns, T, tp, q, cov = lab_samples(case)
    tun = pd.read_csv(f["tunnel"])
    tt = tun["t_ns"].to_numpy(np.int64)
    V = np.interp(t_ns, tt, tun["airspeed_mps"].to_numpy())
    rho_t = air_density(tun["static_pressure_Pa"].to_numpy(), tun["temperature_K"].to_numpy())
    rho = np.interp(t_ns, tt, rho_t)
    ev = pd.read_csv(f["events"], keep_default_na=False)
    start = ev[ev["phase"] == "start"].reset_index(drop=True)
    end = ev[ev["phase"] == "end"].set_index("point")
    labels = list(start["point"])
    ranges = points_from_events(
        t_ns, start["t_ns"].to_numpy(np.int64), end.loc[labels, "t_ns"].to_numpy(np.int64)
    )
    bits = sample_mask(T)
    pts, _ = points_from_samples(
        kind=list(start["kind"]), ranges=ranges, t_ns=t_ns, tensions_N=T, mask_bits=bits,
        airspeed_mps=V, density_kgpm3=rho, pose_t_ns=tp, poses=q, pose_cov=cov,
    )  # fmt: skip

    def num(c: str) -> np.ndarray:
        return pd.to_numeric(start[c], errors="coerce").to_numpy(np.float64)

    index = {lab: i for i, lab in enumerate(labels)}
    arrays: dict[str, Any] = {
        "motion_axis": start["motion_axis"].astype(str).to_numpy(),
        "motion_amplitude": num("motion_amplitude"),
        "motion_frequency_Hz": num("motion_frequency_Hz"),
        "motion_cycles": num("motion_cycles"),
        "motion_settling_cycles": num("motion_settling_cycles"),
        "inertia_tare_index": np.array([index.get(str(x), -1) for x in start["inertia_tare"]]),
    }
    samples = DynamicSamples(
        t_ns, T, bits == 0, ranges, tp, q, np.diagonal(cov, axis1=1, axis2=2).copy(),
        np.ones(len(tp), bool),
    )  # fmt: skip
    return with_updates(pts, arrays=arrays), samples, labels
