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
    p.add_argument(
        "--cable-lengths",
        help="the controller's cable-length log (CSV: t_ns or t_s, L_<cable>_m per cable): the "
        "pose by forward kinematics with its covariance, instead of --poses "
        "(docs/dynamic_tests.md)",
    )
    p.add_argument(
        "--length-sd-m",
        type=float,
        help="σ of each logged cable length, m (required with --cable-lengths)",
    )
    p.add_argument(
        "--raw-only",
        action="store_true",
        help="keep the log's frames (/can_raw) even when none is a load-cell frame of the DBC "
        "(without it, a log with no decodable sample is an error)",
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
    from cdpr.daq.mcap_writer import McapRunWriter
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
    lengths = _read_cable_lengths(args, rig)

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
        w = McapRunWriter(tmp, flush_interval_s=1.0, background_compression=True)
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
                    "cable_lengths": Path(args.cable_lengths).name if args.cable_lengths else "",
                    "cable_lengths_sha256": file_sha256(args.cable_lengths)
                    if args.cable_lengths
                    else "",
                    "cable_length_sd_m": args.length_sd_m,
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
                # the decoded samples and the raw frames as column blocks, whatever the rate
                w.add_stream(
                    stream, desc, blocks=True if stream in ("tensions", "can_raw") else None
                )
            first_ns, can_stats = _write_can_log(w, src, args.can_log, start_ns)
            if (
                can_stats["samples"] == 0 and not args.raw_only
            ):  # nothing decoded: a wrong DBC, bus or log
                raise ConfigError(
                    args.dbc,
                    "",
                    f"no load-cell sample decoded from the {can_stats['frames']} frame(s) of "
                    f"{args.can_log}: the DBC's message ids match no frame of the log",
                )
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
            if lengths is not None:
                _write_length_poses(w, args, lengths, first_ns)
            _write_side_tables(w, args, side, first_ns)
            counts = dict(w.counts)
            w.add_metadata(
                "run_end",
                {
                    "stop_reason": "import complete",
                    "message_counts": counts,
                    "source_stats": vars(src.stats),
                    "can_log": can_stats,
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
    dropped = can_stats["partial_samples_dropped"]
    if dropped:
        print(
            f"note: dropped {dropped} partial sample(s) where the log starts or ends mid-sample "
            "(their frames are in /can_raw)"
        )
    return 0


def _write_can_log(w: Any, src: Any, path: str, start_ns: int) -> tuple[int | None, dict[str, int]]:
    """Write the frames of the CAN log (``/can_raw``) and the samples the source's decoder makes of
    them (``/tensions``), a block of frames at a time (:func:`cdpr.daq.canlog.read_log`: candump
    parsed with numpy, other formats through python-can), with a progress bar on stderr.

    Times as the replay source gives them (``timestamps = "log"``): a frame's log time is its
    timestamp, or for a log with relative times (below ~1973) ``start_ns`` plus its offset from the
    first frame.  A partial sample at the log's very start or end (cut mid-sample) is dropped and
    counted; partial samples inside the log are kept, flagged (status gap).  Returns the first
    log time and the counts."""
    import numpy as np

    from cdpr.daq import can_raw
    from cdpr.daq.canlog import BRS, ERROR, ESI, EXTENDED, FD, REMOTE, RX, read_log
    from cdpr.daq.replay import _RELATIVE_LIMIT_S
    from cdpr.daq.source import STATUS_BAD_FRAME, STATUS_GAP

    dec = src.decoder
    fids = np.array(dec.frame_ids if dec is not None else [], np.int64)
    stats = {"frames": 0, "samples": 0, "partial_samples_dropped": 0}
    first_ns: int | None = None
    log_t0: float | None = None
    progress = _Progress(Path(path).stat().st_size)

    def emit(samples: list[Any], at_end: bool = False) -> None:
        for r in samples:
            # a partial sample where the log starts or ends mid-sample: dropped, counted
            if (at_end or stats["samples"] == 0) and r.status & STATUS_GAP:
                stats["partial_samples_dropped"] += 1
                continue
            w.write(r)
            stats["samples"] += 1

    for cols in read_log(path, progress=progress.update):
        n = len(cols)
        if log_t0 is None:
            log_t0 = float(cols.t_s[0])
        t_bus = cols.t_bus_ns
        rel = cols.t_s < _RELATIVE_LIMIT_S
        t_ns = np.where(rel, start_ns + np.rint((cols.t_s - log_t0) * 1e9).astype(np.int64), t_bus)
        if first_ns is None:
            first_ns = int(t_ns[0])
        fl = cols.flags
        codes, table = _channel_codes(cols.channel)
        bits = {
            "is_extended": fl & EXTENDED, "is_remote": fl & REMOTE, "is_error_frame": fl & ERROR,
            "is_fd": fl & FD, "bitrate_switch": fl & BRS, "error_state_indicator": fl & ESI,
        }  # fmt: skip
        w.write_columns(
            "can_raw",
            t_ns,
            can_raw.block_columns(
                cols.arbitration_id, bits, cols.dlc, cols.data, cols.length, codes, fl & RX, t_bus
            ),
            np.where(fl & ERROR, STATUS_BAD_FRAME, 0),
            {"channel": table},
        )
        if dec is not None:
            lc = np.flatnonzero(
                np.isin(cols.arbitration_id, fids) & ((fl & (ERROR | REMOTE | EXTENDED)) == 0)
            )
            _decode_frames(w, dec, src, cols, lc, t_ns, t_bus, emit, stats)
        stats["frames"] += n
    if dec is not None:
        emit(dec.flush(), at_end=True)
    progress.done()
    return first_ns, stats


def _channel_codes(channel: Any) -> tuple[Any, list[Any]]:
    """Indexes (n,) into a table of the distinct channels (as python-can gives them: a name, a
    number or None) of a block of frames."""
    import numpy as np
    import pandas as pd

    ch0 = channel[0]
    if ch0 is not None and bool(np.all(channel == ch0)):  # one channel (the usual log)
        return np.zeros(len(channel), np.uint8), [ch0]
    codes, uniq = pd.factorize(channel, use_na_sentinel=False)
    return codes, [None if u is None or u != u else u for u in uniq.tolist()]


def _decode_frames(
    w: Any, dec: Any, src: Any, cols: Any, lc: Any, t_ns: Any, t_bus: Any, emit: Any, stats: Any
) -> None:
    """Decode the load-cell frames ``lc`` (indexes into ``cols``): whole samples at once with
    ``dec.decode_block`` where the frames are regular, the others frame by frame with
    ``dec.decode`` (the same decoder state throughout)."""
    import numpy as np

    i, n_lc = 0, len(lc)
    nf = len(dec.frame_ids)
    by_frame = 0  # frames to decode one by one before trying a block again
    while i < n_lc:
        if not by_frame and dec._pending_counter is None and stats["samples"] > 0:
            sel = lc[i : i + 65536]
            lost0 = dec.lost
            m, s = dec.decode_block(
                cols.arbitration_id[sel], np.zeros(len(sel), bool), cols.data[sel],
                cols.length[sel], t_ns[sel], t_bus[sel],
            )  # fmt: skip
            if m:
                src.stats.lost += dec.lost - lost0
                _write_samples(w, s)
                stats["samples"] += len(s["t_ns"])
                i += m
                continue
            by_frame = nf  # an irregular sample: at least its frames one by one
        j = int(lc[i])
        lost0 = dec.lost
        emit(dec.decode(cols.message(j), int(t_ns[j])))
        src.stats.lost += dec.lost - lost0
        i += 1
        by_frame = max(0, by_frame - 1)


def _write_samples(w: Any, s: dict[str, Any]) -> None:
    """``tensions`` samples given as columns (``t_ns``, the stream's fields, ``status``), written
    as they are (:meth:`~cdpr.daq.mcap_writer.McapRunWriter.write_columns`)."""
    cols = {k: v for k, v in s.items() if k not in ("t_ns", "status")}
    w.write_columns("tensions", s["t_ns"], cols, s["status"])


class _Progress:
    """A progress bar on stderr (bytes of the log read) for imports that take more than ~2 s."""

    def __init__(self, total_bytes: int) -> None:
        import time

        self.total = max(1, total_bytes)
        self.t0 = time.monotonic()
        self.shown = False

    def update(self, done_bytes: int) -> None:
        import sys
        import time

        dt = time.monotonic() - self.t0
        if dt < 2.0:
            return
        self.shown = True
        frac = min(1.0, done_bytes / self.total)
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\rimport [{bar:<30s}] {100 * frac:5.1f}% {dt:6.1f} s")
        sys.stderr.flush()

    def done(self) -> None:
        import sys

        if self.shown:
            sys.stderr.write("\n")
            sys.stderr.flush()


def _check_can_log(path: str) -> None:
    """Bad input unless the log holds at least one frame (before any output): an ASC log through
    the numpy parser (:func:`cdpr.daq.canlog.read_asc`, which names a bad line), other formats
    through python-can."""
    import can

    from cdpr.analysis.errors import ConfigError

    if Path(path).suffix.lower() == ".asc":
        from cdpr.daq.canlog import read_asc

        if next(iter(read_asc(path)), None) is None:
            raise ConfigError(path, "", "no CAN frames in the log")
        return
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


def _read_cable_lengths(args: argparse.Namespace, rig: Any) -> Any:
    """The ``--cable-lengths`` log as poses (:mod:`cdpr.pipelines.cable_lengths`), checked before
    anything is written; one pose source only."""
    from cdpr.analysis.errors import ConfigError

    if not args.cable_lengths:
        if args.length_sd_m is not None:
            raise ConfigError("--length-sd-m", "", "given without --cable-lengths")
        return None
    if args.poses:
        raise ConfigError(
            args.cable_lengths, "--cable-lengths", "one pose source: not with --poses"
        )
    from ..cable_lengths import read_cable_lengths

    return read_cable_lengths(args.cable_lengths, rig, args.length_sd_m)


def _write_length_poses(w: Any, args: argparse.Namespace, lengths: Any, first_ns: Any) -> None:
    """Attach the cable-length log and write its poses as ``/pose``."""
    import numpy as np

    from cdpr.analysis.errors import ConfigError
    from cdpr.daq.recorder import Attachment

    from ..cable_lengths import pose_readings

    a = Attachment.from_file(args.cable_lengths, "cable_lengths/" + Path(args.cable_lengths).name)
    w.add_attachment(a.name, a.data, a.media_type)
    if lengths.time_column == "t_s":
        if first_ns is None:
            raise ConfigError(args.cable_lengths, "column t_s", "relative times need CAN frames")
        t_ns = first_ns + np.round(lengths.times.astype(np.float64) * 1e9).astype(np.int64)
    else:
        t_ns = lengths.times.astype(np.int64)
    desc, readings = pose_readings(lengths, t_ns)
    w.add_stream("pose", desc)
    w.write_many(readings)


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
