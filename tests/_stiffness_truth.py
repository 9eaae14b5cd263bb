"""An own stiffness and mass matrix of a cable platform, written apart from
cdpr.analysis.stiffness: the restoring wrench of linear cable springs about the equilibrium
lengths plus gravity, differentiated by central differences over [dp; rotation vector]."""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

G = np.array([0.0, 0.0, -9.80665])


def sk(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def cable_wrench(anchors, attach, p0, x, T0, l0, EA, mass, com):
    """Wrench of cables and gravity at P in {O} at the displaced pose x (6,)."""
    R = expm(sk(x[3:]))
    r = attach @ R.T
    lv = anchors - (p0 + x[:3]) - r
    L = np.linalg.norm(lv, axis=1)
    u = lv / L[:, None]
    A = np.vstack([u.T, np.cross(r, u).T])
    Wg = np.concatenate([mass * G, np.cross(R @ com, mass * G)])
    T = T0 + EA / l0 * (L - l0)  # linear springs about the equilibrium lengths
    return A @ T + Wg


def fd_stiffness(anchors, attach, p0, T0, EA, mass, com, h=1e-7):
    """K (6, 6) = -dW/dx by central differences."""
    l0 = np.linalg.norm(anchors - p0 - attach, axis=1)
    K = np.zeros((6, 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = h
        K[:, j] = -(
            cable_wrench(anchors, attach, p0, e, T0, l0, EA, mass, com)
            - cable_wrench(anchors, attach, p0, -e, T0, l0, EA, mass, com)
        ) / (2 * h)
    return K


def rigid_mass(mass, com, inertia_P):
    M = np.zeros((6, 6))
    M[:3, :3] = mass * np.eye(3)
    M[:3, 3:] = -mass * sk(com)
    M[3:, :3] = mass * sk(com)
    M[3:, 3:] = inertia_P
    return M
