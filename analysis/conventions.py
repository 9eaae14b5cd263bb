"""Conventions of the whole project, defined once.

- SI units everywhere inside; time as integer nanoseconds (``t_ns``).
- Wrench order ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N·m); moments about the platform reference point P,
  components in {O} axes unless a name says otherwise.
- Frame {O}: fixed to the tunnel, x downstream along the tunnel axis, y to the left looking
  downstream, z up.  Frame {P}: fixed to the platform at its reference point P.
- Pose ``q = (p, psi)``: ``p`` the position of P in {O} (m); ``psi = (roll, pitch, yaw)`` Z-Y-X
  Euler angles (rad): roll about x, pitch about y, yaw about z, with
  ``R_O_P = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (the paper's alpha, beta, gamma; "alpha" is never the
  angle of attack here: that is ``aoa``, the sideslip ``sideslip``).
- Quaternions are ``[w, x, y, z]`` (scalar first), unit norm, ``w >= 0``.
- Cable i: ``l_i = b_i - p - R pp_i`` (from the platform point to the anchor), ``u_i = l_i/|l_i|``,
  ``r_i = R pp_i``, column ``a_i = [u_i; r_i x u_i]`` of the structure matrix ``A`` (6 x m).
- Equation of motion (Newton–Euler about P): ``A T + G + W_ext = M qdd + C`` with
  ``G = [m g; (R c) x m g]``; at rest ``A T = -(G + W_ext)`` (the paper's eq. 5-6; its eq. 4
  prints the inertia with the other sign, see :mod:`cdpr.analysis.wrench`).
"""

from __future__ import annotations

from typing import overload

import numpy as np

WRENCH_NAMES: tuple[str, ...] = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
"""Component names in wrench order."""

WRENCH_UNITS: tuple[str, ...] = ("N", "N", "N", "N*m", "N*m", "N*m")
"""Units of the wrench components, in wrench order."""

WRENCH_COLUMNS: tuple[str, ...] = ("fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")
"""Column names used in CSV and HDF5 tables for a wrench, in wrench order."""

POSE_COLUMNS: tuple[str, ...] = ("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")
"""Column names of a pose (position of P in {O}, Z-Y-X Euler angles roll, pitch, yaw)."""

STANDARD_GRAVITY_MPS2: float = 9.80665
"""Standard gravity (m/s^2)."""

GRAVITY_O_MPS2 = np.array([0.0, 0.0, -STANDARD_GRAVITY_MPS2])
"""Default gravity vector in {O} (z up), m/s^2."""

NS_PER_S: int = 1_000_000_000
"""Nanoseconds per second."""

# --------------------------------------------------------------------------------------------
# Status words: one owner.  A reading's ``status`` (every stream) is a bit field of STATUS_*; the
# analysis adds its own MASK_* bits on the samples it cannot use.  No two bits share a value (a
# test checks it), so a word never stands for another by accident.
# --------------------------------------------------------------------------------------------
STATUS_OK: int = 0
STATUS_SATURATED: int = 1 << 0
"""A load cell at the end of its range."""
STATUS_SLACK: int = 1 << 1
"""A cable below its slack threshold."""
STATUS_STALE: int = 1 << 2
"""The sample repeats an old value (no new frame from the sensor)."""
STATUS_BAD_FRAME: int = 1 << 3
"""A frame that could not be decoded (wrong length, checksum, field out of range)."""
STATUS_GAP: int = 1 << 4
"""Samples were lost before this one (a counter jump or a missing frame)."""
STATUS_SENSOR_FAULT: int = 1 << 5
"""The sensor reports a fault of its own."""

STATUS_NAMES: dict[int, str] = {
    STATUS_SATURATED: "saturated",
    STATUS_SLACK: "slack",
    STATUS_STALE: "stale",
    STATUS_BAD_FRAME: "bad_frame",
    STATUS_GAP: "gap",
    STATUS_SENSOR_FAULT: "sensor_fault",
}
"""The flag word of every status bit."""

