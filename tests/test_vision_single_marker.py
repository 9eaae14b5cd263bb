"""Single-marker ArUco pose (issue 14 §4): a pose from one marker's four corners, flagged
``single_marker``, with the larger covariance its four points give, and never the planar "flip"
(the other pose four coplanar points allow, 30-100 mm and tens of degrees away) reported confidently.

Truth: the poses the frames were rendered at (calibration/render.py), or, for the flip statistics,
corners projected with OpenCV at a known pose plus Gaussian noise drawn here."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from cdpr.analysis.rotations import rotation_from_euler
from cdpr.calibration import cv
from cdpr.calibration.camera_model import camera_from_mapping
from cdpr.calibration.markers import flat_prototype_fiducial_layout
from cdpr.calibration.pose import (
    BAD_FLAGS,
    FLAG_AMBIGUOUS,
    FLAG_SINGLE_MARKER,
    estimate_pose_single_marker,
    nees,
    pose_error,
)
from cdpr.calibration.render import VirtualCamera
from cdpr.daq.camera_source import FramePoseEstimator

ROOT = Path(__file__).resolve().parents[1]
P0 = np.array([0.5, 0.0, 0.36])


@pytest.fixture(scope="module")
def setup():
    cam = camera_from_mapping(json.loads((ROOT / "data_samples/camera_virtual.json").read_text()))
    return cam, flat_prototype_fiducial_layout(), VirtualCamera(cam)


def _pose(rng):
    return P0 + rng.uniform(-0.02, 0.02, 3), rotation_from_euler(np.deg2rad(rng.uniform(-6, 6, 3)))


def test_single_marker_pose_is_flagged_with_a_consistent_larger_sigma(setup) -> None:
    """At each pose the estimator first sees all six markers (it measures the corner noise there),
    then a frame with one marker only (track=False: acquired from scratch)."""
    cam, layout, vc = setup
    rng = np.random.default_rng(21)
    nee, ratio_sigma, err_mm, n_amb = [], [], [], 0
    for k in range(len(layout.fiducials)):
        one = dataclasses.replace(layout, fiducials=[layout.fiducials[k]])
        for _ in range(5):
            p, R = _pose(rng)
            est_ = FramePoseEstimator(cam, layout, reference=(P0, np.eye(3)), track=False)
            six = est_.estimate(vc.render_fiducials(layout, p, R, rng))
            assert not (six.flags & (BAD_FLAGS | FLAG_SINGLE_MARKER))
            est = est_.estimate(vc.render_fiducials(one, p, R, rng))
            assert est.flags & FLAG_SINGLE_MARKER and est.n_points == 4
            assert est.extra["sigma_prior_dof"] == 42.0  # 24 corners of the six-marker frame
            if est.flags & BAD_FLAGS:
                assert est.flags & BAD_FLAGS == FLAG_AMBIGUOUS, est.flags
                n_amb += 1
                continue
            assert est.extra["planar_margin"] > 25
            e = pose_error(est.position_O_m, est.R_O_P, p, R)
            assert np.linalg.norm(e[:3]) < 3e-3  # the flip would be 30-100 mm off
            err_mm.append(1e3 * np.linalg.norm(e[:3]))
            nee.append(nees(e, est.covariance))
            ratio_sigma.append(
                np.linalg.norm(est.std_position_m) / np.linalg.norm(six.std_position_m)
            )
    print(
        f"\nsingle marker, {len(nee)} frames ({n_amb} more flagged ambiguous): position error "
        f"max {max(err_mm):.2f} mm, NEES mean {np.mean(nee):.2f} (median {np.median(nee):.2f}), "
        f"position sigma {np.median(ratio_sigma):.1f}x the six-marker one (median)"
    )
    assert n_amb <= 2 and 3.0 <= np.mean(nee) <= 12.0
    assert np.median(ratio_sigma) > 2.0


def test_the_planar_flip_is_never_reported_confidently(setup) -> None:
    """Corners at a known pose plus Gaussian noise up to 0.6 px (real photographs: 0.35-0.45 px),
    the noise prior known as a tracked estimator measures it: every pose not flagged ambiguous is the
    true branch (the flip is 30-100 mm away), within 10 of its reported sigma."""
    cam, layout, _ = setup
    rng = np.random.default_rng(22)
    corners = layout.fiducial_corners_m
    n_amb = n_ok = 0
    for trial in range(400):
        p, R = _pose(rng)
        R_C_P, t_C_P = cam.R_O_C.T @ R, cam.R_O_C.T @ (p - cam.position_O_m)  # by hand
        k = trial % len(corners)
        px = cv.project_points(corners[k], cv.rotation_vector(R_C_P), t_C_P, cam.K, cam.dist)
        sigma = [0.02, 0.1, 0.3, 0.6][trial % 4]
        noisy = px + rng.normal(0, sigma, px.shape)
        # the noise prior as a tracked estimator learns it from multi-marker frames (60 dof)
        est = estimate_pose_single_marker(corners[k], noisy, cam, sigma, prior_dof=60.0)
        assert est.flags & FLAG_SINGLE_MARKER
        if est.flags & FLAG_AMBIGUOUS:
            n_amb += 1
            continue
        e = pose_error(est.position_O_m, est.R_O_P, p, R)
        assert np.linalg.norm(e[:3]) < 10 * np.linalg.norm(est.std_position_m) + 1e-3, (trial, e)
        n_ok += 1
    print(f"\nflip test: {n_ok} confident and right, {n_amb} flagged ambiguous, 0 confident flips")
    assert n_ok > 100


def test_the_flip_with_only_the_nominal_noise_is_rare(setup) -> None:
    """Without a measured noise (``prior_dof`` None, nominal 0.02 px) but corners 15-30x noisier,
    the margin uses the 95 % upper bound of the noise from the four corners: 0 confident flips in
    these 1200 frames (0-3 per 1200 on other seeds; 14 % of frames at 0.6 px with the nominal value
    alone); at the nominal noise most frames still give a confident right pose."""
    cam, layout, _ = setup
    rng = np.random.default_rng(24)
    corners = layout.fiducial_corners_m
    flips = {0.02: 0, 0.3: 0, 0.6: 0}
    right = dict.fromkeys(flips, 0)
    for trial in range(1800):
        p, R = _pose(rng)
        R_C_P, t_C_P = cam.R_O_C.T @ R, cam.R_O_C.T @ (p - cam.position_O_m)
        k, sigma = trial % len(corners), [0.02, 0.3, 0.6][trial % 3]
        px = cv.project_points(corners[k], cv.rotation_vector(R_C_P), t_C_P, cam.K, cam.dist)
        est = estimate_pose_single_marker(
            corners[k], px + rng.normal(0, sigma, px.shape), cam, 0.02
        )
        if not (est.flags & FLAG_AMBIGUOUS):
            e = pose_error(est.position_O_m, est.R_O_P, p, R)
            if np.linalg.norm(e[:3]) > 10e-3:
                flips[sigma] += 1
            else:
                right[sigma] += 1
    print(f"\nnominal noise only: confident flips {flips}, confident right {right} (600 each)")
    assert flips[0.02] == 0 and flips[0.3] + flips[0.6] <= 5 and right[0.02] >= 450


def test_tracked_single_marker_frames_use_the_measured_corner_noise(setup) -> None:
    """Six-marker frames then one-marker frames on a slow path: the single-marker noise prior is the
    corner noise measured on the earlier frames (from the data, not the nominal 0.02 px)."""
    cam, layout, vc = setup
    rng = np.random.default_rng(23)
    one = dataclasses.replace(layout, fiducials=[layout.fiducials[1]])
    est_ = FramePoseEstimator(cam, layout, reference=(P0, np.eye(3)))
    nee = []
    for i in range(24):
        p = P0 + np.array([0.3e-3 * i, -0.2e-3 * i, 0.1e-3 * i])
        R = rotation_from_euler(np.deg2rad([0.05 * i, -0.04 * i, 0.03 * i]))
        est = est_.estimate(vc.render_fiducials(layout if i < 12 else one, p, R, rng))
        assert not (est.flags & BAD_FLAGS), (i, est.flags)
        if i >= 12:
            assert est.flags & FLAG_SINGLE_MARKER
            assert est.extra["sigma_prior_dof"] == 60.0
            assert est.extra["sigma_prior_px"] != 0.02
            nee.append(nees(pose_error(est.position_O_m, est.R_O_P, p, R), est.covariance))
    print(f"\ntracked single marker: NEES mean {np.mean(nee):.2f}")
    assert np.mean(nee) <= 12.0
