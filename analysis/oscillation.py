"""The reduction of a forced oscillation: the motion fitted from the camera, the camera's clock
offset, the cable wrench along the motion and its harmonics, the inertia removed (by the wind-off
oscillation tare and by the rig file's mass), the dynamic derivatives in body axes.

Names and conventions are issue 22's (docs/dynamic_tests.md, helpers' shared vocabulary): the motion
``q(t) = q_mean + e A sin(2 pi f (t - t0))`` along the pose coordinate of the axis; a camera frame
stamped ``t_cam`` shows the pose at ``t_cam - offset`` (offset > 0: the camera's clock ahead of the
load cells'); the load cells' clock is the run's.

**The motion's phase.**  Every point is analysed in the phase ``theta`` of its own fitted motion:
``theta = omega (t_cam - t_ref) + phi0``, chosen so that the moved coordinate's fundamental is
``A sin(theta)`` (in-phase coefficient ``A``, quadrature 0).  At a load-cell sample ``t`` the
camera's clock reads ``t + offset``.  A coefficient "in phase" goes with the displacement, one "in
quadrature" with the velocity.

**σ.**  Three sources, each a covariance of the harmonic coefficients (``(6 p, 6 p)``, ``p = 2H+1``
terms per component, :mod:`cdpr.analysis.harmonics`):

- ``load_cells``: the cable wrench's fit residuals, their correlation counted (cycle batch means
  through :func:`cdpr.analysis.longrun.long_run`);
- ``pose``: the motion fit's covariance (from the camera residuals the same way) carried by
  ``K = dW/dq`` (the cable wrench's sensitivity to the pose at fixed tensions: the pretension's
  geometric stiffness, ~14 N m/rad in pitch on the flat optimum rig) and by the phase of the
  motion (the frame turns with it);
- ``clock_offset``: the offset's σ through the derivative of the coefficients with respect to it.

A point and its tare are independent draws; the offset is common to both (its part is the
difference of their sensitivities).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .aero import body_from_tunnel, coefficient_matrix, transfer_moment
from .dynamics import gravity_wrench, inertia_wrench
from .errors import InputError
from .harmonics import (
    TWO_PI,
    HarmonicFit,
    grid_phases,
    harmonic_basis,
    harmonic_fit,
    harmonic_linear_map,
    harmonic_rate,
    harmonic_values,
    harmonics_from_grid,
    n_terms,
    phase_derivative,
    phase_shift_matrix,
)
from .kinematics import structure_matrix
from .motion import ANGULAR_AXES, Oscillation
from .rig import Rig
from .rotations import rotation_from_euler

FloatArray = NDArray[np.float64]

DYNAMIC_COEFFICIENTS: tuple[str, ...] = ("CD", "CY", "CL", "Cl", "Cm", "Cn", "CN", "CA")
"""The coefficients whose harmonics a dynamic point reports: the six of
:data:`cdpr.analysis.conventions.COEFFICIENTS` and the body-axis normal and axial force
``CN = -F_zB / (q S)``, ``CA = -F_xB / (q S)``."""

NAMED_DERIVATIVES: dict[str, tuple[tuple[str, str, str, float], ...]] = {
    "pitch": (
        ("Cma", "Cm", "in", 1.0),
        ("Cmq_plus_Cmadot", "Cm", "out", 1.0),
        ("CLa", "CL", "in", 1.0),
        ("CLq_plus_CLadot", "CL", "out", 1.0),
        ("CNa", "CN", "in", 1.0),
        ("CNq_plus_CNadot", "CN", "out", 1.0),
    ),
    "yaw": (
        ("Cnb", "Cn", "in", 1.0),
        ("Cnr_cosa_minus_Cnp_sina_minus_Cnbdot", "Cn", "out", -1.0),
        ("Clb", "Cl", "in", 1.0),
        ("Clr_cosa_minus_Clp_sina_minus_Clbdot", "Cl", "out", -1.0),
        ("CYb", "CY", "in", 1.0),
    ),
    "roll": (
        ("Clp_cosa_plus_Clr_sina_plus_Clbdot_sina", "Cl", "out", -1.0),
        ("Clb_sina", "Cl", "in", -1.0),
        ("Cnp_cosa_plus_Cnr_sina_plus_Cnbdot_sina", "Cn", "out", -1.0),
        ("Cnb_sina", "Cn", "in", -1.0),
    ),
}
"""Named derivatives per axis: ``(name, coefficient, in|out, sign)``, the name's value being
``sign`` times the coefficient's in-phase (``a1 / A``) or out-of-phase (``b1 / (A k)``) part with
respect to the pose coordinate.  With the model mounted nose upstream (``R_P_B = diag(-1, 1, -1)``):
pitch = aoa and body ``q = pitch rate``; a yaw oscillation about the tunnel's vertical at mean aoa
``a`` has sideslip = yaw, body ``p = sin(a) yaw_dot``, ``r = -cos(a) yaw_dot``, ``beta_dot =
yaw_dot``; a roll about the tunnel's axis has ``p = -cos(a) roll_dot``, ``r = -sin(a) roll_dot``,
sideslip ``= -sin(a) roll``.  The signs make each name the classical combination it spells (yaw
damping ``Cnr cos a - Cnp sin a - Cnbdot``: negative for a stable model)."""

PRIMARY_COEFFICIENTS: dict[str, tuple[str, ...]] = {
    "pitch": ("Cm", "CL"),
    "yaw": ("Cn", "Cl"),
    "roll": ("Cl", "Cn"),
    "heave": ("CL", "Cm"),
    "sway": ("CY", "Cn"),
    "surge": ("CD",),
}
"""The coefficients whose harmonic content the non-linear check looks at, per axis."""

CHORD_AXES: tuple[str, ...] = ("pitch", "heave", "surge")
"""Axes whose reduced frequency is on the chord, ``k = omega c / (2V)``; the others on the span."""


@dataclass(frozen=True)
class DynamicSettings:
    """Settings of the dynamic reduction (recorded in every summary).

    n_harmonics: harmonics fitted (the fundamental and the next ones); amplitude_tol_rel,
    frequency_tol_rel: the fitted motion's amplitude and frequency against the plan (flags
    ``motion_amplitude_off_plan``, ``motion_frequency_off_plan``); nonlinear_threshold: the
    higher harmonics' amplitude over the fundamental's above which a response is flagged
    ``nonlinear_response`` (when they are also significant, 3 σ); max_offset_sd_ns: a clock offset
    with a larger σ is ``clock_offset_not_identified``; offset_prior_ns: where the offset's
    Newton step starts (a known offset, or 0); n_grid: phases per cycle of the series' maps;
    loop_bins: phase bins of the hysteresis loops; goals: the derivatives' accuracy goals for
    the dwell time (95 % half-width of ``goal_inphase_rel`` of the in-phase value, of ``goal_outphase_rel`` or
    ``goal_outphase_abs`` per rad, whichever is larger, of the out-of-phase one); min_frames:
    camera frames per cycle below which the motion is not fitted; wind_off_mps: below it a point
    has no coefficients.
    """

    n_harmonics: int = 3
    amplitude_tol_rel: float = 0.05
    frequency_tol_rel: float = 0.002
    nonlinear_threshold: float = 0.10
    max_offset_sd_ns: float = 100_000.0
    offset_prior_ns: float = 0.0
    n_grid: int = 128
    loop_bins: int = 48
    goal_inphase_rel: float = 0.02
    goal_outphase_rel: float = 0.05
    goal_outphase_abs: float = 0.3
    min_frames_per_cycle: float = 4.0
    wind_off_mps: float = 1.0


DEFAULT_DYNAMIC = DynamicSettings()
"""The default settings."""


# ------------------------------------------------------------------------------------------------
# the samples' clock and the analysed window
# ------------------------------------------------------------------------------------------------
def analysis_window(start_ns: int, stop_ns: int, osc: Oscillation) -> tuple[int, int, int]:
    """The whole cycles analysed: ``(a_ns, b_ns, cycles)`` from ``start + settling/f`` (the
    motion's start is the point's start) to the planned end or ``stop_ns``, whichever comes
    first, cut to whole cycles of the planned frequency (a cycle short by at most 2 % counts)."""
    f = osc.frequency_Hz
    a = int(start_ns) + int(round(osc.settling_cycles / f * 1e9))
    b_plan = int(start_ns) + int(round((osc.settling_cycles + osc.cycles) / f * 1e9))
    span_s = (min(b_plan, int(stop_ns)) - a) * 1e-9
    cycles = max(0, int(math.floor(span_s * f + 0.02)))
    return a, a + int(round(cycles / f * 1e9)), cycles


# ------------------------------------------------------------------------------------------------
# the motion
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MotionFit:
    """The motion fitted from the camera: each pose coordinate as a harmonic series of the
    motion's phase ``theta = omega (t_cam - t_ref) * 1e-9 + phi0`` (camera clock, ns).

    axis: the moved pose coordinate (0..5); omega_rad_s, sd_omega_rad_s: the fitted angular
    frequency; coef: (6, 2H+1) the pose (m, rad) in that phase, the moved coordinate's
    fundamental ``A sin(theta)``; cov: (6p, 6p) its covariance (from the camera residuals, their
    correlation counted); n_frames, n_cycles, dof; residual_rms (6,).
    """

    axis: int
    omega_rad_s: float
    sd_omega_rad_s: float
    t_ref_ns: int
    phi0_rad: float
    coef: FloatArray
    cov: FloatArray
    n_frames: int
    n_cycles: int
    dof: float
    residual_rms: FloatArray

    @property
    def n_harmonics(self) -> int:
        return (self.coef.shape[1] - 1) // 2

    @property
    def amplitude(self) -> float:
        """A: the moved coordinate's fundamental (m or rad)."""
        return float(self.coef[self.axis, 1])

    def sd_term(self, coordinate: int, term: int) -> float:
        p = self.coef.shape[1]
        i = coordinate * p + term
        return float(math.sqrt(max(self.cov[i, i], 0.0)))

    @property
    def sd_amplitude(self) -> float:
        return self.sd_term(self.axis, 1)

    @property
    def sd_phase_rad(self) -> float:
        """σ of the motion's phase: the moved coordinate's quadrature σ over A."""
        return self.sd_term(self.axis, 2) / abs(self.amplitude)

    @property
    def distortion(self) -> float:
        """The moved coordinate's harmonics 2..H over its fundamental (amplitude ratio)."""
        c = self.coef[self.axis]
        return float(math.sqrt(float(np.sum(c[3:] ** 2))) / abs(self.amplitude))

    def phase(self, t_ns: ArrayLike, offset_ns: float = 0.0) -> FloatArray:
        """The motion's phase (rad) at load-cell times ``t_ns`` with the camera's clock
        ``offset_ns`` ahead (its clock reads ``t + offset``)."""
        d = (np.asarray(t_ns, dtype=np.int64) - np.int64(self.t_ref_ns)).astype(np.float64)
        return np.asarray(self.omega_rad_s * (d + float(offset_ns)) * 1e-9 + self.phi0_rad)

    def pose(self, phase_rad: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Pose, rate and acceleration (n, 6) at the phases (the fitted series and its exact
        time derivatives)."""
        rate = harmonic_rate(self.coef, self.omega_rad_s)
        acc = harmonic_rate(rate, self.omega_rad_s)
        return (
            harmonic_values(self.coef, phase_rad).T,
            harmonic_values(rate, phase_rad).T,
            harmonic_values(acc, phase_rad).T,
        )


def fit_motion(
    t_cam_ns: ArrayLike,
    poses: ArrayLike,
    pose_var: ArrayLike,
    usable: ArrayLike,
    window_ns: tuple[int, int],
    osc: Oscillation,
    n_harmonics: int = 3,
    max_iterations: int = 12,
) -> MotionFit:
    """The motion of one point from its camera frames (not finite differences): the frames with
    camera times in ``window_ns`` (whole cycles), each pose coordinate fitted by a harmonic
    series of the motion's phase, the frequency refined on the moved coordinate by Gauss-Newton
    from the planned one, each frame weighted by ``1 / pose_var`` (k, 6) (the camera's own
    variances in the (x, y, z, roll, pitch, yaw) parametrisation), σ from the residuals
    (:func:`cdpr.analysis.harmonics.harmonic_fit`).  The phase is then turned so the moved
    coordinate's fundamental is ``A sin(theta)``.

    t_cam_ns: (k,) camera times, sorted; poses: (k, 6); usable: (k,) frames that count.
    """
    t_all = np.asarray(t_cam_ns, dtype=np.int64)
    lo = int(np.searchsorted(t_all, window_ns[0], side="left"))  # the frames are time-sorted
    hi = int(np.searchsorted(t_all, window_ns[1], side="right"))
    t = t_all[lo:hi]
    q = np.asarray(poses, dtype=np.float64)[lo:hi]
    var = np.asarray(pose_var, dtype=np.float64)[lo:hi]
    ok = np.asarray(usable, dtype=bool)[lo:hi]
    ok = ok & np.isfinite(q).all(axis=1) & np.isfinite(var).all(axis=1) & (var > 0).all(axis=1)
    idx = np.flatnonzero(ok)
    p = n_terms(n_harmonics)
    if idx.size < 4 * p:
        raise InputError(f"fit_motion: {idx.size} camera frames in the window, {4 * p} needed")
    j = osc.index
    t_ref = int((int(window_ns[0]) + int(window_ns[1])) // 2)
    tau = (t[idx] - t_ref).astype(np.float64) * 1e-9
    y = q[idx, j]
    w = 1.0 / var[idx, j]
    omega = osc.omega_rad_s
    sd_omega = float("nan")
    for _ in range(max_iterations):  # Gauss-Newton on the frequency (iterations, not samples)
        X = harmonic_basis(omega * tau, n_harmonics)
        G = (X.T * w) @ X
        beta = np.linalg.solve(G, (X.T * w) @ y)
        d = np.zeros_like(tau)
        for h in range(1, n_harmonics + 1):
            d += h * tau * (beta[2 * h - 1] * X[:, 2 * h] - beta[2 * h] * X[:, 2 * h - 1])
        Xa = np.column_stack([X, d])
        Ga = (Xa.T * w) @ Xa
        sol = np.linalg.solve(Ga, (Xa.T * w) @ (y - X @ beta))
        step = float(sol[-1])
        res = y - X @ beta - Xa @ sol
        chi2 = float(np.sum(w * res * res)) / max(idx.size - p - 1, 1)
        sd_omega = float(math.sqrt(max(np.linalg.inv(Ga)[-1, -1] * chi2, 0.0)))
        omega += step
        if abs(step) * float(np.max(np.abs(tau))) < 1e-9:
            break
    weights = 1.0 / var[idx]
    hf: HarmonicFit = harmonic_fit(omega * tau, q[idx], n_harmonics, weights=weights)
    a1, b1 = hf.coef[j, 1], hf.coef[j, 2]
    phi = float(math.atan2(b1, a1))
    S = phase_shift_matrix(phi, n_harmonics)
    T = np.kron(np.eye(6), S)
    coef = hf.coef @ S.T
    cov = T @ hf.cov @ T.T
    return MotionFit(
        axis=j,
        omega_rad_s=float(omega),
        sd_omega_rad_s=sd_omega,
        t_ref_ns=t_ref,
        phi0_rad=phi,
        coef=coef,
        cov=0.5 * (cov + cov.T),
        n_frames=int(idx.size),
        n_cycles=hf.n_cycles,
        dof=hf.dof,
        residual_rms=hf.residual_rms,
    )


# ------------------------------------------------------------------------------------------------
# the cable wrench along the motion
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Body:
    """The mass properties the reduction uses: mass (kg), centre of mass in {P} (m), inertia about
    P in {P} (kg m^2), gravity in {O} (m/s^2) (the rig file's, or the weight model's mass and
    centre of mass)."""

    mass_kg: float
    com_P_m: FloatArray
    inertia_P_kgm2: FloatArray
    gravity_O_mps2: FloatArray

    @classmethod
    def of(cls, rig: Rig, mass_kg: float | None = None, com_P_m: ArrayLike | None = None) -> Body:
        return cls(
            float(rig.mass_kg if mass_kg is None else mass_kg),
            np.asarray(rig.com_P_m if com_P_m is None else com_P_m, dtype=np.float64),
            np.asarray(rig.inertia_P_kgm2, dtype=np.float64),
            np.asarray(rig.gravity_O_mps2, dtype=np.float64),
        )


CHUNK = 50_000
"""Samples per chunk of the structure matrices (bounds the memory of a long point)."""


def _cable_wrench(rig: Rig, body: Body, pose: FloatArray, tensions: FloatArray) -> FloatArray:
    """``-A(q) T - G(q)`` (n, 6) at P in {O}, in chunks."""
    out = np.empty((pose.shape[0], 6))
    for s in range(0, pose.shape[0], CHUNK):
        q = pose[s : s + CHUNK]
        R = rotation_from_euler(q[:, 3:])
        A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, q[:, :3], R)
        G = gravity_wrench(body.mass_kg, body.com_P_m, R, body.gravity_O_mps2)
        out[s : s + CHUNK] = -np.einsum("nij,nj->ni", A, tensions[s : s + CHUNK]) - G
    return out


def _pose_sensitivity(rig: Rig, body: Body, pose: FloatArray, tensions: FloatArray) -> FloatArray:
    """``K = d(-A(q) T - G(q))/dq`` (6, 6) at one pose and tensions, by central differences."""
    step = np.array([1e-6] * 3 + [1e-6] * 3)
    Q = np.repeat(pose[None, :], 12, axis=0)
    for i in range(6):
        Q[2 * i, i] += step[i]
        Q[2 * i + 1, i] -= step[i]
    W = _cable_wrench(rig, body, Q, np.repeat(tensions[None, :], 12, axis=0))
    return np.asarray((W[0::2] - W[1::2]).T / (2.0 * step)[None, :])


@dataclass(frozen=True)
class WrenchHarmonics:
    """The cable wrench ``W = -A(q) T - G(q)`` along the motion of one point (at P in {O}), as
    harmonics of the motion's phase.

    coef: (6, p); cov_load_cells, cov_pose: (6p, 6p) (module docstring); d_offset: (6, p) the
    coefficients' derivative with respect to the clock offset (per ns); sensitivity: (6, 6) ``K``;
    inertia_model: (6, p) the harmonics of ``M qdd + C`` of the fitted motion with the rig file's
    mass and inertia; amplitude, sd_amplitude: the motion's; n_samples, n_cycles, dof;
    tension_outside: samples of the window with a tension outside its limits;
    min_margin_N: the smallest margin to a limit over the window; loops: (n_c, bins, 6) the cable
    wrench averaged per cycle and phase bin (NaN where a bin is empty), loop_phase: (bins,) the
    bins' centres.
    """

    coef: FloatArray
    cov_load_cells: FloatArray
    cov_pose: FloatArray
    d_offset: FloatArray
    sensitivity: FloatArray
    inertia_model: FloatArray
    amplitude: float
    sd_amplitude: float
    n_samples: int
    n_cycles: int
    dof: float
    pose_dof: float
    tension_outside: int
    min_margin_N: float
    loops: FloatArray
    loop_phase: FloatArray


def wrench_harmonics(
    rig: Rig,
    t_ns: ArrayLike,
    tensions_N: ArrayLike,
    usable: ArrayLike,
    motion: MotionFit,
    offset_ns: float,
    window_ns: tuple[int, int],
    body: Body | None = None,
    loop_bins: int = 48,
    n_grid: int = 128,
) -> WrenchHarmonics:
    """The cable wrench along the motion of one point and its harmonics (vectorised over samples).

    At every load-cell sample of the window (``t_ns`` on the load cells' clock, ``tensions_N``
    (n, m), ``usable`` (n,)): the pose from the fitted motion at the camera's time
    ``t + offset_ns`` (not finite differences), the structure matrix there, ``W = -A T - G``; its
    harmonics in the motion's phase with σ from the residuals; the pose's σ carried by
    ``K = dW/dq`` at the mean pose and tensions and by the motion's phase; the coefficients'
    derivative with respect to the offset; the rig file's (or ``body``'s) ``M qdd + C`` of the
    fitted motion; the tension limits over the window; the hysteresis bins.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    T = np.asarray(tensions_N, dtype=np.float64)
    ok = np.asarray(usable, dtype=bool) & (t >= window_ns[0]) & (t <= window_ns[1])
    ok &= np.isfinite(T).all(axis=1)
    idx = np.flatnonzero(ok)
    H = motion.n_harmonics
    p = n_terms(H)
    if idx.size < 8 * p:
        raise InputError(f"wrench_harmonics: {idx.size} usable samples in the window")
    body = body or Body.of(rig)
    ph = motion.phase(t[idx], offset_ns)
    q = harmonic_values(motion.coef, ph).T
    Tu = T[idx]
    W = _cable_wrench(rig, body, q, Tu)
    hf = harmonic_fit(ph, W, H)
    coef = hf.coef
    K = _pose_sensitivity(rig, body, motion.coef[:, 0], Tu.mean(axis=0))
    A = motion.amplitude
    J = np.kron(K, np.eye(p))
    J[:, motion.axis * p + 2] += phase_derivative(coef).reshape(-1) / A
    cov_pose = J @ motion.cov @ J.T
    rate = harmonic_rate(motion.coef, motion.omega_rad_s)
    d_off = (K @ rate + motion.omega_rad_s * phase_derivative(coef)) * 1e-9
    # M qdd + C of the fitted motion, on one cycle
    g = grid_phases(n_grid)
    qg, qdg, qddg = motion.pose(g)
    D = inertia_wrench(body.mass_kg, body.com_P_m, body.inertia_P_kgm2, qg, qdg, qddg)
    D_coef = harmonics_from_grid(D, H).reshape(6, p)
    # the tension limits over the window
    margin = np.minimum(Tu - rig.t_min_N, rig.t_max_N - Tu)
    outside = int(np.count_nonzero((margin < 0).any(axis=1)))
    # hysteresis bins: the cable wrench per cycle and phase bin
    nb = int(loop_bins)
    c0 = math.floor(ph[0] / TWO_PI)
    cyc = np.floor(ph / TWO_PI).astype(np.int64) - c0
    b = np.minimum(((ph / TWO_PI - np.floor(ph / TWO_PI)) * nb).astype(np.int64), nb - 1)
    n_c = int(cyc[-1]) + 1
    flat = cyc * nb + b
    cnt = np.bincount(flat, minlength=n_c * nb).astype(np.float64)
    loops = np.full((n_c * nb, 6), np.nan)
    have = cnt > 0
    for k in range(6):  # components, not samples
        loops[have, k] = np.bincount(flat, W[:, k], minlength=n_c * nb)[have] / cnt[have]
    return WrenchHarmonics(
        coef=coef,
        cov_load_cells=hf.cov,
        cov_pose=0.5 * (cov_pose + cov_pose.T),
        d_offset=d_off,
        sensitivity=K,
        inertia_model=D_coef,
        amplitude=A,
        sd_amplitude=motion.sd_amplitude,
        n_samples=int(idx.size),
        n_cycles=hf.n_cycles,
        dof=hf.dof,
        pose_dof=motion.dof,
        tension_outside=outside,
        min_margin_N=float(np.min(margin)),
        loops=loops.reshape(n_c, nb, 6),
        loop_phase=(np.arange(nb) + 0.5) * TWO_PI / nb,
    )


