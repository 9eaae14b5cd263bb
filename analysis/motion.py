"""Forced oscillation of the platform: the commanded motion, the cables' lengths, speeds and
accelerations along it (inverse kinematics), the pose from measured cable lengths (forward
kinematics, least squares with its covariance) and the tensions that carry the motion (the dynamic
tension distribution), all batched over samples.

The motion (docs/dynamic_tests.md; the names are those of issue 22's shared vocabulary): on the
pose ``q = (x, y, z, roll, pitch, yaw)`` (m, rad; Z-Y-X Euler angles) and the unit vector ``e`` of
the axis (surge -> x, sway -> y, heave -> z, roll, pitch, yaw),

    q(t) = q_mean + e * amplitude * env(tau) * sin(2 pi f tau),   tau = t - t0

with ``t0`` the motion's start (the point's ``start`` event).  ``env`` rises from 0 to 1 as a raised
cosine over the ``settling_cycles`` (``0.5 (1 - cos(pi tau f / settling_cycles))``), stays 1 over the
``cycles`` analysed, then falls back to 0 over ``ramp_down_cycles`` (default 1) as a raised cosine;
zero before and after.  With whole numbers of cycles the pose, its rate and its acceleration are
continuous (the envelope's slope is zero at its joins and ``sin`` is zero there).

The platform's equation of motion, with every load a wrench *on the platform* at P in {O} axes
(``G`` gravity, ``W_ext`` the aerodynamic and any other external load) and ``D = M qdd + C`` the
rate of change of its momentum (:func:`cdpr.analysis.dynamics.inertia_wrench`)::

    A(q) T + G + W_ext = D      =>      A(q) T = D - G - W_ext

(Newton-Euler; the paper's eq. (4), ``A T = -(M qdd + C + G + W_ext)``, reverses the sign of the
inertia term with these definitions of ``G`` and ``W_ext``: it holds for a platform at rest only.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .dynamics import gravity_wrench, inertia_wrench
from .errors import InputError
from .kinematics import cable_geometry, structure_matrix
from .rig import Rig
from .rotations import angular_rates, euler_rate_matrix, rotation_from_euler
from .tension import TensionResult, distribute

FloatArray = NDArray[np.float64]

MOTION_AXES: tuple[str, ...] = ("surge", "sway", "heave", "roll", "pitch", "yaw")
"""The axes of a forced oscillation, in pose order: surge x, sway y, heave z (m), roll, pitch,
yaw (rad); ``MOTION_AXES.index(axis)`` is the pose component the motion moves."""

ANGULAR_AXES: tuple[str, ...] = ("roll", "pitch", "yaw")
"""The axes whose amplitude is an angle (rad; ``amplitude_deg`` in a test matrix)."""

CHUNK = 20_000
"""Samples per chunk of :func:`motion_tensions` (bounds the structure matrices held at once)."""


def axis_index(axis: str) -> int:
    """The pose component (0..5) an oscillation axis moves."""
    try:
        return MOTION_AXES.index(axis)
    except ValueError:
        raise InputError(f"axis: expected one of {list(MOTION_AXES)}, got {axis!r}") from None


@dataclass(frozen=True)
class Oscillation:
    """A forced oscillation: ``axis`` (one of :data:`MOTION_AXES`), ``amplitude`` (rad for an
    angular axis, m for a translation, > 0), ``frequency_Hz`` (> 0), ``cycles`` analysed (>= 1),
    ``settling_cycles`` of amplitude ramp before them (>= 1), ``ramp_down_cycles`` after (>= 1)."""

    axis: str
    amplitude: float
    frequency_Hz: float
    cycles: int
    settling_cycles: int
    ramp_down_cycles: int = 1

    def __post_init__(self) -> None:
        axis_index(self.axis)
        for name in ("amplitude", "frequency_Hz"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"{name}: expected a finite number > 0, got {v}")
        for name in ("cycles", "settling_cycles", "ramp_down_cycles"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise InputError(f"{name}: expected a whole number >= 1, got {v!r}")

    @property
    def index(self) -> int:
        """The pose component the motion moves."""
        return axis_index(self.axis)

    @property
    def angular(self) -> bool:
        return self.axis in ANGULAR_AXES

    @property
    def omega_rad_s(self) -> float:
        return 2.0 * math.pi * self.frequency_Hz

    @property
    def window_s(self) -> tuple[float, float]:
        """The analysed window ``(start, end)`` in s from the motion's start: whole cycles at full
        amplitude after the settling cycles."""
        f = self.frequency_Hz
        return self.settling_cycles / f, (self.settling_cycles + self.cycles) / f

    @property
    def duration_s(self) -> float:
        """The whole motion, s: settling, analysed and ramp-down cycles."""
        return (self.settling_cycles + self.cycles + self.ramp_down_cycles) / self.frequency_Hz


@dataclass(frozen=True, kw_only=True)
class OscillationFields:
    """The motion a test point or a virtual-rig segment carries, in the shared names of its
    ``test_point`` events (issue 22): ``motion_axis`` ("" for a steady point), the amplitude in SI
    (rad or m), the frequency, the cycles analysed and the settling cycles before them, and the
    label of the inertia tare that serves it ("" if none).  A base of
    :class:`cdpr.pipelines.campaign.TestPoint` and :class:`cdpr.daq.vrig_schedule.Segment`."""

    motion_axis: str = ""
    motion_amplitude: float = 0.0
    motion_frequency_Hz: float = 0.0
    motion_cycles: int = 0
    motion_settling_cycles: int = 0
    inertia_tare: str = ""

    @property
    def oscillation(self) -> Oscillation | None:
        """The forced oscillation (checked), or None for a point that holds still."""
        if not self.motion_axis:
            return None
        return Oscillation(
            self.motion_axis,
            self.motion_amplitude,
            self.motion_frequency_Hz,
            self.motion_cycles,
            self.motion_settling_cycles,
        )


def envelope(tau_s: ArrayLike, osc: Oscillation) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The amplitude envelope at times ``tau_s`` (...,) from the motion's start and its first and
    second time derivatives (1/s, 1/s^2): raised-cosine ramps up over the settling cycles and down
    over the ramp-down cycles, 1 between, 0 outside."""
    tau = as_float_array(tau_s, "tau_s")
    f = osc.frequency_Hz
    t_up, t_end = osc.window_s
    t_off = t_end + osc.ramp_down_cycles / f
    env = np.zeros_like(tau)
    d = np.zeros_like(tau)
    dd = np.zeros_like(tau)
    up = (tau >= 0.0) & (tau < t_up)
    k = math.pi * f / osc.settling_cycles
    a = k * tau[up]
    env[up] = 0.5 * (1.0 - np.cos(a))
    d[up] = 0.5 * k * np.sin(a)
    dd[up] = 0.5 * k * k * np.cos(a)
    env[(tau >= t_up) & (tau < t_end)] = 1.0
    down = (tau >= t_end) & (tau < t_off)
    k = math.pi * f / osc.ramp_down_cycles
    a = k * (tau[down] - t_end)
    env[down] = 0.5 * (1.0 + np.cos(a))
    d[down] = -0.5 * k * np.sin(a)
    dd[down] = -0.5 * k * k * np.cos(a)
    return env, d, dd


