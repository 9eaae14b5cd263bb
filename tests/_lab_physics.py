"""The lab generator's own rig physics (nothing here imports cdpr).

Written again from the definitions, so that an error in cdpr's statics, tension distribution,
stiffness or dynamics shows up as a disagreement instead of cancelling out:

- the rig read from its TOML file as plain numbers (:class:`LabRig`);
- rotations (Z-Y-X Euler angles, ``R = Rz(yaw) Ry(pitch) Rx(roll)``), the Euler-rate matrix H
  (``omega = H psi_dot``) and its time derivative;
- the structure matrix ``A`` (6 x m): column i is ``[u_i; r_i x u_i]`` with ``u_i`` the unit vector
  from the platform point to the anchor and ``r_i = R pp_i``, so ``A T`` is the cables' wrench on
  the platform at P in {O} axes;
- the controller's tension distribution: min ``|T - T_mid|_2`` subject to ``A T = w`` and the
  limits (:func:`distribute`);
- the stiffness at a pose by central differences of the cables' and gravity's wrench under a
  small displacement with the unstretched cable lengths held (:func:`stiffness`), the mass matrix
  about P and the natural modes (:func:`modes`);
- rigid-body Newton-Euler about P with the centre of mass off P and a full inertia tensor
  (:func:`body_wrench`), and the commanded motions of issue 22 (:class:`Motion`).

Signs: every wrench is ``[Fx, Fy, Fz, Mx, My, Mz]`` at P in {O} axes (N, N m).  Newton-Euler:
``A T + G + W_aero = D`` with ``G`` the gravity load on the platform and ``D`` the rate of change
of momentum (:func:`body_wrench`), so the cables must supply ``w = D - G - W_aero``.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import scipy.linalg
import scipy.optimize

G0 = 9.80665
DEFAULT_EA_N = 7.0e4
"""Axial stiffness E*A when the rig file gives none: a 1 mm 7x7 steel wire rope, the assumption
the rig files of data_samples/ state for `cdpr rig show` (not a value of the code under test)."""

AXES = ("surge", "sway", "heave", "roll", "pitch", "yaw")
"""Motion axes in the order of the pose coordinates ``(x, y, z, roll, pitch, yaw)``."""


# --------------------------------------------------------------------------------------------
# rotations


def rot(euler: np.ndarray) -> np.ndarray:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` (..., 3, 3) from ``(roll, pitch, yaw)`` (..., 3), rad."""
    e = np.asarray(euler, dtype=np.float64)
    cr, sr = np.cos(e[..., 0]), np.sin(e[..., 0])
    cp, sp = np.cos(e[..., 1]), np.sin(e[..., 1])
    cy, sy = np.cos(e[..., 2]), np.sin(e[..., 2])
    R = np.empty(e.shape[:-1] + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def euler_of(R: np.ndarray) -> np.ndarray:
    """``(roll, pitch, yaw)`` (..., 3) of a rotation (..., 3, 3): the inverse of :func:`rot` for
    |pitch| < 90 deg."""
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]`` (..., 3, 3) with ``[v] x = v x x``."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def rotvec_exp(theta: np.ndarray) -> np.ndarray:
    """Rotation (..., 3, 3) of the rotation vector ``theta`` (..., 3) (Rodrigues)."""
    th = np.asarray(theta, dtype=np.float64)
    a = np.linalg.norm(th, axis=-1)[..., None, None]
    K = skew(th)
    small = a < 1e-8
    s = np.where(small, 1.0 - a**2 / 6.0, np.sin(a) / np.where(small, 1.0, a))
    c = np.where(small, 0.5 - a**2 / 24.0, (1.0 - np.cos(a)) / np.where(small, 1.0, a**2))
    return np.eye(3) + s * K + c * (K @ K)