# ------------------------------------------------------------------------------------------------
# the clock offset
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class OffsetInput:
    """What one wind-off oscillation (an inertia tare) gives the clock offset: its load-cell
    times (on their clock), tensions, usable samples, fitted motion and window."""

    t_ns: NDArray[np.int64]
    tensions_N: FloatArray
    usable: NDArray[np.bool_]
    motion: MotionFit
    window_ns: tuple[int, int]


@dataclass(frozen=True)
class ClockOffset:
    """The camera's clock offset (ns, > 0: camera ahead) and its σ; identified: σ below the
    settings' bound with at least one tare; per tare its estimate and σ; chi2_per_dof of the
    tares' agreement (σ scaled up by its root when above 1); note: how it was found."""

    offset_ns: float
    sd_ns: float
    identified: bool
    estimates_ns: FloatArray
    sd_estimates_ns: FloatArray
    chi2_per_dof: float
    note: str


def clock_offset(
    rig: Rig,
    tares: Sequence[OffsetInput],
    body: Body | None = None,
    prior_ns: float = 0.0,
    max_sd_ns: float = 100_000.0,
    max_newton: int = 4,
) -> ClockOffset:
    """The camera's clock offset from the wind-off oscillations: with the right offset the cable
    wrench of a wind-off motion (inertia, gravity and the pretension's geometry, all functions of
    ``sin(theta)``) has no quadrature at the fundamental in any component; an offset error
    ``dt`` puts ``K qdot dt`` (the structure matrix at the wrong pose) and ``omega dt`` times the
    in-phase part (the phase) into it.  Per tare the six quadratures at the ``prior_ns`` offset
    and their derivatives with respect to it (:attr:`WrenchHarmonics.d_offset`: exact at the
    fundamental to first order) give a Newton step (generalised least squares over the
    components with their covariance: load cells and pose), repeated until a step is below a
    fifth of the σ (at most ``max_newton`` evaluations; each tare starts from the previous one's
    estimate, so the later ones take one); the tares' estimates are averaged with their
    weights.  Without a tare, or with a σ above ``max_sd_ns``: not identified (offset 0
    with its σ, the caller flags it)."""
    if not tares:
        return ClockOffset(
            0.0, math.inf, False, np.zeros(0), np.zeros(0), math.nan,
            "no wind-off oscillation (oscillation_tare) in the run",
        )  # fmt: skip
    est, sd = [], []
    at = float(prior_ns)
    for tr in tares:  # tares, not samples
        e_k, sd_k = at, math.inf
        for _ in range(max_newton):  # Newton steps until the step is within a fifth of σ
            try:
                w0 = wrench_harmonics(
                    rig, tr.t_ns, tr.tensions_N, tr.usable, tr.motion, at, tr.window_ns, body
                )
            except InputError:  # a tare without enough usable samples gives nothing
                break
            p = w0.coef.shape[1]
            sel = np.arange(6) * p + 2
            q0 = w0.coef[:, 2]
            s = w0.d_offset[:, 2]  # d quadrature / d offset: K qdot and the phase (per ns)
            C = (w0.cov_load_cells + w0.cov_pose)[np.ix_(sel, sel)]
            Ci = np.linalg.pinv(C, rcond=1e-12)
            info = float(s @ Ci @ s)
            if not info > 0:
                break
            step = -float((s @ Ci @ q0) / info)
            e_k, sd_k = at + step, float(1.0 / math.sqrt(info))
            at = e_k
            if abs(step) < max(0.2 * sd_k, 1.0):
                break
        est.append(e_k)
        sd.append(sd_k)
    e, d = np.asarray(est), np.asarray(sd)
    fin = np.isfinite(d)
    if not fin.any():
        return ClockOffset(0.0, math.inf, False, e, d, math.nan, "no inertia signal in the tares")
    wgt = 1.0 / d[fin] ** 2
    mean = float(np.sum(wgt * e[fin]) / np.sum(wgt))
    sd_mean = float(1.0 / math.sqrt(float(np.sum(wgt))))
    chi2 = math.nan
    if fin.sum() > 1:
        chi2 = float(np.sum(wgt * (e[fin] - mean) ** 2) / (fin.sum() - 1))
        sd_mean *= math.sqrt(max(chi2, 1.0))
    ok = sd_mean <= max_sd_ns
    note = (
        f"from {int(fin.sum())} wind-off oscillation(s): the quadrature of the inertia's "
        "fundamental made zero"
    )
    return ClockOffset(mean, sd_mean, ok, e, d, chi2, note)