@dataclass(frozen=True)
class Motion:
    """A pose trajectory: pose (n, 6) ``[x, y, z, roll, pitch, yaw]`` (m, rad), its rate (n, 6) and
    acceleration (n, 6) (m/s, rad/s; m/s^2, rad/s^2)."""

    pose: FloatArray
    rate: FloatArray
    accel: FloatArray


def oscillation_offset(
    tau_s: ArrayLike, osc: Oscillation
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The moved coordinate's offset from the mean, its rate and acceleration (...,) at times
    ``tau_s`` from the motion's start (exact derivatives of ``A env sin(w tau)``)."""
    tau = as_float_array(tau_s, "tau_s")
    env, d, dd = envelope(tau, osc)
    w = osc.omega_rad_s
    s, c = np.sin(w * tau), np.cos(w * tau)
    A = float(osc.amplitude)
    q = A * env * s
    qd = A * (d * s + env * w * c)
    qdd = A * (dd * s + 2.0 * d * w * c - env * w * w * s)
    return q, qd, qdd


def oscillation_motion(tau_s: ArrayLike, mean_pose: ArrayLike, osc: Oscillation) -> Motion:
    """The commanded motion at times ``tau_s`` (n,) from its start about ``mean_pose`` (6,)."""
    tau = as_float_array(tau_s, "tau_s").reshape(-1)
    q0 = check_trailing(mean_pose, "mean_pose", (6,))
    if q0.shape != (6,):
        raise InputError(f"mean_pose: expected shape (6,), got {q0.shape}")
    x, xd, xdd = oscillation_offset(tau, osc)
    n, j = tau.shape[0], osc.index
    pose = np.broadcast_to(q0, (n, 6)).copy()
    rate = np.zeros((n, 6))
    accel = np.zeros((n, 6))
    pose[:, j] += x
    rate[:, j] = xd
    accel[:, j] = xdd
    return Motion(pose, rate, accel)


# --------------------------------------------------------------------------------------------
# inverse and forward kinematics
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CableMotion:
    """Cable lengths (n, m) from the platform point to the anchor (m), their rates (m/s, positive
    when the cable pays out) and accelerations (m/s^2), and the cable geometry's unit vectors
    (n, m, 3) and lever arms (n, m, 3) in {O}."""

    length_m: FloatArray
    speed_mps: FloatArray
    accel_mps2: FloatArray
    u_O: FloatArray
    r_O_m: FloatArray


def cable_motion(
    anchors_O_m: ArrayLike,
    attach_P_m: ArrayLike,
    pose: ArrayLike,
    pose_rate: ArrayLike,
    pose_accel: ArrayLike,
) -> CableMotion:
    """Inverse kinematics along a trajectory: the cable lengths and their first two derivatives.

    With ``l_i = b_i - p - R pp_i``, ``r_i = R pp_i``, the point's velocity
    ``v_i = pdot + omega x r_i`` and acceleration ``a_i = pddot + omega_dot x r_i + omega x (omega x r_i)``:
    ``L_i' = -u_i . v_i`` and ``L_i'' = (|v_i|^2 - (u_i . v_i)^2) / L_i - u_i . a_i``.
    pose, pose_rate, pose_accel: (..., 6); anchors/attach (m, 3).
    """
    q = check_trailing(pose, "pose", (6,))
    qd = check_trailing(pose_rate, "pose_rate", (6,))
    qdd = check_trailing(pose_accel, "pose_accel", (6,))
    R = rotation_from_euler(q[..., 3:])
    geo = cable_geometry(anchors_O_m, attach_P_m, q[..., :3], R)
    omega, omega_dot = angular_rates(q[..., 3:], qd[..., 3:], qdd[..., 3:])
    r, u, L = geo.r_O_m, geo.u_O, geo.length_m
    w = omega[..., None, :]
    v = qd[..., None, :3] + np.cross(w, r)
    a = qdd[..., None, :3] + np.cross(omega_dot[..., None, :], r) + np.cross(w, np.cross(w, r))
    uv = np.einsum("...i,...i->...", u, v)
    speed = -uv
    accel = (np.einsum("...i,...i->...", v, v) - uv * uv) / L - np.einsum("...i,...i->...", u, a)
    return CableMotion(L, speed, accel, u, r)


@dataclass(frozen=True)
class ForwardKinematics:
    """Poses from cable lengths: pose (n, 6), covariance (n, 6, 6) of ``[x, y, z, roll, pitch,
    yaw]`` from the lengths' sigma (weighted least squares, linearised at the solution),
    residual_m (n, m) measured minus fitted lengths, chi2 (n,) ``sum (residual/sigma)^2`` (about
    m - 6 when the sigma is right), converged (n,) and the iterations used."""

    pose: FloatArray
    covariance: FloatArray
    residual_m: FloatArray
    chi2: FloatArray
    converged: NDArray[np.bool_]
    iterations: int


def forward_kinematics(
    anchors_O_m: ArrayLike,
    attach_P_m: ArrayLike,
    lengths_m: ArrayLike,
    length_sd_m: ArrayLike,
    initial_pose: ArrayLike,
    max_iterations: int = 100,
    tol: float = 1e-6,
) -> ForwardKinematics:
    """The platform pose from measured cable lengths (e.g. a controller's motor encoders): the
    least squares of ``sum_i ((L_i(q) - L_i,meas) / sigma_i)^2``, batched over samples, by
    Gauss-Newton steps, then Newton's (the residuals' curvature from differences of the gradient)
    once a step is below ten sigmas, each step the best of a few multiples of itself: a small
    platform sees its yaw poorly, and there Gauss-Newton alone creeps or oscillates.

    lengths_m: (n, m) measured lengths from the platform point to the anchor; length_sd_m: (m,)
    or scalar sigma of each length (m); initial_pose: (6,) or (n, 6) a starting pose (the
    reference pose, or the commanded one).  The Jacobian ``dL_i/dq = -[u_i ; H^T (r_i x u_i)]``
    (``H`` the Euler-rate matrix) gives the covariance ``(J^T W J)^-1``, ``W = diag(1/sigma^2)``.
    A sample is converged when every component of its last step is below ``tol`` times that
    component's sigma (a millionth of the pose's own uncertainty by default).
    """
    b = check_trailing(anchors_O_m, "anchors_O_m", (3,))
    pp = check_trailing(attach_P_m, "attach_P_m", (3,))
    m = b.shape[-2]
    if m < 6:
        raise InputError(f"forward_kinematics: at least 6 cables are needed, got {m}")
    Lm = check_trailing(lengths_m, "lengths_m", (m,))
    if Lm.ndim != 2:
        raise InputError(f"lengths_m: expected shape (n, {m}), got {Lm.shape}")
    n = Lm.shape[0]
    sd = np.broadcast_to(as_float_array(length_sd_m, "length_sd_m"), (m,))
    if not np.all(np.isfinite(sd) & (sd > 0)):
        raise InputError("length_sd_m: expected finite values > 0 m")
    q = np.broadcast_to(check_trailing(initial_pose, "initial_pose", (6,)), (n, 6)).copy()
    wgt = 1.0 / sd**2
    converged = np.zeros(n, dtype=bool)
    newton = np.zeros(n, dtype=bool)  # near the minimum: Newton's steps
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007  (iterations, not samples)
        act = np.flatnonzero(~converged)
        qa, La = q[act], Lm[act]
        J, res = _fk_jacobian(b, pp, qa, La)
        JtW = np.swapaxes(J, -1, -2) * wgt
        Hm = JtW @ J
        g = np.einsum("nij,nj->ni", JtW, res)
        sigma = np.sqrt(np.diagonal(np.linalg.inv(Hm), axis1=-2, axis2=-1))
        nw = np.flatnonzero(newton[act])
        if nw.size:  # the residuals' curvature matters where a coordinate is poorly seen
            Hn = _fk_hessian(b, pp, qa[nw], La[nw], wgt)
            pd = np.all(np.linalg.eigvalsh(Hn) > 0, axis=-1)
            Hm[nw[pd]] = Hn[pd]
        step = -np.linalg.solve(Hm, g[..., None])[..., 0]
        # the best of a few multiples of the step (a flat, curved valley: Gauss-Newton creeps)
        cost = [
            np.sum((_fk_lengths(b, pp, qa + a * step) - La) ** 2 * wgt, axis=-1) for a in _STEPS
        ]
        step = step * np.asarray(_STEPS)[np.argmin(np.stack(cost), axis=0)][:, None]
        q[act] = qa + step
        size = np.max(np.abs(step) / sigma, axis=-1)
        newton[act] = size < 10.0
        converged[act] = size < tol
        if bool(np.all(converged)):
            break
    J, res = _fk_jacobian(b, pp, q, Lm)
    JtWJ = (np.swapaxes(J, -1, -2) * wgt) @ J
    cov: FloatArray = np.asarray(np.linalg.inv(JtWJ), dtype=np.float64)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    return ForwardKinematics(
        pose=q,
        covariance=cov,
        residual_m=-res,
        chi2=np.sum(res * res * wgt, axis=-1),
        converged=converged,
        iterations=it,
    )


_STEPS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)