def rate_matrix(euler: np.ndarray) -> np.ndarray:
    """H (..., 3, 3) with ``omega_O = H psi_dot`` for ``psi = (roll, pitch, yaw)``.

    From ``R = Rz(g) Ry(b) Rx(a)``: ``omega = g_dot z + b_dot Rz(g) y + a_dot Rz(g) Ry(b) x``."""
    e = np.asarray(euler, dtype=np.float64)
    cb, sb = np.cos(e[..., 1]), np.sin(e[..., 1])
    cg, sg = np.cos(e[..., 2]), np.sin(e[..., 2])
    H = np.zeros(e.shape[:-1] + (3, 3))
    H[..., 0, 0], H[..., 1, 0], H[..., 2, 0] = cb * cg, cb * sg, -sb
    H[..., 0, 1], H[..., 1, 1] = -sg, cg
    H[..., 2, 2] = 1.0
    return H


def rate_matrix_dot(euler: np.ndarray, euler_rate: np.ndarray) -> np.ndarray:
    """dH/dt (..., 3, 3) along a path with angles ``euler`` and rates ``euler_rate``."""
    e = np.asarray(euler, dtype=np.float64)
    ed = np.asarray(euler_rate, dtype=np.float64)
    cb, sb = np.cos(e[..., 1]), np.sin(e[..., 1])
    cg, sg = np.cos(e[..., 2]), np.sin(e[..., 2])
    bd, gd = ed[..., 1], ed[..., 2]
    Hd = np.zeros(e.shape[:-1] + (3, 3))
    Hd[..., 0, 0] = -sb * bd * cg - cb * sg * gd
    Hd[..., 1, 0] = -sb * bd * sg + cb * cg * gd
    Hd[..., 2, 0] = -cb * bd
    Hd[..., 0, 1] = -cg * gd
    Hd[..., 1, 1] = -sg * gd
    return Hd


# --------------------------------------------------------------------------------------------
# the rig


@dataclass(frozen=True)
class LabRig:
    """A rig as plain arrays (SI): cables ``m``, anchors ``b_i`` in {O}, platform points ``pp_i`` in
    {P}, limits, axial stiffness, and the body (mass, centre of mass in {P}, inertia about P in
    {P} axes).  ``path`` and ``text``: the file it came from."""

    name: str
    cable_names: tuple[str, ...]
    anchors_O_m: np.ndarray
    attach_P_m: np.ndarray
    t_min_N: np.ndarray
    t_max_N: np.ndarray
    EA_N: np.ndarray
    mass_kg: float
    com_P_m: np.ndarray
    inertia_P_kgm2: np.ndarray
    gravity_O_mps2: np.ndarray
    reference_pose: np.ndarray
    path: str = ""
    text: str = ""

    @classmethod
    def from_toml(cls, path: str | Path) -> LabRig:
        """Read a rig TOML file (the layout of data_samples/*.toml) with tomllib."""
        text = Path(path).read_text()
        d = tomllib.loads(text)
        cab = d["cables"]
        rig = d.get("rig", {})
        pl = d["platform"]
        ref = np.concatenate(
            [
                np.asarray(rig.get("reference_position_O_m", [0.0, 0.0, 0.0]), float),
                np.asarray(rig.get("reference_euler_rad", [0.0, 0.0, 0.0]), float),
            ]
        )
        return cls(
            name=str(rig.get("name", Path(path).stem)),
            cable_names=tuple(str(c["name"]) for c in cab),
            anchors_O_m=np.array([c["anchor_O_m"] for c in cab], float),
            attach_P_m=np.array([c["attach_P_m"] for c in cab], float),
            t_min_N=np.array([c["t_min_N"] for c in cab], float),
            t_max_N=np.array([c["t_max_N"] for c in cab], float),
            EA_N=np.array([c.get("EA_N", DEFAULT_EA_N) for c in cab], float),
            mass_kg=float(pl["mass_kg"]),
            com_P_m=np.asarray(pl.get("com_P_m", [0.0, 0.0, 0.0]), float),
            inertia_P_kgm2=np.asarray(pl["inertia_P_kgm2"], float),
            gravity_O_mps2=np.asarray(rig.get("gravity_O_mps2", [0.0, 0.0, -G0]), float),
            reference_pose=ref,
            path=str(path),
            text=text,
        )

    @property
    def m(self) -> int:
        return len(self.cable_names)

    @property
    def t_mid_N(self) -> np.ndarray:
        return 0.5 * (self.t_min_N + self.t_max_N)

    def with_body(
        self,
        mass_kg: float | None = None,
        com_P_m: np.ndarray | None = None,
        inertia_P_kgm2: np.ndarray | None = None,
    ) -> LabRig:
        """The same rig carrying another body (the model's true mass properties)."""
        return replace(
            self,
            mass_kg=self.mass_kg if mass_kg is None else float(mass_kg),
            com_P_m=self.com_P_m if com_P_m is None else np.asarray(com_P_m, float),
            inertia_P_kgm2=(
                self.inertia_P_kgm2 if inertia_P_kgm2 is None else np.asarray(inertia_P_kgm2, float)
            ),
        )


