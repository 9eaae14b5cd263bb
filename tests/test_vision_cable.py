"""A cable across an IR mark (issue 11): a dark band 1-3 px wide through one blob shifts its
centroid.  The shape check (calibration.detect.check_blob_shapes: no straight band across the
blob against the mark's own radial profile, one part, rim along the projected outline) must find
the damaged blob, drop it and flag the pose ``occluded_mark``, so that no pose is confidently
wrong; and intact marks must pass whatever their brightness (issue 19 §1: retro-reflective marks
differ by tens of percent with the angle and distance they are seen at, and the lighting is not
even over the frame: a check against the other marks' brightness dropped every mark).

Frames from BOTH renderers: calibration/render.py (with lens distortion) and the independent
tests/vision_grid_renderer.py (pinhole), each mark at its own brightness (+-30 % around 190 DN,
drawn here) under a smooth illumination gradient (30 % across the frame in x, 15 % in y); the
band is drawn on the test side (tests/_cable_band.py, numpy only) through the mark's image centre
computed here with the pinhole model (for the distorted camera: cv's projection, used only to
place the band).  Truth: the poses drawn."""

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
from cdpr.calibration.render import RenderSettings, VirtualCamera
from cdpr.daq.camera_source import FramePoseEstimator

ROOT = Path(__file__).resolve().parents[1]
P0 = np.array([0.5, 0.0, 0.36])
RADIUS_M = 0.004  # the layout's IR disks (flat_prototype_points_layout)
TOL_MM, TOL_DEG = 0.1, 0.05  # an unflagged pose must be this close to the truth
GRADIENT = (0.3, 0.15)  # illumination 30 % brighter at the right edge than at the left, 15 % in y


def _spots(rng) -> np.ndarray:
    """Each mark's level: +-30 % around 190 DN (retro-reflectors at different angles)."""
    return 190.0 * rng.uniform(0.7, 1.3, 6)


def _camera(distorted: bool):
    data = json.loads((ROOT / "data_samples/camera_virtual.json").read_text())
    if not distorted:
        data["dist_coeffs"] = [0.0] * 5  # the second renderer is a distortion-free pinhole
    return camera_from_mapping(data)


def _frame(which: str, cam, layout, p, R, rng, spots=235.0, gradient=(0.0, 0.0)) -> np.ndarray:
    if which == "second":
        R_C_O = cam.R_O_C.T
        X_C = (p + layout.point_centers_m @ R.T - cam.position_O_m) @ R_C_O.T
        N_C = layout.point_normals @ R.T @ R_C_O.T
        return render_ir_disks(
            cam.K, cam.image_size_px, X_C, N_C, RADIUS_M, rng, spot_dn=spots, gradient=gradient
        )
    vc = VirtualCamera(cam, RenderSettings(illumination_gradient=gradient))
    return vc.render_points(layout, p, R, rng, spot_dn=np.broadcast_to(spots, (6,)))