# ------------------------------------------------------------------------------------------------
# the inertia removed
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class InertiaRemoval:
    """The aerodynamic wrench's harmonics (6, p) at P in {O} with the inertia removed two ways.

    aero: by the wind-off oscillation tare when there is one (``W_on - s W_tare``, ``s`` the
    amplitude ratio to the power of the harmonic), else by the model; aero_model: by the rig
    file's mass and inertia (``W_on + (M qdd + C)``); inertia_tare: the inertia the tare measured,
    ``-s W_tare`` (NaN without one); inertia_model: ``M qdd + C``; method: ``"tare"`` or
    ``"model"``; terms, terms_model: covariance (6p, 6p) by source of ``aero`` and
    ``aero_model``; loops: (n_c, bins, 6) the point's bins with the same inertia removed as
    ``aero`` (None when not given); dof, dof_model: degrees of freedom of each term (the fewest of
    the fits it comes from; the clock offset's infinite).
    """

    aero: FloatArray
    aero_model: FloatArray
    inertia_tare: FloatArray
    inertia_model: FloatArray
    method: str
    terms: Mapping[str, FloatArray]
    terms_model: Mapping[str, FloatArray]
    loops: FloatArray | None = field(default=None)
    dof: Mapping[str, float] = field(default_factory=dict)
    dof_model: Mapping[str, float] = field(default_factory=dict)


