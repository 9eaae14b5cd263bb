"""``cdpr play RUN.mcap``: serve a recorded run to Foxglove the way ``record --live-server`` does.

The run is read through ``open_run`` a few seconds at a time (bounded memory) and fed, paced at
``--rate`` times real time, into the same live server as a recording (:mod:`cdpr.daq.live_server`):
the same topics and schema names, the high-rate streams decimated for display, the 3D scene.  With
``--analysis DIR`` (``cdpr analyze --out``; by default an ``analysis/`` folder here or beside the
run's folder when it holds this run) the analysis of the run is overlaid: during each test
point, its final values (wrench, coefficients, σ, flags) on ``/analysis`` and its aerodynamic force
in the scene.  ``--loop`` starts again at the end (the clients are told to reset).  Not replayed:
``/can_raw`` (the decoded tensions are) and the per-sample views (the server makes its own).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

WINDOW_NS = 2_000_000_000
"""The run is read this much at a time."""
STEP_NS = 10_000_000
"""Readings are handed to the server in steps of this much run time."""

ANALYSIS_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "cdpr.analysis_point",
    "description": "cdpr analyze's final values of the test point being replayed (points.csv): "
    "wrench at the moment reference point in {O} axes with sigma, coefficients with sigma, flags",
    "additionalProperties": True,
}


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "play",
        help="serve a recorded run (MCAP) to Foxglove as the live server does, with the analysis",
        description="Replay RUN.mcap to Foxglove over a WebSocket (foxglove-sdk): the topics of "
        "the live server, paced at --rate; --analysis overlays cdpr analyze's results.",
    )
    p.add_argument("run", help="the run file (.mcap)")
    p.add_argument("--rate", type=float, default=1.0, help="speed, times real time (default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument(
        "--analysis",
        help="cdpr analyze's output folder (--out): the run's points.csv is overlaid (default: "
        "analysis/ here or beside the run's folder, when it holds this run)",
    )
    from .record import add_live_argument

    add_live_argument(p)
    p.set_defaults(func=run)


def _derived(topic: str, info: Any) -> bool:
    """Topics the live server makes itself from another stream (a view, a pose's status) or does
    not replay (``/can_raw``)."""
    return (
        "view_of" in info.metadata
        or "status_of" in info.metadata
        or topic.rstrip("/").endswith("can_raw")
    )


def _descriptions(run: Any) -> dict[str, Any]:
    """A stream description per replayed topic, from the run's schemas (so the live server picks
    the same codec, schema name and view as the recorder did)."""
    from cdpr.daq.source import FieldDescription, StreamDescription

    dtypes = {"number": "float64", "integer": "int64", "string": "str", "boolean": "bool"}
    out = {}
    for topic, info in run.streams.items():
        if _derived(topic, info):
            continue
        fields = {
            k: FieldDescription(f.unit, dtypes.get(f.type, "float64"), tuple(f.shape))
            for k, f in info.fields.items()
            if k != "status" and f.type in dtypes
        }
        out[topic.lstrip("/")] = StreamDescription(fields, float(info.rate_hz or 0.0))
    return out


def _readings(run: Any, topic: str, a: int, b: int) -> list[Any]:
    """The readings of ``topic`` with times in ``[a, b)`` (what the recorder had written)."""
    import base64

    import numpy as np

    from cdpr.daq.source import Reading

    info = run.streams[topic]
    if not info.count or info.stop_ns is None or info.stop_ns < a or info.start_ns >= b:
        return []
    df = run.table(topic, start_ns=a, stop_ns=b)
    stream = topic.lstrip("/")
    out = []
    cols = [c for c in df.columns if c not in ("t_ns", "status")]
    st = df["status"].fillna(0).to_numpy(np.int64) if "status" in df else np.zeros(len(df), int)
    t_all = df["t_ns"].to_numpy(np.int64)
    rows = df[cols].to_dict("records")
    pose = info.schema_name == "foxglove.PoseInFrame"
    image = info.schema_name == "foxglove.CompressedImage"
    for t, s, row in zip(t_all.tolist(), st.tolist(), rows, strict=True):
        v = {k: x for k, x in row.items() if not (isinstance(x, float) and math.isnan(x))}
        if pose:
            v = {
                "position_O_m": [row.get("x_m"), row.get("y_m"), row.get("z_m")],
                "quaternion_wxyz": [row.get("qw"), row.get("qx"), row.get("qy"), row.get("qz")],
            }
        elif image and isinstance(v.get("data"), str):
            v["data"] = base64.b64decode(v["data"])
        out.append(Reading(stream, int(t), v, int(s)))
    return out


def _overlay(analysis: str | None, path: Path) -> Any:
    """The run's per-point table from ``cdpr analyze``'s folder (``--analysis``; without it an
    ``analysis/`` folder here or beside the run's folder when it holds this run), or None (said
    on stdout)."""
    import pandas as pd

    from cdpr.analysis.errors import ConfigError

    from ..analyze import result_folder

    if analysis is None:
        for guess in (Path("analysis"), path.resolve().parent.parent / "analysis"):
            if (result_folder(str(path), str(guess)) / "points.csv").is_file():
                analysis = str(guess)
                break
        else:
            print("no analysis overlay (no analysis/ folder with this run; give --analysis, the "
                  "folder of cdpr analyze --out)")  # fmt: skip
            return None

    f = result_folder(str(path), analysis) / "points.csv"
    if not f.is_file():
        raise ConfigError(analysis, f.name, f"no {f} (run cdpr analyze {path} --out {analysis})")
    df = pd.read_csv(f, comment="#")
    print(f"analysis overlay: {f} ({len(df)} points)")
    return df


def _point_at(df: Any, t_ns: int) -> Any:
    if df is None:
        return None
    hit = df[(df["start_ns"] <= t_ns) & (df["stop_ns"] >= t_ns)]
    return None if hit.empty else hit.iloc[0]


def _body(row: Any) -> dict[str, Any]:
    keep = ("point", "kind", "flags", "start_ns", "stop_ns", "airspeed_mps", "q_Pa", "aoa_rad",
            "sideslip_rad", "fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm", "CD", "CY", "CL",
            "Cl", "Cm", "Cn")  # fmt: skip
    out: dict[str, Any] = {}
    for k in keep + tuple(f"sd_{c}" for c in keep[9:]):
        if k in row.index:
            v = row[k]
            out[k] = v.item() if hasattr(v, "item") else v
    return out


def run(args: argparse.Namespace) -> int:
    from cdpr.analysis.errors import ConfigError, InputError
    from cdpr.daq.live_server import DEFAULT_HOST, LiveAddress, LiveServer, parse_address
    from cdpr.daq.run_reader import open_run

    from ..run_arrays import _run_rig

    if not (math.isfinite(args.rate) and args.rate > 0):
        raise InputError(f"--rate must be > 0, got {args.rate}")
    path = Path(args.run)
    if not path.is_file():
        raise ConfigError(args.run, "", "no such run file")
    address = (
        parse_address(args.live_server)
        if args.live_server is not None
        else LiveAddress(DEFAULT_HOST, 8765)
    )
    overlay = _overlay(args.analysis, path)
    with open_run(path) as rec:
        rig = _run_rig(rec, path)
        topics = [t for t, i in rec.streams.items() if not _derived(t, i) and i.count]
        starts = [i.start_ns for t, i in rec.streams.items() if t in topics]
        stops = [i.stop_ns for t, i in rec.streams.items() if t in topics]
        if not starts:
            raise ConfigError(args.run, "", "no messages to replay")
        t0, t1 = min(starts), max(stops)
        live = LiveServer(address, rig=rig, name="cdpr play")
        live.start()
        live.streams(_descriptions(rec))
        print(
            f"playing {path.name} ({(t1 - t0) / 1e9:.1f} s at {args.rate:g}x) on {live.url} "
            "(Foxglove: Open connection -> Foxglove WebSocket; layout "
            "data_samples/foxglove_layout.json); Ctrl-C stops",
            flush=True,
        )
        try:
            while True:
                _play_once(rec, topics, t0, t1, args.rate, live, overlay)
                if not args.loop:
                    break
                live.new_session()
            end = time.monotonic() + 5.0
            while not live.idle() and time.monotonic() < end:
                time.sleep(0.01)
        finally:
            live.stop()
    print(f"played {path.name}: {live.published} messages published")
    return 0


def _play_once(
    rec: Any, topics: list[str], t0: int, t1: int, rate: float, live: Any, overlay: Any
) -> None:
    wall0 = time.monotonic()
    current = None
    for a in range(t0, t1 + 1, WINDOW_NS):
        b = a + WINDOW_NS
        got = [r for t in topics for r in _readings(rec, t, a, b)]
        got.sort(key=lambda r: r.t_ns)
        k = 0
        for step in range(a, b, STEP_NS):
            batch = []
            while k < len(got) and got[k].t_ns < step + STEP_NS:
                batch.append(got[k])
                k += 1
            if not batch:
                continue
            delay = wall0 + (step - t0) / 1e9 / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            row = _point_at(overlay, step)
            if row is not None and (current is None or row["point"] != current):
                current = row["point"]
                body = _body(row)
                live.publish_json("/analysis", ANALYSIS_SCHEMA, body, step)
                F = [body.get(c) for c in ("fx_N", "fy_N", "fz_N")]
                ok = all(isinstance(x, float) and math.isfinite(x) for x in F)
                live.force_O_N = F if ok else None
            elif row is None and current is not None:
                current, live.force_O_N = None, None
            live(batch)
