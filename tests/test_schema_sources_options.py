# ruff: noqa: E501  (the tables of bad cases read one case a line)
"""The daq config's ``[sources.<name>]`` tables (one schema per driver kind) and the sensitivity
options on the schema library: good files load to the values written here by hand; bad files
give exit 2 through ``cdpr`` with one line naming the file and the key, before any device is
touched and with nothing written."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from cdpr.pipelines.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
TUNNEL = (SAMPLES / "tunnel.toml").read_text()

# one source of every kind the config can name (serial ports and the CAN log need not exist to
# load: a port is opened when the recording starts, the log is read then)
ALL_KINDS = """
[run]
label = "kinds"

[sources.cells]
kind = "can_loadcell"
interface = "virtual"
channel = "schema-test"
bitrate = 500000
rate_hz = 100
cables = ["a", "b", "c", "d", "e", "f", "g", "h"]
offset_counts = [0, 1, 2, 3, 4, 5, 6, 7]
gain_N_per_count = 2.5e-5
max_bus_load = 0.8
bus_options = { receive_own_messages = false }
reopen_backoff_s = [0.2, 4]

[sources.lc]
kind = "serial_loadcell"
port = "/dev/ttyUSB7"
baudrate = 921600
rate_hz = 250.0
cables = ["p", "q"]
gain_N_per_count = [1e-4, 2e-4]

[sources.tun]
kind = "serial_tunnel"
port = "/dev/ttyUSB8"
baudrate = 57600
rate_hz = 5

[sources.hand]
kind = "manual_tunnel"
airspeed_mps = 25.51
temperature_K = 290.0
label = "tp2"

[sources.log]
kind = "can_replay"
path = "x.log"
speed = "max"
batch = 500
decode = false

