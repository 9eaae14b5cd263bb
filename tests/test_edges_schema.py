"""The schema library (pydantic) and its one error formatter: file, key, problem.

Expected messages are written by hand from the rig-file layout (docs) and the schema's ranges.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from cdpr.analysis.errors import ConfigError
from cdpr.daq.aero_model import AeroModel, aero_from_mapping
from cdpr.daq.schema import load_rig, rig_from_mapping

ROOT = Path(__file__).resolve().parents[1]
A0 = "anchor_O_m = [0.0, 0.255, 0.67]"
RIG_TEXT = (ROOT / "data_samples" / "flat_optimum.toml").read_text()


def _error(text: str, tmp_path: Path) -> str:
    p = tmp_path / "r.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_rig(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: ") and "\n" not in msg
    return msg.removeprefix(f"{p}: ")


@pytest.mark.parametrize(
    "old,new,expected",
    [
        ("mass_kg = 0.64", "mass_kg = nan", "platform.mass_kg: expected a finite number, got nan"),
        ("mass_kg = 0.64", 'mass_kg = "0.64"', "platform.mass_kg: expected a valid number, got '0.64'"),
        ("mass_kg = 0.64", "mass_kg = true", "platform.mass_kg: expected a valid number, got True"),
        ("mass_kg = 0.64", "mass_kg = -1", "platform.mass_kg: must be > 0.0, got -1"),
        ("mass_kg = 0.64", "mass_kg = 1e300", "platform.mass_kg: must be <= 1000000.0"),
        ("mass_kg = 0.64", "mass = 0.64", "platform.mass_kg: missing"),
        ("t_min_N = 35.0", "t_min_N = -1.0", "cables[0].t_min_N: must be >= 0.0, got -1.0"),
        (A0, "anchor_O_m = [0.0, 0.255]", "cables[0].anchor_O_m: expected at least 3 numbers, got 2"),
        (A0, "anchor_O_m = [0.0, 0.255, inf]", "cables[0].anchor_O_m[2]: expected a finite number"),
        (A0, A0 + "\ncolour = 1", "cables[0].colour: unknown key"),
    ],
)  # fmt: skip
def test_rig_errors_name_the_key_and_the_problem(tmp_path, old, new, expected):
    assert old in RIG_TEXT
    assert _error(RIG_TEXT.replace(old, new, 1), tmp_path).startswith(expected)


def test_rig_invariants_still_checked_after_the_schema():
    d = tomllib.loads(RIG_TEXT)
    d["cables"][1]["name"] = d["cables"][0]["name"]
    with pytest.raises(ConfigError, match="cables.name: cable names must be unique"):
        rig_from_mapping(d, "x.toml")


def test_rig_round_trip_keeps_every_value():
    rig = load_rig(ROOT / "data_samples" / "flat_optimum.toml")
    d = tomllib.loads(RIG_TEXT)
    assert rig.mass_kg == d["platform"]["mass_kg"]
    assert rig.anchors_O_m.tolist() == [c["anchor_O_m"] for c in d["cables"]]
    assert rig.cable_names == tuple(c["name"] for c in d["cables"])


def test_aero_section():
    assert aero_from_mapping({}, "s.toml") == AeroModel()
    m = aero_from_mapping({"b_ref_m": 0.5, "mrp_P_m": [0.0, 0.0, 0.01]}, "s.toml")
    assert m.s_ref_m2 == 0.5 * AeroModel.c_ref_m and m.mrp_P_m == (0.0, 0.0, 0.01)
    cases = [
        ({"c_ref_m": 1e300}, "s.toml: aero.c_ref_m: must be <= 100.0"),
        ({"CL_alpha": "3.5"}, "s.toml: aero.CL_alpha: expected a valid number, got '3.5'"),
        ({"static_pressure_Pa": 0}, "s.toml: aero.static_pressure_Pa: must be > 0.0, got 0"),
        ({"mrp_P_m": [0, 0]}, "s.toml: aero.mrp_P_m: expected at least 3 numbers, got 2"),
        ({"spin": 1.0}, "s.toml: aero.spin: unknown key"),
    ]
    for data, expected in cases:
        with pytest.raises(ConfigError) as info:
            aero_from_mapping(data, "s.toml")
        assert str(info.value).startswith(expected), str(info.value)


CHARUCO = (ROOT / "data_samples" / "board_charuco.toml").read_text()


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("squares_x = 12", "squares_x = 2", "board.squares_x: must be >= 3, got 2"),
        ("squares_x = 12", "squares_x = 12.0", "board.squares_x: expected a valid integer, got 12.0"),
        ("marker_m = 0.022", "marker_m = 0.022\nmarker_mm = 22", "board.marker_mm: unknown key"),
        ("marker_m = 0.022", "", "board.marker_m: missing"),
        ("marker_m = 0.022", "marker_m = 0.04", "board.marker_m: must be smaller than square_m"),
        ('type = "charuco"', 'type = "dots"', "board.type: expected one of 'charuco', 'chessboard'"),
        ('dictionary = "DICT_5X5_100"', 'dictionary = "5X5"', "board.dictionary: expected a name"),
        ("min_views = 8", "min_views = 0", "calibration.min_views: must be >= 1, got 0"),
        ("fix_k3 = true", "fix_k3 = 1", "calibration.fix_k3: expected a valid boolean, got 1"),
        ("position_m = [0.44, 0.275, 0.0]", "position_m = [0.4, 0.2]", "pose_O.position_m: expected at"),
        ("[pose_O]", "[pose]", "pose: unknown key"),
    ],
)  # fmt: skip
def test_board_file_errors(tmp_path, old, new, expected):
    from cdpr.pipelines.vision_config import load_board

    assert old in CHARUCO
    p = tmp_path / "b.toml"
    p.write_text(CHARUCO.replace(old, new))
    with pytest.raises(ConfigError) as info:
        load_board(p)
    assert str(info.value).startswith(f"{p}: {expected}"), str(info.value)


def test_board_file_of_each_type(tmp_path):
    from cdpr.pipelines.vision_config import load_board

    p = tmp_path / "c.toml"
    p.write_text('[board]\ntype = "circles"\ncircles_x = 4\ncircles_y = 11\nspacing_m = 0.015\n')
    spec, limits = load_board(p)
    assert (spec.type, spec.circles_x, spec.circles_y, spec.spacing_m) == ("circles", 4, 11, 0.015)
    assert spec.asymmetric is False and limits.min_views == 8
    p.write_text(p.read_text() + "[pose_O]\nposition_m = [0, 0, 0]\neuler_rad = [0, 0, 0]\n")
    with pytest.raises(ConfigError, match="pose_O: a circles has no marks"):
        load_board(p)
    spec, limits = load_board(ROOT / "data_samples" / "board_chessboard.toml")
    assert spec.type == "chessboard" and spec.detector == "classic" and limits.min_corners == 54


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("t_max_N = 300.0", "t_max_N = 300.0\ndiameter_m = 0.0", "cables[0].diameter_m: must be > 0.0"),
        ("t_max_N = 300.0", "t_max_N = 300.0\nEA_N = -1.0", "cables[0].EA_N: must be > 0.0, got -1.0"),
        ("t_max_N = 300.0", "t_max_N = 300.0\ndrag_coefficient = nan", "cables[0].drag_coefficient:"),
        ("mass_kg = 0.64", "mass_kg = 0.64\nwindage_drag_area_m2 = -1", "platform.windage_drag_area_m2:"),
    ],
)  # fmt: skip
def test_rig_windage_keys_ranges(tmp_path, old, new, expected):
    assert old in RIG_TEXT
    assert _error(RIG_TEXT.replace(old, new, 1), tmp_path).startswith(expected)


def test_rig_windage_keys_reach_the_rig(tmp_path):
    """The optional cable windage / stretch keys arrive per cable, the defaults elsewhere."""
    from cdpr.analysis.rig import DEFAULT_CABLE_DIAMETER_M

    text = RIG_TEXT.replace("t_max_N = 300.0", "t_max_N = 300.0\ndiameter_m = 0.002", 1)
    text = text.replace("mass_kg = 0.64", "mass_kg = 0.64\nwindage_drag_area_m2 = 0.01")
    p = tmp_path / "w.toml"
    p.write_text(text)
    rig = load_rig(p)
    assert rig.cable_diameter_m[0] == 0.002 and rig.platform_drag_area_m2 == 0.01
    assert (rig.cable_diameter_m[1:] == DEFAULT_CABLE_DIAMETER_M).all()


CAMERA = (ROOT / "data_samples" / "camera_virtual.json").read_text()


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ('"name"', '"nmae"', "nmae: unknown key"),
        ("1280,", "1280.5,", "image_size_px[0]: expected a valid integer, got 1280.5"),
        ("1280,", "0,", "image_size_px[0]: must be >= 1, got 0"),
        ("2000.0,", "1e300,", "camera_matrix[0][0]: must be <= 10000000.0"),
        ("-0.12,", '"k1",', "dist_coeffs[0]: expected a valid number, got 'k1'"),
        ("-0.12,", "-0.12, 1.0,", "dist_coeffs: expected 4, 5 or 8 numbers, got 6"),
        ("-0.12,", "1, 2, 3, 4, 5,", "dist_coeffs: expected at most 8 numbers, got 9"),
        ("0.7592566023652966,", "1.5,", "extrinsics.R_O_C[0][0]: must be <= 1.0"),
        ("0.7592566023652966,", "0.75,", "extrinsics.R_O_C: expected a rotation matrix"),
        ('"opencv-pinhole"', '"fisheye"', "model: expected 'opencv-pinhole', got 'fisheye'"),
        ("0.2,", "NaN,", "NaN is not a JSON value"),
    ],
)
def test_camera_file_errors(tmp_path, old, new, expected):
    from cdpr.pipelines.vision_config import load_camera

    assert old in CAMERA
    p = tmp_path / "cam.json"
    p.write_text(CAMERA.replace(old, new, 1))
    with pytest.raises(ConfigError) as info:
        load_camera(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: ") and expected in msg and "\n" not in msg, msg


def test_camera_file_keeps_free_extrinsics_information():
    from cdpr.pipelines.vision_config import load_camera

    cam = load_camera(ROOT / "data_samples" / "camera_virtual.json")
    assert cam.extrinsics_info == {
        "method": "design value (virtual rig)",
        "looks_at_O_m": [0.5, 0.0, 0.36],
    }
    assert cam.image_size_px == (1280, 1024) and cam.K[0, 0] == 2000.0 and cam.dist[0] == -0.12


IR6 = (ROOT / "data_samples" / "markers_flat_ir6.toml").read_text()
ARUCO = (ROOT / "data_samples" / "markers_flat_aruco.toml").read_text()


@pytest.mark.parametrize(
    ("text", "old", "new", "expected"),
    [
        (IR6, "radius_m = 0.004", "radius_m = -0.004", "point[0].radius_m: must be > 0.0, got -0.004"),
        (IR6, 'label = "nose"', 'label = ""', "point[0].label: expected at least 1 character, got ''"),
        (IR6, 'label = "nose"', 'label = "nose"\ncolour = "red"', "point[0].colour: unknown key"),
        (IR6, 'kind = "points"', 'kind = "points"\ndictionary = "DICT_4X4_50"', "dictionary: not a key"),
        (IR6, 'frame = "P"', 'frame = "Q"', "frame: expected 'P' or 'O', got 'Q'"),
        (ARUCO, "id = 0", "id = -1", "marker[0].id: must be >= 0, got -1"),
        (ARUCO, "id = 0", "id = 1", "marker[1].id: duplicate marker id 1"),
        (ARUCO, 'dictionary = "DICT_4X4_50"', 'dictionary = "4x4"', "dictionary: expected a name like"),
        (ARUCO, "quiet_zone_cells = 1.0", "quiet_zone_cells = -1.0", "quiet_zone_cells: must be >= 0.0"),
    ],
)  # fmt: skip
def test_marker_layout_errors(tmp_path, text, old, new, expected):
    from cdpr.pipelines.vision_config import load_marker_layout

    assert old in text
    p = tmp_path / "m.toml"
    p.write_text(text.replace(old, new, 1))
    with pytest.raises(ConfigError) as info:
        load_marker_layout(p)
    assert str(info.value).startswith(f"{p}: {expected}"), str(info.value)


TUNNEL = (ROOT / "data_samples" / "tunnel.toml").read_text()


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("startup_timeout_s = 5.0", "startup_timeout_s = 0.0", "recorder.startup_timeout_s: must be >"),
        ("stall_timeout_s = 2.0", "stall_timeout_s = 1e300", "recorder.stall_timeout_s: must be <="),
        ("stall_timeout_s = 2.0", "stall_timeout_s = 2.0\nnice = 20", "recorder.nice: must be <= 19"),
        ("stall_timeout_s = 2.0", "stall_timeout_s = 2.0\nnice = -3.5", "recorder.nice: expected a"),
        ('compression = "zstd"', 'compression = "gzip"', "recorder.compression: expected 'zstd'"),
        ("chunk_size_kib = 256", "chunk_size_kib = 0", "recorder.chunk_size_kib: must be >= 1"),
        ('operator = ""', 'operator = ""\nshift = 2', "run.shift: unknown key"),
        ('calibrations = ["loadcell.dbc"]', 'calibrations = "loadcell.dbc"', "run.calibrations: expected"),
        ('calibrations = ["loadcell.dbc"]', 'calibrations = ["nope.dbc"]', "run.calibrations[0]: file not"),
    ],
)  # fmt: skip
def test_daq_config_run_and_recorder_errors(tmp_path, old, new, expected):
    from cdpr.pipelines.daq_config import load_daq_config

    assert old in TUNNEL
    for f in ("flat_optimum.toml", "loadcell.dbc"):
        (tmp_path / f).symlink_to(ROOT / "data_samples" / f)
    p = tmp_path / "t.toml"
    p.write_text(TUNNEL.replace(old, new, 1))
    with pytest.raises(ConfigError) as info:
        load_daq_config(p)
    assert str(info.value).startswith(f"{p}: {expected}"), str(info.value)


def test_daq_config_recorder_values_arrive():
    from cdpr.pipelines.daq_config import load_daq_config

    c = load_daq_config(ROOT / "data_samples" / "tunnel.toml")
    assert (c.label, c.chunk_size, c.flush_interval_s, c.compression) == (
        "tp01",
        256 * 1024,
        0.25,
        "zstd",
    )
    assert (c.queue_readings, c.startup_timeout_s, c.stall_timeout_s, c.nice) == (
        200_000,
        5.0,
        2.0,
        -10,
    )
    assert c.rig == ROOT / "data_samples" / "flat_optimum.toml"


def test_board_type_that_is_not_a_string(tmp_path):
    """Found by the fuzzer: ``type = []`` raised a TypeError."""
    from cdpr.pipelines.vision_config import load_board

    p = tmp_path / "b.toml"
    p.write_text(CHARUCO.replace('type = "charuco"', "type = []"))
    with pytest.raises(ConfigError, match=r"board\.type: expected one of 'charuco'.*got \[\]"):
        load_board(p)
