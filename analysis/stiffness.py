"""The balance's own dynamics: stiffness at a pose, natural frequencies and mode shapes, and the
check of a point's tension spectra against those modes.

Coordinates: a small displacement ``x = [dp; dtheta]`` (6,) of the platform, ``dp`` the translation
of P in {O} (m) and ``dtheta`` a small rotation vector in {O} axes (rad).  ``K`` (6, 6) maps it to
the restoring wrench at P in {O} (``dW = -K x``, N and N m).

Stiffness of cable i (tension T, length l, unit vector u from the platform point to the anchor,
lever arm r = R pp, axial stiffness k = EA/l, the unstretched length held fixed by the winch):

``K_f = k u u^T + (T/l) (I - u u^T)`` (elastic term + tension-dependent geometric term), and with
``[r]`` the cross-product matrix and ``f = T u``::

    K_i = [[ K_f,       -K_f [r]                 ],
           [ [r] K_f,   -[r] K_f [r] - [f][r]    ]]

Gravity (force ``F_g = m g`` at ``c = R com``) adds ``-[F_g][c]`` to the rotational block.  The
sum is symmetric at equilibrium (its antisymmetric part is the net moment); :func:`stiffness_matrix`
returns the symmetric part and the size of the antisymmetric one.  The aerodynamic load's own
stiffness (its change with attitude) is not included.

Mass matrix about P in {O}: ``M = [[m I, -m [c]], [m [c], R I_P R^T]]`` (``I_P`` about P, as the rig
file gives it, so the platform and model are both in it).  Modes: ``K phi = omega^2 M phi``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .conventions import GRAVITY_O_MPS2
from .errors import CdprError, InputError
from .records import CorrectionRecord
from .rig import Rig
from .rotations import skew

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Stiffness:
    """K (..., 6, 6) symmetric part; asymmetry (...,) ``|K - K^T|_F / |K|_F`` before symmetrising
    (about zero at equilibrium); elastic (..., 6, 6) and geometric (..., 6, 6) parts (K = sum)."""

    K: FloatArray
    elastic: FloatArray
    geometric: FloatArray
    asymmetry: FloatArray


def stiffness_matrix(
    anchors_O_m: ArrayLike,
    attach_P_m: ArrayLike,
    position_O_m: ArrayLike,
    R_O_P: ArrayLike,
    tensions_N: ArrayLike,
    EA_N: ArrayLike,
    mass_kg: float = 0.0,
    com_P_m: ArrayLike = (0.0, 0.0, 0.0),
    gravity_O_mps2: ArrayLike = GRAVITY_O_MPS2,
) -> Stiffness:
    """Stiffness at a batch of poses: position_O_m (..., 3), R_O_P (..., 3, 3), tensions_N (..., m),
    EA_N (m,) or scalar (N), anchors/attach (m, 3) or (..., m, 3) (a batch of rigs).  ``mass_kg``
    > 0 adds gravity's term."""
    b = check_trailing(anchors_O_m, "anchors_O_m", (3,))
    pp = check_trailing(attach_P_m, "attach_P_m", (3,))
    p = check_trailing(position_O_m, "position_O_m", (3,))
    R = check_trailing(R_O_P, "R_O_P", (3, 3))
    m = b.shape[-2]
    T = as_float_array(tensions_N, "tensions_N")
    if T.shape[-1:] != (m,):
        raise InputError(f"tensions_N: expected (..., {m}), got {T.shape}")
    EA = np.broadcast_to(as_float_array(EA_N, "EA_N"), (m,))
    if np.any(~np.isfinite(EA)) or np.any(EA <= 0):
        raise InputError("EA_N: expected finite values > 0 N")
    r = np.matmul(pp, np.swapaxes(R, -1, -2))  # (..., m, 3): R pp_i
    lv = b - p[..., None, :] - r
    length = np.linalg.norm(lv, axis=-1)
    if np.any(length < 1e-12):
        raise InputError("stiffness_matrix: a cable has zero length")
    u = lv / length[..., None]
    uu = u[..., :, None] * u[..., None, :]  # (..., m, 3, 3)
    eye = np.eye(3)
    k_el = (EA / length)[..., None, None] * uu
    k_geo = (T / length)[..., None, None] * (eye - uu)
    S = skew(r)  # (..., m, 3, 3)
    F = skew(T[..., None] * u)

    def blocks(Kf: FloatArray, extra: FloatArray | None) -> FloatArray:
        top = np.concatenate([Kf, -Kf @ S], axis=-1)
        rot = -S @ Kf @ S if extra is None else -S @ Kf @ S - extra
        bottom = np.concatenate([S @ Kf, rot], axis=-1)
        return np.asarray(np.concatenate([top, bottom], axis=-2).sum(axis=-3))

    elastic = blocks(k_el, None)
    geometric = blocks(k_geo, F @ S)
    if mass_kg > 0:
        c = np.einsum("...ij,j->...i", R, check_trailing(com_P_m, "com_P_m", (3,)))
        Fg = mass_kg * np.asarray(gravity_O_mps2, dtype=np.float64)
        geometric = geometric.copy()
        geometric[..., 3:, 3:] -= skew(np.broadcast_to(Fg, c.shape)) @ skew(c)
    K = elastic + geometric
    Kt = np.swapaxes(K, -1, -2)
    asym = np.linalg.norm(K - Kt, axis=(-2, -1)) / np.maximum(
        np.linalg.norm(K, axis=(-2, -1)), 1e-300
    )
    return Stiffness(K=0.5 * (K + Kt), elastic=elastic, geometric=geometric, asymmetry=asym)


