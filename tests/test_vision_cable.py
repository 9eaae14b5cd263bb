"""A cable across an IR mark (issue 11): a dark band 1-3 px wide through one blob shifts its
centroid.  The shape check (calibration.detect.check_blob_shapes: flux over the projected disk's
area, one part, rim along the projected outline) must find the damaged blob, drop it and flag the
pose ``occluded_mark``, so that no pose is confidently wrong.

Frames from BOTH renderers: calibration/render.py (with lens distortion) and the independent
tests/vision_grid_renderer.py (pinhole); the band is drawn on the test side (tests/_cable_band.py,
numpy only) through the mark's image centre computed here with the pinhole model (for the
distorted camera: cv's projection, used only to place the band).  Truth: the poses drawn."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _cable_band import draw_cable
from vision_grid_renderer import render_ir_disks

from cdpr.analysis.rotations import rotation_from_euler
from cdpr.calibration import cv
from cdpr.calibration.camera_model import camera_from_mapping
from cdpr.calibration.detect import check_blob_shapes
from cdpr.calibration.markers import flat_prototype_points_layout
from cdpr.calibration.pose import BAD_FLAGS, FLAG_OCCLUDED_MARK, flag_names, nees, pose_error
from cdpr.calibration.render import VirtualCamera
from cdpr.daq.camera_source import FramePoseEstimator

ROOT = Path(__file__).resolve().parents[1]
P0 = np.array([0.5, 0.0, 0.36])
RADIUS_M = 0.004  # the layout's IR disks (flat_prototype_points_layout)
TOL_MM, TOL_DEG = 0.1, 0.05  # an unflagged pose must be this close to the truth


def _camera(distorted: bool):
    data = json.loads((ROOT / "data_samples/camera_virtual.json").read_text())
    if not distorted:
        data["dist_coeffs"] = [0.0] * 5  # the second renderer is a distortion-free pinhole
    return camera_from_mapping(data)


def _frame(which: str, cam, layout, p, R, rng) -> np.ndarray:
    if which == "second":
        R_C_O = cam.R_O_C.T
        X_C = (p + layout.point_centers_m @ R.T - cam.position_O_m) @ R_C_O.T
        N_C = layout.point_normals @ R.T @ R_C_O.T
        return render_ir_disks(cam.K, cam.image_size_px, X_C, N_C, RADIUS_M, rng)
    return VirtualCamera(cam).render_points(layout, p, R, rng)


def _mark_px(which: str, cam, layout, p, R) -> tuple[np.ndarray, np.ndarray]:
    """Image centres (6, 2) and radii (6,) of the marks (radius f r / z)."""
    X_C = (p + layout.point_centers_m @ R.T - cam.position_O_m) @ cam.R_O_C
    radius = cam.K[0, 0] * RADIUS_M / X_C[:, 2]
    if which == "second":
        uv = (X_C @ cam.K.T)[:, :2] / X_C[:, 2:]
    else:
        uv = cv.project_points(X_C, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    return uv, radius


def _pose(rng):
    return P0 + rng.uniform(-0.02, 0.02, 3), rotation_from_euler(np.deg2rad(rng.uniform(-6, 6, 3)))


def _estimate(cam, layout, img):
    return FramePoseEstimator(cam, layout, reference=(P0, np.eye(3))).estimate(img)


def _err(est, p, R) -> tuple[float, float, np.ndarray]:
    e = pose_error(est.position_O_m, est.R_O_P, p, R)
    return 1e3 * float(np.linalg.norm(e[:3])), float(np.rad2deg(np.linalg.norm(e[3:]))), e


@pytest.mark.parametrize("which,seed", [("second", 21), ("render", 22)])
def test_a_cable_across_a_mark_is_flagged_or_harmless(which: str, seed: int) -> None:
    cam, layout = _camera(which == "render"), flat_prototype_points_layout()
    rng = np.random.default_rng(seed)
    n, occluded, bad, worst, worst_occ, nee = 40, 0, 0, (0.0, 0.0), (0.0, 0.0), []
    for _ in range(n):
        p, R = _pose(rng)
        img = _frame(which, cam, layout, p, R, rng)
        uv, rad = _mark_px(which, cam, layout, p, R)
        k = int(rng.integers(6))
        # the band's centre line crosses the disk: offset within the radius, any angle, 1-3 px
        img = draw_cable(
            img, uv[k], rng.uniform(0, np.pi), rng.uniform(-1, 1) * rad[k], rng.uniform(1, 3)
        )
        est = _estimate(cam, layout, img)
        if est.flags & BAD_FLAGS:
            bad += 1
            continue
        pe, re, e = _err(est, p, R)
        nee.append(nees(e, est.covariance))
        if est.flags & FLAG_OCCLUDED_MARK:
            occluded += 1
            worst_occ = (max(worst_occ[0], pe), max(worst_occ[1], re))
            # the pose from the other five marks is still good (issue 11's goal: 1 mm / 0.2 deg)
            assert pe <= 1.0 and re <= 0.2, (pe, re, flag_names(est.flags))
        else:
            worst = (max(worst[0], pe), max(worst[1], re))
            assert pe <= TOL_MM and re <= TOL_DEG, (k, pe, re, est.extra)
    print(
        f"\ncable across a mark, {which} renderer: {n} poses, {bad} unusable, {occluded} "
        f"occluded_mark, {n - bad - occluded} unflagged (worst {worst[0]:.3f} mm "
        f"{worst[1]:.4f} deg); occluded worst {worst_occ[0]:.3f} mm {worst_occ[1]:.4f} deg; "
        f"NEES mean {np.mean(nee):.2f} max {np.max(nee):.1f}"
    )
    assert occluded + bad >= 0.8 * n  # a band across a disk is (almost) always seen
    assert np.mean(nee) <= 12.0


@pytest.mark.parametrize("which,seed", [("second", 23), ("render", 24)])
def test_clean_frames_carry_no_occluded_flag(which: str, seed: int) -> None:
    """Intact marks pass the check: no flag, every flux within 1.5 % of the frame's median and
    every rim within 0.2 px of the projected outline (the measured clean margins: 1.1 % and
    0.15 px on 600 blobs)."""
    cam, layout = _camera(which == "render"), flat_prototype_points_layout()
    rng = np.random.default_rng(seed)
    for _ in range(30):
        p, R = _pose(rng)
        est = _estimate(cam, layout, _frame(which, cam, layout, p, R, rng))
        assert est.flags == 0, flag_names(est.flags)
        assert est.extra["flux_deviation_max"] < 0.015
        assert est.extra["rim_residual_max_px"] < 0.2
        assert est.extra["occluded_marks"] == 0


def test_split_blob_and_lost_mark_are_named() -> None:
    """A wide band through the middle splits a disk in two (two parts in its window): damaged;
    a mark erased from the frame (inside the image, facing the camera): lost.  Both flagged."""
    which = "second"
    cam, layout = _camera(False), flat_prototype_points_layout()
    rng = np.random.default_rng(25)
    p, R = P0, np.eye(3)
    img = _frame(which, cam, layout, p, R, rng)
    uv, rad = _mark_px(which, cam, layout, p, R)
    split = draw_cable(img, uv[2], 0.3, 0.0, 3.0)
    R_C_P, t = cam.pose_C_P(p, R)
    labels = np.arange(6)
    chk = check_blob_shapes(split, layout, cam, cv.rotation_vector(R_C_P), t, labels)
    assert chk.parts[2] == 2 and list(chk.damaged) == [2]
    assert chk.flux_deviation[2] < -0.15  # a 3 px band through a ~16 px disk: ~20 % of its light
    est = _estimate(cam, layout, split)
    assert est.flags & FLAG_OCCLUDED_MARK and est.n_points == 5
    # lost: mark 4 painted over with the background level
    x, y = np.rint(uv[4]).astype(int)
    r = int(np.ceil(rad[4])) + 4
    gone = img.copy()
    gone[y - r : y + r + 1, x - r : x + r + 1] = 12
    est = _estimate(cam, layout, gone)
    assert est.flags & FLAG_OCCLUDED_MARK, flag_names(est.flags)
    assert not est.flags & BAD_FLAGS and est.extra["occluded_marks"] == 1