[sources.cam]
kind = "camera"
camera = "camera_virtual.json"
layout = "markers_flat_aruco.toml"
folder = "frames"
fps = 12.5
image_every = 4
image_format = "png"
jpeg_quality = 70
sigma_px = 0.3
track = false
"""


def _folder(tmp_path: Path, text: str) -> Path:
    """``text`` as ``c.toml`` in ``tmp_path`` beside the files it names."""
    for f in (
        "loadcell.dbc",
        "flat_optimum.toml",
        "camera_virtual.json",
        "markers_flat_aruco.toml",
    ):
        shutil.copy(SAMPLES / f, tmp_path / f)
    (tmp_path / "x.log").write_text("")
    (tmp_path / "frames").mkdir(exist_ok=True)
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


def test_sample_tunnel_config_sources_arrive_unchanged():
    from cdpr.pipelines.daq_config import build_sources, load_daq_config

    cfg = load_daq_config(SAMPLES / "tunnel.toml")
    lc, tun = cfg.sources
    assert (lc.name, lc.kind, tun.name, tun.kind) == (
        "loadcells",
        "can_loadcell",
        "tunnel",
        "manual_tunnel",
    )
    assert lc.settings == {
        "interface": "virtual",
        "channel": "cdpr-tunnel",
        "bitrate": 1000000,
        "rate_hz": 200.0,
        "dbc": str(SAMPLES / "loadcell.dbc"),
        "cables": [
            "front_left_top",
            "front_left_bottom",
            "front_right_top",
            "front_right_bottom",
            "back_left_top",
            "back_left_bottom",
            "back_right_top",
            "back_right_bottom",
        ],
        "offset_counts": 0.0,
        "gain_N_per_count": 5.0e-5,
    }
    assert tun.settings == {
        "airspeed_mps": 17.27,
        "static_pressure_Pa": 101325.0,
        "temperature_K": 293.15,
        "rate_hz": 1.0,
        "label": "tp01",
    }
    src = {s.name: s.settings() for s in build_sources(cfg)}
    assert src["loadcells"]["gain_N_per_count"] == [5.0e-5] * 8
    assert src["tunnel"]["airspeed_mps"] == 17.27


def test_every_kind_loads_and_builds_with_its_values(tmp_path):
    from cdpr.pipelines.daq_config import build_sources, load_daq_config

    p = _folder(tmp_path, ALL_KINDS)
    cfg = load_daq_config(p)
    by = {s.name: s for s in cfg.sources}
    assert [s.kind for s in cfg.sources] == [
        "can_loadcell",
        "serial_loadcell",
        "serial_tunnel",
        "manual_tunnel",
        "can_replay",
        "camera",
    ]
    assert by["cells"].settings["reopen_backoff_s"] == [0.2, 4.0]
    assert by["cells"].settings["offset_counts"] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    assert by["log"].settings["path"] == str(tmp_path / "x.log")
    assert by["cam"].settings["folder"] == str(tmp_path / "frames")
    assert by["cam"].settings["camera"] == str(tmp_path / "camera_virtual.json")
    s = {x.name: x for x in build_sources(cfg)}  # built, nothing opened
    assert not any(x.is_open for x in s.values())
    cells = s["cells"].settings()
    assert (cells["bitrate"], cells["rate_hz"], cells["max_bus_load"]) == (500_000, 100.0, 0.8)
    assert cells["bus_options"] == {"receive_own_messages": False}
    assert cells["offset_counts"] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    assert s["cells"].backoff == (0.2, 4.0)
    assert s["lc"].settings() == {
        "port": "/dev/ttyUSB7",
        "baudrate": 921600,
        "rate_hz": 250.0,
        "cables": ["p", "q"],
        "offset_counts": [0.0, 0.0],
        "gain_N_per_count": [1e-4, 2e-4],
    }
    assert s["tun"].settings() == {
        "port": "/dev/ttyUSB8",
        "baudrate": 57600,
        "rate_hz": 5.0,
        "test_points": False,
    }
    assert s["hand"].settings() == {
        "airspeed_mps": 25.51,
        "static_pressure_Pa": 101325.0,
        "temperature_K": 290.0,
        "rate_hz": 1.0,
        "label": "tp2",
    }
    log = s["log"].settings()
    assert (log["speed"], log["time_scale"], log["timestamps"]) == ("max", 1.0, "log")
    assert s["log"].batch == 500 and s["log"].decoder is None
    cam = s["cam"].settings()
    assert (cam["fps"], cam["image_every"], cam["image_format"], cam["sigma_px"]) == (
        12.5,
        4,
        "png",
        0.3,
    )
    assert (cam["track"], cam["realtime"], s["cam"].jpeg_quality) == (False, True, 70)


# (old, new, key, problem): each edits ALL_KINDS once
SOURCE_CASES = [
    ('channel = "schema-test"', 'channel = "schema-test"\ncolour = 1', "sources.cells.colour", "unknown key"),
    ("bitrate = 500000", 'bitrate = "500k"', "sources.cells.bitrate", "expected 10000, 20000"),
    ("bitrate = 500000", "bitrate = 300000", "sources.cells.bitrate", "or 1000000, got 300000"),
    ("rate_hz = 100\n", "rate_hz = 0\n", "sources.cells.rate_hz", "expected a finite number > 0, got 0"),
    ("rate_hz = 100\n", "rate_hz = -inf\n", "sources.cells.rate_hz", "finite number > 0"),
    ('interface = "virtual"\n', "", "sources.cells.interface", "missing"),
    ("max_bus_load = 0.8", "max_bus_load = 1.5", "sources.cells.max_bus_load", "must be <= 1.0"),
    ("reopen_backoff_s = [0.2, 4]", "reopen_backoff_s = [0.2]", "sources.cells.reopen_backoff_s", "expected at least 2"),
    ("reopen_backoff_s = [0.2, 4]", "reopen_backoff_s = [0.0, 4]", "sources.cells.reopen_backoff_s[0]", "must be > 0.0"),
    ("gain_N_per_count = 2.5e-5", 'gain_N_per_count = "x"', "sources.cells.gain_N_per_count", "expected a valid number or a valid list"),
    ('bus_options = { receive_own_messages = false }', "bus_options = 3", "sources.cells.bus_options", "expected a table"),
    ('port = "/dev/ttyUSB7"', 'port = ""', "sources.lc.port", "expected at least 1 character"),
    ('port = "/dev/ttyUSB7"', "port = 7", "sources.lc.port", "expected a valid string"),
    ("baudrate = 921600", "baudrate = 0", "sources.lc.baudrate", "must be > 0"),
    ('cables = ["p", "q"]', 'cables = ["p", 2]', "sources.lc.cables[1]", "expected a valid string"),
    ('port = "/dev/ttyUSB8"\n', "", "sources.tun.port", "missing"),
    ("rate_hz = 5\n", 'rate_hz = "fast"\n', "sources.tun.rate_hz", "expected a number, got 'fast'"),
    ("airspeed_mps = 25.51", "", "sources.hand.airspeed_mps", "missing"),
    ("airspeed_mps = 25.51", "airspeed_mps = -3.0", "sources.hand.airspeed_mps", "must be >= 0.0"),
    ("temperature_K = 290.0", "temperature_K = nan", "sources.hand.temperature_K", "expected a finite number"),
    ('label = "tp2"', "label = 2", "sources.hand.label", "expected a valid string"),
    ('speed = "max"', 'speed = "fast"', "sources.log.speed", "expected 'recorded' or 'max'"),
    ("batch = 500", "batch = 0", "sources.log.batch", "must be >= 1"),
    ("batch = 500", "batch = 1.5", "sources.log.batch", "expected a valid integer"),
    ('image_format = "png"', 'image_format = "gif"', "sources.cam.image_format", "expected 'jpeg' or 'png'"),
    ("jpeg_quality = 70", "jpeg_quality = 101", "sources.cam.jpeg_quality", "must be <= 100"),
    ("fps = 12.5", "fps = -1.0", "sources.cam.fps", "must be >= 0.0"),
    ("track = false", 'track = "no"', "sources.cam.track", "expected a valid boolean"),
    ('kind = "camera"', 'kind = "webcam"', "sources.cam.kind", "unknown driver 'webcam'"),
    ('kind = "camera"\n', "", "sources.cam.kind", "missing driver name"),
]  # fmt: skip


@pytest.mark.parametrize(("old", "new", "key", "problem"), SOURCE_CASES)
def test_bad_source_settings_exit_2_one_line_before_any_device(
    tmp_path, capsys, monkeypatch, old, new, key, problem
):
    import can
    import serial

    def touched(*a, **k):
        raise AssertionError("a device was touched")

    monkeypatch.setattr(can, "Bus", touched)
    monkeypatch.setattr(serial, "serial_for_url", touched)
    assert old in ALL_KINDS
    p = _folder(tmp_path, ALL_KINDS.replace(old, new, 1))
    out = tmp_path / "runs"
    capsys.readouterr()
    code = main(["record", "--config", str(p), "--out", str(out), "--duration", "1", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert f"{p}: {key}: " in err[0] and problem in err[0], err[0]
    assert not out.exists()


def test_drivers_built_by_code_are_checked_by_the_same_schema():
    """``create_source`` (the virtual rig, scripts) goes through the kind's schema too."""
    from cdpr.analysis.errors import ConfigError
    from cdpr.daq.source import create_source

    with pytest.raises(ConfigError) as e:
        create_source("serial_tunnel", "t", {"port": "/dev/null", "rate_hz": (1, 2)}, "s.toml")
    assert str(e.value) == "s.toml: sources.t.rate_hz: expected a number, got [1, 2]"
    with pytest.raises(ConfigError) as e:
        create_source("manual_tunnel", "m", {"airspeed_mps": 3.0, "speed": 1}, "s.toml")
    assert str(e.value) == "s.toml: sources.m.speed: unknown key"


