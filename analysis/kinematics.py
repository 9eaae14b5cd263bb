"""Cable kinematics and the structure matrix, batched over poses.

For cable i: ``l_i = b_i - p - R pp_i`` (platform point to anchor, {O}), ``u_i = l_i / |l_i|``,
``r_i = R pp_i`` and the structure-matrix column ``a_i = [u_i; r_i x u_i]``.  ``A`` is (..., 6, m) and
maps cable tensions (N) to the wrench the cables apply on the platform at P, in {O} axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .errors import InputError
from .rotations import rotation_from_euler

FloatArray = NDArray[np.float64]


def _checked(
    anchors_O_m: ArrayLike, attach_P_m: ArrayLike, position_O_m: ArrayLike, R_O_P: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The geometry inputs as float arrays, their shapes checked (names expected vs actual)."""
    b = check_trailing(anchors_O_m, "anchors_O_m", (3,))
    pp = check_trailing(attach_P_m, "attach_P_m", (3,))
    p = check_trailing(position_O_m, "position_O_m", (3,))
    R = check_trailing(R_O_P, "R_O_P", (3, 3))
    if b.ndim < 2 or pp.ndim < 2 or b.shape[-2] != pp.shape[-2]:
        raise InputError(
            f"anchors_O_m and attach_P_m: expected (m, 3) with the same m, got {b.shape} and {pp.shape}"
        )
    return b, pp, p, R


def _lever_arms_and_vectors(
    anchors_O_m: ArrayLike, attach_P_m: ArrayLike, position_O_m: ArrayLike, R_O_P: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Checked inputs -> lever arms ``r_i = R pp_i`` and cable vectors ``l_i``, each (..., m, 3)."""
    b, pp, p, R = _checked(anchors_O_m, attach_P_m, position_O_m, R_O_P)
    r = np.matmul(pp, np.swapaxes(R, -1, -2))  # (..., m, 3): r_i = R pp_i
    return r, b - p[..., None, :] - r


def cable_vectors(
    anchors_O_m: ArrayLike, attach_P_m: ArrayLike, position_O_m: ArrayLike, R_O_P: ArrayLike
) -> FloatArray:
    """Cable vectors ``l_i`` (..., m, 3) in {O}, m, from the platform points to the anchors.

    anchors_O_m: (m, 3) or (..., m, 3); attach_P_m: (m, 3) or (..., m, 3); position_O_m: (..., 3);
    R_O_P: (..., 3, 3).
    """
    return _lever_arms_and_vectors(anchors_O_m, attach_P_m, position_O_m, R_O_P)[1]


@dataclass(frozen=True)
class CableGeometry:
    """Everything the cable geometry gives at a batch of poses (all in {O}).

    l_O_m: (..., m, 3) cable vectors; length_m: (..., m); u_O: (..., m, 3) unit vectors from the
    platform to the anchors; r_O_m: (..., m, 3) lever arms ``R pp_i``; A: (..., 6, m) structure matrix.
    """

    l_O_m: FloatArray
    length_m: FloatArray
    u_O: FloatArray
    r_O_m: FloatArray
    A: FloatArray


def cable_geometry(
    anchors_O_m: ArrayLike, attach_P_m: ArrayLike, position_O_m: ArrayLike, R_O_P: ArrayLike
) -> CableGeometry:
    """Cable vectors, lengths, unit vectors, lever arms and structure matrix at a batch of poses.

    Raises :class:`InputError` if a cable has zero length at some pose.
    """
    r, lv = _lever_arms_and_vectors(anchors_O_m, attach_P_m, position_O_m, R_O_P)
    length = np.sqrt(np.einsum("...i,...i->...", lv, lv))
    if np.any(length < 1e-12):
        raise InputError("cable_geometry: a cable has zero length (anchor on the attachment point)")
    u = lv / length[..., None]
    A = np.concatenate([u, np.cross(r, u)], axis=-1)
    return CableGeometry(l_O_m=lv, length_m=length, u_O=u, r_O_m=r, A=np.swapaxes(A, -1, -2))


def structure_matrix(
    anchors_O_m: ArrayLike, attach_P_m: ArrayLike, position_O_m: ArrayLike, R_O_P: ArrayLike
) -> FloatArray:
    """Structure matrix ``A`` (..., 6, m): columns ``[u_i; r_i x u_i]`` at a batch of poses.

    Same numbers as ``cable_geometry(...).A`` (to rounding), computed component-wise on (..., m)
    arrays and written straight into a contiguous (..., 6, m) array (the hot path of batch
    tension distribution).  Raises :class:`InputError` if a cable has zero length at some pose.
    """
    b, pp, p, R = _checked(anchors_O_m, attach_P_m, position_O_m, R_O_P)
    # r_k = (R pp)_k and l_k = b_k - p_k - r_k, each (..., m)
    r = [
        R[..., k, 0, None] * pp[..., 0]
        + R[..., k, 1, None] * pp[..., 1]
        + R[..., k, 2, None] * pp[..., 2]
        for k in range(3)
    ]
    lv = [b[..., k] - p[..., k, None] - r[k] for k in range(3)]
    length = np.sqrt(lv[0] * lv[0] + lv[1] * lv[1] + lv[2] * lv[2])
    if np.any(length < 1e-12):
        raise InputError(
            "structure_matrix: a cable has zero length (anchor on the attachment point)"
        )
    m = pp.shape[-2]
    lead = np.broadcast_shapes(length.shape[:-1], r[0].shape[:-1], b.shape[:-2])
    A = np.empty(lead + (6, m))
    u = [np.divide(lv[k], length, out=A[..., k, :]) for k in range(3)]
    np.subtract(r[1] * u[2], r[2] * u[1], out=A[..., 3, :])
    np.subtract(r[2] * u[0], r[0] * u[2], out=A[..., 4, :])
    np.subtract(r[0] * u[1], r[1] * u[0], out=A[..., 5, :])
    return A


def structure_matrix_at(
    rig_anchors_O_m: ArrayLike, rig_attach_P_m: ArrayLike, pose: ArrayLike
) -> FloatArray:
    """Structure matrix (..., 6, m) from poses (..., 6) = ``[x, y, z, roll, pitch, yaw]`` (m, rad)."""
    q = check_trailing(pose, "pose", (6,))
    return structure_matrix(
        rig_anchors_O_m, rig_attach_P_m, q[..., :3], rotation_from_euler(q[..., 3:])
    )