def mass_matrix(
    mass_kg: float, com_P_m: ArrayLike, inertia_P_kgm2: ArrayLike, R_O_P: ArrayLike
) -> FloatArray:
    """Rigid-body mass matrix (..., 6, 6) about P in {O} for ``x = [dp; dtheta]``; R_O_P
    (..., 3, 3) and inertia_P_kgm2 (..., 3, 3) broadcast."""
    if not mass_kg > 0:
        raise InputError(f"mass_kg: expected > 0 kg, got {mass_kg}")
    R = check_trailing(R_O_P, "R_O_P", (3, 3))
    c = np.einsum("...ij,j->...i", R, check_trailing(com_P_m, "com_P_m", (3,)))
    I_P = check_trailing(inertia_P_kgm2, "inertia_P_kgm2", (3, 3))
    I_O = R @ I_P @ np.swapaxes(R, -1, -2)
    C = np.broadcast_to(mass_kg * skew(c), I_O.shape)
    top = np.concatenate([np.broadcast_to(mass_kg * np.eye(3), C.shape), -C], axis=-1)
    bottom = np.concatenate([C, I_O], axis=-1)
    return np.concatenate([top, bottom], axis=-2)


@dataclass(frozen=True)
class Modes:
    """frequencies_Hz (..., 6) ascending; shapes (..., 6, 6) mode shapes as columns (M-normalised,
    ``[dp (m); dtheta (rad)]``); unstable (...,) True if a negative eigenvalue appeared (the pose is
    not statically stable: its frequency is reported as NaN)."""

    frequencies_Hz: FloatArray
    shapes: FloatArray
    unstable: NDArray[np.bool_]


def natural_modes(K: ArrayLike, M: ArrayLike) -> Modes:
    """Natural frequencies and mode shapes of ``K phi = omega^2 M phi``, batched.

    Solved as the symmetric problem ``L^-1 K L^-T y = omega^2 y`` with ``M = L L^T``.
    """
    K_ = check_trailing(K, "K", (6, 6))
    M_ = check_trailing(M, "M", (6, 6))
    try:
        L = np.linalg.cholesky(M_)
    except np.linalg.LinAlgError:
        raise InputError(
            "M: expected a positive-definite mass matrix (is the inertia zero?)"
        ) from None
    Linv = np.linalg.inv(L)
    A = Linv @ K_ @ np.swapaxes(Linv, -1, -2)
    w2, Y = np.linalg.eigh(0.5 * (A + np.swapaxes(A, -1, -2)))
    shapes = np.swapaxes(Linv, -1, -2) @ Y
    unstable = np.any(w2 < 0, axis=-1)
    with np.errstate(invalid="ignore"):
        f = np.where(w2 >= 0, np.sqrt(np.abs(w2)) / (2 * np.pi), np.nan)
    return Modes(frequencies_Hz=f, shapes=shapes, unstable=unstable)