def _mark_px(which: str, cam, layout, p, R) -> tuple[np.ndarray, np.ndarray]:
    """Image centres (6, 2) and radii (6,) of the marks (radius f r / z)."""
    X_C = (p + layout.point_centers_m @ R.T - cam.position_O_m) @ cam.R_O_C
    radius = cam.K[0, 0] * RADIUS_M / X_C[:, 2]
    if which == "second":
        uv = (X_C @ cam.K.T)[:, :2] / X_C[:, 2:]
    else:
        uv = cv.project_points(X_C, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    return uv, radius


def _crosses(which: str, cam, layout, p, R, k: int, angle: float, offset: float) -> bool:
    """Does the band's centre line (normal (-sin, cos) of ``angle``, ``offset`` px from the mark's
    image centre) cross mark k's projected disk?  (Its rim projected here, 64 points.)"""
    mark = layout.points[k]
    a = np.cross(mark.normal, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(mark.normal, a)
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rim_P = mark.center_m + RADIUS_M * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)
    X_C = (p + rim_P @ R.T - cam.position_O_m) @ cam.R_O_C
    if which == "second":
        rim = (X_C @ cam.K.T)[:, :2] / X_C[:, 2:]
    else:
        rim = cv.project_points(X_C, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    uv, _ = _mark_px(which, cam, layout, p, R)
    along = (rim - uv[k]) @ np.array([-np.sin(angle), np.cos(angle)])
    return bool(along.min() < offset < along.max())


def _pose(rng):
    return P0 + rng.uniform(-0.02, 0.02, 3), rotation_from_euler(np.deg2rad(rng.uniform(-6, 6, 3)))


def _estimate(cam, layout, img):
    return FramePoseEstimator(cam, layout, reference=(P0, np.eye(3))).estimate(img)


def _err(est, p, R) -> tuple[float, float, np.ndarray]:
    e = pose_error(est.position_O_m, est.R_O_P, p, R)
    return 1e3 * float(np.linalg.norm(e[:3])), float(np.rad2deg(np.linalg.norm(e[3:]))), e


@pytest.mark.parametrize(
    "which,marks,seed",
    [
        ("second", "even", 21),
        ("render", "even", 22),
        ("second", "varied", 26),
        ("render", "varied", 27),
    ],
)
def test_a_cable_across_a_mark_is_flagged_or_harmless(which: str, marks: str, seed: int) -> None:
    """40 poses, a band 1-3 px wide across one mark at any angle, its centre line within the
    disk's largest radius of its centre; marks of one brightness ("even") or +-30 % apart under a
    gradient ("varied").  On a tilted mark (an ellipse) a centre line that far may pass outside
    the disk: such a band only darkens the rim's blur tail (the known limit, docs/vision.md) and
    must leave the pose within issue 4's 0.15 mm / 0.03 deg if it is not flagged."""
    cam, layout = _camera(which == "render"), flat_prototype_points_layout()
    rng = np.random.default_rng(seed)
    n, occluded, bad, worst, worst_occ, nee = 40, 0, 0, (0.0, 0.0), (0.0, 0.0), []
    outside = missed_across = 0
    for _ in range(n):
        p, R = _pose(rng)
        if marks == "varied":
            img = _frame(which, cam, layout, p, R, rng, _spots(rng), GRADIENT)
        else:
            img = _frame(which, cam, layout, p, R, rng)
        uv, rad = _mark_px(which, cam, layout, p, R)
        k = int(rng.integers(6))
        angle, offset = rng.uniform(0, np.pi), rng.uniform(-1, 1) * rad[k]
        img = draw_cable(img, uv[k], angle, offset, rng.uniform(1, 3))
        across = _crosses(which, cam, layout, p, R, k, angle, offset)
        outside += not across
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
            missed_across += across
            if across:
                assert pe <= TOL_MM and re <= TOL_DEG, (k, pe, re, est.extra)
            else:
                assert pe <= 0.15 and re <= 0.03, (k, pe, re, est.extra)
    print(
        f"\ncable across a mark, {which} renderer, {marks} marks: {n} poses ({outside} centre "
        f"lines outside a tilted disk), {bad} unusable, {occluded} occluded_mark, "
        f"{n - bad - occluded} unflagged ({missed_across} across; worst {worst[0]:.3f} mm "
        f"{worst[1]:.4f} deg); occluded worst {worst_occ[0]:.3f} mm {worst_occ[1]:.4f} deg; "
        f"NEES mean {np.mean(nee):.2f} max {np.max(nee):.1f}"
    )
    assert occluded + bad >= 0.9 * n  # a band across a disk is (almost) always seen
    assert bad <= 0.1 * n  # and the other five marks give the pose
    assert np.mean(nee) <= 12.0


@pytest.mark.parametrize(
    "which,marks,seed",
    [
        ("second", "even", 23),
        ("render", "even", 24),
        ("second", "varied", 28),
        ("render", "varied", 29),
        ("second", "spread", 30),
        ("render", "spread", 31),
    ],
)
def test_clean_frames_carry_no_occluded_flag(which: str, marks: str, seed: int) -> None:
    """Intact marks pass the check whatever their brightness: no flag, no band above the notch
    tolerance, no centroid bias above 0.06 px, every rim within 0.2 px of the projected outline,
    and the pose within issue 4's
    accuracy (0.15 mm, 0.03 deg RMS).  Marks: one brightness ("even"), +-30 % under a gradient
    ("varied"), or spread over 170-300 DN, the brighter ones clipped at 255 ("spread", issue
    19's report: every frame lost six marks to the former flux test)."""
    cam, layout = _camera(which == "render"), flat_prototype_points_layout()
    rng = np.random.default_rng(seed)
    errs, nee, notch, rim, bias = [], [], [], [], []
    for _ in range(30):
        p, R = _pose(rng)
        if marks == "varied":
            img = _frame(which, cam, layout, p, R, rng, _spots(rng), GRADIENT)
        elif marks == "spread":
            img = _frame(which, cam, layout, p, R, rng, rng.uniform(170.0, 300.0, 6))
        else:
            img = _frame(which, cam, layout, p, R, rng)
        est = _estimate(cam, layout, img)
        assert est.flags == 0, (flag_names(est.flags), est.extra)
        assert est.extra["occluded_marks"] == 0
        notch.append(est.extra["notch_max"])
        rim.append(est.extra["rim_residual_max_px"])
        bias.append(est.extra["bias_max_px"])
        _, _, e = _err(est, p, R)
        errs.append(e)
        nee.append(nees(e, est.covariance))
    E = np.array(errs)
    pos_mm = 1e3 * np.sqrt(np.mean(np.sum(E[:, :3] ** 2, axis=1)))
    rot_deg = np.rad2deg(np.sqrt(np.mean(np.sum(E[:, 3:] ** 2, axis=1))))
    print(
        f"\nclean, {which} renderer, {marks} marks: 30 frames unflagged, {pos_mm:.4f} mm "
        f"{rot_deg:.5f} deg RMS, NEES mean {np.mean(nee):.2f} median {np.median(nee):.2f}; "
        f"notch max {max(notch):.3f} (tolerance 0.08), rim max {max(rim):.3f} px (0.2), bias "
        f"max {max(bias):.3f} px (0.06)"
    )
    assert max(notch) < 0.08 and max(rim) < 0.2 and max(bias) < 0.06
    assert pos_mm <= 0.15 and rot_deg <= 0.03


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
    # a 3 px band through a ~16 px disk: a line of it darker than the mark by half its peak
    assert chk.notch_depth[2] < -0.4 and np.isinf(chk.score[2])
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
