"""Builders for the paper's two reference rigs, with every assumption the paper leaves open stated.

Both are 8-cable, 6-DOF, fully constrained rigs.  Frame {O}: x downstream, y left, z up (see
:mod:`cdpr.analysis.conventions`).

Cubic rig (paper Fig. 3)
    Frame L (x) x W (y) x H (z) with its floor at z = 0, centred on x = y = 0; the platform is a box
    (k1 L, k2 W, k3 H) centred on P = (0, 0, Z), Z = 0.5 H by default.  Assumption (the paper gives no
    coordinates): the default ``layout="crossed"`` joins each upper platform corner to the frame
    corner of its own octant and each lower platform corner to the lower frame corner on the opposite
    y side.  The plain ``layout="cube"`` (every corner to its own octant's frame corner) is singular
    whenever two ratios are equal with P at mid-height: k2 = k3 removes Mx, k1 = k3 removes My and
    k1 = k2 removes Mz, because the cable lines' projections then pass through P; it would be singular
    at the paper's own optimum (k2 = k3 = 0.075), so it cannot be the paper's layout.  The crossed
    layout is singular when k1 = k3 (My).
Flat rig (paper Fig. 4, Table 3)
    Base length L along x, the front (upstream) frame plane at x = 0, the back one at x = L, floor at
    z = 0 and top at z = H.  The platform is an isosceles trapezoid in its own x-y plane: front points
    at x_P = -l/2, y_P = +-w1/2, back points at x_P = +l/2, y_P = +-w2/2.  Each platform point carries
    two cables, to the top and the bottom anchor on its own side (+-y) of its own frame plane; front
    anchors at y = +-K21 w1 / 2, back anchors at y = +-K22 w2 / 2 (the paper: front base width
    K21 w1 = 0.51 m and back base width K22 w2 = 1.12 m at the optimum).  P = (X, 0, 0.5 H).
Mass properties
    The paper gives the masses only.  The centre of mass is at P and the inertia is that of a uniform
    solid box (cubic rig) or of the SDM model approximated as a uniform rod along x of 0.3776 m (flat
    rig); both are config values of the rig file.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .rig import Rig

FloatArray = NDArray[np.float64]

CUBIC_DEFAULTS = {
    "L_m": 2.0,
    "W_m": 1.2,
    "H_m": 1.4,
    "mass_kg": 5.0,
    "t_min_N": 35.0,
    "t_max_N": 1000.0,
}
"""The paper's cubic-rig values (Fig. 3, section 'Numerical simulation ... cubic')."""

FLAT_DEFAULTS = {
    "L_m": 1.0,
    "l_m": 0.03,
    "w1_m": 0.01,
    "w2_m": 0.04,
    "mass_kg": 0.64,
    "t_min_N": 35.0,
    "t_max_N": 300.0,
    "model_length_m": 0.3776,
}
"""The paper's flat-rig values (Fig. 4, Table 3) plus the SDM model length used for its inertia."""


def box_inertia(mass_kg: ArrayLike, l_m: ArrayLike, w_m: ArrayLike, h_m: ArrayLike) -> FloatArray:
    """Inertia (..., 3, 3) about its centre of a uniform solid box l (x) by w (y) by h (z), kg m^2."""
    m, l, w, h = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (mass_kg, l_m, w_m, h_m))
    )
    out = np.zeros(m.shape + (3, 3))
    out[..., 0, 0] = m / 12.0 * (w**2 + h**2)
    out[..., 1, 1] = m / 12.0 * (l**2 + h**2)
    out[..., 2, 2] = m / 12.0 * (l**2 + w**2)
    return out


def rod_inertia(mass_kg: float, length_m: float) -> FloatArray:
    """Inertia (3, 3) of the flat rig's platform + model: a uniform rod of ``length_m`` along x
    (``Iyy = Izz = m L^2 / 12``), ``Ixx`` 5 % of that, about its centre, kg m^2."""
    Iyy = mass_kg * length_m**2 / 12.0
    return np.diag([Iyy * 0.05, Iyy, Iyy])