def remove_inertia(
    point: WrenchHarmonics,
    tare: WrenchHarmonics | None,
    sd_offset_ns: float = 0.0,
) -> InertiaRemoval:
    """Remove the inertia from a point's cable wrench, component by component at each harmonic:
    by its wind-off oscillation tare (its harmonics scaled by the amplitude ratio ``r = A/A_tare``
    as ``r^h``; the tare's mean, which also holds the weight at the mean attitude, unscaled) and,
    beside it, by the rig file's ``M qdd + C``.  σ: the point's and the tare's load-cell and pose
    terms; the clock offset's through the difference of their sensitivities to it (the model
    path: the point's alone, and the amplitude's σ through ``M qdd + C``, the rig file's mass
    and inertia taken as exact).  The hysteresis bins get the same removal at their phases."""
    p = point.coef.shape[1]
    H = (p - 1) // 2
    D = point.inertia_model
    aero_model = point.coef + D
    dD = D.copy()
    dD[:, 0] = 0.0
    dD = dD / point.amplitude
    off = 0.0 if not math.isfinite(sd_offset_ns) else float(sd_offset_ns)
    dm = point.d_offset.reshape(-1)
    terms_model = {
        "load_cells": point.cov_load_cells,
        "pose": point.cov_pose + np.outer(dD.reshape(-1), dD.reshape(-1)) * point.sd_amplitude**2,
        "clock_offset": np.outer(dm, dm) * off**2,
    }
    dof_model = {"load_cells": point.dof, "pose": point.pose_dof, "clock_offset": math.inf}
    if tare is None:
        nan = np.full_like(point.coef, np.nan)
        loops = None if point.loops is None else point.loops + _series_at(D, point.loop_phase)
        return InertiaRemoval(
            aero_model, aero_model, nan, D, "model", terms_model, terms_model, loops,
            dof_model, dof_model,
        )  # fmt: skip
    r = point.amplitude / tare.amplitude
    s = np.ones(p)
    for h in range(1, H + 1):
        s[2 * h - 1] = s[2 * h] = r**h
    inertia_tare = -(tare.coef * s)
    aero = point.coef + inertia_tare
    Sd = np.kron(np.eye(6), np.diag(s))
    d = (point.d_offset - tare.d_offset * s).reshape(-1)
    terms = {
        "load_cells": point.cov_load_cells + Sd @ tare.cov_load_cells @ Sd.T,
        "pose": point.cov_pose + Sd @ tare.cov_pose @ Sd.T,
        "clock_offset": np.outer(d, d) * off**2,
    }
    loops = point.loops + _series_at(inertia_tare, point.loop_phase)
    dof = {
        "load_cells": min(point.dof, tare.dof),
        "pose": min(point.pose_dof, tare.pose_dof),
        "clock_offset": math.inf,
    }
    return InertiaRemoval(
        aero, aero_model, inertia_tare, D, "tare", terms, terms_model, loops, dof, dof_model
    )


