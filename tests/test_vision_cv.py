"""OpenCV pin and adapter: the installed version is in the tested range, only calibration/cv.py
imports cv2, and the adapter normalises shapes and conventions."""

from __future__ import annotations

import ast
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from cdpr.analysis.errors import ConfigError
from cdpr.calibration import cv
from cdpr.calibration.camera_model import CameraModel, camera_from_mapping, look_at
from cdpr.calibration.markers import (
    flat_prototype_fiducial_layout,
    flat_prototype_points_layout,
    layout_from_mapping,
)

ROOT = Path(__file__).resolve().parents[1]


def test_installed_opencv_in_pinned_range() -> None:
    import importlib.metadata as md

    v = tuple(int(x) for x in md.version("opencv-python-headless").split(".")[:2])
    assert (4, 9) <= v < (5, 0)
    assert cv.version_tuple()[:2] == v
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "opencv-python-headless>=4.9,<5" in pyproject["project"]["dependencies"]


def test_only_the_adapter_imports_cv2() -> None:
    offenders = []
    for folder in ("analysis", "calibration", "daq", "pipelines", "bench", "scripts", "tests"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path in (ROOT / "calibration" / "cv.py", ROOT / "tests" / "opencv_reference.py"):
                continue  # the adapter, and the tests' independent OpenCV reference
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                    names = [node.module]
                if any(n == "cv2" or n.startswith("cv2.") for n in names):
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []


def test_adapter_shapes_and_pixel_convention() -> None:
    K = np.array([[1000.0, 0, 319.5], [0, 1000.0, 239.5], [0, 0, 1]])
    # a point on the optical axis projects to the principal point (pixel-centre convention)
    uv = cv.project_points([[0.0, 0.0, 2.0]], np.zeros(3), np.zeros(3), K, np.zeros(5))
    assert uv.shape == (1, 2) and np.allclose(uv, [[319.5, 239.5]])
    # ids are (N,), corners (N, 4, 2) on a drawn marker; a marker drawn with pixel blocks has its
    # outer corner at the pixel boundary, i.e. at -0.5 + border in OpenCV coordinates
    img = np.full((200, 200), 255, np.uint8)
    bits = cv.marker_bits_image("DICT_4X4_50", 7)
    img[50:110, 60:120] = np.kron(bits, np.ones((10, 10), np.uint8))
    corners, ids = cv.ArucoDetector("DICT_4X4_50", cv.ArucoDetectorSettings()).detect(img)
    assert ids.shape == (1,) and ids[0] == 7 and corners.shape == (1, 4, 2)
    assert np.allclose(corners[0, 0], [59.5, 49.5], atol=0.3)
    assert np.allclose(corners[0, 2], [119.5, 109.5], atol=0.3)


def test_undistortion_inverts_projection() -> None:
    cam = camera_from_mapping(json.loads((ROOT / "data_samples/camera_virtual.json").read_text()))
    px = np.random.default_rng(0).uniform([0, 0], [1279, 1023], (500, 2))
    xn = cv.undistort_to_normalized(px, cam.K, cam.dist)
    back = cv.project_points(np.c_[xn, np.ones(len(xn))], np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.abs(back - px).max() < 1e-8


def test_camera_model_json_yaml_round_trip(tmp_path: Path) -> None:
    R, c = look_at([0.2, -0.35, 1.24], [0.5, 0.0, 0.36])
    cam = CameraModel(
        np.array([[2000.0, 0, 640], [0, 2001, 512], [0, 0, 1]]),
        [-0.1, 0.05, 0, 0, 0],
        (1280, 1024),
        R,
        c,
    )
    again = camera_from_mapping(json.loads(cam.to_json()))
    assert again.id == cam.id and np.allclose(again.R_O_C, R)
    y = tmp_path / "cam.yaml"
    cv.write_filestorage_yaml(y, cam.opencv_entries())
    back = cv.read_filestorage_yaml(
        y, ["camera_matrix", "distortion_coefficients", "R_C_O", "t_C_O_m", "camera_id"]
    )
    assert np.allclose(back["camera_matrix"], cam.K)
    assert np.allclose(back["R_C_O"] @ c + back["t_C_O_m"].ravel(), 0)  # optical centre maps to 0
    assert back["camera_id"] == cam.id
    # look_at: the target is on the optical axis
    t_C = cam.R_C_O @ (np.array([0.5, 0.0, 0.36]) - c)
    assert abs(t_C[0]) < 1e-12 and abs(t_C[1]) < 1e-12 and t_C[2] > 0


def test_camera_errors_name_the_key() -> None:
    with pytest.raises(ConfigError, match="cam.json: dist_coeffs"):
        camera_from_mapping(
            {"camera_matrix": np.eye(3).tolist(), "dist_coeffs": [1, 2], "image_size_px": [10, 10]},
            "cam.json",
        )
    with pytest.raises(ConfigError, match="layout.toml: point\\[1\\].label: duplicate"):
        layout_from_mapping(
            {
                "kind": "points",
                "point": [{"label": "a", "center_m": [0, 0, 0], "radius_m": 0.01}] * 4,
            },
            "layout.toml",
        )


def test_data_sample_layouts_match_the_builtin_ones() -> None:
    from cdpr.pipelines.vision_config import load_marker_layout

    for name, ref in (
        ("markers_flat_aruco.toml", flat_prototype_fiducial_layout()),
        ("markers_flat_ir6.toml", flat_prototype_points_layout()),
    ):
        lay = load_marker_layout(ROOT / "data_samples" / name)
        if ref.kind == "fiducial":
            assert np.allclose(lay.fiducial_corners_m, ref.fiducial_corners_m)
        else:
            assert (
                np.allclose(lay.point_centers_m, ref.point_centers_m) and lay.labels == ref.labels
            )


def test_fiducial_corners_follow_opencv_order() -> None:
    lay = flat_prototype_fiducial_layout()
    c = lay.fiducials[0].corners_m
    # TL, TR, BR, BL seen from the marker's face (normal +z): x right, y up
    assert c[1, 0] > c[0, 0] and c[0, 1] > c[3, 1] and np.isclose(np.linalg.norm(c[0] - c[1]), 0.03)


def test_renderer_half_pixel_convention() -> None:
    """A disk rendered without noise lands where cv2.projectPoints puts its centre (pixel centres at
    integer coordinates): a half-pixel slip would show up as 0.5 px."""
    from cdpr.calibration.detect import detect_blobs
    from cdpr.calibration.render import RenderSettings, VirtualCamera

    cam = camera_from_mapping(json.loads((ROOT / "data_samples/camera_virtual.json").read_text()))
    layout = flat_prototype_points_layout()
    vc = VirtualCamera(cam, RenderSettings(noise_sigma_dn=0.0, supersample=6))
    p, R = np.array([0.5, 0.0, 0.36]), np.eye(3)
    blobs = detect_blobs(vc.render_points(layout, p, R, np.random.default_rng(0)))
    truth = vc.project_layout(layout, p, R)
    d = np.linalg.norm(blobs[:, None, :2] - truth[None], axis=2).min(axis=0)
    assert len(blobs) == 6 and d.max() < 0.03
