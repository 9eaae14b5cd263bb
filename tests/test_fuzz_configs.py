"""Property-based fuzzing (hypothesis) of the TOML and CSV readers: rig files, sensitivity configs,
pose / wrench / load-cell tables through ``cdpr`` (the contract of ``tests/_fuzz_contract.py``);
virtual-rig schedules, campaign files, vision and daq configs through their loaders (a command
that accepts them would run a rig or a camera): the loader returns or raises a ``CdprError``
whose one-line message names the file, never another exception.  Each example mutates a valid
file (a value replaced by an absurd one, bytes flipped or inserted, truncation, lines dropped or
duplicated)."""

from __future__ import annotations

import tempfile
from pathlib import Path

from _fuzz_contract import EXAMPLES, FUZZ, check_cli, mutated
from hypothesis import given, settings

from cdpr.analysis.errors import CdprError
from cdpr.daq.schema import load_rig

ROOT = Path(__file__).resolve().parents[1]
RIG_TEXT = (ROOT / "data_samples" / "flat_optimum.toml").read_text()
POSES = "# poses\nx_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad,label\n" + "".join(
    f"{0.5 + 0.001 * k},0.0,0.335,0.0,{0.01 * k},0.0,p{k}\n" for k in range(5)
)
WRENCH = "fx_N,fy_N,fz_N,mx_Nm,my_Nm,mz_Nm\n1.0,0.5,-2.0,0.01,0.02,0.0\n"
POINTS = "channel,load_N,counts\n" + "".join(
    f"{c},{load},{1000 + 20 * load + i}\n" for i, c in enumerate("ab") for load in (0, 50, 100, 150)
)
SENS = "[cubic]\nforces_N = [19.041, 32.183]\nmass_kg = 5.0\n[flat]\nfull_grid = false\nmass_kg = 0.64\n"


def _folder() -> Path:
    return Path(tempfile.mkdtemp(prefix="fuzz-"))


RIG = load_rig(ROOT / "data_samples" / "flat_optimum.toml")
SAMPLES = ROOT / "data_samples"


def check_loader(load, data: bytes, name: str, beside: bool = False) -> object | None:
    """Write ``data`` to a file called ``name`` (``beside``: in a folder that links every file of
    data_samples/, the files it refers to), load it: a value, or a ``CdprError`` whose one-line
    message names the file (anything else fails the test)."""
    folder = _folder()
    if beside:  # links, never to the file written: writing through one would change a sample
        for f in SAMPLES.iterdir():
            if f.name != name:
                (folder / f.name).symlink_to(f)
    path = folder / name
    path.write_bytes(data)
    try:
        return load(path)
    except CdprError as exc:
        msg = str(exc)
        assert str(path) in msg and "\n" not in msg.strip(), msg
        return None


@FUZZ
@given(data=mutated(RIG_TEXT, "="))
def test_fuzz_rig_toml(capsys, data):
    d = _folder()
    rig = d / "rig.toml"
    rig.write_bytes(data)
    (d / "existing.csv").write_text("keep me\n")
    check_cli(capsys, ["rig", "show", str(rig)], d, rig, [])
    out = d / "t.csv"
    check_cli(capsys, ["solve", "--rig", str(rig), "--out", str(out)], d, rig, [out])


@FUZZ
@given(data=mutated(SENS, "="))
def test_fuzz_sensitivity_config(capsys, data):
    d = _folder()
    cfg = d / "s.toml"
    cfg.write_bytes(data)
    check_cli(capsys, ["sensitivity", "--config", str(cfg), "--print-config"], d, cfg, [])


@FUZZ
@given(data=mutated(POSES, ","))
def test_fuzz_pose_table(capsys, data):
    d = _folder()
    poses, out = d / "p.csv", d / "t.csv"
    poses.write_bytes(data)
    rig = str(ROOT / "data_samples" / "flat_optimum.toml")
    check_cli(
        capsys, ["solve", "--rig", rig, "--poses", str(poses), "--out", str(out)], d, poses, [out]
    )


@FUZZ
@given(data=mutated(WRENCH, ","))
def test_fuzz_wrench_table(capsys, data):
    d = _folder()
    w, out = d / "w.csv", d / "t.csv"
    w.write_bytes(data)
    rig = str(ROOT / "data_samples" / "flat_optimum.toml")
    check_cli(capsys, ["solve", "--rig", rig, "--wrench", str(w), "--out", str(out)], d, w, [out])