@dataclass(frozen=True)
class SpectrumCheck:
    """freqs_Hz (nf,), psd (m, nf) (N^2/Hz, one-sided Welch) of each tension;
    too_few_periods: the window holds fewer than ``min_periods`` periods of the lowest mode;
    peak_near_mode: (m,) a tension's highest spectral peak (above the noise floor) lies within
    ``band_rel`` of a mode; peak_Hz: (m,) that peak's frequency; record: flags and values."""

    freqs_Hz: FloatArray
    psd: FloatArray
    too_few_periods: bool
    peak_near_mode: NDArray[np.bool_]
    peak_Hz: FloatArray
    record: CorrectionRecord


def spectrum_check(
    tensions_N: ArrayLike,
    sample_rate_Hz: float,
    modes_Hz: ArrayLike,
    min_periods: float = 10.0,
    band_rel: float = 0.1,
    peak_factor: float = 20.0,
) -> SpectrumCheck:
    """Power spectrum of every tension of one point's averaging window and its check against the
    rig's modes.

    tensions_N: (n_samples, m) uniformly sampled at ``sample_rate_Hz``; modes_Hz: (k,) the rig's
    natural frequencies at the point's pose.  A peak counts when its PSD exceeds ``peak_factor``
    times the median PSD (the noise floor); the mean is removed first (Welch, Hann window).
    """
    from scipy.signal import welch

    x = as_float_array(tensions_N, "tensions_N")
    if x.ndim != 2 or x.shape[0] < 8:
        raise InputError(f"tensions_N: expected (n_samples >= 8, m), got {x.shape}")
    if not sample_rate_Hz > 0:
        raise InputError(f"sample_rate_Hz: expected > 0, got {sample_rate_Hz}")
    modes = as_float_array(modes_Hz, "modes_Hz").reshape(-1)
    modes = modes[np.isfinite(modes) & (modes > 0)]
    if modes.size == 0:
        raise InputError("modes_Hz: expected at least one finite mode > 0 Hz")
    duration_s = x.shape[0] / sample_rate_Hz
    too_few = bool(duration_s * modes.min() < min_periods)
    nper = min(x.shape[0], 1024)
    freqs, psd = welch(x, fs=sample_rate_Hz, nperseg=nper, detrend="constant", axis=0)
    psd = psd.T  # (m, nf)
    body = psd[:, 1:]
    k = np.argmax(body, axis=1) + 1
    peak_Hz = freqs[k]
    peak_val = psd[np.arange(psd.shape[0]), k]
    floor = np.median(body, axis=1)
    significant = peak_val > peak_factor * np.maximum(floor, 1e-300)
    near = np.any(np.abs(peak_Hz[:, None] - modes[None, :]) <= band_rel * modes[None, :], axis=1)
    peak_near = significant & near
    flags = tuple(
        f
        for f, bad in (("too_few_periods", too_few), ("spectrum_peak_near_mode", peak_near.any()))
        if bad
    )
    rec = CorrectionRecord(
        name="spectrum_check",
        source="Welch PSD of each tension; periods of the lowest mode in the window",
        values={
            "duration_s": duration_s,
            "lowest_mode_Hz": float(modes.min()),
            "periods_of_lowest_mode": duration_s * float(modes.min()),
            "peak_Hz": peak_Hz.tolist(),
        },
        flags=flags,
    )
    return SpectrumCheck(freqs, psd, too_few, peak_near, peak_Hz, rec)


@dataclass(frozen=True)
class RigModes:
    """Modes of a rig at one pose, wind off: tensions_N (m,) from the named distribution method,
    the stiffness and the modes; method names the tension distribution used."""

    tensions_N: FloatArray
    stiffness: Stiffness
    modes: Modes
    method: str


