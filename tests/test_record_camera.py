"""``cdpr record`` with a ``kind = "camera"`` source (an image folder read through OpenCV): the run
carries ``/pose`` with its covariance and rate-limited compressed ``/image`` frames, and the camera
model and marker layout as attachments.  Truth: the poses the frames were rendered at."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import tomli_w
from test_recorder_helpers import node_read

from cdpr.analysis.rotations import rotation_from_euler, rotation_from_quaternion
from cdpr.calibration import cv
from cdpr.calibration.camera_model import camera_from_mapping
from cdpr.calibration.markers import flat_prototype_fiducial_layout
from cdpr.calibration.render import VirtualCamera
from cdpr.daq.mcap_io import read_run

ROOT = Path(__file__).resolve().parents[1]
CDPR = [sys.executable, "-m", "cdpr.pipelines.cli"]
CAM = ROOT / "data_samples" / "camera_virtual.json"
FPS = 10.0


def test_record_a_camera_folder(tmp_path: Path) -> None:
    vc = VirtualCamera(camera_from_mapping(json.loads(CAM.read_text())))
    rng = np.random.default_rng(4)
    frames = tmp_path / "frames"
    frames.mkdir()
    truth = []
    poses = [
        (np.array([0.5 + 0.004 * j, 0.0, 0.36]), rotation_from_euler(np.deg2rad([0, 0.5 * j, 0])))
        for j in range(3)
    ]
    images = [vc.render_fiducials(flat_prototype_fiducial_layout(), p, R, rng) for p, R in poses]
    for k in range(40):  # 4 s at 10 fps: longer than the recording; three poses in turn
        truth.append(poses[k % 3])
        cv.write_image(frames / f"f{k:03d}.png", images[k % 3])
    cfg = {
        "run": {"label": "cam"},
        "recorder": {"startup_timeout_s": 20.0},
        "sources": {
            "camera": {
                "kind": "camera",
                "camera": str(CAM),
                "layout": str(ROOT / "data_samples" / "markers_flat_aruco.toml"),
                "folder": "frames",  # relative to the config file
                "fps": FPS,
                "image_rate_hz": 2.0,
                "image_format": "jpeg",
            }
        },
    }
    p = tmp_path / "cam.toml"
    p.write_bytes(tomli_w.dumps(cfg).encode())
    out = tmp_path / "runs"
    res = subprocess.run(
        [*CDPR, "record", "--config", str(p), "--out", str(out), "--duration", "2.5", "--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    (path,) = sorted(out.glob("*_cam.mcap"))
    node = node_read(path)
    assert node["complete"]
    n_pose, n_img = node["topics"]["/pose_status"], node["topics"]["/image"]  # frames, images
    assert 3 <= n_pose <= 27  # 10 fps paced in real time for 2.5 s (fewer on a loaded machine)
    rc = read_run(path)
    t_img = np.array([t for t, _ in rc.messages["/image"]])
    assert n_img >= 1 and np.all(np.diff(t_img) >= 0.5e9 - 1)  # at most 2 images per second
    assert {a["name"] for a in node["attachments"]} == {
        "config/cam.toml",
        "calibration/camera_virtual.json",
        "calibration/markers_flat_aruco.toml",
    }
    got = rc.messages["/pose_status"]  # every frame; its pose (if any) on /pose, same log time
    assert len(got) == n_pose
    pose_at = dict(rc.messages["/pose"])
    good = [(t, b) for t, b in got if b["flags"] == 0]  # flagged poses (not trusted) aside
    assert len(good) >= 0.6 * len(got)
    for t, b in good:
        k = b["frame_index"]
        pos, R = truth[k]
        pp, o = pose_at[t]["pose"]["position"], pose_at[t]["pose"]["orientation"]
        assert np.linalg.norm(np.array([pp["x"], pp["y"], pp["z"]]) - pos) < 1e-3
        dR = rotation_from_quaternion([o["w"], o["x"], o["y"], o["z"]]) @ R.T
        assert np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)) < np.deg2rad(0.1)
        cov = np.array(b["covariance"]).reshape(6, 6)
        assert np.allclose(cov, cov.T) and np.all(np.diag(cov) > 0)
    t = np.array([t for t, _ in got])
    assert np.all(np.diff(t) > 0)
    assert rc.channels["/image"].schema_name == "foxglove.CompressedImage"