def test_set_point_is_checked_by_the_tunnel_point_schema():
    from cdpr.analysis.errors import ConfigError
    from cdpr.daq.source import create_source

    src = create_source("manual_tunnel", "m", {"airspeed_mps": 3.0}, "s.toml")
    src.set_point(5.0, temperature_K=300)
    assert src.point == (5.0, 101325.0, 300.0)
    with pytest.raises(ConfigError) as e:
        src.set_point(-1.0)
    assert str(e.value) == "<set_point>: sources.m.airspeed_mps: must be >= 0.0, got -1.0"


# --- sensitivity options ---------------------------------------------------------------------

SENS_ALL = """
[cubic]
L_m = 2.5
layout = "cube"
k1_values = [0.2, 0.3]
k2_values = [0.1, 0.15]
k3_values = [0.05]
forces_N = [20, 40.5]
baseline_k = [0.2, 0.1, 0.05]
Z_values_m = [0.5, 0.7]
deflection_values_m = [-0.1, 0.0, 0.1]
methods = ["exact"]

[flat]
t_max_N = 250
K21_values = [51, 56]
X_values_m = [0.5, 0.6]
baseline = [56, 28, 0.7, 0.6]
methods = ["penalty"]
full_grid = false

[aero]
speeds_mps = [10, 20.5]
rho_kgpm3 = 1.2
coefficients = [0.1, 0.0, 0.4, 0.0, -0.04, 0.0]

[study]
sigma_T_N = 0.5
margin_method = "penalty"
near_singular_condition = 500
EA_N = 9.0e4
"""


