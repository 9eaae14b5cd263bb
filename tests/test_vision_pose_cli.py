"""``cdpr pose`` on snapshots, on a run file's recorded frames, and on bad input.  Frames are drawn
by the second renderer (tests/vision_grid_renderer.py); the run file is written with the ``mcap``
library's own writer (not ours); truth: the poses the frames were drawn at."""

from __future__ import annotations

import base64
import csv
import json
from pathlib import Path

import numpy as np
import pytest
from vision_grid_renderer import render_ir_disks

from cdpr.analysis.rotations import rotation_from_euler
from cdpr.calibration import cv
from cdpr.calibration.markers import flat_prototype_points_layout
from cdpr.calibration.pose import BAD_FLAGS
from cdpr.pipelines.cli import main
from cdpr.pipelines.vision_config import layout_toml, load_camera

ROOT = Path(__file__).resolve().parents[1]
P0 = np.array([0.5, 0.0, 0.36])


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory):
    d = tmp_path_factory.mktemp("pose")
    data = json.loads((ROOT / "data_samples/camera_virtual.json").read_text())
    data["dist_coeffs"] = [0.0] * 5  # the second renderer is a distortion-free pinhole
    (d / "camera.json").write_text(json.dumps(data))
    layout = flat_prototype_points_layout()
    (d / "marks.toml").write_text(layout_toml(layout))
    cam = load_camera(d / "camera.json")
    rng = np.random.default_rng(31)
    truth, frames = [], []
    for _ in range(4):
        p = P0 + rng.uniform(-0.02, 0.02, 3)
        R = rotation_from_euler(np.deg2rad(rng.uniform(-6, 6, 3)))
        R_C_O = cam.R_O_C.T
        X = (p + layout.point_centers_m @ R.T - cam.position_O_m) @ R_C_O.T
        N = layout.point_normals @ R.T @ R_C_O.T
        frames.append(render_ir_disks(cam.K, cam.image_size_px, X, N, 0.004, rng))
        truth.append((p, R))
    return d, cam, truth, frames


