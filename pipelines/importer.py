"""``cdpr import``: a run recorded by other tools (a CAN log, a pose CSV, the tunnel's log, the
test-point list) made a normal MCAP run.

The CAN log is anything :func:`cdpr.daq.canlog.read_log` reads (candump ``.log``, Vector ``.asc``
and ``.blf``, PEAK ``.trc``, python-can's ``.csv``, and the rest through python-can); its frames are
kept (``/can_raw``) and decoded with the DBC into ``/tensions`` by the decoder the live CAN driver
uses (:mod:`cdpr.daq.can_import`).  The pose CSV (with its optional covariance), the tunnel and
events CSVs are read and checked by :mod:`cdpr.pipelines.import_tables` before anything is
written.  The rig, DBC, calibration and side files are attached; the run is written to a
temporary file and appears under its name only when complete; an existing file is never
overwritten.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError, InputError
from cdpr.daq.can_decoder import build_decoder
from cdpr.daq.can_import import Progress, import_can_log
from cdpr.daq.can_raw import DESCRIPTION as CAN_RAW_DESCRIPTION
from cdpr.daq.mcap_writer import McapRunWriter
from cdpr.daq.recorder import Attachment
from cdpr.daq.runs import run_metadata

from . import __version__
from .config import file_sha256, load_rig
from .import_tables import (
    TimedTable,
    event_stream,
    pose_stream,
    read_events_csv,
    read_pose_csv,
    read_tunnel_csv,
    tunnel_stream,
)


@dataclass
class ImportRequest:
    """What ``cdpr import`` is asked (the CLI's arguments; files as paths, "" or None: not
    given)."""

    can_log: str
    dbc: str
    rig: str
    out: str
    poses: str | None = None
    pose_sd: Sequence[float] | None = None
    calibration: str | None = None
    tunnel: str | None = None
    events: str | None = None
    raw_only: bool = False
    rate_hz: float = 0.0
    label: str = "import"
    cable_lengths: str | None = None
    length_sd_m: float | None = None


@dataclass
class ImportReport:
    """What an import wrote (``counts`` per stream) and the notes to tell the user."""

    out: Path
    counts: dict[str, int]
    notes: list[str] = field(default_factory=list)


def import_run(req: ImportRequest) -> ImportReport:
    """Check every input, then write the run (see the module docstring); bad input is a
    ConfigError or InputError naming the file and key, row or line, with no output left."""
    out = Path(req.out)
    if out.exists():
        raise InputError(f"{out}: exists already; a run is never overwritten")
    for opt, val in (("--can-log", req.can_log), ("--dbc", req.dbc)):
        if not Path(val).is_file():
            raise ConfigError(val, "", f"file not found ({opt})")
    if not (np.isfinite(req.rate_hz) and req.rate_hz >= 0):
        raise InputError(f"--rate: expected a finite sample rate >= 0 Hz, got {req.rate_hz}")
    rig = load_rig(req.rig)
    cal: dict[str, Any] = {}
    if req.calibration:  # the file `cdpr calibrate loadcells` writes
        from cdpr.daq.loadcell import read_calibration_file

        cal = dict(read_calibration_file(req.calibration).settings(rig.cable_names))
    poses = read_pose_csv(req.poses) if req.poses else None
    pose_cov_source = _pose_cov_source(req, poses)
    lengths = _read_cable_lengths(req, rig)
    if lengths is not None:
        pose_cov_source = (
            f"forward kinematics of {Path(req.cable_lengths or '').name}, "
            f"length sd {req.length_sd_m:g} m"
        )
    side = {k: f(v) for k, f, v in (("tunnel", read_tunnel_csv, req.tunnel),
                                     ("events", read_events_csv, req.events)) if v}  # fmt: skip
    decoder = _decoder(req, list(rig.cable_names), cal)

    tmp = out.with_name(f".{out.name}.part")
    tmp.unlink(missing_ok=True)
    start_ns = time.time_ns()
    notes: list[str] = []
    try:
        w = McapRunWriter(tmp, flush_interval_s=1.0, background_compression=True)
        try:
            w.add_metadata("run", _metadata(req, rig.name, decoder, start_ns, pose_cov_source))
            _attach(w, req)
            w.add_stream("can_raw", CAN_RAW_DESCRIPTION)  # frame blocks
            w.add_stream("tensions", decoder.describe(req.rate_hz), blocks=True)
            progress = Progress(req.can_log)
            first_ns, stats = import_can_log(w, req.can_log, decoder, start_ns, progress.update)
            progress.done()
            if stats.samples == 0 and not req.raw_only:  # a wrong DBC, bus or log
                raise ConfigError(
                    req.dbc,
                    "",
                    f"no load-cell sample decoded from the {stats.frames} frame(s) of "
                    f"{req.can_log}: the DBC's message ids match no frame of the log",
                )
            if poses is not None:
                desc, readings = pose_stream(poses, first_ns, req.pose_sd)
                w.add_stream("pose", desc)
                w.write_many(readings)
            if lengths is not None:
                desc, readings = _length_pose_stream(req, lengths, first_ns)
                w.add_stream("pose", desc)
                w.write_many(readings)
            for key, make in (("tunnel", tunnel_stream), ("events", event_stream)):
                if key in side:
                    desc, readings = make(side[key], first_ns)
                    w.add_stream(key, desc)
                    w.write_many(readings)
            counts = dict(w.counts)
            w.add_metadata(
                "run_end",
                {
                    "stop_reason": "import complete",
                    "message_counts": counts,
                    "source_stats": {
                        "read": stats.frames,
                        "lost": stats.lost,
                        "bad": stats.bad_frames,
                        "errors": 0,
                        "reopened": 0,
                        "extra": {"partial_samples": stats.partial_samples, "pauses": stats.pauses},
                    },  # fmt: skip
                    "can_log": stats.as_dict(),
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
    if stats.bad_frames:
        notes.append(
            f"{stats.bad_frames} load-cell frame(s) of the wrong length or repeated in a sample: "
            "counted (bad), their samples flagged bad frame (status 8)"
        )
    if stats.odd_frames:
        notes.append(
            f"{stats.odd_frames} frame(s) no classic CAN bus carries as logged (a DLC past 15 or "
            "more than 8 bytes): kept as python-can reads them, flagged bad frame (status 8) in "
            "/can_raw"
        )
    if pose_cov_source.startswith("none"):
        notes.append(
            f"{req.poses} has no covariance columns (cov_00 .. cov_55) and no --pose-sd was "
            "given: /pose carries no covariance (the analysis flags pose_cov_nominal)"
        )
    if stats.partial_samples_dropped:
        notes.append(
            f"dropped {stats.partial_samples_dropped} partial sample(s) where the log starts or "
            "ends mid-sample (their frames are in /can_raw)"
        )
    return ImportReport(out, counts, notes)


def _decoder(req: ImportRequest, cables: list[str], cal: dict[str, Any]) -> Any:
    """The load-cell decoder of the DBC for the rig's cables; a bad value names the file that
    holds it (the calibration file, the DBC, the rig), not the CAN log."""
    try:
        dec, _ = build_decoder(
            req.can_log, "import", req.dbc, cables, cal.get("offset_counts"),
            cal.get("gain_N_per_count"), req.rate_hz,
        )  # fmt: skip
    except ConfigError as exc:
        key = exc.key.rsplit(".", 1)[-1]
        if req.calibration and key in ("offset_counts", "gain_N_per_count"):
            raise ConfigError(req.calibration, key, exc.problem) from None
        if key == "dbc":  # unreadable, or a cable of the rig without its counts in the DBC
            problem = exc.problem.removeprefix(f"{req.dbc}: ")
            if "Counts signal for cable" in problem:
                problem += f" (the cables of {req.rig})"
            raise ConfigError(req.dbc, "", problem) from None
        if key == "cables":
            raise ConfigError(req.rig, "cables", exc.problem) from None
        raise
    return dec


def _pose_cov_source(req: ImportRequest, poses: TimedTable | None) -> str:
    """Where the imported poses' covariance comes from (recorded in the run's metadata); a
    ``--pose-sd`` that cannot be used is bad input."""
    sd = req.pose_sd
    if sd is not None:
        if poses is None:
            raise InputError("--pose-sd: needs --poses (the poses it is the precision of)")
        if "covariance_euler" in poses.columns:
            raise InputError(
                f"--pose-sd: {req.poses} carries its own covariance (cov_00 .. cov_55); give one "
                "or the other"
            )
        if not all(np.isfinite(x) and x > 0 for x in sd):
            raise InputError(f"--pose-sd: expected six finite standard deviations > 0, got {sd}")
        return "stated per frame by --pose-sd (x, y, z m; roll, pitch, yaw rad): " + " ".join(
            f"{x:g}" for x in sd
        )
    if poses is None:
        return ""
    if "covariance_euler" in poses.columns:
        return f"{Path(poses.path).name} columns cov_00 .. cov_55 (x, y, z, roll, pitch, yaw)"
    return "none (the analysis uses its nominal value and flags pose_cov_nominal)"


def _metadata(
    req: ImportRequest, rig_name: str, decoder: Any, start_ns: int, pose_cov_source: str
) -> dict[str, Any]:
    """The run's ``run`` metadata: provenance of every input (names and sha256)."""
    ids = {"dbc": f"{Path(req.dbc).name}@{file_sha256(req.dbc)[:12]}"}
    if req.calibration:
        ids["calibration"] = f"{Path(req.calibration).name}@{file_sha256(req.calibration)[:12]}"
    files = {}
    for key in ("poses", "cable_lengths", "tunnel", "events"):
        f = getattr(req, key)
        files[key] = Path(f).name if f else ""
        files[f"{key}_sha256"] = file_sha256(f) if f else ""
    source = {
        "path": str(req.can_log),
        "dbc": str(req.dbc),
        "cables": list(decoder.cables),
        "rate_hz": req.rate_hz,
        **decoder.calibration.to_mapping(),
    }
    return run_metadata(
        label=req.label,
        start_ns=start_ns,
        software_version=__version__,
        rig=rig_name,
        rig_sha256=file_sha256(req.rig),
        calibration_ids=ids,
        config={"command": "import", "source": source},
        notes=f"imported from {Path(req.can_log).name}",
        extra={
            "command": "import",
            "can_log": Path(req.can_log).name,
            "can_log_sha256": file_sha256(req.can_log),
            **files,
            "cable_length_sd_m": req.length_sd_m,
            "pose_covariance": pose_cov_source,
        },
    )


