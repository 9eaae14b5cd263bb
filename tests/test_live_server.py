"""The live server (``--live-server``) against the run file written at the same time, through a
real WebSocket client speaking the Foxglove protocol (``tests/_foxglove_client.py``: the
``websockets`` package, subprotocol ``foxglove.sdk.v1``, protobuf decoded with the descriptors the
server advertises; it never imports the SDK).  The run file is read by the ``mcap`` package's own
reader, not the project's.

One simulated campaign (virtual rig, camera, test-point events) serves three clients: one from the
start, one that connects mid-run, one that stops reading after 40 messages.  Then: topics and
schema names against the file, values against the file, the scene's cable end points against the
structure matrix at the pose it was drawn at, the file complete (every sample the rig sent,
nothing dropped) whatever the stalled client did, the on-line results against ``cdpr analyze`` and
the report, ``cdpr play`` of the same run, and a port already in use.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from _foxglove_client import FoxgloveClient
from mcap.reader import make_reader

from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rotations import rotation_from_euler, rotation_from_quaternion
from cdpr.daq.live_layout import foxglove_layout, layout_topics
from cdpr.daq.live_scene import cable_states, scene_geometry
from cdpr.pipelines.config import load_rig

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data_samples"
RIG = DATA / "flat_experiment2.toml"
CLI = [sys.executable, "-m", "cdpr.pipelines.cli"]

MATRIX = """
[campaign]
name = "live-small"
rig = "{data}/flat_experiment2.toml"
camera = "{data}/camera_virtual.json"
markers = "{data}/markers_flat_ir6.toml"
[model]
area_m2 = 0.014646
span_m = 0.2441
chord_m = 0.060
mrp_P_m = [0.0, 0.0, 0.0]
[defaults]
duration_s = 1.6
transition_s = 0.3
[virtual_rig]
rate_hz = 200.0
tunnel_rate_hz = 10.0
seed = 23
[virtual_rig.sensor]
noise_sd_N = 0.05
drift_N_per_s = 0.0
[[points]]
label = "zero"
kind = "zero"
[[points]]
label = "tare"
kind = "tare"
aoa_deg = [0.0, 4.0]
[[points]]
label = "alpha"
kind = "wind_on"
aoa_deg = [0.0, 4.0]
airspeed_mps = [17.27, 25.51]
"""


def _file_messages(path: Path) -> dict[str, list[tuple[int, str, Any]]]:
    """topic -> [(log time, schema name, JSON body)] by the mcap package's reader."""
    out: dict[str, list[tuple[int, str, Any]]] = {}
    with path.open("rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages():
            if schema.name == "cdpr.column_block":
                continue
            out.setdefault(channel.topic, []).append(
                (msg.log_time, schema.name, json.loads(msg.data))
            )
    return out


def _by_time(msgs: list[tuple[int, str, Any]]) -> dict[int, list[Any]]:
    """log time -> the bodies of that time (a burst read from a pty can share one time)."""
    out: dict[int, list[Any]] = {}
    for t, _, b in msgs:
        out.setdefault(t, []).append(b)
    return out


def _file_schemas(path: Path) -> dict[str, str]:
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    return {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The simulated campaign with its three clients (see the module docstring)."""
    tmp = tmp_path_factory.mktemp("live")
    matrix = tmp / "m.toml"
    matrix.write_text(MATRIX.format(data=DATA.as_posix()))
    runs = tmp / "runs"
    cmd = [*CLI, "simulate", "--campaign", str(matrix), "--out", str(runs), "--quiet",
           "--live-server", "0"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    first = proc.stdout.readline()
    m = re.search(r"live server (ws://127\.0\.0\.1:\d+) ", first)
    assert m, first + (proc.stderr.read() if proc.stderr else "")
    url = m[1]
    clients = {
        "first": FoxgloveClient(url).start(),
        "stalled": FoxgloveClient(url, stall_after=40).start(),
    }
    # the second client connects mid-run: once the recording runs and the first client has its
    # first tensions (the schedule has about 14 s to go)
    second = proc.stdout.readline()
    assert second.startswith("recording "), second
    clients["first"].wait_for(
        lambda c: bool(c.of("/tensions/view")) or proc.poll() is not None, 180
    )
    assert proc.poll() is None, "the run ended before the second client could join"
    clients["mid"] = FoxgloveClient(url).start()
    out, err = proc.communicate(timeout=300)
    for c in clients.values():
        c.stop()
    assert proc.returncode == 0, err
    (run,) = runs.glob("*.mcap")
    return {"url": url, "run": run, "matrix": matrix, "tmp": tmp, "stdout": first + second + out,
            "stderr": err, "clients": clients}  # fmt: skip


def test_advertised_topics_and_schemas_are_the_files(session: dict[str, Any]) -> None:
    c = session["clients"]["first"]
    assert c.error is None and c.subprotocol == "foxglove.sdk.v1"
    live = c.topics()
    file_schemas = _file_schemas(session["run"])
    for topic, name in file_schemas.items():
        if name == "cdpr.column_block":  # the file's blocks: served as their per-sample view
            assert topic + "/view" in live
            continue
        assert topic in live, f"{topic} not served live"
        assert live[topic].schema_name == name, topic
    # well-known types as protobuf, our own as JSON with a JSON schema
    for topic in ("/pose", "/events", "/event", "/image"):
        assert (live[topic].encoding, live[topic].schema_encoding) == ("protobuf", "protobuf")
    for topic in ("/tensions/view", "/tunnel", "/recorder", "/online"):
        assert (live[topic].encoding, live[topic].schema_encoding) == ("json", "jsonschema")
    assert live["/scene"].schema_name == "foxglove.SceneUpdate"
    assert live["/tf"].schema_name == "foxglove.FrameTransforms"
    assert json.loads(live["/tensions/view"].metadata["limits_N"])["front_left_top"] == [
        35.0,
        285.0,
    ]
    # the layout in data_samples is this rig's, and reads only topics the server serves
    rig = load_rig(RIG)
    layout = json.loads((DATA / "foxglove_layout.json").read_text())
    assert layout == json.loads(json.dumps(foxglove_layout(rig.cable_names, [0.5, 0.0, 0.36])))
    assert layout_topics(layout) <= set(live)


def test_live_values_are_the_files(session: dict[str, Any]) -> None:
    c = session["clients"]["first"]
    f = _file_messages(session["run"])
    # tensions: the file's 50 Hz view, message for message (same samples, same bodies)
    file_view = _by_time(f["/tensions/view"])
    live_view = c.of("/tensions/view")
    assert live_view and all(r.body in file_view[r.log_time_ns] for r in live_view)
    assert len(live_view) >= 0.95 * len(f["/tensions/view"])
    # poses: one PoseInFrame per camera frame with a pose, equal to the file's; every frame's
    # status as the file's /pose_status
    file_pose = {t: b for t, _, b in f["/pose"]}
    file_status = _by_time(f["/pose_status"])
    live_status = c.of("/pose_status")
    assert len(live_status) >= 0.95 * len(f["/pose_status"])
    assert all(r.body in file_status[r.log_time_ns] for r in live_status)
    live_pose = c.of("/pose")
    assert len(live_pose) >= 0.95 * len(file_pose) and len(file_pose) > 20
    for r in live_pose:
        b = file_pose[r.log_time_ns]["pose"]
        assert r.body.frame_id == "O"
        got = [r.body.pose.position.x, r.body.pose.position.y, r.body.pose.position.z,
               r.body.pose.orientation.x, r.body.pose.orientation.y, r.body.pose.orientation.z,
               r.body.pose.orientation.w]  # fmt: skip
        want = [b["position"][k] for k in "xyz"] + [b["orientation"][k] for k in "xyzw"]
        assert got == pytest.approx(want, abs=1e-12)
        assert r.body.timestamp.seconds * 10**9 + r.body.timestamp.nanos == r.log_time_ns
    # events: every test-point event as a Log message, its fields in the text
    file_tp = [(t, b) for t, _, b in f["/events"] if b["name"] == "test_point"]
    live_tp = [r for r in c.of("/events") if r.body.name == "test_point"]
    assert [r.log_time_ns for r in live_tp] == [t for t, _ in file_tp]
    for r, (_, b) in zip(live_tp, file_tp, strict=True):
        assert r.body.message.startswith(b["message"]) and f"point={b['point']}" in r.body.message
        assert r.body.level == 2  # INFO
    # tunnel conditions as recorded
    file_tun = _by_time(f["/tunnel"])
    assert all(r.body in file_tun[r.log_time_ns] for r in c.of("/tunnel"))


def test_scene_cable_ends_are_the_structure_matrix_points(session: dict[str, Any]) -> None:
    """Each /scene message's cables run from p + R pp_i to b_i at the pose it was drawn at (its
    metadata; the /tf message published with it says the same): the directions and moment arms
    of the structure matrix at that pose."""
    c = session["clients"]["first"]
    rig = load_rig(RIG)
    scenes = c.of("/scene")
    tfs = c.of("/tf")
    assert len(scenes) > 20 and len(tfs) == len(scenes)
    checked = 0
    moved = 0
    for s, tf in list(zip(scenes, tfs, strict=True))[:: max(1, len(scenes) // 15)]:
        (ent,) = [e for e in s.body.entities if e.id == "rig"]
        meta = {kv.key: kv.value for kv in ent.metadata}
        p = np.array(json.loads(meta["position_O_m"]))
        q = np.array(json.loads(meta["quaternion_wxyz"]))
        t = tf.body.transforms[0]  # published right after it, from the same pose
        np.testing.assert_allclose([t.translation.x, t.translation.y, t.translation.z], p)
        np.testing.assert_allclose([t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z], q)
        A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, p, rotation_from_quaternion(q))
        for i, line in enumerate(ent.lines):
            a = np.array([line.points[0].x, line.points[0].y, line.points[0].z])
            b = np.array([line.points[1].x, line.points[1].y, line.points[1].z])
            u = (b - a) / np.linalg.norm(b - a)
            np.testing.assert_allclose(u, A[:3, i], atol=1e-9)
            np.testing.assert_allclose(np.cross(a - p, u), A[3:, i], atol=1e-9)
            np.testing.assert_allclose(b, rig.anchors_O_m[i], atol=1e-12)
        checked += 1
        moved += bool(np.abs(p - rig.reference_position_O_m).max() > 1e-5)
    assert checked >= 10 and moved >= 5  # drawn at the camera's poses, not the reference


def test_cable_states_and_scene_geometry_by_hand() -> None:
    rig = load_rig(RIG)  # limits 35 .. 285 N: near the limit above 285 - 25 = 260 N
    T = [10.0, 35.0, 100.0, 259.0, 261.0, 285.0, 300.0, math.nan]
    assert cable_states(T, rig.t_min_N, rig.t_max_N) == [
        "slack", "ok", "ok", "ok", "near_limit", "near_limit", "saturated", "missing",
    ]  # fmt: skip
    p = np.array([0.51, -0.02, 0.37])
    R = rotation_from_euler(np.array([0.05, -0.1, 0.2]))
    g = scene_geometry(rig, p, R, T, airspeed_mps=20.0, force_O_N=[1.0, 0.0, 2.0],
                       mrp_P_m=(0.01, 0.0, 0.0))  # fmt: skip
    for i in range(rig.n_cables):  # p + R pp_i, written out
        pp = np.asarray(rig.attach_P_m[i])
        np.testing.assert_allclose(g.platform_points[i], p + R @ pp, atol=1e-12)
    np.testing.assert_allclose(g.axes_origin, p + R @ [0.01, 0.0, 0.0], atol=1e-12)
    # default mounting: nose upstream (-x_P), z_B down: body x = -R e_x, body z = -R e_z
    np.testing.assert_allclose(g.axes[0], -R[:, 0], atol=1e-12)
    np.testing.assert_allclose(g.axes[2], -R[:, 2], atol=1e-12)
    assert g.wind is not None and g.wind[2] == pytest.approx(0.1 + 0.004 * 20.0)
    assert g.force is not None and list(g.force[1]) == [1.0, 0.0, 2.0]


def test_mid_run_client_gets_the_same_messages(session: dict[str, Any]) -> None:
    first, mid = session["clients"]["first"], session["clients"]["mid"]
    assert mid.error is None
    assert set(mid.topics()) == set(first.topics())  # every channel advertised to a late client
    got = {
        (r.topic, r.log_time_ns): r.body
        for r in first.received
        if r.schema_name != "foxglove.SceneUpdate"
    }
    late = mid.of("/tensions/view")
    assert late, (mid.transcript, len(mid.received), mid.closed)
    assert late[0].log_time_ns > first.of("/tensions/view")[0].log_time_ns
    same = [r for r in late if (r.topic, r.log_time_ns) in got]
    assert len(same) >= 0.95 * len(late)
    assert all(r.body == got[(r.topic, r.log_time_ns)] for r in same)
    assert len(mid.of("/online")) >= 1


def test_a_client_that_stops_reading_costs_the_file_nothing(session: dict[str, Any]) -> None:
    stalled = session["clients"]["stalled"]
    assert stalled.error is None and len(stalled.received) == 40
    run = session["run"]
    truth = np.load(run.with_name(run.stem + ".truth.npz"))
    sent = int(np.sum(truth["sent"]))
    with run.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        counts = {c.topic: summary.statistics.channel_message_counts.get(cid, 0)
                  for cid, c in summary.channels.items()}  # fmt: skip
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    blocks = _block_samples(run, "/tensions")
    assert blocks == sent, (blocks, sent)  # every sample the rig sent is in the file
    assert meta["run_end"]["dropped_total"] == "0"
    assert counts["/tensions/view"] > 0
    assert "0 dropped" in session["stdout"]


def _block_samples(run: Path, topic: str) -> int:
    n = 0
    with run.open("rb") as fh:
        for _, _, msg in make_reader(fh).iter_messages(topics=[topic]):
            n += json.loads(msg.data)["count"]
    return n


def test_online_results_agree_with_analyze_and_the_report(session: dict[str, Any]) -> None:
    run, matrix, tmp = session["run"], session["matrix"], session["tmp"]
    out = tmp / "analysis"
    res = subprocess.run([*CLI, "analyze", str(run), "--out", str(out), "--matrix", str(matrix),
                          "--no-progress"], capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode in (0, 1), res.stderr
    (pts_file,) = out.glob("*/points.csv")
    pts = pd.read_csv(pts_file).set_index("point")
    # independent of the comparison code: the file's online_result events against points.csv
    f = _file_messages(run)
    online = {b["point"]: b for _, _, b in f["/events"] if b.get("name") == "online_result"}
    assert set(online) == set(pts.index)  # one final on-line result per point
    wind_on = [p for p in pts.index if pts.loc[p, "kind"] == "wind_on"]
    assert len(wind_on) == 4
    for p in wind_on:
        b = online[p]
        assert b["final"] is True and b["n_samples"] == pts.loc[p, "n_samples"]
        for c in ("CL", "CD", "Cm", "CY", "Cl", "Cn", "fx_N", "fz_N", "my_Nm"):
            assert abs(b[c] - pts.loc[p, c]) <= pts.loc[p, f"sd_{c}"], (p, c)
            # the same σ: to 1e-4, since the tare pose's model deflection (and with it the σ)
            # follows the point's tensions, whose zero drift is held on-line (no closing zero yet)
            assert b[f"sd_{c}"] == pytest.approx(pts.loc[p, f"sd_{c}"], rel=1e-4)
        assert "no_closing_zero" in b["flags"].split(";")  # the zero drift held on-line: said
    # cdpr analyze prints the comparison per point, and writes it into points.csv
    assert "on-line against final: 4 of 4 point(s) agree within 1 σ" in res.stdout
    assert "zero: on-line - final dfx_N" in res.stdout and "not judged" in res.stdout
    for p in wind_on:
        assert re.search(rf"{re.escape(p)}: on-line - final dCL .* -> agree", res.stdout)
        assert pts.loc[p, "online_agrees"] == "yes"
        assert pts.loc[p, "online_CL"] == pytest.approx(online[p]["CL"], abs=1e-12)
    # the live client saw the same final results on /online
    live_final = {r.body["point"]: r.body for r in session["clients"]["first"].of("/online")
                  if r.body.get("final")}  # fmt: skip
    assert {p: live_final[p]["CL"] for p in wind_on} == {p: online[p]["CL"] for p in wind_on}
    # the campaign's run page lists on-line against final values, and renders
    rep = tmp / "report"
    cmd = [*CLI, "campaign", str(out), "--out", str(rep), "--matrix", str(matrix), "--runs",
           str(run.parent)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode in (0, 1), res.stderr
    (page,) = rep.glob("run_*.html")
    html = page.read_text()
    assert "On-line against final values" in html and "agree (1σ)" in html
    assert "max |Δ|/σ" in html
    for p in wind_on:
        assert p in html
    png = tmp / "run_page.png"
    _screenshot(page, png)
    assert png.stat().st_size > 10_000
    session["screenshot"] = png


def _screenshot(page: Path, png: Path) -> None:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    assert exe, "chromium is not installed (make install installs it: Debian package chromium)"
    subprocess.run(
        [exe, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
         "--hide-scrollbars", f"--screenshot={png}", "--window-size=1600,2600", page.as_uri()],
        capture_output=True, timeout=120, check=True,
    )  # fmt: skip


def test_play_serves_the_run_with_the_analysis(session: dict[str, Any]) -> None:
    run, tmp = session["run"], session["tmp"]
    out = tmp / "analysis"
    if not out.exists():  # run on its own: the analysis first
        cmd = [*CLI, "analyze", str(run), "--out", str(out), "--matrix", str(session["matrix"]),
               "--no-progress"]  # fmt: skip
        subprocess.run(cmd, capture_output=True, timeout=300)
    cmd = [*CLI, "play", str(run), "--rate", "4", "--analysis", str(out), "--live-server", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    lines = [proc.stdout.readline(), proc.stdout.readline()]
    m = re.search(r"on (ws://127\.0\.0\.1:\d+) ", lines[1])
    assert m, "".join(lines)
    c = FoxgloveClient(m[1]).start()
    rest, err = proc.communicate(timeout=300)
    c.stop()
    assert proc.returncode == 0, err
    f = _file_messages(run)
    file_view = _by_time(f["/tensions/view"])
    live_view = c.of("/tensions/view")
    assert len(live_view) >= 0.9 * len(f["/tensions/view"])
    assert all(r.body in file_view[r.log_time_ns] for r in live_view)  # the same decimation
    pts = pd.read_csv(next(out.glob("*/points.csv"))).set_index("point")
    shown = {r.body["point"]: r.body for r in c.of("/analysis")}
    wind_on = [p for p in pts.index if pts.loc[p, "kind"] == "wind_on"]
    assert set(wind_on) <= set(shown)
    for p in wind_on:
        assert shown[p]["CL"] == pytest.approx(pts.loc[p, "CL"], rel=1e-12)
    assert c.topics()["/pose"].schema_name == "foxglove.PoseInFrame"


@pytest.mark.parametrize("command", ["simulate", "record"])
def test_port_in_use_is_one_line_and_exit_2_before_recording(tmp_path: Path, command: str) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        out = tmp_path / "runs"
        if command == "simulate":
            args = ["simulate", "--rig", str(RIG), "--schedule", str(DATA / "schedule_demo.toml")]
        else:
            args = ["record", "--config", str(DATA / "tunnel.toml"), "--duration", "1"]
        res = subprocess.run([*CLI, *args, "--out", str(out), "--quiet", "--live-server",
                              str(port)], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert f"--live-server: 127.0.0.1:{port}: port {port} is in use" in lines[0]
    assert "recording" not in res.stdout
    assert not list(out.glob("*.mcap")) if out.exists() else True


def test_bad_live_server_option(tmp_path: Path) -> None:
    res = subprocess.run([*CLI, "simulate", "--rig", str(RIG), "--schedule",
                          str(DATA / "schedule_demo.toml"), "--out", str(tmp_path), "--quiet",
                          "--live-server", "localhost:http"], capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert res.returncode == 2
    assert res.stderr.strip() == (
        "cdpr simulate: error: --live-server: localhost:http: expected [HOST:]PORT, e.g. 8765 "
        "or 0.0.0.0:8765"
    )


def test_the_writers_tap_never_waits_for_a_stuck_publisher() -> None:
    """The publisher stuck in the on-line feed: the writer's calls still return at once, the
    deque keeps the newest batches and counts the dropped ones."""
    import threading
    import time

    from cdpr.daq.live_server import LiveServer
    from cdpr.daq.source import Reading

    release = threading.Event()

    class StuckFeed:
        def feed(self, readings: Any) -> None:
            release.wait(30)

        def update(self, final: bool = False) -> tuple[Any, list[Any]]:
            return None, []

        def pending(self) -> int:
            return 0

    live = LiveServer(None, online=StuckFeed(), queue_batches=8)
    live.start()
    live.streams({})
    try:
        calls = []
        t_all = time.perf_counter()
        for k in range(5000):
            batch = [Reading("tensions", k, {"T_a_N": 1.0})]
            t0 = time.perf_counter()
            live(batch)
            calls.append(time.perf_counter() - t0)
        t_all = time.perf_counter() - t_all
        # never waits for the publisher (stuck for 30 s): all 5000 calls in a fraction of that,
        # a call a few microseconds (a deque append; a loaded machine may preempt a few)
        assert not release.is_set() and t_all < 10.0, t_all
        assert float(np.median(calls)) < 1e-3, np.median(calls)
        assert live.batches_in == 5000
        assert live.dropped_batches >= 5000 - 8 - 1  # the publisher holds one, the deque 8
    finally:
        release.set()
        live.stop()
    assert live.idle()


def test_terminal_view_shows_the_online_result(tmp_path: Path) -> None:
    """``cdpr simulate --campaign`` in a tmux pane (a terminal, no --live-server): the live view
    shows the on-line line of the open point with its coefficients."""
    import time

    matrix = tmp_path / "m.toml"
    matrix.write_text(MATRIX.format(data=DATA.as_posix()))
    session = f"cdpr-online-{time.monotonic_ns()}"
    tmux = ["tmux", "-L", session]  # a server of its own: no other tmux user can end it
    # the pane's size, not a COLUMNS/LINES the test runner may export
    cmd = " ".join(["env -u COLUMNS -u LINES", *CLI, "simulate", "--campaign", str(matrix),
                    "--out", str(tmp_path / "r"), "; sleep 60"])  # fmt: skip
    subprocess.run([*tmux, "new-session", "-d", "-s", session, "-x", "220", "-y", "70", cmd],
                   check=True)  # fmt: skip
    try:
        end = time.monotonic() + 240
        seen = screen = ""
        while time.monotonic() < end:
            cap = subprocess.run([*tmux, "capture-pane", "-p", "-t", session],
                                 capture_output=True, text=True)  # fmt: skip
            screen = cap.stdout or cap.stderr
            m = re.search(r"on-line  alpha-a\d-b0-v[\d.]+ \((steady|final), \d+ samples\).*CL "
                          r"-?\d\.\d{4} ± \d\.\d{4}", screen)  # fmt: skip
            if m:
                seen = m[0]
                break
            time.sleep(0.2)
        assert seen, screen
    finally:
        subprocess.run([*tmux, "kill-server"], capture_output=True)
