"""The fast structure-matrix path equals the cable geometry and a plain per-pose construction."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis.errors import InputError
from cdpr.analysis.kinematics import cable_geometry, structure_matrix, structure_matrix_at
from cdpr.analysis.rigs import paper_rigs
from cdpr.analysis.rotations import rotation_from_euler


def _per_pose(anchors: np.ndarray, attach: np.ndarray, p: np.ndarray, R: np.ndarray) -> np.ndarray:
    A = np.empty((6, len(anchors)))
    for i in range(len(anchors)):
        r = R @ attach[i]
        lv = anchors[i] - p - r
        u = lv / np.sqrt(lv @ lv)
        A[:3, i] = u
        A[3:, i] = [r[1] * u[2] - r[2] * u[1], r[2] * u[0] - r[0] * u[2], r[0] * u[1] - r[1] * u[0]]
    return A


def test_structure_matrix_matches_geometry_and_per_pose_loop():
    rig = paper_rigs()["flat_optimum"]
    rng = np.random.default_rng(5)
    pose = np.empty((2, 3, 6))
    pose[..., :3] = rig.reference_position_O_m + rng.uniform(-0.05, 0.05, (2, 3, 3))
    pose[..., 3:] = rng.uniform(-0.3, 0.3, (2, 3, 3))
    R = rotation_from_euler(pose[..., 3:])
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, pose[..., :3], R)
    assert A.shape == (2, 3, 6, 8) and A.flags.c_contiguous
    geo = cable_geometry(rig.anchors_O_m, rig.attach_P_m, pose[..., :3], R).A
    np.testing.assert_allclose(A, geo, rtol=0, atol=1e-14)
    for j in range(2):
        for k in range(3):
            ref = _per_pose(rig.anchors_O_m, rig.attach_P_m, pose[j, k, :3], R[j, k])
            np.testing.assert_allclose(A[j, k], ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(
        structure_matrix_at(rig.anchors_O_m, rig.attach_P_m, pose), A, rtol=0, atol=0
    )


def test_structure_matrix_per_case_geometry_broadcasts():
    rng = np.random.default_rng(6)
    anchors = rng.uniform(-1, 1, (4, 8, 3))
    attach = rng.uniform(-0.1, 0.1, (4, 8, 3))
    A = structure_matrix(anchors, attach, np.zeros(3), np.eye(3))
    assert A.shape == (4, 6, 8)
    for k in range(4):
        ref = _per_pose(anchors[k], attach[k], np.zeros(3), np.eye(3))
        np.testing.assert_allclose(A[k], ref, rtol=0, atol=1e-14)


def test_structure_matrix_zero_length_cable_is_input_error():
    anchors = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    attach = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    with pytest.raises(InputError, match="zero length"):
        structure_matrix(anchors, attach, np.zeros(3), np.eye(3))
