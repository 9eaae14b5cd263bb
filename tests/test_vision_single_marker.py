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
from opencv_reference import ippe_square_poses
from vision_grid_renderer import render_square_markers

from cdpr.analysis.rotations import rotation_from_euler
from cdpr.calibration import cv
from cdpr.calibration.camera_model import camera_from_mapping
from cdpr.calibration.markers import Fiducial, MarkerLayout, flat_prototype_fiducial_layout
from cdpr.calibration.pose import (
    BAD_FLAGS,
    FLAG_AMBIGUOUS,
    FLAG_SINGLE_MARKER,
    estimate_pose_single_marker,
    nees,
    pose_error,
)
from cdpr.calibration.render import RenderSettings, VirtualCamera
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


# ---- issue 19 §6: single markers at the scale and tilt of OpenCV's tutorial photo ----------------
# OpenCV's ArUco tutorial photo (singlemarkersoriginal.jpg, 640x480) shows six DICT_6X6_250 markers
# of 23-45 px at 0.68-0.88 m, tilted 33-51 deg from the line of sight, taken with the camera of
# opencv_contrib's modules/aruco/samples/tutorial_camera_params.yml (Apache-2.0), whose K and
# distortion are these; the tutorial's marker length is 0.05 m.
TUTORIAL_K = np.array([[628.158, 0.0, 324.099], [0.0, 628.156, 260.908], [0.0, 0.0, 1.0]])
TUTORIAL_DIST = np.array([0.0995485, -0.206384, 0.00754589, 0.00336531, 0.0])
TUTORIAL_IDS = (23, 40, 62, 98, 124, 203)
LENGTH_M = 0.05


def _tutorial_camera(distorted: bool):
    return camera_from_mapping(
        {
            "image_size_px": [640, 480],
            "camera_matrix": TUTORIAL_K.tolist(),
            "dist_coeffs": (TUTORIAL_DIST if distorted else np.zeros(5)).tolist(),
        }
    )


def _one_marker(marker_id: int):
    return MarkerLayout(
        kind="fiducial",
        dictionary="DICT_6X6_250",
        quiet_zone_cells=1.0,
        fiducials=[Fiducial(marker_id, np.zeros(3), np.eye(3), LENGTH_M)],
    )


def _tutorial_view(rng, cam):
    """A marker pose like the photo's (in the camera frame: {O} = {C}): centre at a random
    image point 0.68-0.88 m away, its normal tilted 33-51 deg from the line of sight about a
    random axis, a random turn in its plane."""
    z = rng.uniform(0.68, 0.88)
    uv = np.array([rng.uniform(130, 510), rng.uniform(110, 370)])
    xn = cv.undistort_to_normalized(uv[None], cam.K, cam.dist)[0]
    t = np.array([xn[0] * z, xn[1] * z, z])
    ray = t / np.linalg.norm(t)
    axis = np.cross(ray, rng.normal(size=3))
    normal = cv.rodrigues(np.deg2rad(rng.uniform(33, 51)) * axis / np.linalg.norm(axis)) @ -ray
    x0 = np.cross(normal, [0.0, 1.0, 0.3])
    x0 /= np.linalg.norm(x0)
    phi = rng.uniform(0, 2 * np.pi)
    x = np.cos(phi) * x0 + np.sin(phi) * np.cross(normal, x0)
    return t, np.column_stack([x, np.cross(normal, x), normal])


def _render_tutorial(which: str, cam, layout, t, R, rng, blur: float, noise: float):
    if which == "render":
        vc = VirtualCamera(cam, RenderSettings(blur_sigma_px=blur, noise_sigma_dn=noise))
        return vc.render_fiducials(layout, t, R, rng)
    corners_C = layout.fiducial_corners_m @ R.T + t  # {O} = {C}
    bits = [cv.marker_bits_image(layout.dictionary, layout.fiducials[0].id)]
    return render_square_markers(
        cam.K,
        cam.image_size_px,
        corners_C,
        bits,
        layout.quiet_zone_cells,
        rng,
        blur_px=blur,
        noise_dn=noise,
    )


