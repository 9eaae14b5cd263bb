"""The pose between a wind-on point and its tare (issue 21 item 4): the stiffness model's
deflection under the point's load fused with the camera's difference by their covariances, and
the camera trusted alone where the rig is not what the model says.  The deflections that serve
as truth come from the lab generator's own stiffness (tests/_lab_physics.py: central differences
of its own statics, not cdpr's), the loads and the camera noise from here."""

from __future__ import annotations

import numpy as np
import pytest
from _lab_physics import LabRig, gravity_wrench, rate_matrix, stiffness, structure_matrix
from lab_generator import RIGS, distribute

from cdpr.analysis.tare import tare_pose
from cdpr.pipelines.config import load_rig


def _world(rig_name: str, k: int, seed: int, softer: float = 1.0, cam_rad: float = 1e-5):
    """k wind-on points at the reference pose of a data_samples rig with random aerodynamic-size
    loads: (rig, the tare's poses (k, 6), wind-on poses, camera covariances, tare tensions,
    loads, true deflections in Euler angles)."""
    path = RIGS[rig_name]
    lab = LabRig.from_toml(path)
    rng = np.random.default_rng(seed)
    q0 = np.tile(lab.reference_pose, (k, 1))
    q0[:, 4] = rng.uniform(-0.1, 0.1, k)  # pitch of the sweep
    A = structure_matrix(lab, q0)
    T0, _ = distribute(A, -gravity_wrench(lab, q0), lab.t_min_N, lab.t_max_N)
    W = rng.normal(0, 1, (k, 6)) * np.array([0.3, 0.1, 2.0, 0.01, 0.03, 0.01])
    x = np.empty((k, 6))
    for i in range(k):
        K, _ = stiffness(lab, q0[i], T0[i])
        d = np.linalg.solve(K, W[i]) * softer
        x[i] = np.concatenate([d[:3], np.linalg.solve(rate_matrix(q0[i, 3:]), d[3:])])
    sd = np.array([cam_rad * 0.3] * 3 + [cam_rad] * 3)  # the mean pose's noise: m, rad
    C = np.broadcast_to(np.diag(sd**2), (k, 6, 6)).copy()
    qt = q0 + rng.normal(0, 1, (k, 6)) * sd
    qp = q0 + x + rng.normal(0, 1, (k, 6)) * sd
    return load_rig(path), qt, qp, C, T0, W, x


def test_the_model_and_the_camera_fused_beat_the_camera_alone() -> None:
    rig, qt, qp, C, T0, W, x = _world("cubic", 400, 1)
    tp = tare_pose(rig, qp, qt, C, C, T0, W, 0.2)
    assert tp.model_disagrees.mean() < 0.01  # the check's own 0.1 % of false alarms
    err_fused = tp.delta - x
    err_cam = tp.delta_measured - x
    # the fused difference's error is several times smaller than the camera's in pitch
    assert np.std(err_fused[:, 4]) < 0.35 * np.std(err_cam[:, 4])
    # and the model's own prediction is the truth's to well within its stated 20 %
    rel = np.abs(tp.delta_predicted[:, 4] - x[:, 4]) / np.abs(x[:, 4]).clip(1e-9)
    assert np.median(rel) < 0.05
    # the fusion's covariance (S_p - F S_p) covers its error
    cov = tp.cov_predicted - np.einsum("kij,kjl->kil", tp.gain_measured, tp.cov_predicted)
    ok = ~tp.model_disagrees  # (where the camera alone is used, its own covariance applies)
    z = err_fused[ok, 4] / np.sqrt(cov[ok, 4, 4])
    assert 0.9 <= np.mean(np.abs(z) <= 1.96) <= 1.0, np.mean(np.abs(z) <= 1.96)


@pytest.mark.parametrize("softer", [1.5, 3.0, 0.0], ids=["softer-1.5", "softer-3", "held"])
def test_a_rig_that_is_not_the_model_is_told_and_the_model_rescaled(softer: float) -> None:
    """A frame softer than the cables (what the model does not know), or a controller that holds
    the pose (no yield at all): over the run the camera's differences give the factor, the
    model's deflections are rescaled by it (flag), and the fused differences are the truth's."""
    rig, qt, qp, C, T0, W, x = _world("flat", 200, 2, softer=softer)
    tp = tare_pose(rig, qp, qt, C, C, T0, W, 0.2)
    assert tp.model_rescaled
    assert abs(tp.model_scale - softer) < 4 * tp.model_scale_sd + 0.02 * softer
    # the rescaled predictions are the truth's (the model's own deflection: x / softer)
    model = x[:, 4] / softer if softer else tp.delta_predicted[:, 4] / tp.model_scale
    miss = np.abs(tp.delta_predicted[:, 4] - x[:, 4])
    assert np.median(miss) < 0.1 * np.median(np.abs(model)), np.median(miss)
    # and the fused difference is no worse than the camera's
    rms = np.sqrt(np.mean((tp.delta - x)[:, 4] ** 2))
    assert rms <= 1.05 * np.sqrt(np.mean((tp.delta_measured - x)[:, 4] ** 2))
    # a rig that is the model is left alone
    rig, qt, qp, C, T0, W, x = _world("flat", 200, 2, softer=1.0)
    tp = tare_pose(rig, qp, qt, C, C, T0, W, 0.2)
    assert not tp.model_rescaled and abs(tp.model_scale - 1.0) < 4 * tp.model_scale_sd
