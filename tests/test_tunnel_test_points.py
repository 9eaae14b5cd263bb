"""Test points from the tunnel controller: ``$TPT`` lines on the tunnel's serial link (a real
pseudo-terminal) become ``test_point`` events with the live view's fields and the lines' arrival
times; bad lines, a lone ``end``, an overlapping ``start`` and a lost line are kept and said; the
virtual rig sends them (``test_points_on_link``) and ``cdpr analyze`` finds the schedule's points."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

import cdpr.daq.drivers  # noqa: F401
from cdpr.daq.serial_protocol import (
    LineError,
    format_test_point_line,
    format_tunnel_line,
    parse_test_point_line,
)
from cdpr.daq.slcan_emulator import PtyPort
from cdpr.daq.source import create_source

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_experiment2.toml"
CDPR = [sys.executable, "-m", "cdpr.pipelines.cli"]

#: the fields every test_point event carries (docs/campaign.md "Test-point events"), written
#: out here rather than imported from the code under test
TEST_POINT_FIELDS = {
    "message", "name", "point", "phase", "kind", "target_aoa_deg", "target_sideslip_deg",
    "target_airspeed_mps", "repeat_of",
}  # fmt: skip


def _xor(body: bytes) -> int:
    c = 0
    for b in body:
        c ^= b
    return c


def _line(body: str) -> bytes:
    """A line framed by hand (independent of ``frame_line``)."""
    raw = body.encode()
    return b"$" + raw + b"*" + f"{_xor(raw):02X}".encode() + b"\r\n"


def test_tpt_line_by_hand() -> None:
    body = "TPT,0,start,alpha-a2-b0-v25.51,wind_on,2,0,25.51"
    assert format_test_point_line(0, "start", "alpha-a2-b0-v25.51", "wind_on", 2.0, 0.0, 25.51) == (
        _line(body)
    )
    assert _line(body).endswith(b"*4A\r\n")  # the docstring's example
    p = parse_test_point_line(_line(body))
    assert (p.seq, p.phase, p.label, p.kind) == (0, "start", "alpha-a2-b0-v25.51", "wind_on")
    assert (p.target_aoa_deg, p.target_sideslip_deg, p.target_airspeed_mps) == (2.0, 0.0, 25.51)
    short = parse_test_point_line(_line("TPT,7,end,tare-1"))
    assert (short.seq, short.phase, short.label, short.kind) == (7, "end", "tare-1", None)
    for body, why in [
        ("TPT,1,begin,a", "phase"),
        ("TPT,1,start,", "label"),
        ("TPT,1,start,a b", "label"),
        ("TPT,1,start,a*b", "label"),
        ("TPT,1,start,a,wind_on,2,0", "expected 3 or 7 fields"),
        ("TPT,1,start,a,gust,2,0,25", "kind"),
        ("TPT,1,start,a,wind_on,2,x,25", "not a number"),
        ("TPT,1,start,a,wind_on,2,0,-1", "airspeed >= 0"),
        ("TPT,1,start,a,wind_on,nan,0,25", "finite"),
        ("TPT,x,start,a", "seq"),
    ]:
        with pytest.raises(LineError, match=why):
            parse_test_point_line(_line(body))


def _source(port: PtyPort, **kw):
    settings = {"port": str(port.link), "rate_hz": 10.0, "test_points": True, **kw}
    return create_source("serial_tunnel", "tun", settings, "tunnel.toml")


def _read_until(src, done, timeout_s: float = 5.0):
    """Read until ``done(readings)`` or the timeout (generous: a loaded machine)."""
    out = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not done(out):
        out += src.read(0.05)
    return out


def _events(rd, name: str = "test_point"):
    return [r for r in rd if r.stream == "events" and r.values["name"] == name]


def test_tpt_lines_on_a_pty_become_test_point_events_at_their_arrival(tmp_path: Path) -> None:
    port = PtyPort(tmp_path / "ttyTUN")
    try:
        with _source(port) as src:
            t_write0 = time.time_ns()
            assert port.write(
                format_tunnel_line(0, 0.0, 101325.0, 293.15)
                + _line("TPT,0,start,tare-a4,tare,4,0,0")
            )
            first = _read_until(src, lambda rd: len(_events(rd)) >= 1)
            t_read0 = time.time_ns()
            time.sleep(0.3)
            t_write1 = time.time_ns()
            assert port.write(_line("TPT,1,end,tare-a4,tare,4,0,0") + _line("TPT,2,start,on"))
            second = _read_until(src, lambda rd: len(_events(rd)) >= 2)
            t_read1 = time.time_ns()
            assert src.stats.bad == 0 and src.stats.extra.get("test_point_warnings", 0) == 0
    finally:
        port.close()
    (start,) = _events(first)
    end, on = _events(second)
    assert set(start.values) == TEST_POINT_FIELDS
    assert start.values == {
        "message": "test point tare-a4 start", "name": "test_point", "point": "tare-a4",
        "phase": "start", "kind": "tare", "target_aoa_deg": 4.0, "target_sideslip_deg": 0.0,
        "target_airspeed_mps": 0.0, "repeat_of": "",
    }  # fmt: skip
    assert (end.values["point"], end.values["phase"]) == ("tare-a4", "end")
    # a line without targets: label and phase only (the analysis's defaults for the rest)
    assert on.values == {
        "message": "test point on start", "name": "test_point", "point": "on", "phase": "start",
        "repeat_of": "",
    }  # fmt: skip
    # stamped when the line arrived: between its write and the read that returned it
    assert t_write0 <= start.t_ns <= t_read0
    assert t_write1 <= end.t_ns <= t_read1 and end.t_ns - start.t_ns >= 0.3e9
    assert [r.values["seq"] for r in first if r.stream == "tunnel"] == [0]


def test_bad_tpt_lines_are_kept_raw_and_counted(tmp_path: Path) -> None:
    port = PtyPort(tmp_path / "ttyTUN")
    bad_sum = bytearray(_line("TPT,0,start,a"))
    bad_sum[6] = ord("x")  # 'start' -> 'xtart' under the old checksum
    bad = [bytes(bad_sum), _line("TPT,1,halt,a"), _line("TPT,2,start,a,gust,0,0,1")]
    try:
        with _source(port) as src:
            assert port.write(b"".join(bad) + _line("TPT,3,start,b"))
            rd = _read_until(src, lambda rd: len(_events(rd)) >= 1)
            assert src.stats.bad == 3
        # the same line on a link that does not read test points is a bad line, not an event
        with _source(port, test_points=False) as off:
            assert "events" not in off.describe()
            assert port.write(_line("TPT,4,end,b"))
            rd_off = _read_until(off, lambda rd: any(r.stream == "serial_bad" for r in rd))
            assert off.stats.bad == 1
    finally:
        port.close()
    kept = [r for r in rd if r.stream == "serial_bad"]
    assert [r.values["line"] for r in kept] == [b.rstrip(b"\r\n").decode() for b in bad]
    reasons = [r.values["reason"] for r in kept]
    assert "checksum mismatch" in reasons[0] and "phase" in reasons[1] and "kind" in reasons[2]
    assert [e.values["point"] for e in _events(rd)] == ["b"]  # the good line after them
    (off_bad,) = [r for r in rd_off if r.stream == "serial_bad"]
    assert "test_points is false" in off_bad.values["reason"] and not _events(rd_off)


def test_lone_end_overlapping_start_and_a_lost_line_are_kept_and_said(tmp_path: Path) -> None:
    port = PtyPort(tmp_path / "ttyTUN")
    lines = [
        _line("TPT,0,end,x"),  # an end with nothing open
        _line("TPT,1,start,a"),
        _line("TPT,2,start,b"),  # a is still open
        _line("TPT,3,end,b"),
        _line("TPT,5,start,c"),  # seq 4 never came
    ]
    try:
        with _source(port) as src:
            assert port.write(b"".join(lines))
            rd = _read_until(src, lambda rd: len(_events(rd)) >= 5)
            assert src.stats.extra["test_point_warnings"] == 3 and src.stats.lost == 1
    finally:
        port.close()
    # every line is kept as the test_point event it says, in order
    assert [(e.values["point"], e.values["phase"]) for e in _events(rd)] == [
        ("x", "end"), ("a", "start"), ("b", "start"), ("b", "end"), ("c", "start"),
    ]  # fmt: skip
    warn = _events(rd, "test_point_warning")
    assert [(w.values["point"], w.values["phase"]) for w in warn] == [
        ("x", "end"), ("b", "start"), ("c", "start"),
    ]  # fmt: skip
    assert all(w.values["level"] == "warning" for w in warn)
    assert "no matching start" in warn[0].values["problem"]
    assert "while point a is open" in warn[1].values["problem"]
    assert "1 test-point line(s) lost" in warn[2].values["problem"]
    # each warning is stamped with the line it is about
    ev = {(e.values["point"], e.values["phase"]): e.t_ns for e in _events(rd)}
    assert [w.t_ns for w in warn] == [ev["x", "end"], ev["b", "start"], ev["c", "start"]]

    # what the analysis makes of them (its planner reads only the events and the sample times):
    # a and b stay two points, a flagged as never ended; the lone end marks nothing
    from types import SimpleNamespace

    import numpy as np

    from cdpr.pipelines.point_plan import plan_points

    t_ev = sorted(ev.values())
    t_ns = np.arange(t_ev[0] - 10**9, t_ev[-1] + 10**9, 10**6, dtype=np.int64)
    events = [(e.t_ns, dict(e.values)) for e in _events(rd)]
    plan = plan_points(SimpleNamespace(events=events, t_ns=t_ns), None)  # type: ignore[arg-type]
    assert plan.source == "events" and plan.labels == ["a", "b", "c"]
    assert plan.flags == ["no_end_event", "", "no_end_event"]


def test_record_refuses_two_sources_of_test_points(tmp_path: Path) -> None:
    cfg = tmp_path / "tunnel.toml"
    cfg.write_text(
        '[run]\nlabel = "tp"\n[sources.tun]\nkind = "serial_tunnel"\nport = "/nonexistent"\n'
        "test_points = true\n"
    )
    matrix = ROOT / "data_samples" / "campaign_alpha_sweep.toml"
    res = subprocess.run(
        [*CDPR, "record", "--config", str(cfg), "--test-matrix", str(matrix),
         "--out", str(tmp_path / "runs"), "--duration", "1", "--quiet"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert "sources.tun.test_points" in res.stderr and "only one may" in res.stderr
    assert not (tmp_path / "runs").exists() or not list((tmp_path / "runs").glob("*.mcap"))


CAMPAIGN = """
[campaign]
name = "link"
rig = "{rig}"
[model]
area_m2 = 0.0146
span_m = 0.2441
chord_m = 0.06
mrp_P_m = [0.0, 0.0, 0.0]
[virtual_rig]
rate_hz = 200.0
seed = 5
test_points_on_link = true
[[points]]
label = "tare"
kind = "tare"
aoa_deg = [0.0, 4.0]
duration_s = 0.6
transition_s = 0.2
[[points]]
label = "on"
kind = "wind_on"
aoa_deg = [0.0, 4.0]
airspeed_mps = 25.0
duration_s = 0.6
transition_s = 0.3
"""


@pytest.mark.parametrize("transport", ["serial", "virtual"])
def test_simulate_with_points_on_the_link_then_analyze_finds_them(
    tmp_path: Path, transport: str
) -> None:
    # serial: the rig (and its tunnel controller) in a second process; virtual: in this one
    import pandas as pd

    from cdpr.daq.run_reader import open_run

    matrix = tmp_path / "link.toml"
    matrix.write_text(CAMPAIGN.format(rig=RIG.as_posix()))
    runs, out = tmp_path / "runs", tmp_path / "an"
    res = subprocess.run(
        [*CDPR, "simulate", "--campaign", str(matrix), "--out", str(runs), "--quiet",
         "--transport", transport],
        capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "DEGRADED" not in res.stderr, res.stderr  # the events source idles after its last
    assert "test points: from the tunnel link" in res.stdout
    (run,) = runs.glob("*.mcap")
    # the schedule by hand: the sweeps expand to these labels, in this order
    labels = ["tare-a0-b0-v0", "tare-a4-b0-v0", "on-a0-b0-v25", "on-a4-b0-v25"]
    with open_run(run) as r:
        ev = r.table("/events")
        sched = r.table("/events_schedule")
    assert set(ev["name"]) == {"test_point"}  # one set of test points: the link's
    assert list(ev["point"]) == [x for x in labels for _ in (0, 1)]
    assert list(ev["phase"]) == ["start", "end"] * 4
    assert set(sched["name"]) == {"test_point_schedule"}  # the schedule's own, kept apart
    # the link's points arrive within 0.5 s of the schedule's times (pty latency on a busy
    # machine), never before them
    lag = ev["t_ns"].to_numpy() - sched["t_ns"].to_numpy()
    assert (lag >= 0).all() and (lag < 5e8).all(), lag
    res = subprocess.run(
        [*CDPR, "analyze", str(run), "--out", str(out), "--workers", "1", "--no-progress"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode in (0, 1), res.stderr
    (points,) = out.glob("*/points.csv")
    df = pd.read_csv(points)
    assert list(df["point"]) == labels and set(df["source"]) == {"events"}
    assert list(df["kind"]) == ["tare", "tare", "wind_on", "wind_on"]
    assert "no_end_event" not in " ".join(df["flags"].fillna("").astype(str))
