"""Force sensitivity of a cable robot (paper eq. 7 and 12), batched over rig configurations.

The paper's sensitivity of a rig at a pose, for an external wrench ``W_ext`` and a tension
distribution method, is

    S = sqrt(sum_i (dT_i / m)^2),   dT = T0 - Tw,

with ``T0`` the tensions that hold the platform against gravity alone (``A T0 = -G``, eq. 5) and
``Tw`` those that hold it against gravity plus the external wrench (``A Tw = -G - W_ext``, eq. 6),
both from the *same* method (:func:`cdpr.analysis.tension.distribute`); ``m`` is the number of cables.

This module computes S, and the metrics the paper lacks, for whole batches of configurations at
once:

- :func:`cubic_geometry` and :func:`flat_geometry` build the anchors, platform points and reference
  position of many cubic or flat rigs (the layouts of :mod:`cdpr.analysis.rigs`, same cable order)
  as arrays, without constructing a :class:`~cdpr.analysis.rig.Rig` per configuration;
- :func:`structure_matrices` gives ``A`` (..., 6, m) at the reference pose (identity orientation);
- :func:`sensitivity` gives S, dT, T0, Tw and the feasibility and singularity flags;
- :func:`singular_value_metrics`, :func:`wrench_std`, :func:`feasibility_margin` give the condition
  number, the smallest singular value, the bounds ``sigma_min <= |dW| / |dT| <= sigma_max`` (for dT
  in the row space of A), the wrench uncertainty from load-cell noise and the tension margin over a
  set of load cases;
- :func:`sensitivity_of_rig` is the single-configuration path (a :class:`Rig`, the kinematics module
  and the distribution), used as the reference the batched path is tested against.

Why S behaves as it does (used by the reproduction report): whenever no tension bound is active,
every method's answer is affine in the wrench with the same linear part, ``T = T_ref + A^+ (w - A
T_ref)``, so ``dT = A^+ W_ext`` and ``|W_ext| / sigma_max <= m S <= |W_ext| / sigma_min``.  S is
then a convex function of any parameter that enters W_ext linearly (a force's point of application)
and it grows without bound as A approaches a singular configuration if W_ext has a component along
the weak direction.  Only active bounds (for instance the penalty method, which pushes tensions
towards ``T_min``) make S a non-linear function of the load.

Units: tensions N, wrenches ``[Fx, Fy, Fz, Mx, My, Mz]`` in N and N m at P in {O} axes; the singular
values of A mix the two (a force column is dimensionless, a moment column is in m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .conventions import GRAVITY_O_MPS2
from .dynamics import gravity_wrench
from .errors import InputError
from .kinematics import structure_matrix
from .rig import Rig
from .rotations import rotation_from_euler
from .tension import METHODS, SOLVE_RANK_DEFICIENT, distribute

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

CUBIC_LAYOUTS: tuple[str, ...] = ("crossed", "cube")
"""Cable layouts of the cubic rig (see :mod:`cdpr.analysis.rigs`)."""

SINGULAR_RCOND = 1e-9
"""A configuration whose ``sigma_min / sigma_max`` is below this is treated as singular."""


@dataclass(frozen=True)
class RigGeometry:
    """The geometry of a batch of rigs at their reference pose (identity orientation).

    anchors_O_m: (..., m, 3) anchors b_i in {O}, m.
    attach_P_m: (..., m, 3) platform points pp_i in {P}, m.
    position_O_m: (..., 3) reference position of P in {O}, m.
    """

    anchors_O_m: FloatArray
    attach_P_m: FloatArray
    position_O_m: FloatArray

    @property
    def shape(self) -> tuple[int, ...]:
        """The batch shape (leading dimensions)."""
        return tuple(
            np.broadcast_shapes(
                self.anchors_O_m.shape[:-2],
                self.attach_P_m.shape[:-2],
                self.position_O_m.shape[:-1],
            )
        )


def _positive(value: ArrayLike, name: str) -> FloatArray:
    a = as_float_array(value, name)
    if not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise InputError(f"{name}: expected finite values > 0, got {np.ravel(a)[:3]}...")
    return a


# Corner signs in the cable order of rigs.cubic_rig: z (top first), then x, then y.
_CUBE_SIGNS = np.array(
    [(sx, sy, sz) for sz in (1, -1) for sx in (1, -1) for sy in (1, -1)], dtype=np.float64
)


def cubic_geometry(
    k1: ArrayLike,
    k2: ArrayLike,
    k3: ArrayLike,
    *,
    L_m: float = 2.0,
    W_m: float = 1.2,
    H_m: float = 1.4,
    Z_m: ArrayLike | None = None,
    layout: str = "crossed",
) -> RigGeometry:
    """Geometry of many cubic rigs (paper Fig. 3), broadcast over ``k1, k2, k3, Z_m``.

    k1 = l/L, k2 = w/W, k3 = h/H: platform-to-frame ratios, each in (0, 1); ``Z_m`` the height of P
    (default H/2), the platform (k3 H high) must fit between floor and top.  Same layout, cable
    order and assumptions as :func:`cdpr.analysis.rigs.cubic_rig`.  Returns arrays with the
    broadcast shape of the inputs as leading dimensions.
    """
    if layout not in CUBIC_LAYOUTS:
        raise InputError(f"layout: expected one of {CUBIC_LAYOUTS}, got {layout!r}")
    for name, v in (("L_m", L_m), ("W_m", W_m), ("H_m", H_m)):
        _positive(v, name)
    ks = []
    for name, k in (("k1", k1), ("k2", k2), ("k3", k3)):
        a = as_float_array(k, name)
        if not np.all(np.isfinite(a)) or np.any((a <= 0) | (a >= 1)):
            bad = np.ravel(a)[~((np.ravel(a) > 0) & (np.ravel(a) < 1))]
            raise InputError(f"{name}: expected 0 < {name} < 1, got {bad[:3]}")
        ks.append(a)
    Z = as_float_array(0.5 * H_m if Z_m is None else Z_m, "Z_m")
    shape = np.broadcast_shapes(ks[0].shape, ks[1].shape, ks[2].shape, Z.shape)
    k1a, k2a, k3a, Za = (np.broadcast_to(a, shape) for a in (*ks, Z))
    half_h = 0.5 * k3a * H_m
    if not np.all(np.isfinite(Za)) or np.any(Za - half_h <= 0) or np.any(Za + half_h >= H_m):
        raise InputError(
            f"Z_m: expected k3 H / 2 < Z_m < H_m - k3 H / 2 (platform inside the frame, H_m = {H_m})"
        )
    sx, sy, sz = _CUBE_SIGNS.T
    ay = np.where((sz < 0) & (layout == "crossed"), -sy, sy)
    anchors = np.stack([sx * L_m / 2, ay * W_m / 2, np.where(sz > 0, H_m, 0.0)], axis=-1)
    half = np.stack([k1a * L_m / 2, k2a * W_m / 2, half_h], axis=-1)  # (..., 3)
    attach = half[..., None, :] * _CUBE_SIGNS  # (..., 8, 3)
    position = np.stack([np.zeros(shape), np.zeros(shape), Za], axis=-1)
    return RigGeometry(np.broadcast_to(anchors, shape + (8, 3)), attach, position)


def flat_geometry(
    K21: ArrayLike,
    K22: ArrayLike,
    H_m: ArrayLike,
    X_m: ArrayLike = 0.5,
    *,
    L_m: float = 1.0,
    l_m: float = 0.03,
    w1_m: float = 0.01,
    w2_m: float = 0.04,
) -> RigGeometry:
    """Geometry of many flat rigs (paper Fig. 4, Table 3), broadcast over ``K21, K22, H_m, X_m``.

    Front base width K21 w1, back base width K22 w2 (both > 1), frame height ``H_m`` > 0, P at
    (X, 0, H/2) with 0 < X - l/2 and X + l/2 < L.  Same layout, cable order and assumptions as
    :func:`cdpr.analysis.rigs.flat_rig`.
    """
    for name, v in (("L_m", L_m), ("l_m", l_m), ("w1_m", w1_m), ("w2_m", w2_m)):
        _positive(v, name)
    a21, a22 = as_float_array(K21, "K21"), as_float_array(K22, "K22")
    for name, a in (("K21", a21), ("K22", a22)):
        if not np.all(np.isfinite(a)) or np.any(a <= 1):
            raise InputError(f"{name}: expected > 1 (base wider than the platform)")
    H = _positive(H_m, "H_m")
    X = as_float_array(X_m, "X_m")
    if not np.all(np.isfinite(X)) or np.any(X - l_m / 2 <= 0) or np.any(X + l_m / 2 >= L_m):
        raise InputError(f"X_m: expected l/2 < X_m < L - l/2 (inside the frame, L = {L_m} m)")
    shape = np.broadcast_shapes(a21.shape, a22.shape, H.shape, X.shape)
    a21, a22, H, X = (np.broadcast_to(a, shape) for a in (a21, a22, H, X))
    # Cable order of rigs.flat_rig: front (left top, left bottom, right top, right bottom), back.
    side_front = np.array([1, 1, 1, 1, 0, 0, 0, 0], dtype=np.float64)
    sy = np.array([1, 1, -1, -1, 1, 1, -1, -1], dtype=np.float64)
    top = np.array([1, 0, 1, 0, 1, 0, 1, 0], dtype=np.float64)
    half_base = 0.5 * (
        a21[..., None] * w1_m * side_front + a22[..., None] * w2_m * (1 - side_front)
    )
    anchors = np.stack(
        [
            np.broadcast_to(L_m * (1 - side_front), shape + (8,)),
            sy * half_base,
            H[..., None] * top,
        ],
        axis=-1,
    )
    half_plat = 0.5 * (w1_m * side_front + w2_m * (1 - side_front))
    attach = np.stack([np.where(side_front > 0, -l_m / 2, l_m / 2), sy * half_plat, 0 * sy], -1)
    position = np.stack([X, np.zeros(shape), 0.5 * H], axis=-1)
    return RigGeometry(anchors, np.broadcast_to(attach, shape + (8, 3)), position)


def flat_yaw_singular_K22(
    K21: ArrayLike, X_m: ArrayLike, *, L_m: float = 1.0, l_m: float = 0.03
) -> FloatArray:
    """The back-base ratio K22 (...,) at which the flat rig loses its yaw (Mz) direction.

    Seen from above, each front cable runs from a front platform point (X - l/2, +-w1/2) to its
    anchor (0, +-K21 w1/2) and each back cable from (X + l/2, +-w2/2) to (L, +-K22 w2/2); top and
    bottom cables share these projections.  By symmetry each pair of projected lines meets on the x
    axis, the front pair at ``x_f = (X - l/2) K21 / (K21 - 1)``, the back pair at
    ``x_b = (X + l/2) - (L - X - l/2) / (K22 - 1)``.  When ``x_f = x_b`` every cable's line of action
    passes through the vertical line through that point, so no combination of tensions produces a
    yaw moment about it: A is singular.  Solving for K22 gives
    ``K22* = 1 + (L - X - l/2) / (X + l/2 - x_f)`` (independent of H, w1 and w2); ``inf`` where no
    K22 > 1 reaches it.
    """
    K = as_float_array(K21, "K21")
    X = as_float_array(X_m, "X_m")
    if np.any(K <= 1):
        raise InputError("K21: expected > 1")
    x_f = (X - l_m / 2) * K / (K - 1)
    gap = X + l_m / 2 - x_f
    with np.errstate(divide="ignore"):
        k22 = 1 + (L_m - X - l_m / 2) / np.where(gap > 0, gap, np.nan)
    return np.asarray(np.where(gap > 0, k22, np.inf), dtype=np.float64)


def structure_matrices(geometry: RigGeometry) -> FloatArray:
    """Structure matrices A (..., 6, m) of a batch of rigs at their reference pose (R = I).

    Columns ``[u_i; r_i x u_i]`` with ``r_i = pp_i`` and ``u_i`` the unit vector from the platform
    point to the anchor, {O} axes; the same as :func:`cdpr.analysis.kinematics.structure_matrix`
    with an identity rotation, written out per component for speed on large batches.
    """
    b = geometry.anchors_O_m
    r = geometry.attach_P_m
    p = geometry.position_O_m
    shape = geometry.shape
    m = b.shape[-2]
    out = np.empty(shape + (6, m))
    lx = b[..., 0] - p[..., 0:1] - r[..., 0]
    ly = b[..., 1] - p[..., 1:2] - r[..., 1]
    lz = b[..., 2] - p[..., 2:3] - r[..., 2]
    length = np.sqrt(lx * lx + ly * ly + lz * lz)
    if np.any(length < 1e-12):
        raise InputError("geometry: a cable has zero length (anchor on the attachment point)")
    inv = 1.0 / length
    ux, uy, uz = lx * inv, ly * inv, lz * inv
    rx, ry, rz = r[..., 0], r[..., 1], r[..., 2]
    out[..., 0, :] = ux
    out[..., 1, :] = uy
    out[..., 2, :] = uz
    out[..., 3, :] = ry * uz - rz * uy
    out[..., 4, :] = rz * ux - rx * uz
    out[..., 5, :] = rx * uy - ry * ux
    return out


def gravity_load(
    mass_kg: float, gravity_O_mps2: ArrayLike = GRAVITY_O_MPS2, com_P_m: ArrayLike = (0, 0, 0)
) -> FloatArray:
    """Gravity load G (6,) at P in {O} axes for the reference pose (R = I), N and N m."""
    return gravity_wrench(mass_kg, com_P_m, np.eye(3), gravity_O_mps2)


@dataclass(frozen=True)
class SensitivityResult:
    """Sensitivity of a batch of configurations (leading dims ``...``).

    S_N: (...,) paper eq. 12, N; NaN where the configuration is singular or where the method
        reports a rank-deficient (reduced) structure matrix (its tensions are then undefined).
    delta_T_N: (..., m) ``T0 - Tw``, N.
    T0_N, Tw_N: (..., m) wind-off and loaded tensions, N.
    feasible_wind_off: (...,) the method found feasible tensions against gravity alone.
    feasible: (...,) both T0 and Tw feasible and the configuration not singular.
    singular: (...,) ``sigma_min / sigma_max`` of A below the threshold: S is undefined.
    method: the distribution method used for both T0 and Tw.
    """

    S_N: FloatArray
    delta_T_N: FloatArray
    T0_N: FloatArray
    Tw_N: FloatArray
    feasible_wind_off: BoolArray
    feasible: BoolArray
    singular: BoolArray
    method: str


def sensitivity_value(delta_T_N: ArrayLike) -> FloatArray:
    """Paper eq. 12: ``S = sqrt(sum_i (dT_i / m)^2)`` (...,) from dT (..., m), N."""
    dT = as_float_array(delta_T_N, "delta_T_N")
    if dT.ndim < 1 or dT.shape[-1] < 1:
        raise InputError(f"delta_T_N: expected shape (..., m), got {dT.shape}")
    m = dT.shape[-1]
    return np.sqrt(np.einsum("...i,...i->...", dT, dT)) / m


def rank_deficient(A: ArrayLike, rcond: float = SINGULAR_RCOND) -> BoolArray:
    """True (...,) where ``sigma_min / sigma_max`` of A (..., n, m) is below ``rcond``.

    A cheap necessary condition screens the batch first: ``det(A A^T) = prod(sigma^2) <=
    sigma_min^2 sigma_max^(2n - 2) <= (sigma_min / sigma_max)^2 trace(A A^T)^n``, so only the
    configurations with ``det(A A^T) < rcond^2 trace(A A^T)^n`` need their singular values.
    """
    A_ = as_float_array(A, "A")
    n = A_.shape[-2]
    M = np.einsum("...ik,...jk->...ij", A_, A_)
    tr = np.trace(M, axis1=-2, axis2=-1)
    cand = ~(np.linalg.det(M) >= rcond**2 * tr**n)
    out = np.zeros(M.shape[:-2], dtype=bool)
    if np.any(cand):
        s = singular_values(A_[cand])
        out[cand] = ~(s[..., -1] > rcond * s[..., 0])
    return out


def singular_values(A: ArrayLike) -> FloatArray:
    """Singular values (..., n) of A (..., n, m), largest first (from the eigenvalues of A A^T)."""
    A_ = as_float_array(A, "A")
    AAt = np.einsum("...ik,...jk->...ij", A_, A_)
    ev = np.linalg.eigvalsh(AAt)[..., ::-1]
    return np.sqrt(np.maximum(ev, 0.0))


def _check_A(A: ArrayLike) -> FloatArray:
    A_ = as_float_array(A, "A")
    if A_.ndim < 2 or A_.shape[-2] != 6 or A_.shape[-1] < 6:
        raise InputError(f"A: expected shape (..., 6, m) with m >= 6, got {A_.shape}")
    if not np.all(np.isfinite(A_)):
        raise InputError("A: expected finite values, got NaN or inf")
    return A_


def _mask_singular(A: FloatArray, sing: BoolArray) -> FloatArray:
    """A with singular entries replaced by a well-conditioned stand-in (their results are masked)."""
    if not np.any(sing):
        return A
    m = A.shape[-1]
    safe = np.zeros((6, m))
    safe[np.arange(6), np.arange(6)] = 1.0
    safe[np.arange(m - 6) % 6, 6 + np.arange(m - 6)] = -1.0
    return np.where(np.asarray(sing)[..., None, None], safe, A)


def _limits(t_min_N: ArrayLike, t_max_N: ArrayLike, m: int) -> tuple[FloatArray, FloatArray]:
    """Per-cable limits (..., m); scalars apply to every cable."""
    out = []
    for name, v in (("t_min_N", t_min_N), ("t_max_N", t_max_N)):
        a = as_float_array(v, name)
        out.append(check_trailing(np.broadcast_to(a, (m,)) if a.ndim == 0 else a, name, (m,)))
    return out[0], out[1]


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise InputError(f"method: expected one of {sorted(METHODS)}, got {method!r}")


def sensitivity(
    A: ArrayLike,
    W_ext: ArrayLike,
    G: ArrayLike,
    t_min_N: ArrayLike,
    t_max_N: ArrayLike,
    method: str = "closed-form",
    *,
    rcond: float = SINGULAR_RCOND,
    singular: ArrayLike | None = None,
) -> SensitivityResult:
    """S (paper eq. 12) for a batch: A (..., 6, m), W_ext (..., 6), G (..., 6), limits (..., m).

    ``T0 = distribute(method, A, -G)`` and ``Tw = distribute(method, A, -(G + W_ext))``; the
    leading dimensions broadcast (for instance A (n, 1, 6, m) with W_ext (k, 6) gives (n, k)).
    Singular configurations (``sigma_min / sigma_max < rcond``; or the given ``singular`` mask) are
    not passed to the solver: their S is NaN and ``singular`` is True.
    """
    _check_method(method)
    A_ = _check_A(A)
    m = A_.shape[-1]
    W = check_trailing(W_ext, "W_ext", (6,))
    G_ = check_trailing(G, "G", (6,))
    lo, hi = _limits(t_min_N, t_max_N, m)
    sing_A = rank_deficient(A_, rcond) if singular is None else np.asarray(singular, dtype=bool)
    # T0 does not depend on W_ext: solve it once on the leading shape without W's dimensions.
    lead0 = np.broadcast_shapes(
        A_.shape[:-2], G_.shape[:-1], lo.shape[:-1], hi.shape[:-1], sing_A.shape
    )
    lead = np.broadcast_shapes(lead0, W.shape[:-1])
    sing0 = np.broadcast_to(sing_A, lead0)
    A0 = _mask_singular(np.broadcast_to(A_, lead0 + (6, m)), sing0)
    lo0, hi0 = np.broadcast_to(lo, lead0 + (m,)), np.broadcast_to(hi, lead0 + (m,))
    r0 = distribute(method, A0, -np.broadcast_to(G_, lead0 + (6,)), lo0, hi0)
    rw = distribute(
        method,
        np.broadcast_to(A0, lead + (6, m)),
        -np.broadcast_to(G_ + W, lead + (6,)),
        np.broadcast_to(lo0, lead + (m,)),
        np.broadcast_to(hi0, lead + (m,)),
    )
    sing = np.broadcast_to(sing0, lead)
    # A method that reports a rank-deficient (reduced) matrix has no tensions to offer: S undefined.
    failed = np.zeros(lead, dtype=bool)
    for r in (r0, rw):
        if r.status is not None:
            failed = failed | np.broadcast_to(np.asarray(r.status) == SOLVE_RANK_DEFICIENT, lead)
    T0 = np.broadcast_to(r0.tensions_N, lead + (m,))
    dT = T0 - rw.tensions_N
    S = sensitivity_value(dT)
    nan = np.where(sing | failed, np.nan, 1.0)
    feas0 = np.broadcast_to(r0.feasible, lead) & ~sing & ~failed
    return SensitivityResult(
        S_N=S * nan,
        delta_T_N=dT * nan[..., None],
        T0_N=T0 * nan[..., None],
        Tw_N=rw.tensions_N * nan[..., None],
        feasible_wind_off=feas0,
        feasible=feas0 & rw.feasible & ~failed,
        singular=np.array(sing),
        method=method,
    )


def sensitivity_of_rig(
    rig: Rig, W_ext: ArrayLike, method: str = "closed-form", pose: ArrayLike | None = None
) -> SensitivityResult:
    """S of one :class:`Rig` at ``pose`` (6,) (default its reference pose) for wrenches (..., 6).

    The single-configuration path: :func:`cdpr.analysis.kinematics.structure_matrix`,
    :func:`cdpr.analysis.dynamics.gravity_wrench` and the distribution, no batching over rigs.
    """
    if pose is None:
        q = np.concatenate([rig.reference_position_O_m, rig.reference_euler_rad])
    else:
        q = check_trailing(pose, "pose", (6,))
    R = rotation_from_euler(q[3:])
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, q[:3], R)
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    return sensitivity(A, W_ext, G, rig.t_min_N, rig.t_max_N, method)


@dataclass(frozen=True)
class SingularValueMetrics:
    """Conditioning of A (...,): what the paper's S does not show.

    sigma_max, sigma_min: largest and smallest singular values of A (force rows dimensionless,
        moment rows in m).  ``sigma_min <= |A dT| / |dT| <= sigma_max`` for dT in the row space
        of A, so a tension change of 1 N moves the recovered wrench by at least sigma_min and at
        most sigma_max; conversely ``|W| / sigma_max <= |A^+ W| <= |W| / sigma_min``.
    condition: sigma_max / sigma_min (inf when singular).
    """

    sigma_max: FloatArray
    sigma_min: FloatArray
    condition: FloatArray


def singular_value_metrics(A: ArrayLike) -> SingularValueMetrics:
    """Condition number and extreme singular values of A (..., 6, m)."""
    s = singular_values(A)
    smax, smin = s[..., 0], s[..., -1]
    with np.errstate(divide="ignore"):
        cond = np.where(smin > 0, smax / np.where(smin > 0, smin, 1.0), np.inf)
    return SingularValueMetrics(smax, smin, cond)


def wrench_covariance(A: ArrayLike, sigma_T_N: ArrayLike, tare: bool = True) -> FloatArray:
    """Covariance (..., 6, 6) of the wrench recovered from measured tensions, ``A Sigma A^T``.

    ``W_ext = A (T0 - Tw)`` (tare method): each cable's reading has independent noise of standard
    deviation ``sigma_T_N`` (scalar or (..., m), N); with ``tare`` the wind-off reading T0 is
    noisy too, so ``Sigma = 2 diag(sigma^2)``; without it (T0 averaged away) ``Sigma = diag(sigma^2)``.
    """
    A_ = as_float_array(A, "A")
    sig = as_float_array(sigma_T_N, "sigma_T_N")
    if np.any(sig < 0) or not np.all(np.isfinite(sig)):
        raise InputError("sigma_T_N: expected finite values >= 0 N")
    var = np.broadcast_to(sig**2 * (2.0 if tare else 1.0), A_.shape[:-2] + A_.shape[-1:])
    return np.einsum("...ik,...k,...jk->...ij", A_, var, A_)


def wrench_std(A: ArrayLike, sigma_T_N: ArrayLike, tare: bool = True) -> FloatArray:
    """Standard deviation (..., 6) of each recovered wrench component (N, N m); see
    :func:`wrench_covariance`."""
    A_ = as_float_array(A, "A")
    sig = as_float_array(sigma_T_N, "sigma_T_N")
    if np.any(sig < 0) or not np.all(np.isfinite(sig)):
        raise InputError("sigma_T_N: expected finite values >= 0 N")
    var = np.broadcast_to(sig**2 * (2.0 if tare else 1.0), A_.shape[:-2] + A_.shape[-1:])
    return np.sqrt(np.einsum("...ik,...k,...ik->...i", A_, var, A_))


def feasibility_margin(
    A: ArrayLike,
    G: ArrayLike,
    load_cases: ArrayLike,
    t_min_N: ArrayLike,
    t_max_N: ArrayLike,
    method: str = "closed-form",
    *,
    rcond: float = SINGULAR_RCOND,
) -> FloatArray:
    """Worst tension slack (...,) over a set of external load cases, N; negative = infeasible.

    A (..., 6, m); G (..., 6); load_cases (k, 6) external wrenches (include a zero row for
    wind-off).  For every case the method's tensions T give ``min_i min(T_i - t_min_i,
    t_max_i - T_i)``, and the margin is the minimum over the cases; an equilibrium residual above
    1e-6 N counts as ``-inf``; singular configurations get ``-inf``.
    """
    _check_method(method)
    A_ = _check_A(A)
    m = A_.shape[-1]
    Wc = check_trailing(load_cases, "load_cases", (6,))
    if Wc.ndim != 2 or len(Wc) == 0:
        raise InputError(f"load_cases: expected shape (k, 6) with k >= 1, got {Wc.shape}")
    G_ = check_trailing(G, "G", (6,))
    lo, hi = _limits(t_min_N, t_max_N, m)
    lo = lo[..., None, :] if lo.ndim > 1 else lo
    hi = hi[..., None, :] if hi.ndim > 1 else hi
    sing = rank_deficient(A_, rcond)
    A_safe = _mask_singular(A_, sing)[..., None, :, :]
    w_all = -(G_[..., None, :] + np.concatenate([np.zeros((1, 6)), Wc], axis=0))
    lead = np.broadcast_shapes(A_safe.shape[:-2], w_all.shape[:-1], lo.shape[:-1], hi.shape[:-1])
    m_ = A_.shape[-1]
    res = distribute(
        method,
        np.broadcast_to(A_safe, lead + (6, m_)),
        np.broadcast_to(w_all, lead + (6,)),
        np.broadcast_to(lo, lead + (m_,)),
        np.broadcast_to(hi, lead + (m_,)),
    )
    T = res.tensions_N
    slack = np.minimum(T - lo, hi - T).min(axis=-1)
    slack = np.where(res.residual_N > 1e-6 * (1.0 + np.abs(hi).max()), -np.inf, slack)
    margin = np.where(np.isnan(slack), -np.inf, slack).min(axis=-1)
    return np.where(np.broadcast_to(sing, margin.shape), -np.inf, margin)


def aero_wrench(
    V_mps: ArrayLike,
    coefficients: ArrayLike,
    *,
    rho_kgpm3: float = 1.225,
    S_ref_m2: float,
    span_m: float,
    chord_m: float,
) -> FloatArray:
    """Aerodynamic wrench (..., 6) at P in {O} axes from coefficients given in {O} axes.

    ``q = rho V^2 / 2``; ``F = q S [C_Fx, C_Fy, C_Fz]`` and ``M = q S [b C_Mx, c C_My, b C_Mz]``
    (span b for roll and yaw, chord c for pitch).  ``coefficients`` (6,) or (..., 6) are in {O}
    axes (x downstream: a drag is a positive C_Fx; z up: a lift is a positive C_Fz).
    """
    V = as_float_array(V_mps, "V_mps")
    if not np.all(np.isfinite(V)) or np.any(V < 0):
        raise InputError("V_mps: expected finite airspeeds >= 0 m/s")
    C = check_trailing(coefficients, "coefficients", (6,))
    for name, v in (
        ("rho_kgpm3", rho_kgpm3),
        ("S_ref_m2", S_ref_m2),
        ("span_m", span_m),
        ("chord_m", chord_m),
    ):
        _positive(v, name)
    q = 0.5 * rho_kgpm3 * V**2
    scale = np.array([1.0, 1.0, 1.0, span_m, chord_m, span_m]) * S_ref_m2
    return q[..., None] * C * scale