def test_sensitivity_options_load_to_the_values_written():
    import tomllib

    from cdpr.pipelines.sensitivity_options import options_from_mapping

    o = options_from_mapping(tomllib.loads(SENS_ALL), "s.toml")
    c, f, a, s = o.cubic, o.flat, o.aero, o.study
    assert (c.L_m, c.W_m, c.H_m, c.mass_kg, c.t_min_N, c.t_max_N) == (
        2.5,
        1.2,
        1.4,
        5.0,
        35.0,
        1000.0,
    )
    assert (c.layout, c.k1_values, c.k2_values, c.k3_values) == (
        "cube",
        (0.2, 0.3),
        (0.1, 0.15),
        (0.05,),
    )
    assert (c.forces_N, c.baseline_k, c.Z_values_m) == ((20.0, 40.5), (0.2, 0.1, 0.05), (0.5, 0.7))
    assert (c.deflection_values_m, c.methods) == ((-0.1, 0.0, 0.1), ("exact",))
    assert isinstance(c.forces_N[0], float) and isinstance(f.t_max_N, float)
    assert (f.L_m, f.l_m, f.t_min_N, f.t_max_N, f.K21_values) == (
        1.0,
        0.03,
        35.0,
        250.0,
        (51.0, 56.0),
    )
    assert (f.X_values_m, f.baseline, f.methods, f.full_grid) == (
        (0.5, 0.6),
        (56.0, 28.0, 0.7, 0.6),
        ("penalty",),
        False,
    )
    assert f.K22_values == (25.0, 28.0, 31.0, 34.0, 37.0, 40.0, 43.0, 46.0, 49.0, 52.0, 55.0)
    assert (a.speeds_mps, a.max_speed_mps, a.rho_kgpm3) == ((10.0, 20.5), 51.0, 1.2)
    assert a.coefficients == (0.1, 0.0, 0.4, 0.0, -0.04, 0.0)
    assert (s.sigma_T_N, s.margin_method, s.near_singular_condition, s.EA_N) == (
        0.5,
        "penalty",
        500.0,
        9.0e4,
    )


def test_sensitivity_defaults_pass_their_own_schema():
    from cdpr.pipelines.sensitivity_options import (
        StudyOptions,
        options_from_mapping,
        validate_options,
    )

    assert options_from_mapping({}) == StudyOptions()
    validate_options(StudyOptions())