def _read(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def _check_rows(rows, truth) -> None:
    for row, (p, R) in zip(rows, truth, strict=True):
        assert not int(row["flags"]) & BAD_FLAGS, row["flag_names"]
        pos = np.array([float(row[k]) for k in ("x_O_m", "y_O_m", "z_O_m")])
        assert np.linalg.norm(pos - p) < 1e-3
        R_est = rotation_from_euler([float(row[k]) for k in ("roll_rad", "pitch_rad", "yaw_rad")])
        assert np.rad2deg(np.linalg.norm(cv.rotation_vector(R_est @ R.T))) < 0.2
        C = np.array([float(row[f"cov_{i}{j}"]) for i in range(6) for j in range(6)]).reshape(6, 6)
        assert np.allclose(C, C.T, rtol=1e-5, atol=1e-20) and np.all(np.linalg.eigvalsh(C) > 0)
        assert 0 < float(row["sigma_px"]) < 0.5 and int(row["n_points"]) >= 5


def test_pose_from_snapshots_and_a_grey_frame(scene, tmp_path: Path, capsys) -> None:
    d, _cam, truth, frames = scene
    shots = tmp_path / "shots"
    shots.mkdir()
    for i, img in enumerate(frames):
        cv.write_image(shots / f"shot_{i}.png", img)
    out = tmp_path / "poses.csv"
    argv = [
        "pose",
        str(shots),
        "--camera",
        str(d / "camera.json"),
        "--markers",
        str(d / "marks.toml"),
    ]
    assert main([*argv, "--out", str(out)]) == 0
    rows = _read(out)
    assert len(rows) == 4 and rows[0]["t_ns"] == ""
    _check_rows(rows, truth)
    # a grey frame: its row is kept, flagged, and the exit code says so
    cv.write_image(shots / "shot_9.png", np.full_like(frames[0], 128))
    assert main([*argv, "--out", str(out)]) == 3
    rows = _read(out)
    assert "no_pose" in rows[-1]["flag_names"] and rows[-1]["x_O_m"] == "nan"
    assert "1 of 5 frames have no usable pose" in capsys.readouterr().err


def test_pose_from_a_runs_recorded_frames(scene, tmp_path: Path) -> None:
    from mcap.writer import Writer

    d, _cam, truth, frames = scene
    run = tmp_path / "run.mcap"
    with run.open("wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema(
            name="foxglove.CompressedImage", encoding="jsonschema", data=b'{"type": "object"}'
        )
        cid = w.register_channel(topic="/camera/image", message_encoding="json", schema_id=sid)
        for i, img in enumerate(frames):
            t = 1_000_000_000 + i * 33_000_000
            body = {
                "timestamp": {"sec": t // 10**9, "nsec": t % 10**9},
                "frame_id": "camera",
                "data": base64.b64encode(cv.encode_image(img, "png")).decode(),
                "format": "png",
            }
            w.add_message(cid, log_time=t, data=json.dumps(body).encode(), publish_time=t)
        w.finish()
    out = tmp_path / "run_poses.csv"
    argv = [
        "pose",
        str(run),
        "--camera",
        str(d / "camera.json"),
        "--markers",
        str(d / "marks.toml"),
    ]
    assert main([*argv, "--no-track", "--out", str(out)]) == 0
    rows = _read(out)
    assert [int(r["t_ns"]) for r in rows] == [1_000_000_000 + i * 33_000_000 for i in range(4)]
    _check_rows(rows, truth)


def test_bad_input_is_one_line_and_writes_nothing(scene, tmp_path: Path, capsys) -> None:
    d, _cam, _truth, frames = scene
    half = tmp_path / "half.png"
    cv.write_image(half, frames[0][::2, ::2].copy())
    out = tmp_path / "o" / "poses.csv"
    argv = [
        "--camera",
        str(d / "camera.json"),
        "--markers",
        str(d / "marks.toml"),
        "--out",
        str(out),
    ]
    assert main(["pose", str(half), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "half.png" in err and "640x512" in err, err
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    assert main(["pose", str(broken), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert "broken.png" in err and "cannot decode" in err
    empty_run = tmp_path / "empty.mcap"
    from mcap.writer import Writer

    with empty_run.open("wb") as fh:
        w = Writer(fh)
        w.start()
        w.finish()
    assert main(["pose", str(empty_run), *argv]) == 2
    assert "no camera frames" in capsys.readouterr().err
    assert not out.exists() and not out.parent.exists()


def test_pose_from_a_video(scene, tmp_path: Path) -> None:
    d, cam, truth, frames = scene
    video = tmp_path / "clip.avi"
    vw = cv.VideoWriter(str(video), cam.image_size_px, 10.0)
    for img in frames:
        vw.write(img)
    vw.release()
    out = tmp_path / "video_poses.csv"
    argv = [
        "pose",
        str(video),
        "--camera",
        str(d / "camera.json"),
        "--markers",
        str(d / "marks.toml"),
    ]
    assert main([*argv, "--out", str(out)]) == 0
    rows = _read(out)
    assert [int(r["frame"]) for r in rows] == [0, 1, 2, 3]
    t = [int(r["t_ns"]) for r in rows]
    assert all(b > a for a, b in zip(t, t[1:], strict=False))
    _check_rows(rows, truth)  # MJPEG-compressed, still within 1 mm / 0.2 deg


def _ir_frames(cam, n: int, seed: int, spots, gradient=(0.0, 0.0)):
    """``n`` frames of the IR layout (second renderer), each mark at ``spots(rng)`` DN."""
    layout = flat_prototype_points_layout()
    rng = np.random.default_rng(seed)
    truth, frames = [], []
    for _ in range(n):
        p = P0 + rng.uniform(-0.02, 0.02, 3)
        R = rotation_from_euler(np.deg2rad(rng.uniform(-6, 6, 3)))
        R_C_O = cam.R_O_C.T
        X = (p + layout.point_centers_m @ R.T - cam.position_O_m) @ R_C_O.T
        N = layout.point_normals @ R.T @ R_C_O.T
        img = render_ir_disks(
            cam.K, cam.image_size_px, X, N, 0.004, rng, spot_dn=spots(rng), gradient=gradient
        )
        frames.append(img)
        truth.append((p, R))
    return truth, frames


def test_marks_of_different_brightness_give_poses(scene, tmp_path: Path, capsys) -> None:
    """Issue 19 §1: marks spread over 170-300 DN (retro-reflectors seen at different angles and
    distances; the brighter ones clip at 255) under a lighting gradient.  Before: exit 3, "0
    usable poses", every row NaN (a mark brighter than the frame's median by 1.5 % was dropped)."""
    d, cam, _truth, _frames = scene
    truth, frames = _ir_frames(cam, 6, 32, lambda r: r.uniform(170.0, 300.0, 6), (0.3, 0.15))
    shots = tmp_path / "shots"
    shots.mkdir()
    for i, img in enumerate(frames):
        cv.write_image(shots / f"shot_{i}.png", img)
    out = tmp_path / "poses.csv"
    argv = ["pose", str(shots), "--camera", str(d / "camera.json"), "--markers"]
    assert main([*argv, str(d / "marks.toml"), "--out", str(out)]) == 0
    assert "6 usable poses" in capsys.readouterr().out
    rows = _read(out)
    _check_rows(rows, truth)
    assert all(r["flag_names"] == "" for r in rows)  # no mark dropped as occluded


def test_the_blobs_file_sets_the_ir_detector(scene, tmp_path: Path, capsys) -> None:
    """``--blobs FILE`` (a ``[blobs]`` table, the keys of a camera source's ``blobs``): marks
    at 80 DN, under the default threshold of 100 DN, give no pose; with ``threshold_dn = 40``
    every frame's pose is right.  A bad key: one line naming the file and the key, exit 2."""
    d, cam, _truth, _frames = scene
    truth, frames = _ir_frames(cam, 3, 33, lambda r: np.full(6, 80.0))
    shots = tmp_path / "dim"
    shots.mkdir()
    for i, img in enumerate(frames):
        cv.write_image(shots / f"dim_{i}.png", img)
    out = tmp_path / "poses.csv"
    argv = ["pose", str(shots), "--camera", str(d / "camera.json"), "--out", str(out)]
    marks = ["--markers", str(d / "marks.toml")]
    assert main([*argv, *marks]) == 3
    assert "3 of 3 frames have no usable pose" in capsys.readouterr().err
    blobs = tmp_path / "blobs.toml"
    blobs.write_text("[blobs]\nthreshold_dn = 40.0\nnotch_tolerance = 0.1\n")
    assert main([*argv, *marks, "--blobs", str(blobs)]) == 0
    _check_rows(_read(out), truth)
    out.unlink()
    for text, key in (
        ("[blobs]\nthreshold = 40.0\n", "blobs.threshold"),
        ("[blobs]\nthreshold_dn = 400.0\n", "blobs.threshold_dn"),
        ("[blobs]\nmin_area_px = 50.0\nmax_area_px = 40.0\n", "blobs.min_area_px"),
        ("[blob]\nthreshold_dn = 40.0\n", "blob"),
    ):
        blobs.write_text(text)
        assert main([*argv, *marks, "--blobs", str(blobs)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "blobs.toml" in err and key in err, err
        assert not out.exists()
    blobs.write_text("[blobs]\nthreshold_dn = 40.0\n")
    aruco = ["--markers", str(ROOT / "data_samples/markers_flat_aruco.toml")]
    assert main([*argv, *aruco, "--blobs", str(blobs)]) == 2
    assert "fiducial layout, not IR marks" in capsys.readouterr().err
