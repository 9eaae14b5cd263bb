"""A controller's cable-length log as the run's pose source (``cdpr import --cable-lengths``).

Where a rig's controller logs its cable lengths (motor encoders), forward kinematics gives the
platform pose at the controller's rate (:func:`cdpr.analysis.motion.forward_kinematics`: the
weighted least squares of the lengths, with its covariance from the lengths' σ).  The log is a CSV
with a time column, ``t_ns`` (ns since the Unix epoch, the controller's clock) or ``t_s`` (seconds
from the first CAN frame), and one column ``L_<cable>_m`` per cable of the rig file (the length
from the platform's attachment point to the anchor, m: the names ``cdpr plan`` writes); ``#``
lines are comments.  ``--length-sd-m`` gives the encoders' σ per length (one value, m; required:
there is no default σ).

Each row becomes a ``/pose`` message as a camera's (``position_O_m``, ``quaternion_xyzw``,
``euler_rad``, ``covariance`` 6x6 row-major in ``[position_O_m, rotation vector in {O}]``: the
least squares' covariance with ``dtheta = H dpsi``), with ``status`` 8 (a bad frame: the
analysis drops it) where the least squares did not converge or its chi-square is beyond the
point its distribution passes once in a million frames (a length that jumped), and the ``chi2``
of the fit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.motion import forward_kinematics
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import euler_rate_matrix, quaternion_from_euler

from .config import read_table
from .import_tables import table_times

CHUNK = 20_000
"""Rows solved at once (bounds the least squares' temporaries)."""

STATUS_BAD_FRAME = 8
"""The status of a pose the analysis drops (:data:`cdpr.analysis.conventions.STATUS_BAD_FRAME`)."""


@dataclass(frozen=True)
class LengthPoses:
    """Poses from a cable-length log: time column and values (as the CSV gives them), poses
    (n, 6), covariance (n, 6, 6) in ``[position, rotation vector in {O}]``, chi2 (n,), status
    (n,) (0, or 8 where the fit failed), the σ used."""

    path: str
    time_column: str
    times: NDArray[Any]
    poses: NDArray[np.float64]
    covariance: NDArray[np.float64]
    chi2: NDArray[np.float64]
    status: NDArray[np.int64]
    length_sd_m: float


def read_cable_lengths(path: str, rig: Rig, length_sd_m: float | None) -> LengthPoses:
    """The log's poses by forward kinematics (module docstring); a bad file or σ is one
    ``ConfigError`` naming the file, row and column, before anything is written."""
    if length_sd_m is None:
        raise ConfigError(path, "--length-sd-m", "missing: the encoders' σ per length (m)")
    sd = float(length_sd_m)
    if not (np.isfinite(sd) and sd > 0):
        raise ConfigError(path, "--length-sd-m", f"expected a σ > 0 m, got {length_sd_m}")
    cols = [f"L_{c}_m" for c in rig.cable_names]
    df = read_table(path, cols, "cable-length log")
    tcol, tv = table_times(path, df)
    L = np.empty((len(df), rig.n_cables))
    for j, c in enumerate(cols):
        v = np.asarray(df[c], dtype=np.float64)
        bad = np.flatnonzero(~(np.isfinite(v) & (v > 0)))
        if bad.size:
            raise ConfigError(
                path,
                f"row {int(bad[0]) + 2}, column {c}",
                f"expected a length > 0 m, got {v[bad[0]]}",
            )
        L[:, j] = v
    if len(df) == 0:
        raise ConfigError(path, "", "no rows")
    q0 = np.concatenate([rig.reference_position_O_m, np.zeros(3)])
    n = len(df)
    poses = np.empty((n, 6))
    cov = np.empty((n, 6, 6))
    chi2 = np.empty(n)
    conv = np.empty(n, bool)
    start = q0
    for a in range(0, n, CHUNK):  # chunks, not samples (each one batched)
        fk = forward_kinematics(rig.anchors_O_m, rig.attach_P_m, L[a : a + CHUNK], sd, start)
        poses[a : a + CHUNK], cov[a : a + CHUNK] = fk.pose, fk.covariance
        chi2[a : a + CHUNK], conv[a : a + CHUNK] = fk.chi2, fk.converged
        start = fk.pose[-1]
    # the camera's convention: [position, rotation vector in {O}], dtheta = H dpsi
    H = euler_rate_matrix(poses[:, 3:])
    J = np.zeros((n, 6, 6))
    J[:, :3, :3] = np.eye(3)
    J[:, 3:, 3:] = H
    cov_rv = J @ cov @ np.swapaxes(J, 1, 2)
    from scipy.stats import chi2 as chi2_dist  # only here: importing scipy.stats is slow

    limit = float(chi2_dist.isf(1e-6, rig.n_cables - 6))
    status = np.where(conv & (chi2 <= limit), 0, STATUS_BAD_FRAME).astype(np.int64)
    return LengthPoses(path, tcol, tv, poses, cov_rv, chi2, status, sd)


def pose_readings(lp: LengthPoses, t_ns: NDArray[np.int64]) -> tuple[Any, list[Any]]:
    """The ``/pose`` stream description and its readings (one per row)."""
    from cdpr.daq.source import FieldDescription, Reading, StreamDescription

    desc = StreamDescription(
        {
            "position_O_m": FieldDescription("m", shape=(3,)),
            "quaternion_xyzw": FieldDescription("", shape=(4,)),
            "euler_rad": FieldDescription("rad", shape=(3,)),
            "covariance": FieldDescription("m, rad (6x6 row-major)", shape=(36,)),
            "chi2": FieldDescription(""),
        },
        0.0,
        "Platform pose from the controller's cable lengths (forward kinematics), P in {O}; "
        "covariance order [position_O_m, rotation vector in {O}].",
    )
    q = quaternion_from_euler(lp.poses[:, 3:])
    xyzw = np.concatenate([q[:, 1:], q[:, :1]], axis=1)
    pos, eul = lp.poses[:, :3].tolist(), lp.poses[:, 3:].tolist()
    quat, cov = xyzw.tolist(), lp.covariance.reshape(len(t_ns), 36).tolist()
    readings = [
        Reading(
            "pose",
            int(t),
            {
                "position_O_m": p,
                "quaternion_xyzw": qq,
                "euler_rad": e,
                "covariance": c,
                "chi2": float(x),
                "frame_id": "O",
            },  # fmt: skip
            int(st),
        )
        for t, p, qq, e, c, x, st in zip(
            t_ns.tolist(), pos, quat, eul, cov, lp.chi2.tolist(), lp.status.tolist(), strict=True
        )
    ]
    return desc, readings
