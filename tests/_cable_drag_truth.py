"""An own few-line model of the drag of a taut cable in the flow, written apart from
cdpr.analysis.windage: the cable is loaded point by point where it lies inside a regular octagonal
section, the string equation T y'' = -f is solved by finite differences and the platform end's
transverse force T y'(0) is read off.  Used as the truth for the windage model and the virtual rig."""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_banded

RHO, MU, D = 1.2, 1.81e-5, 1.0e-3


def _inside_octagon(x, y, z, apothem, yc, zc, x0, x1):
    dy, dz = np.abs(y - yc), np.abs(z - zc)
    return (x >= x0) & (x <= x1) & (dy <= apothem) & (dz <= apothem) & (dy + dz <= apothem * 2**0.5)


def string_end_force(start, anchor, T, V, apothem, yc, zc, x0, x1, n=4000, rho=RHO, mu=MU, d=D):
    """Own model: load the cable point by point, solve T y'' = -f (y = 0 at both ends) by finite
    differences and read the end force T y'(0) and the turn y'(0) at the platform end."""
    lvec = anchor - start
    length = np.linalg.norm(lvec)
    u = lvec / length
    vn = V * np.array([1.0, 0.0, 0.0]) - V * u[0] * u
    vn_mag = np.linalg.norm(vn)
    re = rho * vn_mag * d / mu
    cd = 1.0 + 10.0 * max(re, 1.0) ** (-2.0 / 3.0)
    s = np.linspace(0.0, length, n + 1)
    pts = start + s[:, None] * u
    f = 0.5 * rho * vn_mag**2 * d * cd * _inside_octagon(*pts.T, apothem, yc, zc, x0, x1)
    h = s[1] - s[0]
    ab = np.zeros((3, n - 1))
    ab[0, 1:], ab[1, :], ab[2, :-1] = 1.0, -2.0, 1.0
    y = np.zeros(n + 1)
    y[1:-1] = solve_banded((1, 1), ab, -f[1:-1] * h * h / T)
    slope0 = (-3 * y[0] + 4 * y[1] - y[2]) / (2 * h)
    e_n = vn / vn_mag
    return T * slope0 * e_n, slope0
