"""Cable and platform windage: the modelled extra wrench and the measured (model-off) tare.

**Model** (:func:`cable_windage`).  The free stream blows along +x_O with speed ``V`` inside the test
section (:class:`~cdpr.analysis.test_section.SectionGeometry`) and is still outside it.  For cable
i, straight from its platform point (arc length ``s = 0``) to its anchor (``s = l``), with unit vector
``u`` (platform to anchor):

- cross-flow principle: only the component of the flow normal to the cable loads it,
  ``V_n = V (x - (x.u) u)``; cable Reynolds number ``Re = rho |V_n| d / mu``;
- drag coefficient of a circular cylinder ``CD(Re) = 1 + 10 Re^(-2/3)`` (White, *Fluid Mechanics*,
  curve fit for 1 < Re < 2e5; about 1.05 at Re = 2700), or a constant from the rig file;
- distributed load ``f = rho |V_n|^2 d CD / 2`` (N/m) along ``e_n = V_n/|V_n|`` on the wetted part
  ``s_a <= s <= s_b`` only;
- a taut string (tension T >> f l) under a transverse load passes to its platform end the share
  ``R = integral f (1 - s/l) ds = f (s_b - s_a) (1 - (s_a + s_b)/(2 l))`` (half for a uniform load on
  the whole cable) and its direction there turns by ``R/T`` rad towards ``e_n``;
- the platform receives ``[R e_n; r_i x R e_n]`` per cable (at P, {O} axes), plus the platform's own
  drag ``q C_D A_platform`` along +x at P when a drag area is given.

The load cells read |T| at the frame end, so this wrench is inside the recovered wrench
(``W_ext = -A T - G`` holds the aero wrench *plus* the windage): subtract it.

sigma: one relative uncertainty ``sigma_rel`` (the CD correlation and the cable diameter, fully
correlated over cables): ``cov = sigma_rel^2 W W^T``.

**Measured tare** (:func:`fit_windage_tare`, :func:`evaluate_windage_tare`): model-off wind-on points
fitted per speed by least squares with a polynomial in angle of attack and sideslip, with the
prediction sigma from the residual variance and the residuals kept for the report.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .aero import flow_angles
from .errors import InputError
from .records import CorrectionRecord
from .rig import Rig
from .rotations import rotation_from_euler
from .test_section import SectionGeometry, segment_inside

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

WHITE_RE_RANGE = (1.0, 2.0e5)
"""Range of cable Reynolds numbers over which the cylinder CD fit holds."""


def cylinder_drag_coefficient(reynolds: ArrayLike) -> FloatArray:
    """Drag coefficient of a circular cylinder in cross-flow, ``1 + 10 Re^(-2/3)`` (White).

    Reynolds numbers below 1 are taken as 1 (the load there is negligible anyway).
    """
    re = np.maximum(as_float_array(reynolds, "reynolds"), WHITE_RE_RANGE[0])
    return np.asarray(1.0 + 10.0 * re ** (-2.0 / 3.0))


@dataclass(frozen=True)
class CableWindage:
    """Modelled windage per point (n points, m cables).

    wrench_N: (n, 6) extra wrench on the platform at P in {O} ([Fx, Fy, Fz, Mx, My, Mz], N, N m);
    cov: (n, 6, 6) its covariance; wetted_length_m: (n, m) the part of each cable in the flow;
    load_N_per_m: (n, m) distributed load magnitude; end_force_N: (n, m) the share reaching the
    platform end; turn_rad: (n, m) the change of the cable's direction at the platform end;
    reynolds: (n, m) cable Reynolds number; cd: (n, m) drag coefficient used;
    record: what was done (flag ``cable_re_outside_fit`` if a Re left the CD fit's range).
    """

    wrench_N: FloatArray
    cov: FloatArray
    wetted_length_m: FloatArray
    load_N_per_m: FloatArray
    end_force_N: FloatArray
    turn_rad: FloatArray
    reynolds: FloatArray
    cd: FloatArray
    record: CorrectionRecord


def cable_windage(
    anchors_O_m: ArrayLike,
    attach_P_m: ArrayLike,
    position_O_m: ArrayLike,
    R_O_P: ArrayLike,
    tensions_N: ArrayLike,
    airspeed_mps: ArrayLike,
    density_kgpm3: ArrayLike,
    viscosity_Pas: ArrayLike,
    diameter_m: ArrayLike,
    section: SectionGeometry,
    drag_coefficient: ArrayLike | None = None,
    sigma_rel: float = 0.15,
    platform_drag_area_m2: float = 0.0,
) -> CableWindage:
    """The windage wrench the cables (and the platform) put on the platform, per point.

    anchors_O_m, attach_P_m: (m, 3) rig geometry; position_O_m: (n, 3); R_O_P: (n, 3, 3);
    tensions_N: (n, m) (for the turn angle only); airspeed_mps, density_kgpm3, viscosity_Pas: (n,);
    diameter_m: (m,) or scalar; drag_coefficient: (m,) constant CD per cable (NaN entries, or None
    for all: :func:`cylinder_drag_coefficient` of the cable Reynolds number);
    sigma_rel: relative sigma of the wrench;
    platform_drag_area_m2: C_D A of the bare platform (0 when it sits inside the model).
    """
    b = check_trailing(anchors_O_m, "anchors_O_m", (3,))
    pp = check_trailing(attach_P_m, "attach_P_m", (3,))
    p = check_trailing(position_O_m, "position_O_m", (3,)).reshape(-1, 3)
    R = check_trailing(R_O_P, "R_O_P", (3, 3)).reshape(-1, 3, 3)
    n, m = p.shape[0], b.shape[0]
    if R.shape[0] != n or pp.shape != (m, 3) or b.ndim != 2:
        raise InputError(
            f"expected anchors (m, 3), attach (m, 3), position (n, 3), R (n, 3, 3); got "
            f"{b.shape}, {pp.shape}, {p.shape}, {R.shape}"
        )
    T = np.broadcast_to(as_float_array(tensions_N, "tensions_N"), (n, m))
    V = np.broadcast_to(as_float_array(airspeed_mps, "airspeed_mps"), (n,))
    rho = np.broadcast_to(as_float_array(density_kgpm3, "density_kgpm3"), (n,))
    mu = np.broadcast_to(as_float_array(viscosity_Pas, "viscosity_Pas"), (n,))
    d = np.broadcast_to(as_float_array(diameter_m, "diameter_m"), (m,))
    if np.any(d <= 0) or np.any(rho <= 0) or np.any(mu <= 0):
        raise InputError("diameter_m, density_kgpm3, viscosity_Pas: expected values > 0")
    if np.any(T <= 0):
        raise InputError("tensions_N: expected values > 0 N (a slack cable has no direction)")

    r = np.einsum("nij,mj->nmi", R, pp)  # (n, m, 3) lever arms R pp_i
    start = p[:, None, :] + r  # platform points in {O}
    lv = b[None, :, :] - start
    length = np.linalg.norm(lv, axis=-1)  # (n, m)
    u = lv / length[..., None]
    s_in, s_out = segment_inside(start, np.broadcast_to(b, start.shape), section)
    s_a, s_b = s_in * length, s_out * length
    wetted = s_b - s_a

    x_hat = np.array([1.0, 0.0, 0.0])
    vn_dir = x_hat - u[..., 0:1] * u  # (n, m, 3): V_n / V
    vn_unit = np.linalg.norm(vn_dir, axis=-1)  # sin of the angle between cable and flow
    e_n = np.divide(
        vn_dir, vn_unit[..., None], out=np.zeros_like(vn_dir), where=vn_unit[..., None] > 1e-12
    )
    vn = V[:, None] * vn_unit  # (n, m)
    re = rho[:, None] * vn * d[None, :] / mu[:, None]
    cd = cylinder_drag_coefficient(re)
    if drag_coefficient is None:
        cd_source = "CD = 1 + 10 Re^(-2/3) (White)"
        given = np.zeros(m, dtype=bool)
    else:
        cd_given = np.broadcast_to(as_float_array(drag_coefficient, "drag_coefficient"), (m,))
        given = ~np.isnan(cd_given)
        if np.any(cd_given[given] <= 0) or not np.all(np.isfinite(cd_given[given])):
            raise InputError("drag_coefficient: expected values > 0 (NaN: CD from Re)")
        cd = np.where(given[None, :], cd_given[None, :], cd)
        cd_source = (
            "CD constant per cable from the rig file"
            if given.all()
            else "CD from the rig file where given, else 1 + 10 Re^(-2/3) (White)"
        )
    f = 0.5 * rho[:, None] * vn**2 * d[None, :] * cd  # N/m
    share = f * wetted * (1.0 - (s_a + s_b) / (2.0 * length))
    F = share[..., None] * e_n  # (n, m, 3)
    W = np.concatenate([F.sum(axis=1), np.cross(r, F).sum(axis=1)], axis=-1)
    q = 0.5 * rho * V**2
    W[:, 0] += q * float(platform_drag_area_m2)
    cov = sigma_rel**2 * W[:, :, None] * W[:, None, :]
    wet_re_fit = re[(wetted > 0) & ~given[None, :]]
    outside = bool(
        np.any(
            (wet_re_fit > WHITE_RE_RANGE[1]) | ((wet_re_fit < WHITE_RE_RANGE[0]) & (wet_re_fit > 0))
        )
    )
    flags = ("cable_re_outside_fit",) if outside else ()
    rec = CorrectionRecord(
        name="windage_model",
        source="cross-flow drag on the wetted part of each cable (" + cd_source + "); taut-string "
        "end share f(s_b - s_a)(1 - (s_a + s_b)/2l); platform drag q CdA",
        values={
            "sigma_rel": sigma_rel,
            "platform_drag_area_m2": float(platform_drag_area_m2),
            "max_abs_force_N": float(np.max(np.abs(W[:, :3]))) if n else 0.0,
            "max_abs_moment_Nm": float(np.max(np.abs(W[:, 3:]))) if n else 0.0,
            "wetted_length_m_mean": wetted.mean(axis=0).tolist() if n else [],
            "cable_re_max": float(np.max(re)) if re.size else 0.0,
        },
        flags=flags,
    )
    return CableWindage(
        wrench_N=W,
        cov=cov,
        wetted_length_m=wetted,
        load_N_per_m=f,
        end_force_N=share,
        turn_rad=share / T,
        reynolds=re,
        cd=cd,
        record=rec,
    )


# ---------------------------------------------------------------------------------------------
# measured windage tare


@dataclass(frozen=True)
class _SpeedFit:
    speed_mps: float
    exponents: tuple[tuple[int, int], ...]
    coef: FloatArray  # (p, 6)
    xtx_inv: FloatArray  # (p, p)
    s2: FloatArray  # (6,) residual variance
    aoa_range_rad: tuple[float, float]
    sideslip_range_rad: tuple[float, float]


@dataclass(frozen=True)
class WindageTareFit:
    """A smooth fit of the model-off wind-on wrench per speed.

    fits: one per speed group; residuals_N: (n, 6) residuals of the fitted points (same order as the
    input); rms_residual: (g, 6) per speed group; record: what was fitted.
    """

    fits: tuple[_SpeedFit, ...]
    residuals_N: FloatArray
    rms_residual: FloatArray
    speed_tolerance: float
    record: CorrectionRecord

    @property
    def speeds_mps(self) -> FloatArray:
        return np.array([f.speed_mps for f in self.fits])


def _design(aoa: FloatArray, slip: FloatArray, exps: tuple[tuple[int, int], ...]) -> FloatArray:
    return np.stack([aoa**i * slip**j for i, j in exps], axis=-1)


def _speed_groups(speed: FloatArray, tol: float) -> NDArray[np.intp]:
    """Group ids (n,) for speeds within ``tol`` (relative) of the group's first speed."""
    order = np.argsort(speed)
    ids = np.empty(speed.size, dtype=np.intp)
    gid, ref = -1, -np.inf
    for k in order:  # over points of a tare table (tens), not samples
        if speed[k] > ref * (1 + tol) + 1e-9:
            gid, ref = gid + 1, speed[k]
        ids[k] = gid
    return ids


def fit_windage_tare(
    airspeed_mps: ArrayLike,
    aoa_rad: ArrayLike,
    sideslip_rad: ArrayLike,
    wrench_N: ArrayLike,
    aoa_degree: int = 2,
    sideslip_degree: int = 2,
    speed_tolerance: float = 0.03,
) -> WindageTareFit:
    """Fit model-off wind-on wrenches (n, 6) per speed as polynomials in aoa and sideslip.

    Points whose speeds agree within ``speed_tolerance`` (relative) form one speed group.  Terms
    ``aoa^i sideslip^j`` with ``i <= aoa_degree``, ``j <= sideslip_degree``, ``i + j <= max`` of
    both; a variable that does not vary within a group (range < 1e-6 rad) drops out.  Each group
    needs more points than terms (so the residual variance exists), else :class:`InputError`.
    """
    v = as_float_array(airspeed_mps, "airspeed_mps").reshape(-1)
    a = np.broadcast_to(as_float_array(aoa_rad, "aoa_rad"), v.shape)
    sl = np.broadcast_to(as_float_array(sideslip_rad, "sideslip_rad"), v.shape)
    W = check_trailing(wrench_N, "wrench_N", (6,)).reshape(-1, 6)
    if W.shape[0] != v.size:
        raise InputError(f"wrench_N: expected ({v.size}, 6), got {W.shape}")
    if np.any(v <= 0):
        raise InputError("airspeed_mps: a windage tare point needs wind on (> 0 m/s)")
    groups = _speed_groups(v, speed_tolerance)
    fits = []
    resid = np.zeros_like(W)
    rms = []
    top = max(aoa_degree, sideslip_degree)
    for g in range(int(groups.max()) + 1):
        sel = groups == g
        ag, sg = a[sel], sl[sel]
        da = aoa_degree if np.ptp(ag) > 1e-6 else 0
        ds = sideslip_degree if np.ptp(sg) > 1e-6 else 0
        exps = tuple((i, j) for i in range(da + 1) for j in range(ds + 1) if i + j <= max(top, 0))
        X = _design(ag, sg, exps)
        n_g, n_p = X.shape
        speed = float(np.mean(v[sel]))
        if n_g <= n_p or np.linalg.matrix_rank(X) < n_p:
            raise InputError(
                f"windage tare at {speed:.2f} m/s: {n_g} points at distinct attitudes cannot fit "
                f"{n_p} terms (need more points than terms)"
            )
        coef, *_ = np.linalg.lstsq(X, W[sel], rcond=None)
        res = W[sel] - X @ coef
        resid[sel] = res
        s2 = np.sum(res**2, axis=0) / (n_g - n_p)
        rms.append(np.sqrt(np.mean(res**2, axis=0)))
        fits.append(
            _SpeedFit(
                speed_mps=speed,
                exponents=exps,
                coef=coef,
                xtx_inv=np.asarray(np.linalg.inv(X.T @ X), dtype=np.float64),
                s2=s2,
                aoa_range_rad=(float(ag.min()), float(ag.max())),
                sideslip_range_rad=(float(sg.min()), float(sg.max())),
            )
        )
    rec = CorrectionRecord(
        name="windage_tare_fit",
        source="least-squares polynomial in aoa and sideslip per speed (model-off wind-on points)",
        values={
            "speeds_mps": [f.speed_mps for f in fits],
            "terms": [[list(e) for e in f.exponents] for f in fits],
            "rms_residual_N": [r.tolist() for r in rms],
        },
    )
    return WindageTareFit(tuple(fits), resid, np.array(rms), speed_tolerance, rec)


@dataclass(frozen=True)
class WindageTare:
    """The measured windage tare at the points: tare_N (n, 6), sigma_N (n, 6), missing (n,) True
    where no speed group matches (tare NaN), extrapolated (n,) True outside the fitted attitudes."""

    tare_N: FloatArray
    sigma_N: FloatArray
    missing: BoolArray
    extrapolated: BoolArray
    record: CorrectionRecord


def evaluate_windage_tare(
    fit: WindageTareFit, airspeed_mps: ArrayLike, aoa_rad: ArrayLike, sideslip_rad: ArrayLike
) -> WindageTare:
    """The fitted tare and its prediction sigma ``sqrt(s^2 x^T (X^T X)^-1 x)`` at n points.

    A point whose speed is not within the fit's tolerance of a fitted speed gets NaN and
    ``missing``: no silent extrapolation in speed.
    """
    v, a, sl = (
        np.ravel(x)
        for x in np.broadcast_arrays(
            as_float_array(airspeed_mps, "airspeed_mps"),
            as_float_array(aoa_rad, "aoa_rad"),
            as_float_array(sideslip_rad, "sideslip_rad"),
        )
    )
    tare = np.full((v.size, 6), np.nan)
    sigma = np.full((v.size, 6), np.nan)
    extrap = np.zeros(v.size, dtype=bool)
    speeds = fit.speeds_mps
    nearest = np.argmin(np.abs(v[:, None] - speeds[None, :]), axis=1)
    ok = np.abs(v - speeds[nearest]) <= fit.speed_tolerance * speeds[nearest]
    eps = 1e-9
    for g, f in enumerate(fit.fits):
        sel = ok & (nearest == g)
        if not sel.any():
            continue
        X = _design(a[sel], sl[sel], f.exponents)
        tare[sel] = X @ f.coef
        lev = np.einsum("ij,jk,ik->i", X, f.xtx_inv, X)
        sigma[sel] = np.sqrt(lev[:, None] * f.s2[None, :])
        uses_aoa = any(i > 0 for i, _ in f.exponents)
        uses_slip = any(j > 0 for _, j in f.exponents)
        lo_a, hi_a = f.aoa_range_rad if uses_aoa else (-np.inf, np.inf)
        lo_s, hi_s = f.sideslip_range_rad if uses_slip else (-np.inf, np.inf)
        extrap[sel] = (
            (a[sel] < lo_a - eps)
            | (a[sel] > hi_a + eps)
            | (sl[sel] < lo_s - eps)
            | (sl[sel] > hi_s + eps)
        )
        if not uses_aoa:
            extrap[sel] |= np.abs(a[sel] - f.aoa_range_rad[0]) > 1e-6
        if not uses_slip:
            extrap[sel] |= np.abs(sl[sel] - f.sideslip_range_rad[0]) > 1e-6
    missing = ~ok
    flags = tuple(
        name
        for name, bad in (("windage_tare_missing", missing), ("windage_tare_extrapolated", extrap))
        if bad.any()
    )
    rec = CorrectionRecord(
        name="windage_tare",
        source="measured model-off windage tare, fitted per speed (fit_windage_tare)",
        values={
            "n_missing": int(missing.sum()),
            "n_extrapolated": int(extrap.sum()),
            "max_abs_tare_N": float(np.nanmax(np.abs(tare[:, :3]))) if (~missing).any() else 0.0,
        },
        flags=flags,
    )
    return WindageTare(tare, sigma, missing, extrap, rec)


def windage_of_rig(
    rig: Rig,
    section: SectionGeometry,
    position_O_m: ArrayLike,
    R_O_P: ArrayLike,
    tensions_N: ArrayLike,
    airspeed_mps: ArrayLike,
    density_kgpm3: ArrayLike,
    viscosity_Pas: ArrayLike,
    sigma_rel: float = 0.15,
) -> CableWindage:
    """:func:`cable_windage` with the rig's geometry, cable diameters, drag coefficients and
    platform drag area (the reduction stage's call)."""
    return cable_windage(
        rig.anchors_O_m,
        rig.attach_P_m,
        position_O_m,
        R_O_P,
        tensions_N,
        airspeed_mps,
        density_kgpm3,
        viscosity_Pas,
        rig.cable_diameter_m,
        section,
        rig.cable_drag_coefficient,
        sigma_rel=sigma_rel,
        platform_drag_area_m2=rig.platform_drag_area_m2,
    )


WINDAGE_SOURCES: tuple[str, ...] = ("measured", "model", "none")
"""Per wind-on point, where the windage subtracted came from."""


@dataclass(frozen=True)
class WindageCorrection:
    """The windage of every point, chosen measured > modelled > none (each (s, ...)).

    applied_N: (s, 6) subtracted from the wind-on points (0 elsewhere); cov: (s, 6, 6) its
    covariance; source: (s,) one of :data:`WINDAGE_SOURCES` on wind-on points ("" elsewhere);
    measured_N, measured_sd_N: (s, 6) the measured tare's fit at every wind-on and windage point
    (NaN elsewhere; on the windage points their residuals are ``wrench - measured_N``); model_N:
    (s, 6) the model's value (NaN without a test section); flags: word -> (s,) mask; records: what
    was done; notes: sentences for the stage log.
    """

    applied_N: FloatArray
    cov: FloatArray
    source: NDArray[np.str_]
    measured_N: FloatArray
    measured_sd_N: FloatArray
    model_N: FloatArray
    flags: dict[str, BoolArray]
    records: tuple[CorrectionRecord, ...]
    notes: tuple[str, ...]


def windage_correction(
    rig: Rig,
    section: SectionGeometry | None,
    kind: ArrayLike,
    airspeed_mps: ArrayLike,
    wrench_O: ArrayLike,
    poses: ArrayLike,
    tensions_N: ArrayLike,
    density_kgpm3: ArrayLike,
    viscosity_Pas: ArrayLike,
    nose_P: ArrayLike = (-1.0, 0.0, 0.0),
    up_P: ArrayLike = (0.0, 0.0, 1.0),
    sigma_rel: float = 0.15,
    aoa_degree: int = 2,
    sideslip_degree: int = 2,
    wind_off_mps: float = 1.0,
    angle_tol_rad: float = float(np.deg2rad(0.1)),
) -> WindageCorrection:
    """The cable and platform windage of each wind-on point.

    - measured tare: the run's model-off wind-on points (kind ``windage``) fitted per speed in
      aoa/sideslip (:func:`fit_windage_tare`), evaluated at each wind-on point
      (:func:`evaluate_windage_tare`; flag ``windage_tare``, outside the fitted attitudes
      ``windage_tare_extrapolated``); a windage point with too few others at its speed is left
      out (``windage_tare_unfit``);
    - else the model from the rig file and the test section (:func:`windage_of_rig`, flag
      ``windage_modelled``);
    - else nothing (flag ``no_windage_correction``).

    kind, airspeed_mps: (s,); wrench_O: (s, 6) the wrench at P in {O} axes with the weight
    removed; poses: (s, 6); tensions_N: (s, m); density_kgpm3, viscosity_Pas: (s,) (the model
    needs both).  An angle the windage points hold within ``angle_tol_rad`` (the sideslip of an
    alpha sweep) is not a fit variable: points within that tolerance of it count as at it, and a
    point within it beyond the ends of the fitted range is evaluated at the end; further out a
    point is flagged as extrapolated.
    """
    kind = np.asarray(kind).astype(str)
    s = kind.shape[0]
    V = np.asarray(airspeed_mps, dtype=np.float64)
    W = check_trailing(wrench_O, "wrench_O", (6,), allow_nan=True)
    q = check_trailing(poses, "poses", (6,), allow_nan=True)
    rho = np.asarray(density_kgpm3, dtype=np.float64)
    mu = np.asarray(viscosity_Pas, dtype=np.float64)
    R = rotation_from_euler(np.nan_to_num(q[:, 3:]))
    aoa, slip = (np.array(a, dtype=np.float64) for a in flow_angles(R, nose_P, up_P))
    finite = np.isfinite(W).all(axis=1) & np.isfinite(V)
    on = (kind == "wind_on") & finite & (V > wind_off_mps)
    wnd = (kind == "windage") & finite & (V > wind_off_mps)
    recs: list[CorrectionRecord] = []
    notes: list[str] = []
    flags: dict[str, BoolArray] = {}
    measured = np.full((s, 6), np.nan)
    measured_sd = np.full((s, 6), np.nan)
    extrap = np.zeros(s, bool)
    if wnd.any():
        for ang in (aoa, slip):
            if np.ptp(ang[wnd]) < angle_tol_rad:
                held = float(np.mean(ang[wnd]))
                ang[np.abs(ang - held) <= angle_tol_rad] = held
        # a windage point whose speed has too few others (a speed ramp caught in its window)
        # cannot be fitted: it is left out and flagged, the other speeds are still fitted
        close = (np.abs(V[:, None] - V[None, :]) <= 0.03 * V[None, :]) & wnd[None, :]
        lonely = wnd & (close.sum(axis=1) < aoa_degree + 2)
        fitset = wnd & ~lonely
        flags["windage_tare_unfit"] = lonely
        if lonely.any():
            notes.append(f"{int(lonely.sum())} windage point(s) left out: too few at their speed")
        try:
            if not fitset.any():
                raise InputError("no speed with enough windage points")
            fit = fit_windage_tare(
                V[fitset], aoa[fitset], slip[fitset], W[fitset], aoa_degree, sideslip_degree
            )
        except InputError as exc:
            notes.append(f"measured tare not fitted: {exc}")
            flags["windage_tare_unfit"] = wnd
        else:
            recs.append(fit.record)
            at = np.flatnonzero(on | wnd)
            g = np.argmin(np.abs(V[at, None] - fit.speeds_mps[None, :]), axis=1)
            for ang, rng in ((aoa, "aoa_range_rad"), (slip, "sideslip_range_rad")):
                lo, hi = (np.array([getattr(f, rng)[k] for f in fit.fits])[g] for k in (0, 1))
                x = ang[at]
                x = np.where((x < lo) & (x >= lo - angle_tol_rad), lo, x)
                ang[at] = np.where((x > hi) & (x <= hi + angle_tol_rad), hi, x)
            ev = evaluate_windage_tare(fit, V[at], aoa[at], slip[at])
            measured[at], measured_sd[at], extrap[at] = ev.tare_N, ev.sigma_N, ev.extrapolated
            recs.append(ev.record)
            notes.append(f"measured tare from {int(fitset.sum())} model-off points")
    model = np.full((s, 6), np.nan)
    model_cov = np.full((s, 6, 6), np.nan)
    if section is not None:
        ok = (on | wnd) & np.isfinite(mu) & np.isfinite(rho)
        if ok.any():
            T = np.asarray(tensions_N, dtype=np.float64)
            cw = windage_of_rig(
                rig, section, q[ok, :3], R[ok], T[ok], V[ok], rho[ok], mu[ok], sigma_rel
            )
            model[ok], model_cov[ok] = cw.wrench_N, cw.cov
            recs.append(cw.record)
    use_meas = on & np.isfinite(measured).all(axis=1)
    use_model = on & ~use_meas & np.isfinite(model).all(axis=1)
    none = on & ~use_meas & ~use_model
    applied = np.zeros((s, 6))
    applied[use_meas] = measured[use_meas]
    applied[use_model] = model[use_model]
    cov = np.zeros((s, 6, 6))
    cov[use_meas] = measured_sd[use_meas, :, None] ** 2 * np.eye(6)
    cov[use_model] = model_cov[use_model]
    source = np.full(s, "", dtype=object)
    source[use_meas], source[use_model], source[none] = WINDAGE_SOURCES
    flags.update(
        {
            "windage_tare": use_meas,
            "windage_tare_extrapolated": use_meas & extrap,
            "windage_modelled": use_model,
            "no_windage_correction": none,
        }
    )
    if wnd.any() and (on & ~use_meas).any():
        flags["windage_tare_missing"] = on & ~use_meas
    notes.append(
        f"{int(use_meas.sum())} measured, {int(use_model.sum())} modelled, "
        f"{int(none.sum())} uncorrected"
    )
    return WindageCorrection(
        applied, cov, source.astype(str), measured, measured_sd, model, flags, tuple(recs),
        tuple(notes),
    )  # fmt: skip