# (old, new, key, problem): each edits SENS_ALL once
SENS_CASES = [
    ("EA_N = 9.0e4", "EA_N = 9.0e4\nE_Pa = 2e11", "study.E_Pa", "unknown key"),
    ("[aero]", "[wind]\nspeed = 1\n[aero]", "wind", "unknown key"),
    ("EA_N = 9.0e4", "EA_N = -1.0", "study.EA_N", "must be > 0.0, got -1.0"),
    ("EA_N = 9.0e4", 'EA_N = "7e4"', "study.EA_N", "expected a valid number, got '7e4'"),
    ("EA_N = 9.0e4", "EA_N = nan", "study.EA_N", "expected a finite number"),
    ("EA_N = 9.0e4", "EA_N = 1e300", "study.EA_N", "must be <= 1000000000000.0"),
    ("sigma_T_N = 0.5", "sigma_T_N = -0.1", "study.sigma_T_N", "must be >= 0.0"),
    ("near_singular_condition = 500", "near_singular_condition = 1", "study.near_singular_condition", "must be > 1.0"),
    ('margin_method = "penalty"', 'margin_method = "best"', "study.margin_method", "expected 'closed-form'"),
    ("L_m = 2.5", "L_m = 0", "cubic.L_m", "must be > 0.0, got 0"),
    ('layout = "cube"', 'layout = "star"', "cubic.layout", "expected 'crossed' or 'cube', got 'star'"),
    ("k1_values = [0.2, 0.3]", "k1_values = [0.2, 0.5]", "cubic.k1_values[1]", "must be <= 0.4"),
    ("k1_values = [0.2, 0.3]", "k1_values = []", "cubic.k1_values", "expected at least 1"),
    ("k1_values = [0.2, 0.3]", "k1_values = [0.03]", "cubic.k1_values", "no (k1, k2, k3) of the grids"),
    ("forces_N = [20, 40.5]", "forces_N = [20, 0]", "cubic.forces_N[1]", "must be > 0.0"),
    ("baseline_k = [0.2, 0.1, 0.05]", "baseline_k = [0.2, 0.1]", "cubic.baseline_k", "expected at least 3 numbers, got 2"),
    ("baseline_k = [0.2, 0.1, 0.05]", "baseline_k = [0.1, 0.2, 0.05]", "cubic.baseline_k", "k3 <= k2 <= k1"),
    ("Z_values_m = [0.5, 0.7]", "Z_values_m = [0.5, 1.39]", "cubic.Z_values_m", "platform inside the frame"),
    ("deflection_values_m = [-0.1, 0.0, 0.1]", "deflection_values_m = [0.7]", "cubic.deflection_values_m", "|d| <= 0.6 m"),
    ('methods = ["exact"]', 'methods = ["fast"]', "cubic.methods[0]", "got 'fast'"),
    ("t_max_N = 250", "t_max_N = 20", "flat.t_min_N", "expected 0 <= t_min_N < t_max_N"),
    ("K21_values = [51, 56]", "K21_values = [1.0]", "flat.K21_values[0]", "must be > 1.0"),
    ("X_values_m = [0.5, 0.6]", "X_values_m = [0.99]", "flat.X_values_m", "0.015 < X < 0.985 m"),
    ("baseline = [56, 28, 0.7, 0.6]", "baseline = [56, 28, 0.7]", "flat.baseline", "expected at least 4"),
    ("baseline = [56, 28, 0.7, 0.6]", "baseline = [56, 1, 0.7, 0.6]", "flat.baseline", "K21, K22 > 1"),
    ("baseline = [56, 28, 0.7, 0.6]", "baseline = [56, 28, -0.7, 0.6]", "flat.baseline", "expected H > 0"),
    ("full_grid = false", "full_grid = 0", "flat.full_grid", "expected a valid boolean"),
    ("speeds_mps = [10, 20.5]", "speeds_mps = [10, -20.5]", "aero.speeds_mps[1]", "must be > 0.0"),
    ("rho_kgpm3 = 1.2", "rho_kgpm3 = 0.0", "aero.rho_kgpm3", "must be > 0.0"),
    ("coefficients = [0.1, 0.0, 0.4, 0.0, -0.04, 0.0]", "coefficients = [0.1]", "aero.coefficients", "expected at least 6"),
    ("[study]", "cubic = 3\n[study]", "aero.cubic", "unknown key"),
]  # fmt: skip


@pytest.mark.parametrize(("old", "new", "key", "problem"), SENS_CASES)
def test_bad_sensitivity_options_exit_2_one_line_nothing_written(
    tmp_path, capsys, old, new, key, problem
):
    assert old in SENS_ALL
    p = tmp_path / "s.toml"
    p.write_text(SENS_ALL.replace(old, new, 1))
    out = tmp_path / "study"
    capsys.readouterr()
    code = main(["sensitivity", "--config", str(p), "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert f"{p}: {key}: " in err[0] and problem in err[0], err[0]
    assert sorted(x.name for x in tmp_path.iterdir()) == ["s.toml"]


def test_found_by_the_fuzzer(tmp_path):
    """A rate of 1e-320 Hz overflowed the CAN frame budget (OverflowError); a camera with none of
    device, video, folder was blamed on ``<config>`` instead of the file."""
    from cdpr.analysis.errors import ConfigError
    from cdpr.pipelines.daq_config import build_sources, load_daq_config

    p = _folder(tmp_path, ALL_KINDS.replace("rate_hz = 100\n", "rate_hz = 1e-320\n", 1))
    with pytest.raises(ConfigError) as e:
        load_daq_config(p)
    assert str(e.value) == f"{p}: sources.cells.rate_hz: must be >= 1e-06, got 1e-320"
    p = _folder(tmp_path, ALL_KINDS.replace('folder = "frames"\n', "", 1))
    with pytest.raises(ConfigError) as e:
        build_sources(load_daq_config(p))
    assert str(e.value) == f"{p}: sources.cam: give exactly one of device, video, folder"