def rig_modes(
    rig: Rig,
    position_O_m: ArrayLike | None = None,
    euler_rad: ArrayLike | None = None,
    method: str = "improved-closed-form",
) -> RigModes:
    """Natural modes of ``rig`` at a pose (default its reference pose) under gravity alone.

    Tensions from :func:`cdpr.analysis.tension.distribute` with ``method`` (``A T = -G``); EA,
    mass, centre of mass and inertia (platform and model) from the rig.  Raises
    :class:`~cdpr.analysis.errors.InfeasibleError` if no tension distribution exists there.
    """
    from .dynamics import gravity_wrench
    from .errors import InfeasibleError
    from .kinematics import structure_matrix
    from .rotations import rotation_from_euler
    from .tension import distribute

    p = (
        rig.reference_position_O_m
        if position_O_m is None
        else check_trailing(position_O_m, "position_O_m", (3,))
    )
    psi = (
        rig.reference_euler_rad
        if euler_rad is None
        else check_trailing(euler_rad, "euler_rad", (3,))
    )
    R = rotation_from_euler(psi)
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, p, R)
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    res = distribute(method, A, -G, rig.t_min_N, rig.t_max_N)
    if not bool(np.all(res.feasible)):
        raise InfeasibleError(f"{rig.name}: no feasible tensions at the pose ({method})")
    T = np.asarray(res.tensions_N, dtype=np.float64)
    st, modes = modes_at(rig, p, R, T)
    return RigModes(tensions_N=T, stiffness=st, modes=modes, method=method)


def modes_at(
    rig: Rig, position_O_m: ArrayLike, R_O_P: ArrayLike, tensions_N: ArrayLike
) -> tuple[Stiffness, Modes]:
    """The rig's stiffness and natural modes at a batch of poses (position (..., 3), R_O_P
    (..., 3, 3)) under given tensions (..., m): EA, mass, centre of mass and inertia from the rig,
    gravity's term included (as :func:`rig_modes`, for tensions other than gravity's alone, e.g.
    those that carry a motion)."""
    R = check_trailing(R_O_P, "R_O_P", (3, 3))
    st = stiffness_matrix(
        rig.anchors_O_m,
        rig.attach_P_m,
        position_O_m,
        R,
        tensions_N,
        rig.cable_EA_N,
        rig.mass_kg,
        rig.com_P_m,
        rig.gravity_O_mps2,
    )
    M = mass_matrix(rig.mass_kg, rig.com_P_m, rig.inertia_P_kgm2, R)
    return st, natural_modes(st.K, M)


def dominant_coordinates(shapes: ArrayLike, M: ArrayLike) -> FloatArray:
    """Each mode's share of kinetic energy per coordinate (..., 6 coordinates, 6 modes): the
    columns of ``|phi * (M phi)|`` normalised to sum 1 (coordinates ``[x, y, z, roll, pitch,
    yaw]`` as small displacements and rotations in {O})."""
    phi = check_trailing(shapes, "shapes", (6, 6))
    Mm = check_trailing(M, "M", (6, 6))
    e = np.abs(phi * (Mm @ phi))
    return np.asarray(e / np.maximum(e.sum(axis=-2, keepdims=True), 1e-300))


@dataclass(frozen=True)
class HarmonicCheck:
    """The harmonics ``h f`` (h = 1..n) of a motion against modes: harmonic_Hz (n,), mode (n,) the
    index of the nearest mode, distance_rel (n,) the distance from ``h f`` to that mode's band
    ``[lo, hi]`` relative to the band's edge (0 inside it), near (n,) ``distance_rel <=
    band_rel``."""

    harmonic_Hz: FloatArray
    mode: NDArray[np.intp]
    distance_rel: FloatArray
    near: NDArray[np.bool_]


