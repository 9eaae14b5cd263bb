"""The live view as an operator sees it: a recording of the virtual rig's slcan adapter (a real pty)
runs in a tmux pane; the test reads the screen with ``capture-pane`` and presses keys with
``send-keys``: the test point starts and ends on SPACE, the cables are listed by name with their
limits, the point becomes steady, a wrench estimate is shown, the port vanishing raises an alarm,
and Ctrl-C ends the run with the test-point events recorded."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from cdpr.daq.mcap_io import read_run
from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping
from cdpr.pipelines.config import load_rig

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"

DRIVER = """
import json, sys
import cdpr.daq.drivers
from cdpr.daq.recorder import RecorderOptions
from cdpr.daq.source import create_source
from cdpr.pipelines.commands.record import record_run
from cdpr.pipelines.config import load_rig
a = json.loads(sys.argv[1])
rig = load_rig(a["rig"])
src = [create_source(k, n, s) for n, (k, s) in a["sources"].items()]
st = record_run(src, __import__("pathlib").Path(a["out"]), metadata={}, attachments=[],
                options=RecorderOptions(startup_timeout_s=60.0), duration_s=None, quiet=False,
                t_min_N=list(rig.t_min_N), t_max_N=list(rig.t_max_N), rig=rig,
                test_points=a["points"])
"""

POINTS = [
    {"point": "tp1", "kind": "polar", "target_aoa_deg": 5.0, "target_sideslip_deg": 0.0,
     "target_airspeed_mps": 17.27, "repeat_of": ""},
    {"point": "tp2", "kind": "repeat", "target_aoa_deg": 5.0, "target_sideslip_deg": 0.0,
     "target_airspeed_mps": 17.27, "repeat_of": "tp1"},
]  # fmt: skip


def _screen(session: str) -> str:
    return subprocess.run(
        ["tmux", "capture-pane", "-p", "-t", session], capture_output=True, text=True
    ).stdout


def _wait_screen(session: str, text: str, timeout_s: float = 60.0) -> str:
    end = time.monotonic() + timeout_s
    while True:
        s = _screen(session)
        if text in s:
            return s
        assert time.monotonic() < end, f"{text!r} never shown; screen:\n{s}"
        time.sleep(0.1)


def test_live_view_through_tmux(tmp_path: Path) -> None:
    rig = load_rig(RIG)
    sched = schedule_from_mapping(
        {
            "schedule": {"name": "live", "rate_hz": 200.0, "seed": 3},
            "segments": [{"label": "hold", "duration_s": 90.0, "wind_mps": 17.27}],
            # late enough that the steps before it finish first on a loaded machine
            "faults": [{"kind": "port_vanish", "start_s": 20.0, "duration_s": 30.0}],
        },
        "<test>",
        rig,
    )
    vr = VirtualRig(rig, sched)
    link = tmp_path / "lc"
    run = vr.start("slcan", link=link, wait_reader_s=60.0)
    out = tmp_path / "run.mcap"
    args = {
        "rig": str(RIG),
        "sources": vr.source_settings("slcan", link=str(link)),
        "out": str(out),
        "points": POINTS,
    }
    (tmp_path / "driver.py").write_text(DRIVER)
    session = f"cdpr-live-{time.monotonic_ns()}"
    # the pane's size, not a COLUMNS/LINES the test runner may export
    cmd = f"env -u COLUMNS -u LINES {sys.executable} {tmp_path / 'driver.py'} '{json.dumps(args)}'"
    cmd += "; sleep 60"
    subprocess.run(
        ["tmux", "new-session", "-d", "-s", session, "-x", "200", "-y", "60", cmd], check=True
    )
    try:
        _wait_screen(session, "test point  1/2 tp1 next")
        s = _wait_screen(session, f"│ {rig.cable_names[-1]} ")  # the first tensions arrived
        assert "aoa 5°, sideslip 0°, airspeed 17.27 m/s" in s
        for i, c in enumerate(rig.cable_names):  # every cable by name, with its limits
            (line,) = [x for x in s.splitlines() if f"│ {c} " in x]
            cells = [x.strip() for x in line.split("│")]
            assert cells[3:5] == [f"{rig.t_min_N[i]:g}", f"{rig.t_max_N[i]:g}"], line
            assert cells[5] == "ok" and float(cells[2]) > rig.t_min_N[i], line
        subprocess.run(["tmux", "send-keys", "-t", session, "Space"], check=True)
        s = _wait_screen(session, "tp1 RUNNING")
        s = _wait_screen(session, "STEADY ")
        assert "wrench   Fx" in s and "(absolute, at the reference pose)" in s
        assert "no alarms" in s
        subprocess.run(["tmux", "send-keys", "-t", session, "Space"], check=True)
        s = _wait_screen(session, "test point  2/2 tp2 next")
        assert "repeat of tp1" in s
        s = _wait_screen(session, "ALARM  loadcell: no data for", timeout_s=90.0)
        subprocess.run(["tmux", "send-keys", "-t", session, "C-c"], check=True)
        s = _wait_screen(session, "finished ")
        assert "receive failed" not in s
    finally:
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
        run.stop()
    # on /events, the topic cdpr analyze reads (not the recorder's /event)
    assert not [b for _, b in read_run(out).messages["/event"] if b.get("name") == "test_point"]
    ev = [b for _, b in read_run(out).messages["/events"] if b.get("name") == "test_point"]
    assert [(b["point"], b["phase"]) for b in ev] == [("tp1", "start"), ("tp1", "end")]
    for b in ev:
        assert b["kind"] == "polar" and b["target_aoa_deg"] == 5.0
        assert b["target_sideslip_deg"] == 0.0 and b["target_airspeed_mps"] == 17.27
        assert b["repeat_of"] == ""
    faults = [b for _, b in read_run(out).messages["/event"] if b.get("name") == "fault"]
    assert any(b["fault"] == "stalled" and b["source"] == "loadcell" for b in faults)