def cable_vectors(rig: LabRig, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lever arms ``r_i = R pp_i`` (..., m, 3), cable vectors ``l_i = b_i - p - r_i`` (..., m, 3)
    and lengths (..., m) at poses (..., 6)."""
    q = np.asarray(poses, dtype=np.float64)
    R = rot(q[..., 3:])
    r = np.einsum("...ij,mj->...mi", R, rig.attach_P_m)
    lv = rig.anchors_O_m - q[..., None, :3] - r
    return r, lv, np.linalg.norm(lv, axis=-1)


def structure_matrix(rig: LabRig, poses: np.ndarray) -> np.ndarray:
    """A (..., 6, m): column i is ``[u_i; r_i x u_i]`` (``A T`` = the cables' wrench at P, {O})."""
    r, lv, ln = cable_vectors(rig, poses)
    u = lv / ln[..., None]
    return np.swapaxes(np.concatenate([u, np.cross(r, u)], axis=-1), -1, -2)


def gravity_wrench(rig: LabRig, poses: np.ndarray) -> np.ndarray:
    """Gravity load on the body at P in {O}: ``[m g; (R c) x m g]`` (..., 6)."""
    q = np.asarray(poses, dtype=np.float64)
    f = rig.mass_kg * np.broadcast_to(rig.gravity_O_mps2, q.shape[:-1] + (3,))
    rc = np.einsum("...ij,j->...i", rot(q[..., 3:]), rig.com_P_m)
    return np.concatenate([f, np.cross(rc, f)], axis=-1)


# --------------------------------------------------------------------------------------------
# the controller's tension distribution


class InfeasibleError(ValueError):
    """No tensions within the limits hold the asked wrench (``index``: the sample)."""

    index: int = -1


def distribute(
    A: np.ndarray, w: np.ndarray, t_min: np.ndarray, t_max: np.ndarray
) -> tuple[np.ndarray, int]:
    """The controller's tensions: min ``|T - T_mid|_2`` subject to ``A T = w`` and
    ``t_min <= T <= t_max`` (``T_mid = (t_min + t_max)/2``), for a batch A (n, 6, m), w (n, 6).

    Method: the closed form ``T = T_mid + A^T (A A^T)^-1 (w - A T_mid)``, the optimum of the
    equality-constrained problem; where it lies within the limits it is the optimum of the whole
    QP (the KKT conditions hold with zero multipliers on the bounds).  A sample outside the limits
    is solved as the QP in A's null space by scipy (``scipy.optimize.minimize``: SLSQP, else
    trust-constr); a sample neither can hold raises :class:`InfeasibleError`.  Returns the tensions
    (n, m) and the number of samples that needed SLSQP."""
    A = np.asarray(A, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    mid = 0.5 * (t_min + t_max)
    resid = w - np.einsum("nij,j->ni", A, mid)
    y = np.linalg.solve(A @ np.swapaxes(A, -1, -2), resid[..., None])[..., 0]
    T = mid + np.einsum("nij,ni->nj", A, y)
    tol = 1e-9 * np.maximum(1.0, t_max)
    out = np.flatnonzero(((T < t_min - tol) | (T > t_max + tol)).any(axis=1))
    for k in out:
        try:
            T[k] = _qp_one(A[k], w[k], t_min, t_max, T[k])
        except InfeasibleError as exc:
            exc.index = int(k)
            raise
    return T, len(out)


def _qp_one(
    A: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray, T_cf: np.ndarray
) -> np.ndarray:
    """The QP of one sample in the null space of A: ``T = T_cf + N z`` (N an orthonormal basis of
    A's null space, ``T_cf`` the closed form, whose offset from ``T_mid`` is orthogonal to N), so
    the objective is ``|z|^2`` under ``lo <= T_cf + N z <= hi``: SLSQP, then trust-constr if
    SLSQP stops short."""
    N = scipy.linalg.null_space(A)
    cons = scipy.optimize.LinearConstraint(N, lo - T_cf, hi - T_cf)
    z0 = np.zeros(N.shape[1])
    best = None
    options = {
        "SLSQP": {"maxiter": 1000},
        "trust-constr": {"maxiter": 5000, "gtol": 1e-12, "xtol": 1e-14},
    }
    for method in ("SLSQP", "trust-constr"):
        res = scipy.optimize.minimize(
            lambda z: float(z @ z), z0, jac=lambda z: 2 * z, method=method, constraints=[cons],
            options=options[method],
        )  # fmt: skip
        T = T_cf + N @ res.x
        if np.all(T >= lo - 1e-7) and np.all(T <= hi + 1e-7):
            best = np.clip(T, lo, hi)
            break
    if best is None or np.max(np.abs(A @ best - w)) > 1e-6 * max(1.0, float(np.max(np.abs(w)))):
        raise InfeasibleError(
            f"no tensions within [{lo.min():g}, {hi.max():g}] N hold the wrench "
            f"{np.array2string(w, precision=4)}"
        )
    return best


# --------------------------------------------------------------------------------------------
# stiffness and modes


def displaced_wrench(
    rig: LabRig, pose: np.ndarray, tensions_N: np.ndarray, x: np.ndarray
) -> np.ndarray:
    """The cables' plus gravity's wrench at P in {O} (k, 6) after small displacements x (k, 6)
    ``[dp; dtheta]`` (dtheta a rotation vector in {O}) from ``pose`` with ``tensions_N``, the
    unstretched cable lengths held: ``T_i = T0_i + EA_i (l_i - l0_i) / l0_i``."""
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    R0 = rot(pose[3:])
    R = rotvec_exp(x[:, 3:]) @ R0
    p = pose[:3] + x[:, :3]
    r = np.einsum("kij,mj->kmi", R, rig.attach_P_m)
    lv = rig.anchors_O_m - p[:, None, :] - r
    ln = np.linalg.norm(lv, axis=-1)
    l0 = np.linalg.norm(rig.anchors_O_m - pose[:3] - rig.attach_P_m @ R0.T, axis=-1)
    T = tensions_N + rig.EA_N * (ln - l0) / l0
    f = T[..., None] * lv / ln[..., None]
    F = f.sum(axis=1)
    M = np.cross(r, f).sum(axis=1)
    fg = rig.mass_kg * rig.gravity_O_mps2
    rc = np.einsum("kij,j->ki", R, rig.com_P_m)
    return np.concatenate([F + fg, M + np.cross(rc, fg)], axis=1)


def stiffness(
    rig: LabRig, pose: np.ndarray, tensions_N: np.ndarray, step: float = 1e-7
) -> tuple[np.ndarray, float]:
    """``K = -dW/dx`` (6, 6) by central differences of :func:`displaced_wrench` (steps of
    ``step`` m and rad), symmetrised; and the relative size of its antisymmetric part."""
    E = np.eye(6) * step
    Wp = displaced_wrench(rig, pose, tensions_N, E)
    Wm = displaced_wrench(rig, pose, tensions_N, -E)
    K = -(Wp - Wm).T / (2 * step)
    asym = float(np.linalg.norm(K - K.T) / np.linalg.norm(K))
    return 0.5 * (K + K.T), asym


def mass_matrix(rig: LabRig, pose: np.ndarray) -> np.ndarray:
    """Mass matrix (6, 6) about P for ``[dp; dtheta]`` in {O}: kinetic energy
    ``1/2 m |v + w x rc|^2 + 1/2 w^T I_c w`` = ``1/2 [v; w]^T M [v; w]`` with ``rc = R c``."""
    R = rot(pose[3:])
    rc = R @ rig.com_P_m
    I_O = R @ rig.inertia_P_kgm2 @ R.T
    M = np.zeros((6, 6))
    M[:3, :3] = rig.mass_kg * np.eye(3)
    M[:3, 3:] = -rig.mass_kg * skew(rc)
    M[3:, :3] = rig.mass_kg * skew(rc)
    M[3:, 3:] = I_O
    return M


def modes(rig: LabRig, pose: np.ndarray, tensions_N: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Natural frequencies (6,) in Hz, ascending, and mode shapes (6, 6) (columns, M-normalised):
    ``K phi = omega^2 M phi`` (scipy.linalg.eigh)."""
    K, _ = stiffness(rig, pose, tensions_N)
    w2, phi = scipy.linalg.eigh(K, mass_matrix(rig, pose))
    return np.sqrt(np.clip(w2, 0.0, None)) / (2 * np.pi), phi


# --------------------------------------------------------------------------------------------
# Newton-Euler


def body_wrench(rig: LabRig, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """The net wrench (..., 6) at P in {O} that the motion ``q, qd, qdd`` (..., 6) of the rigid
    body needs (= the rate of change of its momentum, moments about P):

        F = m (a_P + omega_dot x rc + omega x (omega x rc))
        M_P = I_O omega_dot + omega x (I_O omega) + m rc x a_P

    with ``rc = R c``, ``I_O = R I_P R^T`` (about P), ``omega = H psi_dot``,
    ``omega_dot = H psi_ddot + H_dot psi_dot``.  The cables then supply
    ``body_wrench - G - W_aero``."""
    q, qd, qdd = (np.asarray(a, dtype=np.float64) for a in (q, qd, qdd))
    psi, psid, psidd = q[..., 3:], qd[..., 3:], qdd[..., 3:]
    R = rot(psi)
    H = rate_matrix(psi)
    w = np.einsum("...ij,...j->...i", H, psid)
    wd = np.einsum("...ij,...j->...i", H, psidd) + np.einsum(
        "...ij,...j->...i", rate_matrix_dot(psi, psid), psid
    )
    rc = np.einsum("...ij,j->...i", R, rig.com_P_m)
    I_O = R @ rig.inertia_P_kgm2 @ np.swapaxes(R, -1, -2)
    a = qdd[..., :3]
    m = rig.mass_kg
    F = m * (a + np.cross(wd, rc) + np.cross(w, np.cross(w, rc)))
    Iw = np.einsum("...ij,...j->...i", I_O, w)
    M = np.einsum("...ij,...j->...i", I_O, wd) + np.cross(w, Iw) + m * np.cross(rc, a)
    return np.concatenate([F, M], axis=-1)


def momenta(rig: LabRig, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear momentum (..., 3) and angular momentum about the origin of {O} (..., 3) of the body
    (used by the self-test of :func:`body_wrench`): ``L = m v_c``,
    ``H_O = x_c x L + I_c omega`` with the inertia about the centre of mass
    ``I_c = I_P - m (|c|^2 1 - c c^T)`` (parallel axes), in {O} axes."""
    q, qd = np.asarray(q, float), np.asarray(qd, float)
    R = rot(q[..., 3:])
    w = np.einsum("...ij,...j->...i", rate_matrix(q[..., 3:]), qd[..., 3:])
    c = rig.com_P_m
    rc = np.einsum("...ij,j->...i", R, c)
    L = rig.mass_kg * (qd[..., :3] + np.cross(w, rc))
    Ic_P = rig.inertia_P_kgm2 - rig.mass_kg * (float(c @ c) * np.eye(3) - np.outer(c, c))
    Ic = R @ Ic_P @ np.swapaxes(R, -1, -2)
    Hc = np.einsum("...ij,...j->...i", Ic, w)
    return L, np.cross(q[..., :3] + rc, L) + Hc


# --------------------------------------------------------------------------------------------
# the commanded motion of an oscillation point (helpers/dynamic_spec.md)


@dataclass(frozen=True)
class Motion:
    """``q(t) = q_mean + e A env(t) sin(2 pi f (t - t0))``: axis one of :data:`AXES`, amplitude in
    rad (angles) or m, ``env`` a raised cosine 0 -> 1 over ``settling_cycles``, 1 over the
    analysed ``cycles``, then 1 -> 0 over ``rampdown_cycles``.  Times in s of the run clock."""

    axis: str
    amplitude: float
    frequency_Hz: float
    cycles: int
    settling_cycles: int
    q_mean: tuple[float, ...]
    t0_s: float
    rampdown_cycles: int = 1

    @property
    def omega(self) -> float:
        return 2 * np.pi * self.frequency_Hz

    @property
    def window_s(self) -> tuple[float, float]:
        f = self.frequency_Hz
        return (
            self.t0_s + self.settling_cycles / f,
            self.t0_s + (self.settling_cycles + self.cycles) / f,
        )

    @property
    def stop_s(self) -> float:
        return self.window_s[1] + self.rampdown_cycles / self.frequency_Hz

    def envelope(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """env, d env/dt, d2 env/dt2 at times t (s)."""
        t = np.asarray(t, dtype=np.float64)
        f = self.frequency_Hz
        a, b = self.window_s
        e, ed, edd = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
        up = (t >= self.t0_s) & (t < a)
        if self.settling_cycles > 0:
            k = np.pi * f / self.settling_cycles
            x = k * (t[up] - self.t0_s)
            e[up], ed[up], edd[up] = (
                0.5 * (1 - np.cos(x)),
                0.5 * k * np.sin(x),
                0.5 * k * k * np.cos(x),
            )
        full = (t >= a) & (t <= b)
        e[full] = 1.0
        down = (t > b) & (t < self.stop_s)
        k = np.pi * f / self.rampdown_cycles
        x = k * (t[down] - b)
        e[down], ed[down], edd[down] = (
            0.5 * (1 + np.cos(x)),
            -0.5 * k * np.sin(x),
            -0.5 * k * k * np.cos(x),
        )
        return e, ed, edd

    def states(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, q_dot, q_ddot (n, 6) at times t (n,) in s (analytic)."""
        t = np.asarray(t, dtype=np.float64)
        e, ed, edd = self.envelope(t)
        w = self.omega
        s, c = np.sin(w * (t - self.t0_s)), np.cos(w * (t - self.t0_s))
        A = self.amplitude
        x = A * e * s
        xd = A * (ed * s + e * w * c)
        xdd = A * (edd * s + 2 * ed * w * c - e * w * w * s)
        k = AXES.index(self.axis)
        q = np.tile(np.asarray(self.q_mean, float), (len(t), 1))
        qd = np.zeros_like(q)
        qdd = np.zeros_like(q)
        q[:, k] += x
        qd[:, k] = xd
        qdd[:, k] = xdd
        return q, qd, qdd