def _series_at(coef: FloatArray, phase: FloatArray) -> FloatArray:
    """A (6, p) series at the phases: (bins, 6)."""
    return np.asarray(harmonic_values(coef, phase).T)


# ------------------------------------------------------------------------------------------------
# the derivatives
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Derivatives:
    """The dynamic derivatives of one point (see :func:`dynamic_derivatives`).

    wrench_mrp: (6, p) the aerodynamic wrench with moments about the MRP ({O} axes) as harmonics;
    wrench_mrp_terms: name -> (6p, 6p); coef: (8, p) the coefficients :data:`DYNAMIC_COEFFICIENTS`
    (NaN wind off); terms: name -> (8p, 8p); inphase, outphase, sd_inphase, sd_outphase: (8,);
    k: the reduced frequency; named: name -> (value, σ); named_dof: name -> the effective degrees
    of freedom of that σ (Welch-Satterthwaite over the terms); harmonic_content: (8,) the harmonics
    2..H over the fundamental; harmonic_sd: (8,) σ of those harmonics' amplitude; nonlinear: the
    primary coefficients' content above the threshold and significant; dwell_s: name -> the dwell
    time that reaches the goal; loops: (n_c, bins, 8) the coefficients per cycle and phase bin,
    loop_angle: (bins,) the moved coordinate there; mean_flow: (aoa, sideslip) at the mean pose.
    """

    wrench_mrp: FloatArray
    wrench_mrp_terms: Mapping[str, FloatArray]
    coef: FloatArray
    terms: Mapping[str, FloatArray]
    inphase: FloatArray
    outphase: FloatArray
    sd_inphase: FloatArray
    sd_outphase: FloatArray
    k: float
    named: Mapping[str, tuple[float, float]]
    named_dof: Mapping[str, float]
    harmonic_content: FloatArray
    harmonic_sd: FloatArray
    nonlinear: bool
    dwell_s: Mapping[str, float]
    loops: FloatArray | None
    loop_angle: FloatArray | None


