"""Intrinsics from real ChArUco photographs (issue 19, Material): the four photos of OpenCV's ArUco
calibration tutorial (tests/data/charuco/README.md: source, licence, how they were stored).  The
reference is OpenCV's own ChArUco calibration of the same stored files, computed here by
tests/opencv_reference.py (cv2 directly: CharucoDetector, matchImagePoints,
calibrateCameraExtended); ours is ``cdpr calibrate camera`` with the tutorial's board."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from opencv_reference import charuco_calibration

from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests/data/charuco"
PHOTOS = sorted(DATA.glob("img_*.jpg"))


def test_charuco_photos_match_opencv_within_its_sigma(tmp_path: Path, capsys) -> None:
    assert len(PHOTOS) == 4
    out = tmp_path / "camera.json"
    argv = ["calibrate", "camera", str(DATA), "--board", str(DATA / "board.toml")]
    assert main([*argv, "--out", str(out)]) == 0
    ours = json.loads(out.read_text())
    cal = ours["calibration"]
    K = np.array(ours["camera_matrix"])
    got = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    assert cal["n_views"] == 4 and cal["rejected"] == {}
    ref = charuco_calibration(PHOTOS, (5, 7), 0.04, 0.02, "DICT_6X6_250")
    ours_pv = [cal["per_view_rms_px"][str(p)] for p in PHOTOS]
    print("\nview      OpenCV  ours (px)")
    for p, a, b in zip(PHOTOS, ref["per_view_rms_px"], ours_pv, strict=True):
        print(f"{p.name:10s} {a:.3f}  {b:.3f}")
    for k in ("fx", "fy", "cx", "cy"):
        print(
            f"{k}: OpenCV {ref[k]:.2f} +- {ref['std'][k]:.2f}, ours {got[k]:.2f} +- "
            f"{cal['std'][k]:.2f} ({(got[k] - ref[k]) / ref['std'][k]:+.2f} of OpenCV's sigma)"
        )
    print(f"RMS: OpenCV {ref['rms_px']:.4f}, ours {cal['rms_px']:.4f}")
    assert cal["n_corners"] == sum(ref["n_corners"]) == 4 * 24  # every inner corner, both
    # within OpenCV's own sigma, and our sigma of the same size (four views: ~3 % on f)
    for k in ("fx", "fy", "cx", "cy"):
        assert abs(got[k] - ref[k]) <= ref["std"][k], k
        assert 0.5 * ref["std"][k] <= cal["std"][k] <= 2.0 * ref["std"][k], k
    assert cal["rms_px"] <= ref["rms_px"] + 0.005
    assert all(b <= a + 0.03 for a, b in zip(ref["per_view_rms_px"], ours_pv, strict=True))
