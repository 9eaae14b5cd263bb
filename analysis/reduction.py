"""The reduction core: one ordered list of stages over per-point arrays.

A :class:`Points` holds one row per test point: its inputs (mean tensions and their covariance, mean
pose and its covariance, airspeed, density, kind), what the stages add (the wrench, each σ term, axes,
coefficients), one list of flag words per point, and the log of the stages that ran.

A *stage* is a plain function ``stage(points, **settings) -> Points`` wrapped by :func:`stage`: it
returns a new :class:`Points` (inputs are never modified), adds its correction, adds its covariance
term under its own name in ``cov_terms`` (so σ can be listed by source), flags the points it could not
treat, and the decorator appends a :class:`Step` (name, settings, points flagged) to the log.  A stage
that cannot run for a point leaves NaN and a flag there, never a nominal value in silence.

The order (see ``cdpr.pipelines.reduce``): steady points and masks (upstream, :mod:`.balance`) →
[zero drift] → structure matrix → weight model → weight tare → [windage] → [inertia] → balance
interaction matrix → axes and moment transfer → [wall corrections] → coefficients → tension
check.  Bracketed slots are stages other modules plug in with the same signature; they read and add
the same keys.

Keys in ``Points.arrays`` (s points, m cables):

- inputs: ``kind`` (s,) str (``wind_on``, ``tare``, ``zero``, ``windage``, ``unknown``),
  ``start_ns`` (s,), ``tension_N`` (s, m), ``tension_cov_N2`` (s, m, m), ``pose`` (s, 6),
  ``pose_cov`` (s, 6, 6), ``airspeed_mps`` (s,) (NaN when unknown), ``density_kgpm3`` (s,);
- added: ``A`` (s, 6, m); ``wrench_N`` (s, 6) aerodynamic wrench at P in {O} (moved to the MRP by
  the axes stage, ``wrench_mrp_N``), ``tare_index`` (s,) (-1: none), and the aero outputs.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .aero import (
    ModelGeometry,
    body_from_tunnel,
    coefficient_matrix,
    dynamic_pressure,
    flow_angles,
    transfer_moment,
    wind_from_body,
)
from .balance_model import apply_balance_model
from .errors import InputError
from .kinematics import structure_matrix
from .rig import Rig
from .rotations import rotation_from_euler
from .tension import distribute
from .uncertainty import pose_jacobian
from .weight import WeightModel, fit_weight, weight_basis

FloatArray = NDArray[np.float64]

WIND_OFF_KINDS: tuple[str, ...] = ("tare", "zero")
"""Point kinds taken wind-off: they feed the weight model and serve as tares."""


@dataclass(frozen=True)
class Step:
    """What one stage did: its name, its settings (plain values) and the points it flagged."""

    name: str
    settings: Mapping[str, Any]
    flagged: int
    note: str = ""


@dataclass(frozen=True)
class Points:
    """Per-point arrays flowing through the stages (see the module docstring for the keys).

    cov_terms: name -> (s, 6, 6) covariance of ``wrench_N`` from that source, in the current axes
    and reference point of the wrench; flags: one list of words per point; steps: the stage log;
    meta: results that are not per point (the weight model).
    """

    arrays: Mapping[str, NDArray[Any]]
    cov_terms: Mapping[str, FloatArray] = field(default_factory=dict)
    flags: tuple[tuple[str, ...], ...] = ()
    steps: tuple[Step, ...] = ()
    meta: Mapping[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(len(self.arrays["kind"]))

    def __getitem__(self, key: str) -> NDArray[Any]:
        return self.arrays[key]

    @property
    def wrench_cov(self) -> FloatArray:
        """Total covariance (s, 6, 6): the sum of every term."""
        tot = np.zeros((self.n, 6, 6))
        for c in self.cov_terms.values():
            tot = tot + c
        return tot

    def flag_text(self) -> list[str]:
        """One ``;``-separated string of flag words per point."""
        return [";".join(f) for f in self.flags]


def new_points(**arrays: ArrayLike) -> Points:
    """A :class:`Points` from the input arrays (checked shapes), with empty flags and log."""
    kind = np.asarray(arrays["kind"]).astype(str)
    s = kind.shape[0]
    T = np.asarray(arrays["tension_N"], dtype=np.float64)
    m = T.shape[-1] if T.ndim == 2 else -1
    want = {
        "start_ns": (s,),
        "tension_N": (s, m),
        "tension_cov_N2": (s, m, m),
        "pose": (s, 6),
        "pose_cov": (s, 6, 6),
        "airspeed_mps": (s,),
        "density_kgpm3": (s,),
    }
    out: dict[str, NDArray[Any]] = {"kind": kind}
    for key, shape in want.items():
        if key not in arrays:
            raise InputError(f"new_points: {key} missing")
        dtype = np.int64 if key == "start_ns" else np.float64
        a = np.asarray(arrays[key], dtype=dtype)
        if a.shape != shape:
            raise InputError(f"{key}: expected shape {shape}, got {a.shape}")
        out[key] = a
    for key, val in arrays.items():
        out.setdefault(key, np.asarray(val))
    return Points(out, {}, tuple(() for _ in range(s)))


Stage = Callable[[Points], Points]
"""A stage with its settings bound (``functools.partial``): points in, points out."""


def stage(name: str) -> Callable[[Callable[..., Points]], Callable[..., Points]]:
    """Decorator: run the stage and append a :class:`Step` with its plain settings and the number
    of points whose flags it extended."""

    def deco(fn: Callable[..., Points]) -> Callable[..., Points]:
        @functools.wraps(fn)
        def run(points: Points, **settings: Any) -> Points:
            out = fn(points, **settings)
            flagged = sum(
                1 for a, b in zip(points.flags, out.flags, strict=True) if len(b) > len(a)
            )
            plain = {k: _plain(v) for k, v in settings.items()}
            note = str(out.meta.get("_note", ""))
            meta = {k: v for k, v in out.meta.items() if k != "_note"}
            return replace(out, steps=out.steps + (Step(name, plain, flagged, note),), meta=meta)

        run.stage_name = name  # type: ignore[attr-defined]
        return run

    return deco


def _plain(v: Any) -> Any:
    if isinstance(v, Rig):
        return v.name
    if isinstance(v, ModelGeometry | WeightModel):
        return type(v).__name__
    if isinstance(v, np.ndarray):
        return f"<array {v.shape}>" if v.size > 12 else v.tolist()
    if isinstance(v, list | tuple):
        return f"<{len(v)} values>" if len(v) > 12 else [_plain(x) for x in v]
    if isinstance(v, float | int | str | bool) or v is None:
        return v
    return repr(v)


def with_updates(
    p: Points,
    arrays: Mapping[str, NDArray[Any]] | None = None,
    terms: Mapping[str, FloatArray] | None = None,
    flag: Mapping[str, NDArray[np.bool_]] | None = None,
    meta: Mapping[str, Any] | None = None,
    replace_terms: bool = False,
) -> Points:
    """A new :class:`Points` with ``arrays`` added or replaced, σ ``terms`` added (or, with
    ``replace_terms``, replacing all), the word of each ``flag`` mask (s,) appended to those points,
    and ``meta`` merged (``"_note"``: a sentence for the stage log).  What a stage returns."""
    a = dict(p.arrays)
    a.update(arrays or {})
    t = dict(terms or {}) if replace_terms else {**p.cov_terms, **(terms or {})}
    flags = [list(f) for f in p.flags]
    for word, mask in (flag or {}).items():
        for i in np.flatnonzero(mask):
            if word not in flags[i]:
                flags[i].append(word)
    return replace(
        p,
        arrays=a,
        cov_terms=t,
        flags=tuple(tuple(f) for f in flags),
        meta={**p.meta, **(meta or {})},
    )


def _sandwich(M: FloatArray, C: FloatArray) -> FloatArray:
    return np.asarray(M @ C @ np.swapaxes(M, -1, -2), dtype=np.float64)


@stage("flags_from_masks")
def flags_from_masks(p: Points, *, words: list[str] | None = None) -> Points:
    """Carry per-point flag words from upstream (masked samples, source, fallbacks) into the log.

    words: one ``;``-separated string per point (empty for none)."""
    w = words or [""] * p.n
    if len(w) != p.n:
        raise InputError(f"words: expected {p.n} strings, got {len(w)}")
    flags: dict[str, NDArray[np.bool_]] = {}
    for i, text in enumerate(w):
        for word in filter(None, text.split(";")):
            flags.setdefault(word, np.zeros(p.n, bool))[i] = True
    return with_updates(p, flag=flags)


@stage("structure_matrix")
def structure_matrix_stage(p: Points, *, rig: Rig) -> Points:
    """``A`` (s, 6, m) at each point's measured mean pose; ``-A T`` is the cables' load.  A point
    without a pose (no usable camera frame) gets NaN and the flag ``no_pose``."""
    q = p["pose"]
    if q.shape[0] and p["tension_N"].shape[1] != rig.n_cables:
        raise InputError(f"tension_N: expected {rig.n_cables} cables for rig {rig.name!r}")
    ok = np.isfinite(q).all(axis=1)
    A = np.full((p.n, 6, rig.n_cables), np.nan)
    A[ok] = structure_matrix(
        rig.anchors_O_m, rig.attach_P_m, q[ok, :3], rotation_from_euler(q[ok, 3:])
    )
    return with_updates(p, arrays={"A": A}, flag={"no_pose": ~ok})


def _minus_AT(rig: Rig, poses: FloatArray, T: FloatArray) -> FloatArray:
    """``-A(q) T`` for poses (s, k, 6) and tensions (s, m) -> (s, k, 6)."""
    A = structure_matrix(
        rig.anchors_O_m, rig.attach_P_m, poses[..., :3], rotation_from_euler(poses[..., 3:])
    )
    return -np.einsum("skij,sj->ski", A, T)


def _load_and_pose_terms(
    rig: Rig, p: Points, idx: NDArray[np.int64], theta: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """For points ``idx``: ``y = -A T - B theta`` (k, 6), its covariance from the load cells and
    from the pose (each (k, 6, 6)), linearised at the measured values, and ``J = dy/dq``."""
    q = p["pose"][idx]
    T = p["tension_N"][idx]
    A = p["A"][idx]
    B = weight_basis(q, rig.gravity_O_mps2)
    y = -np.einsum("kij,kj->ki", A, T) - B @ theta
    c_load = _sandwich(A, p["tension_cov_N2"][idx])

    def fun(qp: FloatArray) -> FloatArray:
        Bp = weight_basis(qp, rig.gravity_O_mps2)
        return _minus_AT(rig, qp, T) - Bp @ theta

    J = pose_jacobian(fun, q) if len(idx) else np.zeros((0, 6, 6))
    c_pose = _sandwich(J, p["pose_cov"][idx])
    return y, c_load, c_pose, J


@stage("weight_model")
def weight_model_stage(
    p: Points,
    *,
    rig: Rig,
    prior_mass_rel_sd: float = 0.05,
    prior_com_sd_m: float = 0.01,
    model: WeightModel | None = None,
    fit: bool = True,
) -> Points:
    """Fit the weight model from the wind-off points (``tare`` and ``zero`` with finite data), or
    take ``model`` (e.g. from a separate tare run).  Prior: the rig file's mass and centre of mass
    with ``prior_mass_rel_sd`` and ``prior_com_sd_m``.  With no wind-off point and no model the
    weight stage flags every wind-on point ``no_tare``."""
    if model is not None:
        return with_updates(p, meta={"weight_model": model, "_note": "weight model given"})
    if not fit:
        return with_updates(p, meta={"weight_model": None, "_note": "not fitted (settings)"})
    off = np.isin(p["kind"], WIND_OFF_KINDS) & np.isfinite(p["tension_N"]).all(axis=1)
    off &= np.isfinite(p["pose"]).all(axis=1)
    idx = np.flatnonzero(off)
    if idx.size == 0:
        return with_updates(
            p, meta={"weight_model": None, "_note": "no wind-off point: no weight model"}
        )
    y, c_load, c_pose, _ = _load_and_pose_terms(rig, p, idx, np.zeros(4))
    wm = fit_weight(
        p["pose"][idx],
        y,
        c_load + c_pose,
        rig.gravity_O_mps2,
        rig.mass_kg,
        rig.com_P_m,
        prior_mass_rel_sd * rig.mass_kg,
        prior_com_sd_m,
    )
    sd = wm.com_sd_m
    note = (
        f"{wm.n_tares} wind-off points: mass {wm.mass_kg:.5f} ± {np.sqrt(wm.theta_cov[0, 0]):.5f} kg "
        f"(rig file {rig.mass_kg:g}); CoM_P {np.round(wm.com_P_m * 1e3, 3).tolist()} ± "
        f"{np.round(sd * 1e3, 3).tolist()} mm; chi2/dof {wm.chi2_per_dof:.3g}"
        + (f"; left to the prior: {', '.join(wm.weak)}" if wm.weak else "")
    )
    return with_updates(p, meta={"weight_model": wm, "_note": note})


@stage("weight_tare")
def weight_tare(
    p: Points,
    *,
    rig: Rig,
    position_tol_m: float = 1e-3,
    angle_tol_rad: float = float(np.deg2rad(0.1)),
    allow_nominal_weight: bool = False,
    prior_mass_rel_sd: float = 0.05,
    prior_com_sd_m: float = 0.01,
    tare_shares_pose: bool = False,
) -> Points:
    """Remove the weight: ``W = -A(q) T - G(q)``.

    Where a wind-off point j sits at the same pose (within the tolerances; the nearest in time), its
    own load stands for the weight: ``W_i = (-A_i T_i) - (-A_j T_j) - (G(q_i) - G(q_j))`` with the
    small pose-difference term from the weight model (flag ``tare``).  Elsewhere the weight model
    gives ``G(q_i)`` (flag ``weight_model``).  With neither, the point gets NaN and ``no_tare`` —
    unless ``allow_nominal_weight`` (an explicit choice, e.g. ``cdpr wrench`` without ``--tare``):
    then the rig file's mass (flag ``weight_nominal``, its prior spread in σ).

    σ terms: ``load_cells`` (both points), ``pose`` (both points' pose covariances through
    ``dW/dq``, independent measurements; with ``tare_shares_pose`` the tare was taken at the very
    same measured pose, as in ``cdpr wrench --tare``, and the one pose error acts through
    ``J_i - J_j``), ``weight_model`` (theta's covariance through ``B(q_i) - B(q_j)`` or ``B(q_i)``).
    """
    s = p.n
    wm: WeightModel | None = p.meta.get("weight_model")
    m0 = rig.mass_kg
    nominal = np.concatenate([[m0], m0 * rig.com_P_m])
    nominal_cov = np.diag([(prior_mass_rel_sd * m0) ** 2] + [(m0 * prior_com_sd_m) ** 2] * 3)
    theta, theta_cov = (wm.theta, wm.theta_cov) if wm is not None else (nominal, nominal_cov)
    kind = p["kind"]
    finite = np.isfinite(p["tension_N"]).all(axis=1) & np.isfinite(p["pose"]).all(axis=1)
    off = np.isin(kind, WIND_OFF_KINDS) & finite
    q = np.where(finite[:, None], p["pose"], 0.0)
    same = (np.linalg.norm(q[:, None, :3] - q[None, :, :3], axis=-1) <= position_tol_m) & (
        np.abs(q[:, None, 3:] - q[None, :, 3:]).max(axis=-1) <= angle_tol_rad
    )
    ok = same & off[None, :] & ~np.eye(s, dtype=bool)
    dt = np.abs(p["start_ns"][:, None] - p["start_ns"][None, :]).astype(np.float64)
    dt[~ok] = np.inf
    tare = (
        np.where(np.isfinite(dt).any(axis=1), np.argmin(dt, axis=1), -1) if s else np.zeros(0, int)
    )
    tare = np.where(finite & ~off, tare, -1)

    W = np.full((s, 6), np.nan)
    c_load = np.zeros((s, 6, 6))
    c_pose = np.zeros((s, 6, 6))
    c_wm = np.zeros((s, 6, 6))
    idx = np.flatnonzero(finite)
    y, cl, cp, Jy = _load_and_pose_terms(rig, p, idx, theta)
    W[idx], c_load[idx], c_pose[idx] = y, cl, cp
    J = np.zeros((s, 6, 6))
    J[idx] = Jy
    B = weight_basis(q, rig.gravity_O_mps2)
    c_wm[idx] = _sandwich(B[idx], np.broadcast_to(theta_cov, (len(idx), 4, 4)))
    # tare where one matches: subtract the tare's own residual (its weight, measured)
    has = tare >= 0
    j = tare[has]
    if j.size:
        W[has] = W[has] - W[j]
        c_load[has] = c_load[has] + c_load[j]
        if tare_shares_pose:  # one pose measurement for both: its error acts through J_i - J_j
            c_pose[has] = _sandwich(J[has] - J[j], p["pose_cov"][has])
        else:
            c_pose[has] = c_pose[has] + c_pose[j]
        dB = B[has] - B[j]
        c_wm[has] = _sandwich(dB, np.broadcast_to(theta_cov, (j.size, 4, 4)))
    model_used = finite & ~has & ~off & (wm is not None)
    no_tare = finite & ~has & ~off & (wm is None)
    flags: dict[str, NDArray[np.bool_]] = {
        "tare": has,
        "weight_model": model_used,
        "nonfinite_input": ~finite,
    }
    if wm is not None and wm.weak:
        for name in wm.weak:
            flags[f"weight_model_prior_{name}"] = model_used | (has & (wm is not None))
    if wm is None:
        dq = np.zeros(s, bool)
        if j.size:
            dq[has] = np.any(p["pose"][has] != p["pose"][j], axis=1)
        flags["pose_diff_nominal_weight"] = dq
        if allow_nominal_weight:
            flags["weight_nominal"] = no_tare
        else:
            W[no_tare] = np.nan
            c_load[no_tare] = c_pose[no_tare] = c_wm[no_tare] = np.nan
            flags["no_tare"] = no_tare
    # wind-off points keep their residual against the weight model (a check), NaN without one
    if wm is None:
        W[off] = np.nan
    return with_updates(
        p,
        arrays={"wrench_N": W, "tare_index": tare.astype(np.int64)},
        terms={"load_cells": c_load, "pose": c_pose, "weight_model": c_wm},
        flag=flags,
        replace_terms=True,
    )


@stage("subtract_wrench")
def subtract_wrench(
    p: Points, *, what: str, wrench_N: ArrayLike, cov: ArrayLike | None = None
) -> Points:
    """Subtract a known per-point wrench (s, 6) at P in {O} (e.g. the inertia wrench ``M qdd + C``
    of a moving platform, ``what = "inertia"``), with its covariance (s, 6, 6) as the σ term
    ``what`` when given."""
    w = np.asarray(wrench_N, dtype=np.float64)
    if w.shape != (p.n, 6):
        raise InputError(f"wrench_N: expected ({p.n}, 6), got {w.shape}")
    terms = {}
    if cov is not None:
        c = np.asarray(cov, dtype=np.float64)
        if c.shape != (p.n, 6, 6):
            raise InputError(f"cov: expected ({p.n}, 6, 6), got {c.shape}")
        terms[what] = c
    return with_updates(
        p, arrays={"wrench_N": p["wrench_N"] - w}, terms=terms, meta={"_note": what}
    )


@stage("balance_interaction")
def balance_interaction(
    p: Points, *, interaction: ArrayLike | None = None, second_order: Any = None
) -> Points:
    """Apply the balance calibration of ``cdpr calibrate balance``: the 6x6 interaction matrix
    ``W <- K W``, or, when given, the second-order model ``second_order = (K1, K2)``:
    ``W <- K1 W + K2 q(W)`` (:mod:`cdpr.analysis.balance_model`); every σ term is carried through
    the (linearised) map ``J C J^T``.  Without either, the wrench passes unchanged and the log
    says so."""
    if interaction is None and second_order is None:
        return with_updates(p, meta={"_note": "no balance calibration given: not applied"})
    if second_order is not None:
        K1, K2 = second_order
        note = "second-order balance model applied"
    else:
        K1, K2 = interaction, None
        note = "interaction matrix applied"
    K = np.asarray(K1, dtype=np.float64)
    if K.shape != (6, 6) or not np.all(np.isfinite(K)):
        raise InputError(f"interaction: expected a finite (6, 6) matrix, got {K.shape}")
    W, J = apply_balance_model(p["wrench_N"], K, K2)
    W[~np.isfinite(p["wrench_N"]).all(axis=1)] = np.nan
    terms = {k: _sandwich(J, v) for k, v in p.cov_terms.items()}
    return with_updates(p, arrays={"wrench_N": W}, terms=terms, meta={"_note": note})


@stage("axes_and_moments")
def axes_and_moments(p: Points, *, geometry: ModelGeometry) -> Points:
    """Moments moved to the moment reference point (``wrench_mrp_N``, {O} axes), the angles
    ``aoa_rad``/``sideslip_rad``, body-axis force/moment (``force_B_N``, ``moment_B_Nm``) and
    wind-axis ``drag_N, side_N, lift_N``, and the total covariance moved along
    (``wrench_mrp_cov``; ``cov_terms`` stay those of ``wrench_N`` at P)."""
    R = rotation_from_euler(np.nan_to_num(p["pose"][:, 3:]))
    r_O = np.einsum("sij,j->si", R, np.asarray(geometry.mrp_P_m, dtype=np.float64))
    rx = np.zeros((p.n, 3, 3))
    rx[:, 0, 1], rx[:, 0, 2] = -r_O[:, 2], r_O[:, 1]
    rx[:, 1, 0], rx[:, 1, 2] = r_O[:, 2], -r_O[:, 0]
    rx[:, 2, 0], rx[:, 2, 1] = -r_O[:, 1], r_O[:, 0]
    T = np.tile(np.eye(6), (p.n, 1, 1))
    T[:, 3:, :3] = -rx  # M - r x F
    W_mrp = transfer_moment(np.nan_to_num(p["wrench_N"]), r_O)
    W_mrp[~np.isfinite(p["wrench_N"]).all(axis=1)] = np.nan
    R_B_O = body_from_tunnel(R, geometry.nose_P, geometry.up_P)
    aoa, ss = flow_angles(R, geometry.nose_P, geometry.up_P)
    F_B = np.einsum("sij,sj->si", R_B_O, W_mrp[:, :3])
    M_B = np.einsum("sij,sj->si", R_B_O, W_mrp[:, 3:])
    F_W = np.einsum("sij,sj->si", wind_from_body(aoa, ss), F_B)
    arrays = {
        "wrench_mrp_N": W_mrp,
        "aoa_rad": aoa,
        "sideslip_rad": ss,
        "force_B_N": F_B,
        "moment_B_Nm": M_B,
        "drag_N": -F_W[:, 0],
        "side_N": F_W[:, 1],
        "lift_N": -F_W[:, 2],
        "wrench_mrp_cov": _sandwich(T, p.wrench_cov),
    }
    flags = {"geometry_from_options": np.full(p.n, geometry.source == "options")}
    return with_updates(p, arrays=arrays, flag=flags)


COEFFICIENTS: tuple[str, ...] = ("CD", "CY", "CL", "Cl", "Cm", "Cn")


@stage("coefficients")
def coefficients(p: Points, *, geometry: ModelGeometry, wind_off_mps: float = 1.0) -> Points:
    """Dynamic pressure ``q_Pa = rho V^2 / 2`` and ``CD, CY, CL, Cl, Cm, Cn`` with ``sd_*`` (from
    the total wrench covariance; the attitude's and q's own errors are not included) for wind-on
    points with a finite airspeed above ``wind_off_mps``; NaN elsewhere, flag ``no_airspeed`` on
    wind-on points without one (``no_density`` without a density)."""
    s = p.n
    V = p["airspeed_mps"]
    rho = p["density_kgpm3"]
    wind = np.isin(p["kind"], ("wind_on", "windage", "unknown"))
    okv = np.isfinite(V) & np.isfinite(rho) & (rho > 0)
    q = np.full(s, np.nan)
    q[okv] = dynamic_pressure(rho[okv], V[okv])
    use = wind & okv & (V > wind_off_mps) & np.isfinite(p["wrench_N"]).all(axis=1)
    out = {c: np.full(s, np.nan) for c in COEFFICIENTS}
    out.update({f"sd_{c}": np.full(s, np.nan) for c in COEFFICIENTS})
    if use.any():
        R = rotation_from_euler(p["pose"][use, 3:])
        g = geometry
        Kc = coefficient_matrix(
            R, q[use], g.area_m2, g.span_m, g.chord_m, g.mrp_P_m, g.nose_P, g.up_P
        )
        C = np.einsum("sij,sj->si", Kc, p["wrench_N"][use])
        cov = _sandwich(Kc, p.wrench_cov[use])
        sd = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0.0, None))
        for k, c in enumerate(COEFFICIENTS):
            out[c][use] = C[:, k]
            out[f"sd_{c}"][use] = sd[:, k]
    wind_on = p["kind"] == "wind_on"
    flags = {
        "no_airspeed": wind_on & ~np.isfinite(V),
        "no_density": wind_on & np.isfinite(V) & ~(np.isfinite(rho) & (rho > 0)),
    }
    return with_updates(p, arrays={"q_Pa": q, **out}, flag=flags)


@stage("tension_check")
def tension_check(p: Points, *, rig: Rig, method: str = "exact", limit_N: float = 1.0) -> Points:
    """The paper's check: the tensions ``method`` commands for ``-(G + W)`` (weight model, else the
    rig file's mass) against the measured ones: ``check_dT_N`` (s, m), ``check_max_abs_dT_N`` (s,),
    flag ``check_fail`` above ``limit_N``.  Points without a wrench get NaN."""
    wm: WeightModel | None = p.meta.get("weight_model")
    theta = (
        wm.theta if wm is not None else np.concatenate([[rig.mass_kg], rig.mass_kg * rig.com_P_m])
    )
    W = p["wrench_N"]
    ok = np.isfinite(W).all(axis=1)
    dT = np.full(p["tension_N"].shape, np.nan)
    if ok.any():
        G = weight_basis(p["pose"][ok], rig.gravity_O_mps2) @ theta
        exp = distribute(method, p["A"][ok], -(G + W[ok]), rig.t_min_N, rig.t_max_N)
        dT[ok] = p["tension_N"][ok] - exp.tensions_N
    mx = np.where(ok, np.abs(np.nan_to_num(dT)).max(axis=1) if p.n else 0.0, np.nan)
    return with_updates(
        p,
        arrays={"check_dT_N": dT, "check_max_abs_dT_N": mx},
        flag={"check_fail": ok & (mx > limit_N)},
        meta={"_note": f"method {method}, limit {limit_N} N"},
    )


def run_stages(points: Points, stages: list[Stage]) -> Points:
    """Run the stages in order."""
    for st in stages:
        points = st(points)
    return points


def points_from_samples(
    *,
    kind: ArrayLike,
    ranges: list[tuple[int, int]],
    t_ns: ArrayLike,
    tensions_N: ArrayLike,
    mask_bits: ArrayLike,
    airspeed_mps: ArrayLike | None,
    density_kgpm3: ArrayLike | None,
    pose_t_ns: ArrayLike,
    poses: ArrayLike,
    pose_cov: ArrayLike | None,
    pose_sd_fallback: ArrayLike | None = None,
    pose_bad: ArrayLike | None = None,
) -> tuple[Points, dict[str, NDArray[Any]]]:
    """Per-point inputs of the core from sample streams, and the point statistics.

    kind: (s,) point kinds; ranges: (s) ``[start, stop)`` indices into the tension samples
    (``t_ns`` (n,), ``tensions_N`` (n, m), ``mask_bits`` (n,) from
    :func:`cdpr.analysis.balance.sample_mask`); airspeed_mps, density_kgpm3: (n,) on the tension
    times, or None (no tunnel data: NaN, the coefficients stage flags ``no_airspeed``).
    The pose stream is separate (``pose_t_ns`` (k,), ``poses`` (k, 6), ``pose_cov`` (k, 6, 6) as
    the camera reports it per frame, ``pose_bad`` (k,) frames to drop): each point takes the frames
    inside its time span; the covariance of its mean pose is the mean reported covariance over the
    number of frames used.  Without a reported covariance, ``pose_sd_fallback`` (6,) is used and the
    point flagged ``pose_cov_nominal``; with neither, an error.

    Tension covariance: the squared standard errors of the per-cable means (independent cables).
    Flags: ``masked`` plus the mask words, ``no_samples`` (nothing usable), ``no_pose``,
    ``pose_flagged`` (some camera frames in the point dropped), ``pose_cov_nominal``.
    Returns the points and a dict of extra per-point columns (counts, start/stop times).
    """
    from .balance import mask_words, point_stats

    t = np.asarray(t_ns, dtype=np.int64)
    T = np.asarray(tensions_N, dtype=np.float64)
    bits = np.asarray(mask_bits, dtype=np.int64)
    s = len(ranges)
    st = point_stats(T, ranges, bits)
    idx = np.asarray(ranges, dtype=np.int64).reshape(s, 2)
    nonempty = idx[:, 1] > idx[:, 0]
    start_ns = np.where(nonempty, t[np.minimum(idx[:, 0], len(t) - 1)], 0)
    stop_ns = np.where(nonempty, t[np.maximum(idx[:, 1] - 1, 0)], 0)
    n = t.shape[0]

    def on_points(x: ArrayLike | None) -> FloatArray:
        if x is None:
            return np.full(s, np.nan)
        v = np.asarray(x, dtype=np.float64)
        if v.shape != (n,):
            raise InputError(f"tunnel stream: expected ({n},) on the tension times, got {v.shape}")
        return np.asarray(point_stats(v, ranges, bits).mean[:, 0], dtype=np.float64)

    V, rho = on_points(airspeed_mps), on_points(density_kgpm3)
    # pose stream: frames within each point's time span
    tp = np.asarray(pose_t_ns, dtype=np.int64)
    qp = np.asarray(poses, dtype=np.float64)
    if qp.shape != (tp.shape[0], 6):
        raise InputError(f"poses: expected ({tp.shape[0]}, 6), got {qp.shape}")
    pbad = np.zeros(tp.shape[0], bool) if pose_bad is None else np.asarray(pose_bad, dtype=bool)
    a = np.searchsorted(tp, start_ns, side="left")
    b = np.searchsorted(tp, stop_ns, side="right")
    pranges = [
        (int(i), int(j)) if ok else (int(i), int(i))
        for i, j, ok in zip(a, b, nonempty, strict=True)
    ]
    pbits = np.where(pbad, 1, 0).astype(np.int64)
    ps = point_stats(qp, pranges, pbits)
    nf = np.maximum(ps.n_used, 1).astype(np.float64)
    nominal = np.zeros(s, bool)
    if pose_cov is not None:
        C = np.asarray(pose_cov, dtype=np.float64)
        if C.shape != (tp.shape[0], 6, 6):
            raise InputError(f"pose_cov: expected ({tp.shape[0]}, 6, 6), got {C.shape}")
        cm = point_stats(C.reshape(-1, 36), pranges, pbits).mean.reshape(s, 6, 6)
        pcov = cm / nf[:, None, None]
    elif pose_sd_fallback is not None:
        sd = np.asarray(pose_sd_fallback, dtype=np.float64)
        if sd.shape != (6,):
            raise InputError(f"pose_sd_fallback: expected (6,), got {sd.shape}")
        pcov = np.broadcast_to(np.diag(sd**2), (s, 6, 6)) / nf[:, None, None]
        nominal[:] = True
    else:
        raise InputError("pose_cov: no covariance in the pose stream and no fallback given")
    tcov = st.sem[..., None] * np.eye(T.shape[1]) * st.sem[:, None, :]
    pts = new_points(
        kind=kind,
        start_ns=start_ns,
        tension_N=st.mean,
        tension_cov_N2=tcov,
        pose=ps.mean,
        pose_cov=np.array(pcov),
        airspeed_mps=V,
        density_kgpm3=rho,
    )
    words = []
    for i in range(s):
        w = []
        if st.n_masked[i]:
            w.append("masked")
            w += mask_words(int(st.masked_bits[i]))
        if st.n_used[i] < 2:
            w.append("no_samples")
        if ps.n_used[i] == 0:
            w.append("no_pose")
        elif ps.n_masked[i]:
            w.append("pose_flagged")
        if nominal[i]:
            w.append("pose_cov_nominal")
        words.append(";".join(w))
    pts = flags_from_masks(pts, words=words)
    extra = {
        "start_ns": start_ns,
        "stop_ns": stop_ns,
        "n_samples": st.n_samples,
        "n_masked": st.n_masked,
        "n_pose_frames": ps.n_used,
        "tension_sd_N": st.sd,
    }
    return pts, extra
