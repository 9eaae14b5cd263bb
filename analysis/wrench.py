"""Recovery of the external (aerodynamic) wrench from measured cable tensions and pose (paper eq. 4-7).

The equation of motion of the platform (Newton–Euler about P, see :mod:`cdpr.analysis.dynamics`)::

    A(q) T + G + W_ext = M qdd + C

with ``A`` (..., 6, m) the structure matrix at the measured pose, ``T`` (..., m) the cable tensions
(N), ``G`` the gravity load and ``M qdd + C`` the platform's mass times its acceleration (inertia,
centrifugal and Coriolis terms).  At rest this is the paper's eq. (5)-(6), ``A T = -(G + W_ext)``.
The paper's eq. (4) prints the inertia on the load side, ``A T = -(M qdd + C + G + W_ext)``: with its
own G (the gravity force) and A (unit vectors towards the anchors, the cables pulling), that sign
contradicts Newton's second law (a platform accelerated by the cables alone would then need a
negative mass), so the code follows Newton–Euler, checked against the momentum of an independent
rigid body in ``tests/test_lab_generator.py``.  Every wrench here is the
load *on the platform* at its reference point P, components in {O} axes (x downstream, z up), order
``[Fx, Fy, Fz, Mx, My, Mz]`` in N and N m, moments about P.

Two methods recover ``W_ext``:

- **tare** (paper eq. 7): wind-off tensions ``T0`` measured at the same pose give ``A T0 = -G``, so
  ``W_ext = A (T0 - Tw)``.  Needs no mass model; errors in ``A`` scale with ``T0 - Tw`` only.
- **absolute**: ``W_ext = -A Tw - G`` from the mass model (mass, centre of mass, gravity).

When the platform moves, the inertia wrench ``D = M qdd + C`` (from the pose time series,
:func:`inertia_wrench_from_poses`) is added back: ``W_ext = A (T0 - Tw) + D`` (tare taken static) or
``W_ext = -A Tw - G + D``: what the cables and gravity do not supply of the platform's ``m a``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .dynamics import finite_difference, gravity_wrench, inertia_wrench, weight_basis
from .errors import InputError
from .kinematics import structure_matrix
from .rig import Rig
from .rotations import rotation_from_euler

FloatArray = NDArray[np.float64]

METHODS: tuple[str, ...] = ("tare", "absolute")
"""Names of the wrench-recovery methods."""


def _check_A_T(A: ArrayLike, T: ArrayLike, name_T: str) -> tuple[FloatArray, FloatArray]:
    a = as_float_array(A, "A")
    if a.ndim < 2 or a.shape[-2] != 6:
        raise InputError(f"A: expected shape (..., 6, m), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError("A: expected finite values, got NaN or inf")
    t = check_trailing(T, name_T, (a.shape[-1],))
    return a, t


def wrench_tare(
    A: ArrayLike, tensions_wind_on_N: ArrayLike, tensions_wind_off_N: ArrayLike
) -> FloatArray:
    """Tare method (paper eq. 7): ``W_ext = A (T0 - Tw)`` (..., 6), N and N m at P in {O} axes.

    A: (..., 6, m) structure matrix at the measured pose.
    tensions_wind_on_N: (..., m) tensions Tw with the load applied, N.
    tensions_wind_off_N: (..., m) tensions T0 measured wind-off at the same pose, N.
    """
    a, tw = _check_A_T(A, tensions_wind_on_N, "tensions_wind_on_N")
    t0 = check_trailing(tensions_wind_off_N, "tensions_wind_off_N", (a.shape[-1],))
    return np.einsum("...ij,...j->...i", a, t0 - tw)


def wrench_absolute(
    A: ArrayLike,
    tensions_N: ArrayLike,
    gravity_wrench_N: ArrayLike,
    inertia_wrench_N: ArrayLike | None = None,
) -> FloatArray:
    """Absolute method: ``W_ext = -A T - G [+ (M qdd + C)]`` (..., 6) at P in {O} axes.

    A: (..., 6, m) structure matrix; tensions_N: (..., m) measured tensions, N;
    gravity_wrench_N: (..., 6) gravity load G on the platform (see
    :func:`cdpr.analysis.dynamics.gravity_wrench`); inertia_wrench_N: optional (..., 6) ``M qdd + C``
    (see :func:`inertia_wrench_from_poses`), omitted for a static platform.
    """
    a, t = _check_A_T(A, tensions_N, "tensions_N")
    g = check_trailing(gravity_wrench_N, "gravity_wrench_N", (6,))
    w = -np.einsum("...ij,...j->...i", a, t) - g
    if inertia_wrench_N is not None:
        w = w + check_trailing(inertia_wrench_N, "inertia_wrench_N", (6,))
    return w


def pose_derivatives(poses: ArrayLike, t_ns: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """First and second time derivatives ``(qd, qdd)`` (n, 6) each of a pose time series.

    poses: (n, 6) ``[x, y, z, roll, pitch, yaw]`` (m, rad) sampled at integer-nanosecond times
    t_ns (n,), strictly increasing, n >= 3.  The Euler angles are unwrapped, then differentiated
    twice with :func:`cdpr.analysis.dynamics.finite_difference` (second-order central differences,
    one-sided at the ends, so the first and last samples are the least accurate; noise in the
    poses is amplified twice: fit a smooth motion first where there is one).
    """
    q = check_trailing(poses, "poses", (6,))
    if q.ndim != 2:
        raise InputError(f"poses: expected shape (n, 6), got {q.shape}")
    q = q.copy()
    q[:, 3:] = np.unwrap(q[:, 3:], axis=0)
    qd = finite_difference(q, t_ns)
    return qd, finite_difference(qd, t_ns)


def inertia_wrench_from_poses(
    mass_kg: float,
    com_P_m: ArrayLike,
    inertia_P_kgm2: ArrayLike,
    poses: ArrayLike,
    t_ns: ArrayLike,
) -> FloatArray:
    """Inertia plus Coriolis wrench ``M qdd + C`` (n, 6) at P in {O} axes from a pose time series
    (its derivatives by :func:`pose_derivatives`)."""
    qd, qdd = pose_derivatives(poses, t_ns)
    return inertia_wrench(mass_kg, com_P_m, inertia_P_kgm2, poses, qd, qdd)


def recover_wrench(
    rig: Rig,
    poses: ArrayLike,
    tensions_N: ArrayLike,
    tare_tensions_N: ArrayLike | None = None,
    inertia_wrench_N: ArrayLike | None = None,
    weight_theta: ArrayLike | None = None,
) -> FloatArray:
    """External wrench ``W_ext`` (..., 6) on the platform at P in {O} axes (N, N m) for a rig.

    poses: (..., 6) measured poses ``[x, y, z, roll, pitch, yaw]`` (m, rad).
    tensions_N: (..., m) measured tensions, N.
    tare_tensions_N: optional (..., m) wind-off tensions at the same poses: tare method
        ``A (T0 - Tw)``; without it the absolute method ``-A Tw - G``.
    inertia_wrench_N: optional (..., 6) ``M qdd + C`` of a moving platform, added in either method
        (Newton–Euler: the cables and gravity supply ``M qdd + C - W_ext``).
    weight_theta: optional (4,) ``[m, m c_x, m c_y, m c_z]`` (kg, kg m; c in {P}), a fitted weight
        (:mod:`cdpr.analysis.weight`): ``G = B(q) theta`` (:func:`~cdpr.analysis.dynamics.weight_basis`);
        None: the rig file's mass and centre of mass.  Absolute method only.
    """
    q = check_trailing(poses, "poses", (6,))
    R = rotation_from_euler(q[..., 3:])
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, q[..., :3], R)
    if tare_tensions_N is not None:
        w = wrench_tare(A, tensions_N, tare_tensions_N)
        if inertia_wrench_N is not None:
            w = w + check_trailing(inertia_wrench_N, "inertia_wrench_N", (6,))
        return w
    if weight_theta is None:
        G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    else:
        G = weight_basis(q, rig.gravity_O_mps2) @ check_trailing(weight_theta, "weight_theta", (4,))
    return wrench_absolute(A, tensions_N, G, inertia_wrench_N)
