"""Every tension method broadcasts one wrench (and one set of limits) over a batch of poses."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rigs import cubic_rig
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.tension import distribute


@pytest.mark.parametrize("method", ["closed-form", "improved-closed-form", "penalty", "exact"])
def test_one_wrench_for_many_poses_equals_pose_by_pose(method: str) -> None:
    rig = cubic_rig(0.3, 0.2, 0.1)
    rng = np.random.default_rng(5)
    p = rig.reference_position_O_m + rng.normal(scale=0.02, size=(5, 3))
    R = rotation_from_euler(rng.normal(scale=0.03, size=(5, 3)))
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, p, R)
    w = -gravity_wrench(rig.mass_kg, rig.com_P_m, np.eye(3), rig.gravity_O_mps2) + [
        3,
        0,
        0,
        0,
        0,
        0,
    ]
    batch = distribute(method, A, w, rig.t_min_N, rig.t_max_N)
    assert batch.tensions_N.shape == (5, 8)
    # the penalty method iterates to a chunk-wide tolerance (docs/tension.md: within 1e-3 N)
    tol = 1e-3 if method == "penalty" else 1e-6
    for i in range(5):
        one = distribute(method, A[i], w, rig.t_min_N, rig.t_max_N)
        np.testing.assert_allclose(batch.tensions_N[i], one.tensions_N, rtol=0, atol=tol)
        # independent check of equilibrium: the cable forces balance the requested wrench
        np.testing.assert_allclose(A[i] @ batch.tensions_N[i], w, atol=tol)
    # a 3 N load on a 5 kg platform is well inside this rig's limits: every pose is feasible and
    # the reported feasibility agrees with the tensions themselves
    assert batch.feasible.all()
    assert np.all(batch.tensions_N >= rig.t_min_N - tol)
    assert np.all(batch.tensions_N <= rig.t_max_N + tol)