@pytest.mark.parametrize("which,seed", [("render", 41), ("second", 42)])
def test_single_markers_at_the_tutorials_scale_against_opencv_ippe_square(
    which: str, seed: int
) -> None:
    """Rendered single markers like the tutorial photo's (blur 0.6-1.5 px, noise 1-3 DN), each
    alone, acquired from scratch (no previous frame): every pose not flagged ambiguous is the
    true branch (never a confident flip), its covariance covers the truth (NEES), and it is
    nearer the truth than OpenCV's IPPE_SQUARE on OpenCV's own corners (its default detector and
    its best refinement, computed here by opencv_reference).  Before (issue 19): every such pose
    of the photo was flagged ambiguous, and the corners refined once from OpenCV's were 1.5 mm
    (blur 0.7) to 16 mm (blur 1.5) too far on these renders."""
    cam = _tutorial_camera(which == "render")
    rng = np.random.default_rng(seed)
    n, amb, nee, err_mm, dz_mm = 60, 0, [], [], []
    ref_err: dict[str, list[float]] = {"none": [], "apriltag": []}
    ref_dz: dict[str, list[float]] = {"none": [], "apriltag": []}
    for _ in range(n):
        t, R = _tutorial_view(rng, cam)
        layout = _one_marker(int(rng.choice(TUTORIAL_IDS)))
        img = _render_tutorial(
            which, cam, layout, t, R, rng, rng.uniform(0.6, 1.5), rng.uniform(1, 3)
        )
        est = FramePoseEstimator(cam, layout, track=False).estimate(img)
        assert est.flags & FLAG_SINGLE_MARKER and np.all(np.isfinite(est.position_O_m))
        e = pose_error(est.position_O_m, est.R_O_P, t, R)
        if est.flags & FLAG_AMBIGUOUS:
            amb += 1
            # flagged: the covariance covers both solutions (the truth is one of them)
            assert nees(e, est.covariance) < 25.0, (e, est.extra)
            continue
        assert not est.flags & BAD_FLAGS, est.flags
        assert np.rad2deg(np.linalg.norm(e[3:])) < 5.0, (e, est.extra)  # the flip: 60-100 deg
        nee.append(nees(e, est.covariance))
        err_mm.append(1e3 * np.linalg.norm(e[:3]))
        dz_mm.append(1e3 * e[2])
        mid = layout.fiducials[0].id
        for refinement in ref_err:
            ref = ippe_square_poses(img, "DICT_6X6_250", LENGTH_M, cam.K, cam.dist, refinement)
            assert mid in ref
            R_ref = cv.rodrigues(ref[mid]["rvecs"][0])
            e_ref = pose_error(ref[mid]["tvecs"][0], R_ref, t, R)
            ref_err[refinement].append(1e3 * np.linalg.norm(e_ref[:3]))
            ref_dz[refinement].append(1e3 * e_ref[2])
    nee_a = np.array(nee)
    print(
        f"\ntutorial-scale single markers, {which} renderer: {n} frames, {amb} flagged "
        f"ambiguous, 0 confident flips; ours: position error median {np.median(err_mm):.2f} mm "
        f"(max {max(err_mm):.1f}), depth bias {np.mean(dz_mm):+.2f} mm, NEES median "
        f"{np.median(nee_a):.1f}, {np.mean(nee_a <= 16.81):.0%} within chi2_6 99 %; "
        + "; ".join(
            f"OpenCV IPPE_SQUARE ({k}): median {np.median(v):.2f} mm, depth bias "
            f"{np.mean(ref_dz[k]):+.2f} mm"
            for k, v in ref_err.items()
        )
    )
    assert amb <= 0.2 * n
    assert np.median(nee_a) <= 12.0 and np.mean(nee_a <= 16.81) >= 0.85
    for v in ref_err.values():
        assert np.median(err_mm) < np.median(v)


def test_the_previous_frame_resolves_the_flip_and_an_ambiguous_pose_covers_both() -> None:
    """Corners of a tutorial-scale marker (35 px, tilted 33-51 deg) with 0.3-0.6 px noise: the
    fit alone often cannot tell the two solutions apart (flagged ambiguous).  Then (a) the
    flagged pose's covariance covers the truth whichever solution it reports; (b) the previous
    frame's pose (the truth one frame earlier: 1 deg and 2 mm away) picks the true solution,
    never the flip; (c) a "previous" pose as far from both solutions resolves nothing."""
    cam = _tutorial_camera(True)
    corners = _one_marker(40).fiducial_corners_m[0]
    rng = np.random.default_rng(43)
    n_amb = n_prev = n_conf = 0
    for trial in range(300):
        t, R = _tutorial_view(rng, cam)
        px = cv.project_points(corners, cv.rotation_vector(R), t, cam.K, cam.dist)
        sigma = [0.3, 0.6][trial % 2]
        noisy = px + rng.normal(0, sigma, px.shape)
        alone = estimate_pose_single_marker(corners, noisy, cam, sigma, prior_dof=60.0)
        e = pose_error(alone.position_O_m, alone.R_O_P, t, R)
        if not alone.flags & FLAG_AMBIGUOUS:
            assert np.rad2deg(np.linalg.norm(e[3:])) < 10.0  # a confident pose is never the flip
            n_conf += 1
            continue
        n_amb += 1
        assert nees(e, alone.covariance) < 25.0, (trial, e)  # (a)
        step = cv.rodrigues(np.deg2rad(1.0) * rng.normal(size=3) / np.sqrt(3))
        prev = (cv.rotation_vector(step @ R), t + rng.normal(0, 2e-3 / np.sqrt(3), 3))
        est = estimate_pose_single_marker(corners, noisy, cam, sigma, guess=prev, prior_dof=60.0)
        e = pose_error(est.position_O_m, est.R_O_P, t, R)
        assert est.flags & FLAG_AMBIGUOUS or np.rad2deg(np.linalg.norm(e[3:])) < 10.0  # (b)
        if not est.flags & FLAG_AMBIGUOUS:
            assert est.extra["planar_by_previous"] == 1.0
            n_prev += 1
        # (c) a guess turned 90 deg about the line of sight from the truth: near neither solution
        ray = t / np.linalg.norm(t)
        far = (cv.rotation_vector(cv.rodrigues(np.pi / 2 * ray) @ R), t)
        est = estimate_pose_single_marker(corners, noisy, cam, sigma, guess=far, prior_dof=60.0)
        assert est.flags & FLAG_AMBIGUOUS
    print(
        f"\nflip and the previous frame: {n_conf} confident by the fit, {n_amb} ambiguous alone, "
        f"{n_prev} of those resolved by the previous frame (all right), 0 confident flips"
    )
    assert n_amb >= 50 and n_prev >= 0.9 * n_amb
