"""Pose from 2D-3D correspondences: PnP, LM refinement, reprojection error, covariance, outliers.

Pipeline of :func:`estimate_pose`: SQPnP (or the iterative solver from a guess) for a first pose of
{P} in the camera frame {C}, Levenberg-Marquardt refinement (``cv2.solvePnPRefineLM``), residuals,
points beyond ``outlier_k`` sigma dropped and the pose refined again, then the covariance
``Sigma = s^2 (J^T J)^-1`` from the projection Jacobian ``J`` (2N x 6) with respect to a
translation ``dt_C`` and a small rotation ``dtheta_C`` applied on the left (``R' = exp(dtheta) R``),
and everything expressed in the tunnel frame {O} through the camera extrinsics.

Noise from the data: ``s^2 = (nu0 sigma_px^2 + RSS) / (nu0 + 2n - 6)``, the inliers' residual sum
of squares over its ``2n - 6`` degrees of freedom, pooled with the detector's nominal ``sigma_px``
only where the data are thin: ``nu0 = max(0, 6 - (2n - 6))`` (``prior_dof`` overrides it), so from
6 points on the residuals alone decide, and with 4 or 5 points the nominal value keeps one lucky
small residual from making the pose look exact.  ``s`` is returned in ``extra["sigma_px"]`` (and
the residual degrees of freedom in ``extra["dof"]``).  With ``noise_shape`` (correlated image
noise of known shape, e.g. edge-fitted marker corners) ``s^2 = RSS / tr((I - H) Sigma)`` and the
covariance is the least-squares sandwich ``s^2 (J^T J)^-1 J^T Sigma J (J^T J)^-1``.

Covariance layout (6 x 6): ``[position_O_m (3), rotation_O_rad (3)]``, the rotation part being a
small rotation vector in {O} axes applied on the left: ``R_est = exp([dtheta]x) R_true``.
The extrinsics are treated as exact (their error is a constant bias over a run, not noise).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.analysis.rotations import euler_from_rotation, quaternion_from_rotation

from . import cv
from .camera_model import CameraModel

F64 = NDArray[np.float64]

# status flags of a pose (bit field, shared with detect.py and the camera source)
FLAG_NO_POSE = 1 << 0  # no pose at all (nothing detected, PnP failed)
FLAG_FEW_POINTS = 1 << 1  # fewer correspondences than needed for a trustworthy pose
FLAG_AMBIGUOUS = 1 << 2  # labelling of point markers ambiguous (margin over runner-up too small)
FLAG_HIGH_RESIDUAL = 1 << 3  # reprojection RMS above the limit
FLAG_OUTLIERS = 1 << 4  # some correspondences rejected as outliers
FLAG_TRACK_RESET = 1 << 5  # tracking lost, re-acquired from scratch (informational)
FLAG_SINGLE_MARKER = 1 << 6  # pose from one square marker's corners (informational)
FLAG_SATURATED = 1 << 7  # markers' whites clipped at 255: edges biased (overexposed; unusable)
FLAG_OCCLUDED_MARK = 1 << 8  # an IR mark's blob damaged (e.g. a cable across it) or lost: dropped
FLAG_NAMES = {
    FLAG_NO_POSE: "no_pose",
    FLAG_FEW_POINTS: "few_points",
    FLAG_AMBIGUOUS: "ambiguous",
    FLAG_HIGH_RESIDUAL: "high_residual",
    FLAG_OUTLIERS: "outliers",
    FLAG_TRACK_RESET: "track_reset",
    FLAG_SINGLE_MARKER: "single_marker",
    FLAG_SATURATED: "saturated",
    FLAG_OCCLUDED_MARK: "occluded_mark",
}
BAD_FLAGS = FLAG_NO_POSE | FLAG_FEW_POINTS | FLAG_AMBIGUOUS | FLAG_HIGH_RESIDUAL | FLAG_SATURATED
"""Flags that make a pose unusable for analysis (outliers, resets, a single marker and an occluded
mark are informational: the pose's covariance, from fewer points, says how much less it is worth)."""


MIN_NOISE_DOF = 6.0
"""Residual degrees of freedom below which the nominal sigma_px fills in (see the module doc)."""


def flag_names(flags: int) -> list[str]:
    """Names of the bits set in ``flags``."""
    return [n for b, n in FLAG_NAMES.items() if flags & b]


@dataclass
class PoseEstimate:
    """One pose of {P}: in {O} (``position_O_m`` (3,), ``R_O_P`` (3, 3), ``q_wxyz`` (4,),
    ``euler_rad`` (3,) Z-Y-X as :mod:`cdpr.analysis.rotations`), in {C} (``rvec_C``, ``tvec_C_m``),
    reprojection RMS (px, Euclidean per point), per-point residuals (N, 2) px, inlier mask (N,),
    covariance (6, 6) ``[position_O_m, rotation_O_rad]`` and ``flags`` (see ``FLAG_*``)."""

    position_O_m: F64
    R_O_P: F64
    rvec_C: F64
    tvec_C_m: F64
    reprojection_rms_px: float
    residuals_px: F64
    inliers: NDArray[np.bool_]
    covariance: F64
    flags: int = 0
    n_points: int = 0
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not (self.flags & BAD_FLAGS)

    @property
    def q_wxyz(self) -> F64:
        return quaternion_from_rotation(self.R_O_P)

    @property
    def euler_rad(self) -> F64:
        return euler_from_rotation(self.R_O_P)

    @property
    def std_position_m(self) -> F64:
        return np.sqrt(np.diag(self.covariance)[:3])

    @property
    def std_rotation_rad(self) -> F64:
        return np.sqrt(np.diag(self.covariance)[3:])


def failed_pose(flags: int = FLAG_NO_POSE) -> PoseEstimate:
    """A placeholder pose (NaN) carrying ``flags``."""
    nan3 = np.full(3, np.nan)
    return PoseEstimate(
        nan3,
        np.full((3, 3), np.nan),
        nan3,
        nan3,
        float("nan"),
        np.zeros((0, 2)),
        np.zeros(0, bool),
        np.full((6, 6), np.nan),
        flags | FLAG_NO_POSE,
        0,
    )


def _exp_so3(w: F64) -> F64:
    return cv.rodrigues(w)


def projection_jacobian(object_points: F64, rvec: F64, tvec: F64, K: F64, dist: F64) -> F64:
    """J (2N, 6): d(pixels)/d[dt_C (m), dtheta_C (rad, left: R' = exp(dtheta) R)].

    The points are moved into the camera frame (minus t) first, so the pose becomes (rvec = 0, t):
    at rvec = 0 OpenCV's d/drvec is exactly the left small-rotation derivative.
    """
    R = cv.rodrigues(rvec)
    Y = np.asarray(object_points, np.float64) @ R.T
    _, jac = cv.project_points_jacobian(Y, np.zeros(3), tvec, K, dist)
    return np.concatenate([jac[:, 3:6], jac[:, 0:3]], axis=1)


def estimate_pose(
    object_points_P: ArrayLike,
    image_points_px: ArrayLike,
    camera: CameraModel,
    sigma_px: float,
    guess: tuple[F64, F64] | None = None,
    method: str = "sqpnp",
    min_points: int = 4,
    outlier_k: float = 5.0,
    max_rms_px: float = 2.0,
    prior_dof: float | None = None,
    noise_shape: ArrayLike | None = None,
) -> PoseEstimate:
    """Pose of {P} from (N, 3) points in {P} (m) and their (N, 2) image positions (px).

    sigma_px: nominal standard deviation of one image coordinate of one point (px): the outlier
    gate and the prior of the noise estimate (module docstring), pooled with the residuals.
    guess: optional ``(rvec_C, tvec_C)`` to start the iterative solver from (tracking).
    noise_shape: optional (2N, 2N) relative covariance of the image coordinates (x0, y0, x1, ..),
    e.g. block-diagonal :func:`cdpr.calibration.detect.edge_fit_corner_covariance` for edge-fitted
    marker corners; None: independent, equal noise (module docstring).
    Returns a :class:`PoseEstimate`; on failure its flags say why (the pose is then NaN or
    untrustworthy).
    """
    obj = np.asarray(object_points_P, np.float64).reshape(-1, 3)
    img = np.asarray(image_points_px, np.float64).reshape(-1, 2)
    n = len(obj)
    if n < max(min_points, 3) or n < 4:
        return failed_pose(FLAG_FEW_POINTS)
    K, dist = camera.K, camera.dist
    if guess is not None:
        ok, rvec, tvec = True, np.asarray(guess[0], np.float64), np.asarray(guess[1], np.float64)
    else:
        ok, rvec, tvec = cv.solve_pnp(obj, img, K, dist, method)
    if not ok or not np.all(np.isfinite(tvec)):
        return failed_pose(FLAG_NO_POSE)
    rvec, tvec = cv.refine_pnp_lm(obj, img, K, dist, rvec, tvec)
    flags = 0
    inl = np.ones(n, dtype=bool)
    res = cv.project_points(obj, rvec, tvec, K, dist) - img
    r = np.linalg.norm(res, axis=1)
    bad = r > max(outlier_k * sigma_px * np.sqrt(2), 0.5)
    if bad.any() and (n - bad.sum()) >= max(min_points, 4):
        inl = ~bad
        flags |= FLAG_OUTLIERS
        if 2 * bad.sum() > n:  # most points rejected: the "inliers" are not a trustworthy set
            flags |= FLAG_FEW_POINTS
        rvec, tvec = cv.refine_pnp_lm(obj[inl], img[inl], K, dist, rvec, tvec)
        res = cv.project_points(obj, rvec, tvec, K, dist) - img
    elif bad.any():  # too few points would remain: keep them all, and say the pose is untrustworthy
        flags |= FLAG_OUTLIERS | FLAG_FEW_POINTS
    if tvec[2] <= 0:
        return failed_pose(FLAG_NO_POSE)
    rms = float(np.sqrt(np.mean(np.sum(res[inl] ** 2, axis=1))))
    if rms > max_rms_px:
        flags |= FLAG_HIGH_RESIDUAL
    J = projection_jacobian(obj[inl], rvec, tvec, K, dist)
    # noise from the data (module docstring)
    dof = 2 * int(inl.sum()) - 6
    rss = float(np.sum(res[inl] ** 2))
    nu0 = max(0.0, MIN_NOISE_DOF - dof) if prior_dof is None else float(prior_dof)
    try:
        JtJi = np.linalg.inv(J.T @ J)
        if noise_shape is None:
            sigma2 = (nu0 * sigma_px**2 + rss) / max(nu0 + dof, 1e-12)
            cov_C = sigma2 * JtJi
        else:  # correlated noise of known shape (scaled to a mean variance of 1 per coordinate)
            idx = np.flatnonzero(np.repeat(inl, 2))
            Sh = np.asarray(noise_shape, np.float64)[np.ix_(idx, idx)]
            Sh = Sh / np.mean(np.diag(Sh))
            H = J @ JtJi @ J.T
            expected = float(np.trace(Sh) - np.trace(H @ Sh))  # E[RSS] per unit variance
            rss_eq = rss * dof / max(expected, 1e-12)  # as if the noise were independent
            sigma2 = (nu0 * sigma_px**2 + rss_eq) / max(nu0 + dof, 1e-12)
            JtS = J.T @ Sh @ J
            cov_C = sigma2 * JtJi @ JtS @ JtJi  # least squares under correlated noise
    except np.linalg.LinAlgError:
        sigma2 = float("nan")
        cov_C = np.full((6, 6), np.inf)
        flags |= FLAG_FEW_POINTS
    B = np.zeros((6, 6))
    B[:3, :3] = camera.R_O_C
    B[3:, 3:] = camera.R_O_C
    cov_O = B @ cov_C @ B.T
    R_C_P = cv.rodrigues(rvec)
    p_O, R_O_P = camera.pose_O_from_C(R_C_P, tvec)
    extra = {"sigma_px": float(np.sqrt(sigma2)), "dof": float(dof)}
    return PoseEstimate(p_O, R_O_P, rvec, tvec, rms, res, inl, cov_O, flags, int(inl.sum()), extra)


CHI2_2DOF_Q05 = 0.10259
"""5 % quantile of chi-square with 2 dof (scipy.stats.chi2.ppf(0.05, 2) = -2 ln 0.95)."""

PLANAR_MARGIN_MIN = 25.0
"""Chi-square units (the best solution's ``s^2``) by which the other planar solution must fit worse."""


def estimate_pose_single_marker(
    corners_P_m: ArrayLike,
    corners_px: ArrayLike,
    camera: CameraModel,
    sigma_px: float,
    guess: tuple[F64, F64] | None = None,
    prior_dof: float | None = None,
    margin_min: float = PLANAR_MARGIN_MIN,
    noise_shape: ArrayLike | None = None,
) -> PoseEstimate:
    """Pose of {P} from the four corners of one square marker (``(4, 3)`` in {P}, ``(4, 2)`` px).

    Four coplanar points allow two poses (the planar "flip": IPPE's two solutions,
    ``cv.solve_pnp_planar_all``, each refined by :func:`estimate_pose`).  They are told apart by:

    1. the fit: the lower residual wins when the other solution (a different pose: > 1 mm or
       > 0.5 deg away) fits worse by ``margin_min`` in units of the noise ``s^2``
       (``extra["planar_margin"]``);
    2. else, in a sequence, the previous frame: ``guess`` (the pose predicted from the last
       ones) picks the solution within a quarter of the two solutions' angle from it, if the
       other is beyond three quarters (``extra["planar_by_previous"]`` = 1);
    3. else the frame is flagged ``FLAG_AMBIGUOUS`` and the covariance covers both solutions:
       ``Sigma + d d^T`` with ``d`` the other solution's offset (it lies within one sigma).

    ``prior_dof`` None means ``sigma_px`` is only nominal (not measured on this camera): the margin
    is then in units of the larger of ``s^2`` and the 95 % upper bound of the noise from the four
    corners alone (``RSS / chi2_2(0.05)``), since a nominal value far below the real noise would
    otherwise let the flip win confidently (measured: 14 % of frames at 0.6 px noise).
    The result always carries ``FLAG_SINGLE_MARKER``; its covariance is the usual ``s^2 (J^T J)^-1``
    of four points (2 residual degrees of freedom: ``s`` is pooled with ``sigma_px`` over
    ``prior_dof``, see the module docstring; ``noise_shape`` as :func:`estimate_pose`), several
    times larger than with six markers.
    """
    obj = np.asarray(corners_P_m, np.float64).reshape(-1, 3)
    img = np.asarray(corners_px, np.float64).reshape(-1, 2)
    if len(obj) != 4:
        return failed_pose(FLAG_FEW_POINTS | FLAG_SINGLE_MARKER)
    cands = [
        e
        for e in (
            estimate_pose(
                obj, img, camera, sigma_px, guess=g, prior_dof=prior_dof, noise_shape=noise_shape
            )
            for g in cv.solve_pnp_planar_all(obj, img, camera.K, camera.dist)
        )
        if not (e.flags & FLAG_NO_POSE)
    ]
    if not cands:
        return failed_pose(FLAG_NO_POSE | FLAG_SINGLE_MARKER)
    rss = np.array([float(np.sum(e.residuals_px**2)) for e in cands])
    order = np.argsort(rss)
    best = cands[order[0]]
    s2 = best.extra["sigma_px"] ** 2
    if prior_dof is None:  # the noise is not known: its 95 % upper bound from the 2 residual dof
        s2 = max(s2, rss[order[0]] / CHI2_2DOF_Q05)
    other, margin = None, float("inf")
    for k in order[1:]:
        d = pose_error(cands[k].position_O_m, cands[k].R_O_P, best.position_O_m, best.R_O_P)
        if np.linalg.norm(d[:3]) > 1e-3 or np.linalg.norm(d[3:]) > np.deg2rad(0.5):
            other, margin = cands[k], (rss[k] - rss[order[0]]) / max(s2, 1e-30)
            break
    chosen = best
    by_previous = False
    if other is not None and margin < margin_min and guess is not None:
        R_guess = cv.rodrigues(np.asarray(guess[0], np.float64))

        def angle(e: PoseEstimate) -> float:
            return float(np.linalg.norm(cv.rotation_vector(cv.rodrigues(e.rvec_C) @ R_guess.T)))

        flip = float(np.linalg.norm(cv.rotation_vector(other.R_O_P @ best.R_O_P.T)))
        near, far = (best, other) if angle(best) <= angle(other) else (other, best)
        if angle(near) < 0.25 * flip and angle(far) > 0.75 * flip:
            chosen, by_previous = near, True
    chosen.flags |= FLAG_SINGLE_MARKER
    chosen.extra["planar_margin"] = float(margin)
    chosen.extra["planar_by_previous"] = float(by_previous)
    if other is not None and margin < margin_min and not by_previous:
        chosen.flags |= FLAG_AMBIGUOUS
        alt = best if chosen is other else other
        d = pose_error(alt.position_O_m, alt.R_O_P, chosen.position_O_m, chosen.R_O_P)
        chosen.covariance = chosen.covariance + np.outer(d, d)
    return chosen


def pose_error(
    position_O_m: ArrayLike, R_O_P: ArrayLike, true_position_O_m: ArrayLike, true_R_O_P: ArrayLike
) -> F64:
    """Estimate minus truth (6,): ``[p_est - p_true (m), dtheta_O (rad)]`` with
    ``R_est = exp([dtheta]x) R_true`` (the covariance's left-rotation parametrisation in {O})."""
    dp = np.asarray(position_O_m, np.float64) - np.asarray(true_position_O_m, np.float64)
    dth = cv.rotation_vector(np.asarray(R_O_P, np.float64) @ np.asarray(true_R_O_P, np.float64).T)
    return np.concatenate([dp, dth])


def nees(error6: ArrayLike, covariance: ArrayLike) -> float:
    """Normalised estimation error squared ``e^T Sigma^-1 e`` (chi-square with 6 dof if consistent)."""
    e = np.asarray(error6, np.float64)
    return float(e @ np.linalg.solve(np.asarray(covariance, np.float64), e))


def camera_pose_from_points(
    object_points_O: ArrayLike,
    image_points_px: ArrayLike,
    camera: CameraModel,
    sigma_px: float,
) -> tuple[F64, F64, F64, float, float]:
    """Extrinsics from points known in {O}: ``(R_O_C, position_O_m, covariance (6, 6), rms_px,
    sigma_px used for the covariance)`` (``sigma_px`` is the prior, see :func:`estimate_pose`).

    The covariance is of ``[position_O_m of the camera, rotation_O_rad]`` (left rotation in {O}).
    """
    cam0 = CameraModel(camera.K, camera.dist, camera.image_size_px)  # {O} = {C} for the solve
    est = estimate_pose(object_points_O, image_points_px, cam0, sigma_px)
    if est.flags & (FLAG_NO_POSE | FLAG_FEW_POINTS):
        from cdpr.analysis.errors import InputError

        raise InputError(f"extrinsics: PnP failed ({', '.join(flag_names(est.flags))})")
    R_C_O = cv.rodrigues(est.rvec_C)
    t_C_O = est.tvec_C_m
    R_O_C = R_C_O.T
    c_O = -R_O_C @ t_C_O
    # covariance of (c_O, theta_O) from that of (t_C, theta_C): first-order propagation
    cov_C = est.covariance  # in "{O}" = {C} here
    # c = -R^T t ; dc = -R^T dt + [c]x (R^T dtheta_C)   (left perturbation R' = exp(dth) R)
    Rt = R_O_C
    cx = np.array([[0, -c_O[2], c_O[1]], [c_O[2], 0, -c_O[0]], [-c_O[1], c_O[0], 0]])
    G = np.zeros((6, 6))
    G[:3, :3] = -Rt
    G[:3, 3:] = cx @ Rt
    G[3:, 3:] = -Rt  # R_O_C' = R^T exp(-dth): rotation error in {O} = -R^T dth
    cov = G @ cov_C @ G.T
    return R_O_C, c_O, cov, est.reprojection_rms_px, est.extra["sigma_px"]
