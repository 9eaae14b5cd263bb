"""Camera sources on real files (image folder, MJPG video written and read by OpenCV) and the
virtual camera; truth: the poses the frames were rendered at."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rotations import rotation_from_euler, rotation_from_quaternion
from cdpr.calibration import cv
from cdpr.calibration.camera_model import camera_from_mapping
from cdpr.calibration.markers import flat_prototype_fiducial_layout, flat_prototype_points_layout
from cdpr.calibration.render import VirtualCamera
from cdpr.daq.camera_source import CameraSource, VirtualCameraSource
from cdpr.daq.source import STATUS_BAD_FRAME

ROOT = Path(__file__).resolve().parents[1]
CAM = ROOT / "data_samples/camera_virtual.json"
P0 = np.array([0.5, 0.0, 0.36])


def _cam():
    return camera_from_mapping(json.loads(CAM.read_text()))


def _traj(k: int):
    t = 0.05 * k
    p = P0 + 0.01 * np.array([np.sin(t), np.cos(2 * t) - 1, 0.5 * np.sin(3 * t)])
    return p, rotation_from_euler(np.deg2rad([3 * np.sin(t), 2 * np.sin(2 * t), 4 * np.cos(t)]))


def _rot_err_deg(q, R):
    dR = rotation_from_quaternion(q) @ R.T
    return np.rad2deg(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))


def test_image_folder_source(tmp_path: Path) -> None:
    cam, layout = _cam(), flat_prototype_fiducial_layout()
    vc = VirtualCamera(cam)
    rng = np.random.default_rng(0)
    truth = []
    for k in range(5):
        p, R = _traj(k)
        truth.append((p, R))
        cv.write_image(tmp_path / f"f{k:03d}.png", vc.render_fiducials(layout, p, R, rng))
    (tmp_path / "f002b.png").write_bytes(b"corrupt")  # sorts between f002 and f003: a lost frame
    src = CameraSource(
        "cam",
        str(CAM),
        ROOT / "data_samples/markers_flat_aruco.toml",
        folder=str(tmp_path),
        fps=25.0,
        image_every=2,
        image_format="png",
    )
    poses, images = [], []
    with src:
        while not src.finished:
            for r in src.read():
                (poses if r.stream == "pose" else images).append(r)
    assert len(poses) == 5 and src.stats.lost == 1
    assert all(r.status == 0 and r.values["flags"] == 0 for r in poses)
    for r, (p, R) in zip(poses, truth, strict=True):
        assert np.linalg.norm(np.array(r.values["position_O_m"]) - p) < 1e-4
        assert _rot_err_deg(r.values["quaternion_wxyz"], R) < 0.02
        assert len(r.values["covariance"]) == 36
    dt = np.diff([r.t_ns for r in poses])
    assert np.all(dt > 0) and dt[0] == 40_000_000
    assert [r.values["frame_index"] for r in images] == [0, 2, 4]
    img0 = cv.decode_image(images[0].values["data"])
    assert np.array_equal(img0, cv.read_image(tmp_path / "f000.png"))  # PNG is lossless
    assert set(src.describe()) == {"pose", "image"}


def test_video_file_source_points(tmp_path: Path) -> None:
    cam, layout = _cam(), flat_prototype_points_layout()
    vc = VirtualCamera(cam)
    rng = np.random.default_rng(1)
    path = tmp_path / "run.avi"
    w = cv.VideoWriter(str(path), cam.image_size_px, 30.0)
    truth = [_traj(k) for k in range(6)]
    for p, R in truth:
        w.write(vc.render_points(layout, p, R, rng))
    w.release()
    src = CameraSource("cam", cam, layout, video=str(path))
    poses = []
    with src:
        while not src.finished:
            poses += [r for r in src.read() if r.stream == "pose"]
    assert len(poses) == 6
    for r, (p, R) in zip(poses, truth, strict=True):
        assert r.status == 0
        assert (
            np.linalg.norm(np.array(r.values["position_O_m"]) - p) < 3e-4
        )  # JPEG-compressed frames
        assert _rot_err_deg(r.values["quaternion_wxyz"], R) < 0.05
    assert np.all(np.diff([r.t_ns for r in poses]) > 0)


def test_virtual_camera_source_matches_truth() -> None:
    cam = _cam()
    t0 = 1_700_000_000_000_000_000

    def pose_at(t_ns: int):
        return _traj(int(round((t_ns - t0) / 20e6)))

    src = VirtualCameraSource(
        "vcam",
        cam,
        flat_prototype_points_layout(),
        pose_at,
        rate_hz=50.0,
        realtime=False,
        t_start_ns=t0,
        seed=3,
        image_every=5,
        truth_stream=True,
        reference=(P0, np.eye(3)),
    )
    got: dict[str, list] = {"pose": [], "pose_truth": [], "image": []}
    with src:
        for _ in range(10):
            for r in src.read():
                got[r.stream].append(r)
    assert len(got["pose"]) == 10 and len(got["pose_truth"]) == 10 and len(got["image"]) == 2
    for r, tr in zip(got["pose"], got["pose_truth"], strict=True):
        assert r.t_ns == tr.t_ns and r.status == 0
        p, R = pose_at(r.t_ns)
        assert np.allclose(tr.values["position_O_m"], p)
        assert np.linalg.norm(np.array(r.values["position_O_m"]) - p) < 2e-4
        assert _rot_err_deg(r.values["quaternion_wxyz"], R) < 0.05
    assert got["pose"][1].t_ns - got["pose"][0].t_ns == 20_000_000
    jpg = cv.decode_image(got["image"][0].values["data"])
    assert jpg.shape == (1024, 1280)


def test_virtual_camera_source_flags_when_markers_leave_the_view() -> None:
    cam = _cam()
    src = VirtualCameraSource(
        "vcam",
        cam,
        flat_prototype_fiducial_layout(),
        lambda t: (P0 + [0.0, 0.0, -2.0], np.eye(3)),
        realtime=False,
        t_start_ns=0,
    )
    with src:
        r = src.read()[0]
    assert r.status == STATUS_BAD_FRAME and r.values["flags"] & 1


def test_realtime_virtual_source_paces_frames() -> None:
    import time

    cam = _cam()
    src = VirtualCameraSource(
        "vcam", cam, flat_prototype_points_layout(), lambda t: (P0, np.eye(3)), rate_hz=20.0
    )
    t = time.monotonic()
    n = 0
    with src:
        while n < 4:
            n += len([r for r in src.read(0.5) if r.stream == "pose"])
    assert time.monotonic() - t >= 0.14  # 4 frames at 20 Hz span 3 periods


def test_bad_camera_settings_are_config_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="exactly one of device, video, folder"):
        CameraSource("cam", str(CAM), flat_prototype_points_layout())
    with pytest.raises(ConfigError, match="video file not found"):
        CameraSource(
            "cam", str(CAM), flat_prototype_points_layout(), video=str(tmp_path / "nope.avi")
        ).open()
    with pytest.raises(ConfigError, match="missing.json: file not found"):
        CameraSource(
            "cam",
            str(tmp_path / "missing.json"),
            flat_prototype_points_layout(),
            folder=str(tmp_path),
        )


def test_simulated_run_recorded_poses_match_the_virtual_rig(tmp_path: Path) -> None:
    """The must-show: the virtual rig's truth -> rendered IR frames -> VirtualCameraSource -> the
    recorder's MCAP file, read back with the mcap library's own reader; poses within the targets."""
    from mcap.reader import make_reader

    from cdpr.daq.recorder import Recorder
    from cdpr.daq.source import now_ns
    from cdpr.daq.virtual_rig import VirtualRig, load_schedule
    from cdpr.pipelines.config import load_rig

    rig = load_rig(ROOT / "data_samples/flat_experiment2.toml")
    vr = VirtualRig(rig, load_schedule(ROOT / "data_samples/schedule_demo.toml", rig))
    vr.t0_ns = now_ns()
    src = VirtualCameraSource(
        "camera",
        str(CAM),
        str(ROOT / "data_samples/markers_flat_ir6.toml"),
        pose_at=vr.true_pose_at,
        rate_hz=10.0,
        image_rate_hz=2.0,
        reference=(rig.reference_position_O_m, rotation_from_euler(rig.reference_euler_rad)),
    )
    path = tmp_path / "run.mcap"
    rec = Recorder([src], path)
    rec.start()
    # record until 8 pose frames and 2 images are written (about 1.6 s idle; a loaded machine
    # renders slower and loses frames, so wait for the frames, not for a time)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        c = rec.status().counts
        if c.get("pose", 0) >= 8 and c.get("image", 0) >= 2:
            break
        time.sleep(0.05)
    rec.stop()
    poses, images, status = [], 0, {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            if schema.name == "foxglove.PoseInFrame" and channel.topic == "/pose":
                poses.append(json.loads(message.data))
            elif channel.topic == "/pose_status":  # every frame's status, at the frame's time
                status[message.log_time] = json.loads(message.data)["status"]
            elif schema.name == "foxglove.CompressedImage":
                images += 1
    assert len(poses) >= 8 and images >= 2  # 10 poses/s and 2 images/s
    for b in poses:
        t_ns = b["timestamp"]["sec"] * 1_000_000_000 + b["timestamp"]["nsec"]
        p, R = vr.true_pose_at(t_ns)
        o = b["pose"]["orientation"]
        q = [o["w"], o["x"], o["y"], o["z"]]
        pos = b["pose"]["position"]
        assert status[t_ns] == 0
        assert np.linalg.norm(np.array([pos["x"], pos["y"], pos["z"]]) - p) < 0.15e-3
        assert _rot_err_deg(q, R) < 0.03


def test_apriltag_layout() -> None:
    """The same six markers as AprilTag 36h11 tags (8 cells across): detected, edge-fitted, posed."""
    from dataclasses import replace

    from cdpr.daq.camera_source import FramePoseEstimator

    cam = _cam()
    lay = flat_prototype_fiducial_layout()
    lay = replace(
        lay,
        dictionary="DICT_APRILTAG_36h11",
        fiducials=[replace(f, size_m=0.032) for f in lay.fiducials],
    )
    p, R = _traj(3)
    img = VirtualCamera(cam).render_fiducials(lay, p, R, np.random.default_rng(4))
    est = FramePoseEstimator(cam, lay).estimate(img)
    assert est.ok and est.n_points == 24
    assert np.linalg.norm(est.position_O_m - p) < 1e-4