def _attach(w: McapRunWriter, req: ImportRequest) -> None:
    """The input files, so the run is self-contained."""
    w.add_attachment("rig/" + Path(req.rig).name, Path(req.rig).read_bytes(), "application/toml")
    for f, folder in ((req.dbc, "calibration"), (req.calibration, "calibration"),
                      (req.poses, "poses"), (req.cable_lengths, "cable_lengths"),
                      (req.tunnel, "tunnel"), (req.events, "events")):  # fmt: skip
        if f:
            a = Attachment.from_file(f, f"{folder}/{Path(f).name}")
            w.add_attachment(a.name, a.data, a.media_type)


def _read_cable_lengths(req: ImportRequest, rig: Any) -> Any:
    """The ``--cable-lengths`` log as poses (:mod:`cdpr.pipelines.cable_lengths`), checked before
    anything is written; one pose source only."""
    if not req.cable_lengths:
        if req.length_sd_m is not None:
            raise ConfigError("--length-sd-m", "", "given without --cable-lengths")
        return None
    if req.poses:
        raise ConfigError(req.cable_lengths, "--cable-lengths", "one pose source: not with --poses")
    if req.pose_sd is not None:
        raise InputError("--pose-sd: goes with --poses; --cable-lengths takes --length-sd-m")
    from .cable_lengths import read_cable_lengths

    return read_cable_lengths(req.cable_lengths, rig, req.length_sd_m)


def _length_pose_stream(req: ImportRequest, lengths: Any, first_ns: int | None) -> Any:
    """``/pose`` from the cable-length log: (description, readings); relative times (``t_s``)
    from the first CAN frame."""
    from .cable_lengths import pose_readings

    if lengths.time_column == "t_s":
        if first_ns is None:
            raise ConfigError(
                req.cable_lengths or "", "column t_s", "relative times need CAN frames"
            )
        t_ns = first_ns + np.round(lengths.times.astype(np.float64) * 1e9).astype(np.int64)
    else:
        t_ns = lengths.times.astype(np.int64)
    return pose_readings(lengths, t_ns)