STATUS_ALL: int = 0
for _bit in STATUS_NAMES:
    STATUS_ALL |= _bit

CHANNEL_STATUS_SATURATED: int = 1
CHANNEL_STATUS_SLACK: int = 2
CHANNEL_STATUS_FAULT: int = 4
CHANNEL_TO_STATUS: tuple[tuple[int, int], ...] = (
    (CHANNEL_STATUS_SATURATED, STATUS_SATURATED),
    (CHANNEL_STATUS_SLACK, STATUS_SLACK),
    (CHANNEL_STATUS_FAULT, STATUS_SENSOR_FAULT),
)
"""A load cell's own channel status (the ``status_<cable>`` field of ``/tensions``: the DBC's
``ChN_Saturated``/``ChN_Slack``/``ChN_Fault`` signals, or the serial line's three bits per cell) is a
different, smaller vocabulary: each of its bits maps to one STATUS_* bit here and only here."""


@overload
def status_from_channel_bits(channel_bits: int) -> int: ...
@overload
def status_from_channel_bits(channel_bits: np.ndarray) -> np.ndarray: ...
def status_from_channel_bits(channel_bits: int | np.ndarray) -> int | np.ndarray:
    """STATUS_* bits from load-cell channel status bits: an int for an int (the per-frame path,
    no numpy round trip), else an int64 array of the same shape."""
    if isinstance(channel_bits, int):
        return sum(status for bit, status in CHANNEL_TO_STATUS if channel_bits & bit)
    c = np.asarray(channel_bits).astype(np.int64)
    out = np.zeros(c.shape, np.int64)
    for bit, status in CHANNEL_TO_STATUS:
        out |= np.where(c & bit, status, 0)
    return out


MASK_NAN: int = 1 << 8
"""Analysis mask: a NaN or inf in the sample."""
MASK_COUNTER_GAP: int = 1 << 9
"""Analysis mask: the sample counter jumped before this sample."""
MASK_POSE: int = 1 << 10
"""Analysis mask: a flagged camera frame."""

MASK_NAMES: dict[int, str] = {
    **STATUS_NAMES,
    MASK_NAN: "nan",
    MASK_COUNTER_GAP: "counter_gap",
    MASK_POSE: "pose_flagged",
}
"""Name of every bit a sample mask can carry (the flag words of the per-point table)."""

# --------------------------------------------------------------------------------------------
# Names of things the reduction produces and the test matrix uses
# --------------------------------------------------------------------------------------------
COEFFICIENTS: tuple[str, ...] = ("CD", "CY", "CL", "Cl", "Cm", "Cn")
"""The six aerodynamic coefficients, in this order: wind-axis forces on ``q S`` (drag, side force,
lift) and body-axis moments about the MRP (roll and yaw on ``q S b``, pitch on ``q S c``)."""

STEADY_POINT_KINDS: tuple[str, ...] = ("wind_on", "tare", "zero", "windage")
"""Kinds of a steady test point: wind on; wind-off weight tare; wind-off zero (level, for the zero
drift); model-off wind-on windage tare."""

OSCILLATION_POINT_KINDS: tuple[str, ...] = ("oscillation", "oscillation_tare")
"""Kinds of a forced-oscillation test point (issue 22): wind on, and its wind-off inertia tare
(the same motion wind off; docs/dynamic_tests.md)."""

POINT_KINDS: tuple[str, ...] = STEADY_POINT_KINDS + OSCILLATION_POINT_KINDS
"""Every test-point kind a test matrix, a schedule and the test-point events may name."""

WIND_OFF_KINDS: tuple[str, ...] = ("tare", "zero")
"""Point kinds taken wind-off at rest: they feed the weight model and serve as tares (an
``oscillation_tare`` is wind off too, but moves: the inertia tare of the oscillation points)."""

TENSION_METHODS: tuple[str, ...] = ("closed-form", "improved-closed-form", "penalty", "exact")
"""Names of the tension-distribution methods (:data:`cdpr.analysis.tension.METHODS` has one entry
per name, in this order)."""
