"""An independent truth for forced oscillations (issue 22), written apart from cdpr: the motion of
the issue's formula, the cables' geometry, rigid-body Newton-Euler from momentum differences, the
aero load of a model pitching about its moment reference point, and feasibility by scipy's
linprog and quadprog.  Nothing here imports cdpr; the rig is read from its TOML file as numbers.

Newton-Euler with every load on the platform at P in {O}: ``A T + G + W = dL/dt`` (force) and the
moment about P of the same; so the cables must supply ``A T = D - G - W``.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import quadprog
from scipy.optimize import linprog

G0 = 9.80665
RHO = 101325.0 / (287.05287 * 293.15)  # the aero model's dry air at its defaults


@dataclass(frozen=True)
class TRig:
    anchors: np.ndarray
    attach: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    mass: float
    com: np.ndarray
    inertia_P: np.ndarray
    home: np.ndarray
    EA: np.ndarray


def read_rig(path: Path) -> TRig:
    d = tomllib.loads(Path(path).read_text())
    cab = d["cables"]
    return TRig(
        np.array([c["anchor_O_m"] for c in cab], float),
        np.array([c["attach_P_m"] for c in cab], float),
        np.array([c["t_min_N"] for c in cab], float),
        np.array([c["t_max_N"] for c in cab], float),
        float(d["platform"]["mass_kg"]),
        np.array(d["platform"]["com_P_m"], float),
        np.array(d["platform"]["inertia_P_kgm2"], float),
        np.array(d["rig"]["reference_position_O_m"], float),
        np.array([c.get("EA_N", 7.0e4) for c in cab], float),
    )


def rot(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def motion(
    t: np.ndarray, mean: np.ndarray, j: int, amp: float, f: float, n_set: int, n_cyc: int
) -> np.ndarray:
    """The issue's formula: q = q_mean + e A env sin(2 pi f t), raised-cosine ramps (n, 6)."""
    t = np.asarray(t, float)
    env = np.where(t < n_set / f, 0.5 * (1 - np.cos(np.pi * t * f / n_set)), 1.0)
    t_end = (n_set + n_cyc) / f
    env = np.where(t >= t_end, 0.5 * (1 + np.cos(np.pi * (t - t_end) * f)), env)
    env = np.where((t < 0) | (t >= t_end + 1 / f), 0.0, env)
    q = np.tile(mean, (t.size, 1))
    q[:, j] += amp * env * np.sin(2 * np.pi * f * t)
    return q


def lengths(rig: TRig, q: np.ndarray) -> np.ndarray:
    R = rot(*q[3:])
    return np.linalg.norm(rig.anchors - q[:3] - rig.attach @ R.T, axis=1)


def structure(rig: TRig, q: np.ndarray) -> np.ndarray:
    R = rot(*q[3:])
    r = rig.attach @ R.T
    u = rig.anchors - q[:3] - r
    u = u / np.linalg.norm(u, axis=1)[:, None]
    return np.vstack([u.T, np.cross(r, u).T])


def gravity(rig: TRig, q: np.ndarray) -> np.ndarray:
    f = np.array([0.0, 0.0, -rig.mass * G0])
    return np.concatenate([f, np.cross(rot(*q[3:]) @ rig.com, f)])


def momentum_rate(rig: TRig, pose_of_t, t: float, h: float = 1e-4) -> np.ndarray:
    """``D`` (6,) at P in {O}: m times the centre of mass's acceleration, and the rate of the
    angular momentum about the centre of mass plus the moment of ``m a_c`` about P; every
    derivative by central differences of the pose function ``pose_of_t(t) -> (6,)``."""
    Ic = rig.inertia_P - rig.mass * (rig.com @ rig.com * np.eye(3) - np.outer(rig.com, rig.com))

    def com(s: float) -> np.ndarray:
        q = pose_of_t(s)
        return q[:3] + rot(*q[3:]) @ rig.com

    def omega(s: float) -> np.ndarray:
        Rd = (rot(*pose_of_t(s + h)[3:]) - rot(*pose_of_t(s - h)[3:])) / (2 * h)
        W = Rd @ rot(*pose_of_t(s)[3:]).T
        return np.array([W[2, 1], W[0, 2], W[1, 0]])

    def h_c(s: float) -> np.ndarray:
        R = rot(*pose_of_t(s)[3:])
        return R @ Ic @ R.T @ omega(s)

    F = rig.mass * (com(t + h) - 2 * com(t) + com(t - h)) / h**2
    M = (h_c(t + h) - h_c(t - h)) / (2 * h) + np.cross(com(t) - pose_of_t(t)[:3], F)
    return np.concatenate([F, M])


def pitch_aero(theta: float, theta_dot: float, V: float, c: dict) -> np.ndarray:
    """Aero load (6,) at P in {O} of a model pitching about P (its MRP), nose upstream: aoa =
    pitch, pitch rate q = aoa rate; lift up (+z_O), drag downstream (+x_O), nose-up moment +M_y.
    ``c``: CL_alpha, CD0, k_induced, Cm_alpha, CLq + CLadot (CLq_sum), Cmq + Cmadot (Cmq_sum),
    S, cref."""
    qS = 0.5 * RHO * V * V * c["S"]
    k = theta_dot * c["cref"] / (2 * V)
    CL = c["CL_alpha"] * theta + c["CLq_sum"] * k
    CD = c["CD0"] + c["k_induced"] * CL**2
    Cm = c["Cm_alpha"] * theta + c["Cmq_sum"] * k
    # wind axes: drag along +x_O, lift along +z_O (the free stream is along +x_O)
    return np.array([qS * CD, 0.0, qS * CL, 0.0, qS * c["cref"] * Cm, 0.0])


def feasible(A: np.ndarray, w: np.ndarray, tmin: np.ndarray, tmax: np.ndarray) -> bool:
    """Some T with A T = w inside the limits (linprog, HiGHS)."""
    m = A.shape[1]
    res = linprog(
        np.zeros(m), A_eq=A, b_eq=w, bounds=list(zip(tmin, tmax, strict=True)), method="highs"
    )
    return bool(res.status == 0)


def controller(A: np.ndarray, w: np.ndarray, tmin: np.ndarray, tmax: np.ndarray) -> np.ndarray:
    """min |T - T_mid| with A T = w and the limits (quadprog)."""
    m = A.shape[1]
    mid = 0.5 * (tmin + tmax)
    C = np.hstack([A.T, np.eye(m), -np.eye(m)])
    b = np.concatenate([w, tmin, -tmax])
    return np.asarray(quadprog.solve_qp(np.eye(m), mid, C, b, meq=6)[0])
