"""ArUco dictionaries from a file (issue 14 section 4), in the FileStorage format OpenCV's
``Dictionary::writeDictionary`` writes and its tutorials read: a layout naming a custom dictionary
file beside it is detected and gives accurate poses; a bad file is one line naming file and key."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cdpr.calibration import cv
from cdpr.calibration.camera_model import camera_from_mapping
from cdpr.calibration.markers import flat_prototype_fiducial_layout
from cdpr.calibration.pose import BAD_FLAGS, pose_error
from cdpr.calibration.render import VirtualCamera
from cdpr.daq.camera_source import FramePoseEstimator
from cdpr.pipelines.cli import main
from cdpr.pipelines.vision_config import layout_toml, load_marker_layout

ROOT = Path(__file__).resolve().parents[1]


def _custom_dictionary(n: int, size: int, rng: np.random.Generator) -> list[str]:
    """n random size x size codes whose Hamming distance, over the four rotations, is >= 5."""
    codes: list[np.ndarray] = []
    while len(codes) < n:
        c = rng.integers(0, 2, (size, size))
        rots = [np.rot90(c, k) for k in range(4)]
        if any(np.sum(rots[k] != rots[0]) < 5 for k in (1, 2, 3)):
            continue
        if all(np.sum(r != o) >= 5 for o in codes for r in rots):
            codes.append(c)
    return ["".join(str(int(b)) for b in c.ravel()) for c in codes]


def _write_dict(path: Path, codes: list[str], size: int) -> None:
    lines = ["%YAML:1.0", "---", f"nmarkers: {len(codes)}", f"markersize: {size}"]
    lines.append("maxCorrectionBits: 1")
    lines += [f'marker_{i}: "{c}"' for i, c in enumerate(codes)]
    path.write_text("\n".join(lines) + "\n")


def test_custom_dictionary_file_beside_the_layout(tmp_path: Path, capsys) -> None:
    rng = np.random.default_rng(3)
    _write_dict(tmp_path / "custom.yml", _custom_dictionary(8, 5, rng), 5)
    text = layout_toml(flat_prototype_fiducial_layout()).replace(
        'dictionary = "DICT_4X4_50"', 'dictionary = "custom.yml"'
    )
    assert 'dictionary = "custom.yml"' in text
    (tmp_path / "layout.toml").write_text(text)
    layout = load_marker_layout(tmp_path / "layout.toml")
    assert layout.dictionary == str(tmp_path / "custom.yml")
    # the markers drawn from the custom dictionary differ from DICT_4X4_50's
    assert not np.array_equal(
        cv.marker_bits_image(layout.dictionary, 0), cv.marker_bits_image("DICT_4X4_50", 0)
    )
    cam = camera_from_mapping(json.loads((ROOT / "data_samples/camera_virtual.json").read_text()))
    vc = VirtualCamera(cam)
    p, R = np.array([0.505, -0.004, 0.362]), np.eye(3)
    img = vc.render_fiducials(layout, p, R, rng)
    est = FramePoseEstimator(cam, layout).estimate(img)
    assert not est.flags & BAD_FLAGS and est.n_points == 24
    e = pose_error(est.position_O_m, est.R_O_P, p, R)
    assert np.linalg.norm(e[:3]) < 2e-4 and np.rad2deg(np.linalg.norm(e[3:])) < 0.05
    # with the predefined dictionary the custom markers are not found
    assert FramePoseEstimator(cam, flat_prototype_fiducial_layout()).estimate(img).n_points < 24

    # a bad dictionary file: one line naming the file and the key, exit 2
    (tmp_path / "custom.yml").write_text(
        '%YAML:1.0\n---\nnmarkers: 2\nmarkersize: 4\nmarker_0: "01"\n'
    )
    cv._DICT_CACHE.clear()
    cv.write_image(tmp_path / "f.png", img)
    argv = [
        "pose",
        str(tmp_path / "f.png"),
        "--camera",
        str(ROOT / "data_samples/camera_virtual.json"),
    ]
    code = main(
        [*argv, "--markers", str(tmp_path / "layout.toml"), "--out", str(tmp_path / "p.csv")]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "custom.yml" in err and "marker_0" in err, err
    assert not (tmp_path / "p.csv").exists()