def cubic_rig(
    k1: float,
    k2: float,
    k3: float,
    *,
    L_m: float = 2.0,
    W_m: float = 1.2,
    H_m: float = 1.4,
    Z_m: float | None = None,
    mass_kg: float = 5.0,
    t_min_N: float = 35.0,
    t_max_N: float = 1000.0,
    layout: str = "crossed",
    name: str | None = None,
) -> Rig:
    """The paper's cubic rig (Fig. 3) for platform ratios k1 = l/L, k2 = w/W, k3 = h/H.

    ``Z_m`` is the height of P (default H/2); ``layout`` is ``"cube"`` or ``"crossed"`` (module doc).
    """
    for key, k in (("k1", k1), ("k2", k2), ("k3", k3)):
        if not 0 < k < 1:
            raise InputError(f"{key}: expected 0 < {key} < 1, got {k}")
    if layout not in ("cube", "crossed"):
        raise InputError(f"layout: expected 'cube' or 'crossed', got {layout!r}")
    Z = 0.5 * H_m if Z_m is None else float(Z_m)
    if not 0 < Z < H_m:
        raise InputError(f"Z_m: expected 0 < Z_m < H_m = {H_m}, got {Z}")
    l, w, h = k1 * L_m, k2 * W_m, k3 * H_m
    signs = [(sx, sy, sz) for sz in (1, -1) for sx in (1, -1) for sy in (1, -1)]
    anchors, attach, names = [], [], []
    for sx, sy, sz in signs:
        ay = -sy if (layout == "crossed" and sz < 0) else sy
        anchors.append([sx * L_m / 2, ay * W_m / 2, H_m if sz > 0 else 0.0])
        attach.append([sx * l / 2, sy * w / 2, sz * h / 2])
        names.append(
            ("top" if sz > 0 else "bottom")
            + ("_back" if sx > 0 else "_front")
            + ("_left" if sy > 0 else "_right")
        )
    inertia = box_inertia(mass_kg, l, w, h)
    return Rig(
        name=name or f"cubic-k{k1:g}-{k2:g}-{k3:g}",
        description="Cubic-platform rig of the paper's Fig. 3",
        cable_names=tuple(names),
        anchors_O_m=np.array(anchors),
        attach_P_m=np.array(attach),
        mass_kg=mass_kg,
        com_P_m=np.zeros(3),
        inertia_P_kgm2=inertia,
        t_min_N=np.full(8, t_min_N),
        t_max_N=np.full(8, t_max_N),
        reference_position_O_m=np.array([0.0, 0.0, Z]),
        assumptions={
            "source": "paper Fig. 3: L, W, H, mass and limits; layout and inertia assumed",
            "parameters": f"k1={k1}, k2={k2}, k3={k3}, L={L_m} m, W={W_m} m, H={H_m} m, Z={Z} m",
            "layout": (
                "each platform corner to the frame corner of its own octant (no crossed cables)"
                if layout == "cube"
                else "as 'cube' but the bottom cables go to the opposite y side (crossed)"
            ),
            "inertia": "uniform solid box of the platform's size, centre of mass at P",
        },
    )


def flat_rig(
    K21: float,
    K22: float,
    H_m: float,
    X_m: float = 0.5,
    *,
    L_m: float = 1.0,
    l_m: float = 0.03,
    w1_m: float = 0.01,
    w2_m: float = 0.04,
    mass_kg: float = 0.64,
    t_min_N: float = 35.0,
    t_max_N: float = 300.0,
    model_length_m: float = 0.3776,
    name: str | None = None,
) -> Rig:
    """The paper's flat rig (Fig. 4, Table 3): front base width K21 w1, back base width K22 w2.

    P = (X, 0, H/2); see the module doc for the layout assumed.
    """
    if not 0 < X_m < L_m:
        raise InputError(f"X_m: expected 0 < X_m < L_m = {L_m}, got {X_m}")
    if H_m <= 0:
        raise InputError(f"H_m: expected > 0, got {H_m}")
    if K21 * w1_m <= w1_m or K22 * w2_m <= w2_m:
        raise InputError(f"K21, K22: expected > 1 (base wider than platform), got {K21}, {K22}")
    Wf, Wb = K21 * w1_m, K22 * w2_m
    anchors, attach, names = [], [], []
    for side, x_anchor, x_p, half_base, half_plat in (
        ("front", 0.0, -l_m / 2, Wf / 2, w1_m / 2),
        ("back", L_m, l_m / 2, Wb / 2, w2_m / 2),
    ):
        for sy, lr in ((1, "left"), (-1, "right")):
            for z, tb in ((H_m, "top"), (0.0, "bottom")):
                anchors.append([x_anchor, sy * half_base, z])
                attach.append([x_p, sy * half_plat, 0.0])
                names.append(f"{side}_{lr}_{tb}")
    return Rig(
        name=name or f"flat-K21_{K21:g}-K22_{K22:g}-H{H_m:g}-X{X_m:g}",
        description="Flat-platform rig of the paper's Fig. 4 / Table 3",
        cable_names=tuple(names),
        anchors_O_m=np.array(anchors),
        attach_P_m=np.array(attach),
        mass_kg=mass_kg,
        com_P_m=np.zeros(3),
        inertia_P_kgm2=rod_inertia(mass_kg, model_length_m),
        t_min_N=np.full(8, t_min_N),
        t_max_N=np.full(8, t_max_N),
        reference_position_O_m=np.array([X_m, 0.0, 0.5 * H_m]),
        assumptions={
            "source": "paper Fig. 4 and Table 3: L, l, w1, w2, K21, K22, H, X, mass and limits",
            "parameters": (
                f"K21={K21}, K22={K22}, H={H_m} m, X={X_m} m, L={L_m} m, l={l_m} m, "
                f"w1={w1_m} m, w2={w2_m} m"
            ),
            "layout": (
                "front frame plane x=0, back x=L; each platform point to the top and bottom anchor "
                "on its own side of its own frame plane"
            ),
            "inertia": (
                f"SDM model as a uniform rod of {model_length_m} m along x (Iyy = Izz = m L^2/12), "
                "Ixx = 5 % of that; centre of mass at P"
            ),
        },
    )


def paper_rigs() -> dict[str, Rig]:
    """The reference configurations shipped in ``data_samples/``, by file stem."""
    return {
        "cubic_optimum": cubic_rig(0.15, 0.075, 0.075, name="cubic-optimum"),
        "flat_optimum": flat_rig(51, 28, 0.67, 0.5, name="flat-optimum"),
        "flat_experiment2": flat_rig(61, 34, 0.72, 0.5, t_max_N=285.0, name="flat-experiment2"),
    }