def harmonic_check(
    frequency_Hz: float,
    modes_lo_Hz: ArrayLike,
    modes_hi_Hz: ArrayLike,
    n_harmonics: int = 3,
    band_rel: float = 0.1,
) -> HarmonicCheck:
    """The first ``n_harmonics`` multiples of ``frequency_Hz`` against modes whose frequency
    ranges over ``[modes_lo_Hz, modes_hi_Hz]`` (k,) (e.g. over a cycle of the motion): a harmonic
    is near a mode when it lies within ``band_rel`` (relative) of that range."""
    if not (np.isfinite(frequency_Hz) and frequency_Hz > 0):
        raise InputError(f"frequency_Hz: expected > 0, got {frequency_Hz}")
    if n_harmonics < 1:
        raise InputError(f"n_harmonics: expected >= 1, got {n_harmonics}")
    lo = as_float_array(modes_lo_Hz, "modes_lo_Hz").reshape(-1)
    hi = as_float_array(modes_hi_Hz, "modes_hi_Hz").reshape(-1)
    if lo.shape != hi.shape or lo.size == 0 or np.any(~np.isfinite(lo) | ~np.isfinite(hi)):
        raise InputError("modes_lo_Hz, modes_hi_Hz: expected finite ranges of the same length")
    h = float(frequency_Hz) * np.arange(1, n_harmonics + 1, dtype=np.float64)
    below = (lo[None, :] - h[:, None]) / lo[None, :]
    above = (h[:, None] - hi[None, :]) / hi[None, :]
    d = np.maximum(np.maximum(below, above), 0.0)  # (n, k)
    j = np.argmin(d, axis=1)
    dist = d[np.arange(h.size), j]
    return HarmonicCheck(h, j, dist, dist <= band_rel)


@dataclass(frozen=True)
class PointSpectra:
    """The spectrum check of every point (computed from the samples, which the core does not
    hold): ``modes_Hz`` (s, 6) the rig's natural frequencies at each point's pose (NaN: none),
    ``too_few_periods`` and ``peak_near_mode`` (s,), ``peak_Hz`` (s, m), and the spectra of each
    point for the report's plot (``freqs_Hz`` (s) arrays, ``psd`` (s) (m, nf) arrays)."""

    modes_Hz: NDArray[np.float64]
    too_few_periods: NDArray[np.bool_]
    peak_near_mode: NDArray[np.bool_]
    peak_Hz: NDArray[np.float64]
    freqs_Hz: list[NDArray[np.float64]]
    psd: list[NDArray[np.float64]]


def point_spectra(
    rig: Rig,
    t_ns: NDArray[np.int64],
    tensions_N: NDArray[np.float64],
    ranges: Sequence[tuple[int, int]],
    poses: NDArray[np.float64],
) -> PointSpectra:
    """:func:`spectrum_check` of each point's tension window against the
    rig's modes at the point's mean pose (:func:`rig_modes`).  A window
    with fewer than 8 finite samples, or a pose where no tension distribution exists, gets NaN."""
    s, m = len(ranges), tensions_N.shape[1]
    # the mean sample rate over the run: reception times come in bursts (a loaded host, a pty), so
    # the median interval can be near zero while the samples are evenly spaced at the source
    span_ns = float(t_ns[-1] - t_ns[0]) if len(t_ns) > 1 else 0.0
    fs = (len(t_ns) - 1) * 1e9 / span_ns if span_ns > 0 else float("nan")
    modes = np.full((s, 6), np.nan)
    few = np.zeros(s, bool)
    near = np.zeros(s, bool)
    peak = np.full((s, m), np.nan)
    freqs: list[NDArray[np.float64]] = []
    psd: list[NDArray[np.float64]] = []
    for i, (a, b) in enumerate(ranges):  # one Welch estimate per point (vectorised inside)
        freqs.append(np.zeros(0))
        psd.append(np.zeros((m, 0)))
        x = tensions_N[a:b]
        x = x[np.isfinite(x).all(axis=1)]
        if x.shape[0] < 8 or not np.isfinite(poses[i]).all() or not np.isfinite(fs):
            continue
        try:
            f = rig_modes(rig, poses[i, :3], poses[i, 3:]).modes.frequencies_Hz
        except CdprError:
            continue
        modes[i] = f
        if not np.isfinite(f).any():
            continue
        sc = spectrum_check(x, fs, f)
        few[i], near[i], peak[i] = sc.too_few_periods, bool(sc.peak_near_mode.any()), sc.peak_Hz
        freqs[i], psd[i] = sc.freqs_Hz, sc.psd
    return PointSpectra(modes, few, near, peak, freqs, psd)