def _maps(
    pose: FloatArray,
    q_Pa: float,
    area_m2: float,
    span_m: float,
    chord_m: float,
    mrp_P_m: ArrayLike,
    nose_P: ArrayLike,
    up_P: ArrayLike,
) -> FloatArray:
    """(g, 14, 6): per pose, the linear maps of the wrench at P in {O} to the wrench about the
    MRP ({O} axes, rows 0-5) and to the coefficients :data:`DYNAMIC_COEFFICIENTS` (rows 6-13,
    NaN when q is not > 0)."""
    R = rotation_from_euler(pose[:, 3:])
    g = pose.shape[0]
    M = np.full((g, 14, 6), np.nan)
    r = np.einsum("gij,j->gi", R, np.asarray(mrp_P_m, dtype=np.float64))
    for c in range(6):  # the transfer, column by column (linear)
        e = np.zeros((g, 6))
        e[:, c] = 1.0
        M[:, :6, c] = transfer_moment(e, r)
    if q_Pa > 0:
        M[:, 6:12] = coefficient_matrix(
            R, np.full(g, q_Pa), area_m2, span_m, chord_m, mrp_P_m, nose_P, up_P
        )
        R_B_O = body_from_tunnel(R, nose_P, up_P)
        qS = q_Pa * area_m2
        M[:, 12, :3] = -R_B_O[:, 2, :] / qS  # CN = -F_zB / (q S)
        M[:, 13, :3] = -R_B_O[:, 0, :] / qS  # CA = -F_xB / (q S)
        M[:, 12:, 3:] = 0.0
    return M


