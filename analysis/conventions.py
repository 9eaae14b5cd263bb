"""Conventions of the whole project, defined once.

- SI units everywhere inside; time as integer nanoseconds (``t_ns``).
- Wrench order ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N·m); moments about the platform reference point P,
  components in {O} axes unless a name says otherwise.
- Frame {O}: fixed to the tunnel, x downstream along the tunnel axis, y to the left looking
  downstream, z up.  Frame {P}: fixed to the platform at its reference point P.
- Pose ``q = (p, psi)``: ``p`` the position of P in {O} (m); ``psi = (alpha, beta, gamma)`` Z-Y-X Euler
  angles (rad): alpha roll about x, beta pitch about y, gamma yaw about z, with
  ``R_O_P = Rz(gamma) @ Ry(beta) @ Rx(alpha)``.
- Quaternions are ``[w, x, y, z]`` (scalar first), unit norm, ``w >= 0``.
- Cable i: ``l_i = b_i - p - R pp_i`` (from the platform point to the anchor), ``u_i = l_i/|l_i|``,
  ``r_i = R pp_i``, column ``a_i = [u_i; r_i x u_i]`` of the structure matrix ``A`` (6 x m).
- Statics: ``A T = -(G + W_ext)`` with ``G = [m g; (R c) x m g]``; a moving platform
  ``A T + G + W_ext = M qdd + C`` (Newton-Euler, :mod:`cdpr.analysis.dynamics`; the paper's eq. 4
  puts ``M qdd + C`` on the loads' side, which holds at rest only).
"""

from __future__ import annotations

import numpy as np

WRENCH_NAMES: tuple[str, ...] = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
"""Component names in wrench order."""

WRENCH_UNITS: tuple[str, ...] = ("N", "N", "N", "N*m", "N*m", "N*m")
"""Units of the wrench components, in wrench order."""

WRENCH_COLUMNS: tuple[str, ...] = ("fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")
"""Column names used in CSV and HDF5 tables for a wrench, in wrench order."""

POSE_COLUMNS: tuple[str, ...] = ("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")
"""Column names of a pose (position of P in {O}, Z-Y-X Euler angles alpha, beta, gamma)."""

STANDARD_GRAVITY_MPS2: float = 9.80665
"""Standard gravity (m/s^2)."""

GRAVITY_O_MPS2 = np.array([0.0, 0.0, -STANDARD_GRAVITY_MPS2])
"""Default gravity vector in {O} (z up), m/s^2."""

STEADY_POINT_KINDS: tuple[str, ...] = ("wind_on", "tare", "zero", "windage")
"""Test-point kinds of a platform held still: wind on, wind-off weight tare, level wind-off zero,
model-off windage (docs/campaign.md)."""

OSCILLATION_POINT_KINDS: tuple[str, ...] = ("oscillation", "oscillation_tare")
"""Test-point kinds of a forced oscillation (issue 22): wind on, and its wind-off inertia tare
(docs/dynamic_tests.md)."""

POINT_KINDS: tuple[str, ...] = STEADY_POINT_KINDS + OSCILLATION_POINT_KINDS
"""Every test-point kind a test matrix, a schedule and the test-point events may name."""

NS_PER_S: int = 1_000_000_000
"""Nanoseconds per second."""
