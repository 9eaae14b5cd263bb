"""Loud failures on real transports: a socketcan bus that does not exist fails ``cdpr record`` with one
line and exit 3; a pty that closes mid-run, a python-can bus flooded with error frames and a camera
folder that runs dry each become fault events, an alarm while they last and a degraded summary,
with the data recorded before kept."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np
import tomli_w
from test_recorder_helpers import node_read

import cdpr.daq.drivers  # noqa: F401  - registers the drivers
from cdpr.calibration import cv
from cdpr.calibration.camera_model import camera_from_mapping
from cdpr.calibration.markers import flat_prototype_fiducial_layout
from cdpr.calibration.render import VirtualCamera
from cdpr.daq.mcap_io import read_run
from cdpr.daq.recorder import Recorder, RecorderOptions
from cdpr.daq.serial_protocol import format_loadcell_line
from cdpr.daq.slcan_emulator import PtyPort
from cdpr.daq.source import create_source
from cdpr.pipelines.commands.record import report_faults
from cdpr.pipelines.config import load_rig

ROOT = Path(__file__).resolve().parents[1]
CDPR = [sys.executable, "-m", "cdpr.pipelines.cli"]
CABLES = ["a", "b", "c", "d"]


def _wait(cond, timeout_s: float = 30.0, what: str = "") -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.02)


def _faults(path: Path) -> list[dict]:
    return [b for _, b in read_run(path).messages["/event"] if b.get("name") == "fault"]


def test_record_with_a_missing_socketcan_bus_fails_loudly(tmp_path: Path) -> None:
    cfg = {
        "run": {"label": "nobus", "rig": str(ROOT / "data_samples/flat_optimum.toml")},
        "recorder": {"startup_timeout_s": 1.0},
        "sources": {
            "loadcells": {
                "kind": "can_loadcell",
                "interface": "socketcan",
                "channel": "cdprnobus0",
                "bitrate": 1000000,
                "rate_hz": 200.0,
                "dbc": str(ROOT / "data_samples/loadcell.dbc"),
                "cables": list(load_rig(ROOT / "data_samples/flat_optimum.toml").cable_names),
            },
            "tunnel": {"kind": "manual_tunnel", "airspeed_mps": 10.0, "rate_hz": 5.0},
        },
    }
    p = tmp_path / "tunnel.toml"
    p.write_bytes(tomli_w.dumps(cfg).encode())
    out = tmp_path / "runs"
    # no --duration: the recorder must stop by itself, well before the 60 s test timeout
    res = subprocess.run(
        [*CDPR, "record", "--config", str(p), "--out", str(out), "--quiet"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 3, (res.stdout, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(
        "cdpr record: failed: source 'loadcells' delivered nothing within 1 s"
    )
    assert "cdprnobus0" in lines[0] and "Traceback" not in res.stderr
    assert "0 dropped" in res.stdout  # the recording itself is finished ...
    (path,) = sorted(out.glob("*_nobus.mcap"))
    node = node_read(path)
    assert node["complete"] and node["topics"].get("/tensions", 0) == 0
    assert node["topics"]["/tunnel"] >= 1  # ... with what the other sources delivered
    faults = _faults(path)
    assert [(f["source"], f["fault"]) for f in faults if f["fault"] == "no_data"] == [
        ("loadcells", "no_data")
    ]
    end = read_run(path).metadata["run_end"]
    assert end["failure"].startswith("source 'loadcells' delivered nothing")
    assert end["stop_reason"].startswith("failed: ")

    # --allow-degraded goes on with the tunnel for the whole duration, and still exits 3
    res = subprocess.run(
        [*CDPR, "record", "--config", str(p), "--out", str(out), "--quiet", "--duration", "2",
         "--allow-degraded", "--label", "degraded"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 3, res.stderr
    assert "DEGRADED" in res.stderr and "source loadcells: delivered nothing" in res.stderr
    (path,) = sorted(out.glob("*_degraded.mcap"))
    assert read_run(path).metadata["run_end"]["stop_reason"] == "duration reached"


def _lc_source(link: Path):
    settings = {
        "port": str(link),
        "rate_hz": 100.0,
        "cables": CABLES,
        "gain_N_per_count": 0.01,
        "reopen_backoff_s": [0.05, 0.2],
    }
    return create_source("serial_loadcell", "lc", settings, "rig.toml")


def test_a_pty_that_closes_mid_run_is_a_fault_and_an_alarm(tmp_path: Path) -> None:
    port = PtyPort(tmp_path / "ttyLC")
    stop = threading.Event()

    def feed() -> None:
        k = 0
        while not stop.is_set():
            if port.write(format_loadcell_line(k, k, [k, 1, 2, 3], 0)):
                k += 1
            time.sleep(0.01)

    feeder = threading.Thread(target=feed, daemon=True)
    path = tmp_path / "run.mcap"
    opts = RecorderOptions(startup_timeout_s=20.0, stall_timeout_s=0.5)
    try:
        rec = Recorder([_lc_source(port.link)], path, options=opts)
        rec.start()
        _wait(port.reader_attached, what="the recorder opening the port")
        feeder.start()
        _wait(lambda: rec.status().counts.get("tensions", 0) >= 20, what="20 samples")
        assert rec.status().alarms == []
        stop.set()
        feeder.join()
        port.vanish()  # unplugged: the pty closes, its link is removed
        _wait(lambda: rec.status().alarms, what="an alarm")
        assert rec.status().alarms[0].startswith("lc: no data for")
        rec.stop()
    finally:
        stop.set()
        port.close()
    st = rec.status()
    assert report_faults(st) == 3
    assert st.faults[0].startswith("source lc: stalled 1x")
    kinds = {f["fault"] for f in _faults(path)}
    assert "stalled" in kinds and "errors" in kinds
    rc = read_run(path)
    seq = [b["seq"] for _, b in rc.messages["/tensions"]]
    # everything read before the loss is kept, in order, without a gap
    assert len(seq) >= 20 and seq == list(range(seq[0], seq[0] + len(seq)))
    assert json.loads(rc.metadata["run_end"]["faults"]) == st.faults


def test_can_error_frames_and_bus_off_are_faults(tmp_path: Path) -> None:
    channel = f"cdpr-errframes-{time.monotonic_ns()}"
    src = create_source(
        "can_loadcell",
        "lc",
        {
            "interface": "virtual",
            "channel": channel,
            "bitrate": 1000000,
            "rate_hz": 100.0,
            "reopen_backoff_s": [0.05, 0.2],
        },
        "t.toml",
    )
    path = tmp_path / "run.mcap"
    sender = can.Bus(interface="virtual", channel=channel, bitrate=1000000)
    try:
        with Recorder([src], path, options=RecorderOptions(startup_timeout_s=20.0)) as rec:
            # readiness: a virtual bus only delivers to the buses open when a frame is sent, so
            # send a frame no load cell uses until the recorder has read one (the source's bus is
            # open), then the error frames
            end = time.monotonic() + 30.0
            while rec.status().sources["lc"].read == 0:
                assert time.monotonic() < end, "the source never read a frame"
                sender.send(can.Message(arbitration_id=0x7F0, data=[1, 2, 3]))
                time.sleep(0.05)
            # error frames as SocketCAN reports them (CAN_ERR_FLAG; the class in the id):
            # 0x004 controller problem (error warning in data[1])
            for _ in range(3):
                sender.send(can.Message(arbitration_id=0x4, is_error_frame=True, data=[0, 4]))
            _wait(lambda: rec.status().sources["lc"].extra.get("error_frames") == 3, what="3")
            # 0x040 CAN_ERR_BUSOFF: the controller left the bus; the driver reopens it
            sender.send(can.Message(arbitration_id=0x40, is_error_frame=True, dlc=8))
            _wait(lambda: rec.status().sources["lc"].reopened >= 1, what="the reopen")
    finally:
        sender.shutdown()
    (line,) = rec.status().faults
    assert line.startswith("source lc: ") and "4 CAN error frames" in line
    assert "1 CAN bus-off" in line and "1 reopens" in line
    kinds = {f["fault"] for f in _faults(path)}
    assert {"error_frames", "bus_off", "reopened"} <= kinds


def test_a_camera_folder_that_runs_dry_is_a_fault(tmp_path: Path) -> None:
    cam_file = ROOT / "data_samples/camera_virtual.json"
    vc = VirtualCamera(camera_from_mapping(json.loads(cam_file.read_text())))
    rng = np.random.default_rng(1)
    folder = tmp_path / "frames"
    folder.mkdir()
    img = vc.render_fiducials(flat_prototype_fiducial_layout(), [0.5, 0.0, 0.36], np.eye(3), rng)
    for k in range(4):
        cv.write_image(folder / f"f{k:03d}.png", img)
    cam = create_source(
        "camera",
        "cam",
        {
            "camera": str(cam_file),
            "layout": str(ROOT / "data_samples/markers_flat_aruco.toml"),
            "folder": str(folder),
            "fps": 20.0,
        },
    )
    tunnel = create_source("manual_tunnel", "tunnel", {"airspeed_mps": 5.0, "rate_hz": 20.0})
    path = tmp_path / "run.mcap"
    with Recorder([cam, tunnel], path, options=RecorderOptions(startup_timeout_s=20.0)) as rec:
        _wait(lambda: rec.status().faults, what="the fault")
        assert rec.status().alarms == ["cam: ended"]
    assert rec.status().faults == ["source cam: ended early"]
    rc = read_run(path)
    assert len(rc.messages["/pose_status"]) == 4 and rc.messages["/pose_status"][0][1]["flags"] == 0
    (f,) = _faults(path)
    assert (
        f["source"] == "cam" and f["fault"] == "ended" and "while the run went on" in f["message"]
    )


def _file_size_limit(limit_bytes: int):
    def pre() -> None:
        import resource
        import signal

        # a full disk: writes past the limit fail with EFBIG (instead of the default SIGXFSZ kill)
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return pre


def test_a_full_disk_stops_with_one_line_and_keeps_what_was_written(tmp_path: Path) -> None:
    from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping

    rig = load_rig(ROOT / "data_samples/flat_optimum.toml")
    sched = schedule_from_mapping(
        {
            "schedule": {"name": "full", "rate_hz": 200.0, "seed": 5},
            "segments": [{"label": "hold", "duration_s": 60.0, "wind_mps": 17.27}],
        },
        "<test>",
        rig,
    )
    vr = VirtualRig(rig, sched)
    link = tmp_path / "lc"
    run = vr.start("slcan", link=link, wait_reader_s=60.0)
    kind, settings = vr.source_settings("slcan", link=str(link))["loadcell"]
    cfg = {
        "run": {"label": "full", "rig": str(ROOT / "data_samples/flat_optimum.toml")},
        "recorder": {"startup_timeout_s": 60.0},
        "sources": {"loadcell": {"kind": kind, **settings}},
    }
    p = tmp_path / "full.toml"
    p.write_bytes(tomli_w.dumps(cfg).encode())
    out = tmp_path / "runs"
    try:  # no --duration: the recorder stops by itself when the disk is full
        res = subprocess.run(
            [*CDPR, "record", "--config", str(p), "--out", str(out), "--quiet"],
            capture_output=True,
            text=True,
            timeout=120,
            preexec_fn=_file_size_limit(250_000),
        )
    finally:
        run.stop()
    (path,) = sorted(out.glob("*_full.mcap"))
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert lines[0].startswith(f"cdpr record: error: {path}: File too large: recording stopped")
    assert path.stat().st_size <= 250_000
    res = subprocess.run([*CDPR, "recover", str(path)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    rc = read_run(path.with_name(path.stem + ".recovered.mcap"))
    seq = [b["seq"] for _, b in rc.messages["/tensions"]]
    assert len(seq) > 100 and seq == list(range(seq[0], seq[0] + len(seq)))


def test_a_host_clock_jump_is_a_fault(monkeypatch) -> None:
    # no way here to step the machine's real clock (no CAP_SYS_TIME, and libfaketime breaks
    # Python's sleeps): the host clock the monitor reads is stepped 30 s forward instead
    from cdpr.daq import health

    events: list[tuple] = []
    h = health.HealthMonitor(
        {"a": [10.0]},
        lambda msg, level, **kw: events.append((msg, kw)),
        startup_timeout_s=60.0,
        stall_timeout_s=60.0,
    )
    c = {"a": type("C", (), {"errors": 0, "lost": 0, "bad": 0, "dropped": 0, "reopened": 0,
                              "last_error": "", "extra": {}})()}  # fmt: skip
    h.check(c, stopping=False, others_running=True)
    assert events == []
    real = time.time_ns
    monkeypatch.setattr(health.time, "time_ns", lambda: real() + 30_000_000_000)
    h.check(c, stopping=False, others_running=True)
    h.check(c, stopping=False, others_running=True)  # one jump, one event
    ((msg, kw),) = events
    assert kw["fault"] == "clock_jump" and kw["source"] == "host"
    assert 29.9 < kw["step_s"] < 30.1 and msg.startswith("host clock jumped by +30.0")
    assert h.summary()[0].startswith("host clock: jumped 1x (+30.0")