@settings(FUZZ, max_examples=max(10, EXAMPLES // 3))  # each example fits every channel: slower
@given(data=mutated(POINTS, ","))
def test_fuzz_loadcell_points(capsys, data):
    d = _folder()
    pts, out = d / "points.csv", d / "cal.toml"
    pts.write_bytes(data)
    check_cli(capsys, ["calibrate", "loadcells", str(pts), "--out", str(out)], d, pts, [out])


CAMPAIGN = (SAMPLES / "campaign_alpha_sweep.toml").read_text()
SCHEDULE = (SAMPLES / "schedule_demo.toml").read_text()


@FUZZ
@given(data=mutated(SCHEDULE, "="))
def test_fuzz_vrig_schedule(data):
    from cdpr.daq.vrig_schedule import load_schedule

    def load(path: Path) -> object:
        return load_schedule(path, RIG)

    assert check_loader(load, SCHEDULE.encode(), "schedule.toml") is not None
    check_loader(load, data, "schedule.toml")


@FUZZ
@given(data=mutated(CAMPAIGN, "="))
def test_fuzz_campaign_schedule(data):
    """The campaign's ``[virtual_rig]`` table becomes a schedule: errors name the campaign file."""
    from cdpr.pipelines.campaign import load_test_matrix, schedule_from_matrix

    def load(path: Path) -> object:
        return schedule_from_matrix(load_test_matrix(path), RIG)

    assert check_loader(load, CAMPAIGN.encode(), "campaign.toml", beside=True) is not None
    check_loader(load, data, "campaign.toml", beside=True)


@FUZZ
@given(data=mutated((SAMPLES / "board_charuco.toml").read_text(), "="))
def test_fuzz_board_file(data):
    from cdpr.pipelines.vision_config import load_board

    check_loader(load_board, data, "board.toml")


@FUZZ
@given(data=mutated((SAMPLES / "camera_virtual.json").read_text(), ":,"))
def test_fuzz_camera_json(data):
    from cdpr.pipelines.vision_config import load_camera

    check_loader(load_camera, data, "camera.json")


@FUZZ
@given(data=mutated((SAMPLES / "markers_flat_ir6.toml").read_text(), "=,"))
def test_fuzz_marker_layout(data):
    from cdpr.pipelines.vision_config import load_marker_layout

    check_loader(load_marker_layout, data, "markers.toml")


@FUZZ
@given(data=mutated((SAMPLES / "tunnel.toml").read_text(), "="))
def test_fuzz_daq_config(data):
    from cdpr.pipelines.daq_config import load_daq_config

    check_loader(load_daq_config, data, "tunnel.toml", beside=True)


# every driver kind a daq config can name, each setting on its schema (daq/source_schema.py);
# only files of data_samples/ are named (the replay's log need only exist to be built)
SOURCES = f"""[run]
label = "fuzz"
[sources.cells]
kind = "can_loadcell"
interface = "virtual"
channel = "fuzz"
bitrate = 500000
rate_hz = 100.0
dbc = "loadcell.dbc"
offset_counts = [0, 1, 2, 3, 4, 5, 6, 7]
gain_N_per_count = 2.5e-5
max_bus_load = 0.8
reopen_backoff_s = [0.2, 4.0]
[sources.lc]
kind = "serial_loadcell"
port = "/dev/ttyUSB7"
baudrate = 921600
rate_hz = 250.0
cables = ["p", "q"]
[sources.tun]
kind = "serial_tunnel"
port = "/dev/ttyUSB8"
rate_hz = 5.0
[sources.hand]
kind = "manual_tunnel"
airspeed_mps = 25.51
temperature_K = 290.0
[sources.log]
kind = "can_replay"
path = "{ROOT / "tests" / "data" / "can" / "issue_1299.asc"}"
speed = "max"
decode = false
[sources.cam]
kind = "camera"
camera = "camera_virtual.json"
layout = "markers_flat_aruco.toml"
device = 0
image_format = "png"
"""


@FUZZ
@given(data=mutated(SOURCES, "=,"))
def test_fuzz_daq_sources(data):
    """Every ``[sources.<name>]`` table through the config loader and the drivers' constructors
    (``build_sources``: nothing is opened)."""
    from cdpr.pipelines.daq_config import build_sources, load_daq_config

    def load(path: Path) -> object:
        return build_sources(load_daq_config(path))

    assert check_loader(load, SOURCES.encode(), "sources.toml", beside=True) is not None
    check_loader(load, data, "sources.toml", beside=True)


SENS_ALL = """[cubic]
L_m = 2.5
layout = "cube"
k1_values = [0.2, 0.3]
k3_values = [0.05]
baseline_k = [0.2, 0.1, 0.05]
Z_values_m = [0.5, 0.7]
methods = ["exact"]
[flat]
t_max_N = 250.0
K21_values = [51, 56]
baseline = [56, 28, 0.7, 0.6]
full_grid = false
[aero]
speeds_mps = [10, 20.5]
coefficients = [0.1, 0.0, 0.4, 0.0, -0.04, 0.0]
[study]
sigma_T_N = 0.5
margin_method = "penalty"
near_singular_condition = 500.0
EA_N = 9.0e4
"""


@FUZZ
@given(data=mutated(SENS_ALL, "=,"))
def test_fuzz_sensitivity_every_section(capsys, data):
    """Every section of the options (``study.EA_N`` included) through ``cdpr sensitivity``."""
    d = _folder()
    cfg = d / "s.toml"
    cfg.write_bytes(data)
    check_cli(capsys, ["sensitivity", "--config", str(cfg), "--print-config"], d, cfg, [])
