"""``cdpr import``: a run recorded by other tools (a CAN log plus a pose CSV) as a normal MCAP run.

The CAN log is anything python-can reads (candump ``.log``, ``.asc``, ``.blf``, ...); its frames are
kept (``/can_raw``) and decoded with the DBC into ``/tensions`` exactly as the live CAN driver does.
The optional pose CSV has a time column, ``t_ns`` (ns since the Unix epoch) or ``t_s`` (seconds
from the first CAN frame), and the pose columns ``x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad``;
each row becomes a ``/pose`` message (``foxglove.PoseInFrame``, platform {P} in the tunnel frame {O}).
The rig, DBC, calibration and pose files are attached.  The output is written to a temporary file
and appears under its name only when complete; an existing file is never overwritten.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "import",
        help="turn a CAN log (candump/ASC/BLF) plus a pose CSV into a normal MCAP run",
    )
    p.add_argument("--can-log", required=True, help="CAN log (.log candump, .asc, .blf, ...)")
    p.add_argument("--dbc", required=True, help="DBC of the load-cell amplifier")
    p.add_argument("--poses", help="pose CSV (t_ns or t_s, x_m, y_m, z_m, roll_rad, ...)")
    p.add_argument("--rig", required=True, help="rig file (TOML); cable names come from it")
    p.add_argument(
        "--calibration",
        help="load-cell calibration file (written by `cdpr calibrate loadcells`)",
    )
    p.add_argument(
        "--tunnel",
        help="tunnel conditions CSV (t_ns or t_s, airspeed_mps, density_kgpm3 or "
        "static_pressure_Pa + temperature_K): the /tunnel stream",
    )
    p.add_argument(
        "--events",
        help="test-point events CSV (t_ns or t_s, point, phase start|end, kind, optional "
        "target_aoa_deg, target_sideslip_deg, target_airspeed_mps, repeat_of): /events",
    )
    p.add_argument("--rate", type=float, default=0.0, help="nominal sample rate, Hz (metadata)")
    p.add_argument("--label", default="import", help="label recorded in the metadata")
    p.add_argument("--out", required=True, help="output run file (.mcap, never overwritten)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    from cdpr.analysis.conventions import POSE_COLUMNS
    from cdpr.analysis.errors import ConfigError, InputError
    from cdpr.analysis.rotations import quaternion_from_euler
    from cdpr.daq.mcap_io import McapRunWriter
    from cdpr.daq.recorder import Attachment
    from cdpr.daq.replay import CanReplaySource
    from cdpr.daq.runs import run_metadata
    from cdpr.daq.source import FieldDescription, Reading, StreamDescription

    from .. import __version__
    from ..config import file_sha256, load_rig, read_table

    out = Path(args.out)
    if out.exists():
        raise InputError(f"{out}: exists already; a run is never overwritten")
    for opt, val in (("--can-log", args.can_log), ("--dbc", args.dbc)):
        if not Path(val).is_file():
            raise ConfigError(val, "", f"file not found ({opt})")
    if not (np.isfinite(args.rate) and args.rate >= 0):
        raise InputError(f"--rate: expected a finite sample rate >= 0 Hz, got {args.rate}")
    _check_can_log(args.can_log)
    rig = load_rig(args.rig)
    cal: dict[str, object] = {}
    if args.calibration:  # the file `cdpr calibrate loadcells` writes
        from cdpr.daq.loadcell import read_calibration_file

        cal = dict(read_calibration_file(args.calibration).settings(rig.cable_names))
    poses = None
    if args.poses:
        df = read_table(args.poses, POSE_COLUMNS, "pose table")
        if "t_ns" in df.columns:
            tcol = "t_ns"
        elif "t_s" in df.columns:
            tcol = "t_s"
        else:
            raise ConfigError(args.poses, "column t_ns", "missing: need a t_ns or t_s column")
        tv = _pose_times(args.poses, df, tcol)
        poses = (tcol, tv, df[list(POSE_COLUMNS)].to_numpy(dtype=np.float64))

    side = _read_side_tables(args)

    try:
        src = CanReplaySource(
            "can",
            path=str(args.can_log),
            speed="max",
            dbc=str(args.dbc),
            cables=list(rig.cable_names),
            rate_hz=args.rate,
            timestamps="log",
            origin=str(args.can_log),
            **cal,  # type: ignore[arg-type]
        )
    except ConfigError as exc:  # name the file that holds the bad value, not the CAN log
        key = exc.key.rsplit(".", 1)[-1]
        if args.calibration and key in ("offset_counts", "gain_N_per_count"):
            raise ConfigError(args.calibration, key, exc.problem) from None
        if key == "dbc":
            raise ConfigError(args.dbc, "", exc.problem) from None
        if key == "cables":  # the rig's cables against the DBC's channels
            raise ConfigError(args.rig, "cables", exc.problem) from None
        raise
    tmp = out.with_name(f".{out.name}.part")
    tmp.unlink(missing_ok=True)
    start_ns = time.time_ns()
    counts: dict[str, int] = {}
    try:
        w = McapRunWriter(tmp, flush_interval_s=1.0)
        try:
            md = run_metadata(
                label=args.label,
                start_ns=start_ns,
                software_version=__version__,
                rig=rig.name,
                rig_sha256=file_sha256(args.rig),
                calibration_ids={
                    "dbc": f"{Path(args.dbc).name}@{file_sha256(args.dbc)[:12]}",
                    **(
                        {
                            "calibration": f"{Path(args.calibration).name}@"
                            f"{file_sha256(args.calibration)[:12]}"
                        }  # fmt: skip
                        if args.calibration
                        else {}
                    ),
                },
                config={"command": "import", "source": src.settings()},
                notes=f"imported from {Path(args.can_log).name}",
                extra={
                    "command": "import",
                    "can_log": Path(args.can_log).name,
                    "can_log_sha256": file_sha256(args.can_log),
                    "poses": Path(args.poses).name if args.poses else "",
                    "poses_sha256": file_sha256(args.poses) if args.poses else "",
                    **_side_provenance(args),
                },
            )
            w.add_metadata("run", md)
            w.add_attachment(
                "rig/" + Path(args.rig).name, Path(args.rig).read_bytes(), "application/toml"
            )
            a = Attachment.from_file(args.dbc, "calibration/" + Path(args.dbc).name)
            w.add_attachment(a.name, a.data, a.media_type)
            if args.calibration:
                a = Attachment.from_file(
                    args.calibration, "calibration/" + Path(args.calibration).name
                )
                w.add_attachment(a.name, a.data, a.media_type)
            if args.poses:
                a = Attachment.from_file(args.poses, "poses/" + Path(args.poses).name)
                w.add_attachment(a.name, a.data, a.media_type)
            for stream, desc in src.describe().items():
                w.add_stream(stream, desc)
            first_ns: int | None = None
            with src:
                while True:
                    batch = src.read(0.5)
                    for r in batch:
                        if first_ns is None:
                            first_ns = r.t_ns
                        w.write(r)
                    if not batch and src.exhausted:
                        break
            if poses is not None:
                tcol, tv, q6 = poses
                if tcol == "t_s":
                    if first_ns is None:
                        raise ConfigError(
                            args.poses, "column t_s", "relative times need CAN frames in the log"
                        )
                    t_ns = first_ns + np.round(tv.astype(np.float64) * 1e9).astype(np.int64)
                else:
                    t_ns = tv.astype(np.int64)
                w.add_stream(
                    "pose",
                    StreamDescription(
                        {
                            "position_O_m": FieldDescription("m", shape=(3,)),
                            "quaternion_xyzw": FieldDescription("", shape=(4,)),
                            "euler_rad": FieldDescription("rad", shape=(3,)),
                        },
                        0.0,
                        "Imported platform pose, P in {O}.",
                    ),
                )
                q_wxyz = quaternion_from_euler(q6[:, 3:6])
                for k in range(len(t_ns)):
                    w.write(
                        Reading(
                            "pose",
                            int(t_ns[k]),
                            {
                                "position_O_m": q6[k, :3].tolist(),
                                "quaternion_xyzw": [*q_wxyz[k, 1:].tolist(), float(q_wxyz[k, 0])],
                                "euler_rad": q6[k, 3:].tolist(),
                                "frame_id": "O",
                            },
                        )
                    )
            _write_side_tables(w, args, side, first_ns)
            counts = dict(w.counts)
            w.add_metadata(
                "run_end",
                {
                    "stop_reason": "import complete",
                    "message_counts": counts,
                    "source_stats": vars(src.stats),
                },
            )
        finally:
            w.finish()
        os.link(tmp, out)  # fails if out appeared meanwhile: never overwrite
        tmp.unlink()
    except FileExistsError:
        tmp.unlink(missing_ok=True)
        raise InputError(f"{out}: exists already; a run is never overwritten") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    print(f"wrote {out}: " + ", ".join(f"{k} {v}" for k, v in counts.items() if v))
    return 0


def _check_can_log(path: str) -> None:
    """Bad input unless python-can reads at least one frame from the log (before any output)."""
    import can

    from cdpr.analysis.errors import ConfigError

    try:
        reader = can.LogReader(path)
    except (ValueError, OSError) as exc:
        raise ConfigError(path, "", f"cannot read the CAN log: {exc}") from None
    try:
        next(iter(reader))
    except StopIteration:
        raise ConfigError(path, "", "no CAN frames in the log") from None
    except Exception as exc:  # python-can raises what its parsers raise
        raise ConfigError(path, "first frame", f"not a CAN log python-can reads: {exc}") from None
    finally:
        if hasattr(reader, "stop"):
            reader.stop()


def _pose_times(path: str, df: Any, tcol: str) -> Any:
    """The pose time column: finite numbers that never decrease; ``t_ns`` must be integers."""
    from ..import_tables import table_times

    return table_times(path, df)[1]


def _read_side_tables(args: argparse.Namespace) -> dict[str, Any]:
    """The ``--tunnel`` and ``--events`` tables, checked before anything is written."""
    from ..import_tables import read_events_csv, read_tunnel_csv

    side: dict[str, Any] = {}
    if args.tunnel:
        side["tunnel"] = read_tunnel_csv(args.tunnel)
    if args.events:
        side["events"] = read_events_csv(args.events)
    return side


def _side_provenance(args: argparse.Namespace) -> dict[str, str]:
    from ..config import file_sha256

    out = {}
    for key in ("tunnel", "events"):
        f = getattr(args, key)
        out[key] = Path(f).name if f else ""
        out[f"{key}_sha256"] = file_sha256(f) if f else ""
    return out


def _write_side_tables(
    w: Any, args: argparse.Namespace, side: dict[str, Any], first_ns: Any
) -> None:
    """Attach the side tables and write ``/tunnel`` and ``/events`` (times from the first CAN
    frame for ``t_s`` columns)."""
    from cdpr.daq.recorder import Attachment

    from ..import_tables import event_stream, tunnel_stream

    for key, make in (("tunnel", tunnel_stream), ("events", event_stream)):
        if key not in side:
            continue
        f = getattr(args, key)
        a = Attachment.from_file(f, f"{key}/" + Path(f).name)
        w.add_attachment(a.name, a.data, a.media_type)
        desc, readings = make(side[key], first_ns)
        w.add_stream(key, desc)
        for r in readings:
            w.write(r)
