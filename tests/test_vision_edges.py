"""Vision that never lies confidently (issue 11, "Vision"), on IR frames drawn by the second,
independent renderer (tests/vision_grid_renderer.py: numpy ray-disk intersection, no OpenCV, not
calibration/render.py).  Truth: the poses the frames were drawn at.  Goal: no unflagged pose more
than 1 mm or 0.2 deg off; NEES mean within [3, 12]."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from vision_grid_renderer import render_ir_disks

from cdpr.analysis.rotations import rotation_from_euler
from cdpr.calibration.camera_model import camera_from_mapping
from cdpr.calibration.markers import flat_prototype_points_layout
from cdpr.calibration.pose import BAD_FLAGS, FLAG_NO_POSE, nees, pose_error
from cdpr.daq.camera_source import FramePoseEstimator

ROOT = Path(__file__).resolve().parents[1]
P0 = np.array([0.5, 0.0, 0.36])


@pytest.fixture(scope="module")
def setup():
    data = json.loads((ROOT / "data_samples/camera_virtual.json").read_text())
    data["dist_coeffs"] = [0.0] * 5  # the second renderer is a distortion-free pinhole
    cam = camera_from_mapping(data)
    return cam, flat_prototype_points_layout()


def _draw(cam, layout, p, R, rng, keep=None, extra_C=None):
    """Frame of the layout at pose (p, R) in {O}; ``keep``: mask of marks drawn; ``extra_C``:
    additional spurious disk centres in {C}."""
    R_C_O = cam.R_O_C.T
    X_C = (p + layout.point_centers_m @ R.T - cam.position_O_m) @ R_C_O.T
    N_C = layout.point_normals @ R.T @ R_C_O.T
    if keep is not None:
        X_C, N_C = X_C[keep], N_C[keep]
    if extra_C is not None:
        X_C = np.vstack([X_C, extra_C])
        N_C = np.vstack([N_C, np.tile(N_C[:1], (len(extra_C), 1))])
    return render_ir_disks(cam.K, cam.image_size_px, X_C, N_C, 0.004, rng)


def _error_ok(est, p, R) -> tuple[bool, np.ndarray]:
    e = pose_error(est.position_O_m, est.R_O_P, p, R)
    return bool(np.linalg.norm(e[:3]) <= 1e-3 and np.rad2deg(np.linalg.norm(e[3:])) <= 0.2), e


def _pose(rng):
    return P0 + rng.uniform(-0.02, 0.02, 3), rotation_from_euler(np.deg2rad(rng.uniform(-6, 6, 3)))


def test_ir_accuracy_and_nees_on_the_second_renderer(setup) -> None:
    cam, layout = setup
    rng = np.random.default_rng(8)
    errs, nee, flagged = [], [], 0
    for _ in range(40):
        p, R = _pose(rng)
        est = FramePoseEstimator(cam, layout, reference=(P0, np.eye(3))).estimate(
            _draw(cam, layout, p, R, rng)
        )
        if est.flags & BAD_FLAGS:
            flagged += 1
            continue
        ok, e = _error_ok(est, p, R)
        assert ok, e
        errs.append(e)
        nee.append(nees(e, est.covariance))
    E = np.array(errs)
    print(
        f"\nIR, second renderer: {len(E)} poses, {flagged} flagged, position RMS "
        f"{1e3 * np.sqrt(np.mean(np.sum(E[:, :3] ** 2, 1))):.4f} mm, rotation RMS "
        f"{np.rad2deg(np.sqrt(np.mean(np.sum(E[:, 3:] ** 2, 1)))):.5f} deg, NEES mean "
        f"{np.mean(nee):.2f}, median {np.median(nee):.2f}"
    )
    assert flagged == 0 and 3.0 <= np.mean(nee) <= 12.0


def test_tracking_survives_a_jump_larger_than_the_search_window(setup) -> None:
    """Marks moving 12-16 mm (~35-45 px) between frames are cut by the +-24 px search windows:
    they must be re-detected on the whole frame, never measured cut (before: 1.45 mm / 0.23 deg
    off at 14 mm, unflagged)."""
    cam, layout = setup
    rng = np.random.default_rng(9)
    for step_mm in (12.0, 14.0, 16.0):
        fe = FramePoseEstimator(cam, layout, reference=(P0, np.eye(3)))
        assert fe.estimate(_draw(cam, layout, P0, np.eye(3), rng)).ok  # tracking primed
        p = P0 + np.array([step_mm * 1e-3, 0.0, 0.0])
        est = fe.estimate(_draw(cam, layout, p, np.eye(3), rng))
        assert not est.flags & BAD_FLAGS
        ok, e = _error_ok(est, p, np.eye(3))
        assert ok, (step_mm, e)


def test_grey_and_noise_frames_give_no_pose(setup) -> None:
    cam, layout = setup
    rng = np.random.default_rng(10)
    w, h = cam.image_size_px
    for bad in (np.full((h, w), 128, np.uint8), rng.integers(0, 256, (h, w), dtype=np.uint8)):
        fe = FramePoseEstimator(cam, layout, reference=(P0, np.eye(3)))
        assert fe.estimate(_draw(cam, layout, P0, np.eye(3), rng)).ok  # tracking primed
        est = fe.estimate(bad)
        assert est.flags & BAD_FLAGS, est.flags
        assert est.flags & FLAG_NO_POSE or not np.all(np.isfinite(est.position_O_m))


def test_missing_marks_plus_a_spurious_blob_are_flagged_or_accurate(setup) -> None:
    cam, layout = setup
    rng = np.random.default_rng(12)
    for k in range(6):
        p, R = _pose(rng)
        keep = np.ones(6, bool)
        keep[[k, (k + 2) % 6]] = False
        R_C_O = cam.R_O_C.T
        near = (p + layout.point_centers_m[k] @ R.T - cam.position_O_m) @ R_C_O.T
        spurious = near + np.array([0.004, 0.003, 0.0])
        est = FramePoseEstimator(cam, layout, reference=(P0, np.eye(3))).estimate(
            _draw(cam, layout, p, R, rng, keep=keep, extra_C=spurious[None])
        )
        if not est.flags & BAD_FLAGS:
            ok, e = _error_ok(est, p, R)
            assert ok, (k, e, est.flags)


def test_a_mark_cut_by_the_image_border_is_not_measured(setup) -> None:
    cam, layout = setup
    rng = np.random.default_rng(13)
    R = np.eye(3)
    R_C_O = cam.R_O_C.T
    fx = cam.K[0, 0]
    good = 0
    for k in range(6):
        # shift the platform along the camera's x axis until mark k is centred on the left border
        X = (P0 + layout.point_centers_m[k] @ R.T - cam.position_O_m) @ R_C_O.T
        u = cam.K[0, 0] * X[0] / X[2] + cam.K[0, 2]
        p = P0 - cam.R_O_C[:, 0] * (u * X[2] / fx)
        est = FramePoseEstimator(cam, layout, reference=(p, np.eye(3))).estimate(
            _draw(cam, layout, p, R, rng)
        )
        if not est.flags & BAD_FLAGS:
            ok, e = _error_ok(est, p, R)
            assert ok, (k, e)
            assert nees(e, est.covariance) < 40
            good += 1
    # with mark 0 cut, the other five give a good pose (before: 2.8 mm off, flagged high residual)
    assert good >= 1


def test_camera_source_can_be_told_not_to_track(setup, tmp_path: Path, monkeypatch) -> None:
    """A folder of unrelated snapshots read through ``CameraSource(track=False)``: every frame is
    searched on the whole image (never in windows around the last pose) and is accurate."""
    from cdpr.calibration import cv
    from cdpr.daq import camera_source
    from cdpr.daq.camera_source import CameraSource

    cam, layout = setup
    rng = np.random.default_rng(14)
    poses = [_pose(rng) for _ in range(4)]
    for i, (p, R) in enumerate(poses):
        cv.write_image(tmp_path / f"snap_{i}.png", _draw(cam, layout, p, R, rng))
    searched: list[bool] = []
    real = camera_source.detect_blobs

    def spy(gray, settings=None, predicted=None):
        searched.append(predicted is None)
        return real(gray, settings, predicted)

    monkeypatch.setattr(camera_source, "detect_blobs", spy)
    for track in (True, False):
        searched.clear()
        src = CameraSource("cam", cam, layout, folder=str(tmp_path), track=track)
        assert src.settings()["track"] is track
        for i, (p, R) in enumerate(poses):
            est = src.estimator.estimate(cv.read_image(tmp_path / f"snap_{i}.png"))
            assert not est.flags & BAD_FLAGS
            ok, e = _error_ok(est, p, R)
            assert ok, (track, i, e)
        whole_frame_first = searched[0]
        assert whole_frame_first
        assert all(searched) is (not track)


def test_colour_and_resized_frames_are_clear_errors(setup) -> None:
    from cdpr.analysis.errors import InputError
    from cdpr.calibration.detect import FiducialDetector, detect_blobs
    from cdpr.calibration.markers import flat_prototype_fiducial_layout

    cam, layout = setup
    rng = np.random.default_rng(15)
    img = _draw(cam, layout, P0, np.eye(3), rng)
    colour = np.repeat(img[:, :, None], 3, axis=2)
    with pytest.raises(InputError, match=r"gray \(H, W\) image, got shape \(1024, 1280, 3\)"):
        FramePoseEstimator(cam, layout, reference=(P0, np.eye(3))).estimate(colour)
    with pytest.raises(InputError, match="gray"):
        detect_blobs(colour)
    fid = FiducialDetector(flat_prototype_fiducial_layout(), cam)
    with pytest.raises(InputError, match="640x512 px, the camera model is 1280x1024"):
        fid.detect(np.ascontiguousarray(img[::2, ::2]))


def test_ir_estimator_rejects_a_half_size_frame_naming_it(setup) -> None:
    """The IR path checks the frame against the camera model too (a half-size frame gave a pose
    1.06 m off): an InputError naming the frame, for a counted frame and for a named one."""
    from cdpr.analysis.errors import InputError

    cam, layout = setup
    rng = np.random.default_rng(16)
    img = _draw(cam, layout, P0, np.eye(3), rng)
    est = FramePoseEstimator(cam, layout, reference=(P0, np.eye(3)))
    assert not (est.estimate(img).flags & BAD_FLAGS)  # frame 0: a good one
    half = np.ascontiguousarray(img[::2, ::2])
    with pytest.raises(InputError, match=r"^frame 1: 640x512 px, the camera model is 1280x1024"):
        est.estimate(half)
    with pytest.raises(InputError, match=r"^shot_07\.png: 640x512 px"):
        est.estimate(half, name="shot_07.png")