def _fk_lengths(b: FloatArray, pp: FloatArray, q: FloatArray) -> FloatArray:
    lv = b - q[:, None, :3] - np.einsum("nij,mj->nmi", rotation_from_euler(q[:, 3:]), pp)
    return np.asarray(np.sqrt(np.einsum("nmi,nmi->nm", lv, lv)))


def _axis_rotations(a: FloatArray, axis: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """R_k(a), its first and second derivatives (n, 3, 3) for a rotation about axis k."""
    c, s = np.cos(a), np.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.zeros(a.shape + (3, 3))
    d1 = np.zeros_like(R)
    R[..., axis, axis] = 1.0
    R[..., i, i] = R[..., j, j] = c
    R[..., i, j], R[..., j, i] = -s, s
    d1[..., i, i] = d1[..., j, j] = -s
    d1[..., i, j], d1[..., j, i] = -c, c
    d2 = -R.copy()
    d2[..., axis, axis] = 0.0
    return R, d1, d2


def _fk_hessian(
    b: FloatArray, pp: FloatArray, q: FloatArray, L_meas: FloatArray, wgt: FloatArray
) -> FloatArray:
    """The full Hessian (n, 6, 6) of ``sum w r^2 / 2``: ``sum w (J J^T + r d2L/dq2)``, with the
    second derivatives of each length through those of ``R = Rz Ry Rx`` (exact)."""
    Rx = _axis_rotations(q[:, 3], 0)
    Ry = _axis_rotations(q[:, 4], 1)
    Rz = _axis_rotations(q[:, 5], 2)
    R = Rz[0] @ Ry[0] @ Rx[0]
    lv = b - q[:, None, :3] - np.einsum("nij,mj->nmi", R, pp)
    L = np.sqrt(np.einsum("nmi,nmi->nm", lv, lv))
    u = lv / L[..., None]
    n, m = L.shape
    D = np.zeros((n, m, 6, 3))  # d l / d q_a
    D[:, :, [0, 1, 2], [0, 1, 2]] = -1.0

    def rot(kx: int, ky: int, kz: int) -> FloatArray:  # a derivative of R by its factors' orders
        return np.asarray(Rz[kz] @ Ry[ky] @ Rx[kx])

    first = (rot(1, 0, 0), rot(0, 1, 0), rot(0, 0, 1))
    for k in range(3):
        D[:, :, 3 + k] = -np.einsum("nij,mj->nmi", first[k], pp)
    Ju = np.einsum("nmai,nmi->nma", D, u)  # the Jacobian (n, m, 6)
    DD = D @ np.swapaxes(D, -1, -2)
    H2 = (DD - Ju[..., :, None] * Ju[..., None, :]) / L[..., None, None]
    orders = {(0, 0): (2, 0, 0), (1, 1): (0, 2, 0), (2, 2): (0, 0, 2),
              (0, 1): (1, 1, 0), (0, 2): (1, 0, 1), (1, 2): (0, 1, 1)}  # fmt: skip
    for (k, l_), o in orders.items():
        c = -np.einsum("nmi,nmi->nm", u, np.einsum("nij,mj->nmi", rot(*o), pp))
        H2[:, :, 3 + k, 3 + l_] += c
        if k != l_:
            H2[:, :, 3 + l_, 3 + k] += c
    r = (L - L_meas) * wgt
    return np.asarray(np.einsum("nma,nmb,m->nab", Ju, Ju, wgt) + np.einsum("nm,nmab->nab", r, H2))


def _fk_jacobian(
    b: FloatArray, pp: FloatArray, q: FloatArray, L_meas: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``(J (n, m, 6), L(q) - L_meas (n, m))`` of the forward-kinematics least squares."""
    R = rotation_from_euler(q[:, 3:])
    geo = cable_geometry(b, pp, q[:, :3], R)
    H = euler_rate_matrix(q[:, 3:])
    ru = np.cross(geo.r_O_m, geo.u_O)  # (n, m, 3)
    J = np.concatenate([-geo.u_O, -np.einsum("nmi,nij->nmj", ru, H)], axis=-1)
    return J, geo.length_m - L_meas


# --------------------------------------------------------------------------------------------
# the tensions that carry a motion
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MotionTensions:
    """The dynamic tension distribution along a trajectory: ``result`` (the distribution's
    :class:`~cdpr.analysis.tension.TensionResult`, tensions (n, m)), the wrench the cables must
    apply ``cable_wrench_O`` (n, 6) ``= D - G - W_ext``, the inertia wrench ``inertia_O``
    ``D = M qdd + C`` (n, 6) and the gravity load ``gravity_O`` (n, 6), all at P in {O}."""

    result: TensionResult
    cable_wrench_O: FloatArray
    inertia_O: FloatArray
    gravity_O: FloatArray


def motion_tensions(
    rig: Rig,
    motion: Motion,
    external_wrench_O: ArrayLike,
    method: str = "exact",
    chunk: int = CHUNK,
) -> MotionTensions:
    """Tensions that make the rig's platform (and model) follow ``motion`` under gravity, its own
    inertia (rigid-body Newton-Euler with the rig file's mass, centre of mass and inertia about P)
    and ``external_wrench_O`` (n, 6) (aerodynamic and other loads on the platform at P in {O}):
    ``distribute(method, A(q), D - G - W_ext, t_min, t_max)``, in chunks of ``chunk`` samples."""
    q, qd, qdd = motion.pose, motion.rate, motion.accel
    n = q.shape[0]
    W = np.broadcast_to(check_trailing(external_wrench_O, "external_wrench_O", (6,)), (n, 6))
    D = inertia_wrench(rig.mass_kg, rig.com_P_m, rig.inertia_P_kgm2, q, qd, qdd)
    R = rotation_from_euler(q[:, 3:])
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    w = D - G - W
    parts = []
    for s in range(0, max(n, 1), chunk):
        e = min(s + chunk, n)
        A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, q[s:e, :3], R[s:e])
        parts.append(distribute(method, A, w[s:e], rig.t_min_N, rig.t_max_N))
    res = parts[0] if len(parts) == 1 else _concat(parts)
    return MotionTensions(res, w, D, G)


def _concat(parts: list[TensionResult]) -> TensionResult:
    st = [p.status for p in parts]
    return TensionResult(
        tensions_N=np.concatenate([p.tensions_N for p in parts]),
        feasible=np.concatenate([p.feasible for p in parts]),
        residual_N=np.concatenate([p.residual_N for p in parts]),
        max_violation_N=np.concatenate([p.max_violation_N for p in parts]),
        objective=parts[0].objective,
        method=parts[0].method,
        status=None if any(s is None for s in st) else np.concatenate(st),  # type: ignore[arg-type]
    )