def dynamic_derivatives(
    aero: ArrayLike,
    terms: Mapping[str, ArrayLike],
    motion: MotionFit,
    axis: str,
    q_Pa: float,
    airspeed_mps: float,
    area_m2: float,
    span_m: float,
    chord_m: float,
    mrp_P_m: ArrayLike = (0.0, 0.0, 0.0),
    nose_P: ArrayLike = (-1.0, 0.0, 0.0),
    up_P: ArrayLike = (0.0, 0.0, 1.0),
    window_s: float = math.nan,
    loops: ArrayLike | None = None,
    loop_phase: ArrayLike | None = None,
    settings: DynamicSettings = DEFAULT_DYNAMIC,
    dof: Mapping[str, float] | None = None,
) -> Derivatives:
    """The derivatives of one point from its aerodynamic wrench's harmonics (6, p) at P in {O}.

    On a grid of one cycle the series is moved to the MRP and into the body and wind axes at the
    fitted pose of each phase (the axes turn with the model) and divided by ``q S`` (``b`` or
    ``c``); the coefficients' harmonics follow (exact within the series), their covariance by the
    same linear map per source.  In-phase ``a1 / A``, out-of-phase ``b1 / (A k)``,
    ``k = omega l / (2V)`` (``l`` the chord for pitch, heave, surge; the span for yaw, roll,
    sway); named derivatives per :data:`NAMED_DERIVATIVES`.  The amplitude's σ is added to each
    derivative's relative σ.  ``dof``: each term's degrees of freedom, combined per derivative
    by Welch-Satterthwaite (a term without one counts as exact).  Wind off (``q_Pa`` not > 0):
    the wrench about the MRP only."""
    W = np.asarray(aero, dtype=np.float64)
    p = W.shape[1]
    H = (p - 1) // 2
    g = grid_phases(settings.n_grid)
    pose_g, _, _ = motion.pose(g)
    M = _maps(pose_g, q_Pa, area_m2, span_m, chord_m, mrp_P_m, nose_P, up_P)  # (g, 14, 6)
    J = harmonic_linear_map(M, H)  # (14 p, 6 p)
    out = (J @ W.reshape(-1)).reshape(14, p)
    cov = {k: J @ np.asarray(v) @ J.T for k, v in terms.items()}
    wm = out[:6]
    wm_terms = {k: v[: 6 * p, : 6 * p] for k, v in cov.items()}
    coef = out[6:]
    cterms = {k: v[6 * p :, 6 * p :] for k, v in cov.items()}
    tot = sum(cterms.values()) if cterms else np.zeros((8 * p, 8 * p))
    sd = np.sqrt(np.clip(np.diag(tot), 0.0, None)).reshape(8, p)
    A = motion.amplitude
    lref = chord_m if axis in CHORD_AXES else span_m
    k = motion.omega_rad_s * lref / (2.0 * airspeed_mps) if airspeed_mps > 0 else math.nan
    rel_A = motion.sd_amplitude / abs(A)
    inphase = coef[:, 1] / A
    outphase = coef[:, 2] / (A * k)
    sd_in = np.hypot(sd[:, 1] / abs(A), inphase * rel_A)
    sd_out = np.hypot(sd[:, 2] / abs(A * k), outphase * rel_A)
    names = list(DYNAMIC_COEFFICIENTS)
    named: dict[str, tuple[float, float]] = {}
    named_dof: dict[str, float] = {}
    dwell: dict[str, float] = {}
    for name, c, part, sign in NAMED_DERIVATIVES.get(axis, ()):
        i = names.index(c)
        v, s_ = (inphase[i], sd_in[i]) if part == "in" else (outphase[i], sd_out[i])
        named[name] = (float(sign * v), float(s_))
        j = i * p + (1 if part == "in" else 2)
        var = {t: float(np.asarray(m)[j, j]) for t, m in cterms.items()}
        named_dof[name] = welch_satterthwaite(var, dof or {})
        goal = (
            settings.goal_inphase_rel * abs(v)
            if part == "in"
            else max(settings.goal_outphase_rel * abs(v), settings.goal_outphase_abs)
        )
        dwell[name] = float(window_s * (1.96 * s_ / goal) ** 2) if goal > 0 else math.nan
    # harmonic content of each coefficient (2..H over the fundamental) and its σ
    fund = np.hypot(coef[:, 1], coef[:, 2])
    high = np.sqrt(np.sum(coef[:, 3:] ** 2, axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        content = high / fund
        var_hi = np.sum((coef[:, 3:] * sd[:, 3:]) ** 2, axis=1) / np.where(high > 0, high**2, 1.0)
    sd_hi = np.sqrt(var_hi)
    prim = [names.index(c) for c in PRIMARY_COEFFICIENTS.get(axis, ())]
    nonlinear = bool(
        any(
            content[i] > settings.nonlinear_threshold and high[i] > 3.0 * sd_hi[i]
            for i in prim
            if np.isfinite(content[i])
        )
    )
    lc = la = None
    if loops is not None and loop_phase is not None and q_Pa > 0:
        L = np.asarray(loops, dtype=np.float64)
        lp = np.asarray(loop_phase, dtype=np.float64)
        pose_b, _, _ = motion.pose(lp)
        Mb = _maps(pose_b, q_Pa, area_m2, span_m, chord_m, mrp_P_m, nose_P, up_P)[:, 6:]
        lc = np.einsum("bij,cbj->cbi", Mb, L)
        la = pose_b[:, motion.axis]
    return Derivatives(
        wrench_mrp=wm,
        wrench_mrp_terms=wm_terms,
        coef=coef,
        terms=cterms,
        inphase=inphase,
        outphase=outphase,
        sd_inphase=sd_in,
        sd_outphase=sd_out,
        k=float(k),
        named=named,
        named_dof=named_dof,
        harmonic_content=content,
        harmonic_sd=sd_hi / np.where(fund > 0, fund, np.nan),
        nonlinear=nonlinear,
        dwell_s=dwell,
        loops=lc,
        loop_angle=la,
    )


def welch_satterthwaite(variances: Mapping[str, float], dof: Mapping[str, float]) -> float:
    """The effective degrees of freedom of a sum of variance terms (Welch-Satterthwaite,
    GUM G.4): ``(sum u_i^2)^2 / sum(u_i^4 / nu_i)``; a term without a ``dof`` (or an infinite
    one) is exact."""
    tot = sum(variances.values())
    den = sum(v * v / dof[k] for k, v in variances.items() if k in dof and math.isfinite(dof[k]))
    return float(tot * tot / den) if den > 0 else math.inf


def coverage_factor(dof: float, level: float = 0.95) -> float:
    """The two-sided coverage factor of Student's t at ``level`` with ``dof`` degrees of freedom
    (the normal's for infinite ones)."""
    from scipy.special import ndtri, stdtrit

    q = 0.5 + level / 2.0
    if not math.isfinite(dof):
        return float(ndtri(q))
    return float(stdtrit(max(dof, 1.0), q))


def is_angular(axis: str) -> bool:
    """True for roll, pitch, yaw (amplitudes in rad)."""
    return axis in ANGULAR_AXES
