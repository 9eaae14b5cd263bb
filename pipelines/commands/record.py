"""``cdpr record``: record the hardware named in an acquisition config into a new MCAP run."""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "record",
        help="record the sources of an acquisition config (tunnel.toml) into a new MCAP run",
        description="Record every source of the config into <out>/<date>_<time>_<label>.mcap "
        "until --duration elapses or Ctrl-C / SIGTERM; the file is always finished. Exit codes: "
        "0 clean run; 2 bad input; 3 a source failed or degraded (the run is kept, the faults are "
        "printed and recorded as /event messages with name 'fault').",
    )
    p.add_argument(
        "--config", required=True, help="acquisition config (TOML), see docs/recording.md"
    )
    p.add_argument("--out", help="output folder (default: [recorder] out, else runs/)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--label", help="test-point label (default: [run] label)")
    p.add_argument("--notes", help="operator notes (added to [run] notes)")
    p.add_argument(
        "--airspeed",
        type=float,
        help="tunnel airspeed of this test point, m/s (manual_tunnel sources)",
    )
    p.add_argument("--pressure", type=float, help="static pressure of this test point, Pa")
    p.add_argument("--temperature", type=float, help="air temperature of this test point, K")
    p.add_argument("--quiet", action="store_true", help="no live view")
    p.add_argument(
        "--test-matrix",
        help="test matrix (TOML, docs/campaign.md): the live view steps through its points, "
        "SPACE starts and ends the current one (a 'test_point' event each); refused with a "
        "serial_tunnel source that reads the controller's test points (test_points = true)",
    )
    add_live_argument(p)
    p.add_argument(
        "--allow-degraded",
        action="store_true",
        help="keep recording when a source delivers nothing within [recorder] startup_timeout_s "
        "(default: stop); the run still exits 3",
    )
    p.set_defaults(func=run)


def add_live_argument(p: argparse.ArgumentParser) -> None:
    """``--live-server [HOST:]PORT`` (``record``, ``simulate``, ``play``)."""
    p.add_argument(
        "--live-server",
        metavar="[HOST:]PORT",
        help="serve the run to Foxglove over a WebSocket (foxglove-sdk) on PORT, bound to "
        "127.0.0.1 unless HOST is given (0.0.0.0: every interface); 0 picks a free port. Same "
        "topics and schema names as the run file, plus /scene, /tf and the on-line reduction "
        "(/online); docs/live.md. Off by default",
    )


def start_live(
    text: str | None,
    rig: Any,
    *,
    matrix_file: str | None = None,
    terminal: bool = False,
    name: str = "cdpr record",
) -> Any:
    """The live server of ``--live-server`` (started: a port in use is a ``ConfigError`` here,
    before anything is recorded) with the on-line reduction when the rig is known; without
    ``--live-server``, the on-line reduction alone for the terminal view (``terminal``); None when
    neither is wanted.  Prints the server's address."""
    from cdpr.daq.live_server import LiveServer, parse_address

    address = parse_address(text) if text is not None else None
    if address is None and not (terminal and rig is not None):
        return None
    online = None
    opts = None
    if rig is not None:
        from ..online import OnlineReduction, online_options

        opts = online_options(matrix_file)
        online = OnlineReduction(rig, opts)
    live = LiveServer(
        address,
        rig=rig,
        geometry=None if opts is None else opts.geometry,
        online=online,
        name=name,
    )
    live.start()
    if live.url is not None:
        print(
            f"live server {live.url} (Foxglove: Open connection -> Foxglove WebSocket; layout "
            "data_samples/foxglove_layout.json)",
            flush=True,
        )
    return live


def record_run(
    sources: Sequence[Any],
    path: Path,
    *,
    metadata: dict[str, str],
    attachments: Sequence[Any],
    options: Any,
    duration_s: float | None,
    quiet: bool,
    t_min_N: Sequence[float] | None = None,
    t_max_N: Sequence[float] | None = None,
    on_started: Any = None,
    nice: int | None = None,
    rig: Any = None,
    test_points: Sequence[Any] | None = None,
    live: Any = None,
) -> Any:
    """Run a :class:`~cdpr.daq.recorder.Recorder` until ``duration_s``, SIGINT or SIGTERM.

    The signal handlers only request a stop; ``Recorder.stop`` (summary, footer, fsync) runs in a
    ``finally``.  The live view is shown when stdout is a terminal and ``quiet`` is false.
    ``rig``: the live view's wrench estimate; ``test_points``: the points the operator steps
    through in the live view (``test_point`` events).
    ``nice``: the process priority to ask for (e.g. -10: ahead of ordinary processes, so a busy
    machine does not starve the acquisition); refused (no privilege) it is an event, not an error.
    ``live``: a started :class:`~cdpr.daq.live_server.LiveServer` (:func:`start_live`) fed from
    the recorder; its on-line results of ended points are recorded before the file is finished,
    and it is stopped on every exit path.
    Returns the recorder's final status.
    """
    from cdpr.daq.recorder import Recorder

    extra = None
    if test_points is not None:
        # the live view's test_point events go on /events, the topic cdpr analyze reads
        from cdpr.daq.live import test_point_streams

        extra = test_point_streams()
    rec = Recorder(
        sources,
        path,
        metadata=metadata,
        attachments=attachments,
        options=options,
        extra_streams=extra,
    )
    if live is not None:
        live.attach(rec)

    def handler(signum: int, frame: Any) -> None:
        rec.request_stop(signal.Signals(signum).name)

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    # before the threads start: Linux keeps a nice value per thread, new threads inherit it
    prio = _set_priority(nice) if nice is not None else None
    try:
        rec.start()
        if prio is not None:
            rec.event(prio[1], level=prio[0], name="recorder")
        print(f"recording {path}", flush=True)
        if on_started is not None:
            on_started(rec)
        if not quiet and sys.stdout.isatty():
            from cdpr.daq.live import LiveView

            online = None if live is None or live.online is None else live.online_line
            with LiveView(
                rec, t_min_N=t_min_N, t_max_N=t_max_N, rig=rig, test_points=test_points,
                online=online,
            ):  # fmt: skip
                rec.wait(duration_s)
        else:
            rec.wait(duration_s)
    finally:
        try:
            if live is not None:  # the on-line results of ended points go into the file
                live.finish_points()
            rec.stop()
        finally:
            for s, h in old.items():
                signal.signal(s, h)
            if live is not None:
                live.stop()
    st = rec.status()
    n = sum(v for k, v in st.counts.items() if k not in ("recorder", "event"))
    drops = sum(c.dropped for c in st.sources.values())
    print(
        f"finished {path}: {n} readings in {st.elapsed_s:.1f} s, {drops} dropped "
        f"({st.stop_reason})",
        flush=True,
    )
    report_faults(st)
    return st


def _test_points(path: str) -> list[Any]:
    """The points of a test matrix file, in run order (``cdpr.pipelines.campaign``)."""
    from cdpr.analysis.errors import ConfigError

    from ..campaign import load_test_matrix
    from ..config import load_rig
    from ..motion_plan import check_matrix_motion

    matrix = load_test_matrix(path)
    # before anything is recorded: an oscillation point the motion plan refuses is refused here
    if any(p.oscillation is not None for p in matrix.points):
        check_matrix_motion(matrix, load_rig(matrix.rig_path))
    points = [p.event_fields() for p in matrix.points]
    if not points:
        raise ConfigError(path, "points", "no test points")
    return points


def _one_test_point_source(origin: str, sources: Sequence[Any], matrix: str) -> None:
    """Refuse two sources of ``test_point`` events: the live view stepping through ``--test-matrix``
    and a tunnel link that reads the controller's ``$TPT`` lines (``test_points = true``).  One run
    holds one set of test points (docs/campaign.md, "Test points from the tunnel controller")."""
    from cdpr.analysis.errors import ConfigError

    for sc in sources:
        if sc.kind == "serial_tunnel" and sc.settings.get("test_points") is True:
            raise ConfigError(
                origin,
                f"sources.{sc.name}.test_points",
                f"the tunnel link marks the test points and --test-matrix {matrix} would mark "
                "them too: only one may; set test_points = false to step through the matrix in "
                "the live view, or drop --test-matrix to take the controller's points",
            )


def _set_priority(nice: int) -> tuple[str, str]:
    """Set this thread's nice value (threads started later inherit it); (level, event message)."""
    import os

    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except OSError as exc:
        return (
            "warning",
            f"could not set the recorder's priority to nice {nice} ({exc.strerror}): under CPU "
            "load it may fall behind (give it CAP_SYS_NICE or run it as root)",
        )
    return "info", f"recorder priority: nice {os.getpriority(os.PRIO_PROCESS, 0)}"


def report_faults(st: Any) -> int:
    """Print a failed or degraded recording's faults on stderr; the exit code (0 clean, 3)."""
    faults = list(st.faults)
    if st.failure:
        # one line; the failed source's own summary would only repeat it
        print(
            f"cdpr record: failed: {st.failure}; the data recorded so far is kept", file=sys.stderr
        )
        name = st.failure.split("'")[1] if st.failure.count("'") >= 2 else ""
        faults = [f for f in faults if not f.startswith(f"source {name}:")]
    if faults:
        print(f"cdpr record: DEGRADED run, {len(faults)} faulty source(s):", file=sys.stderr)
        for line in faults:
            print(f"  {line}", file=sys.stderr)
    return 3 if st.failure or st.faults else 0


def run(args: argparse.Namespace) -> int:
    from cdpr.daq.recorder import Attachment, RecorderOptions
    from cdpr.daq.runs import new_run_path, run_metadata

    from .. import __version__
    from ..config import file_sha256, load_rig
    from ..daq_config import build_sources, load_daq_config

    cfg = load_daq_config(args.config)
    test_points = _test_points(args.test_matrix) if args.test_matrix else None
    if test_points is not None:
        _one_test_point_source(str(cfg.path), cfg.sources, args.test_matrix)
    if args.duration is not None and not args.duration > 0:
        from cdpr.analysis.errors import InputError

        raise InputError(f"--duration must be > 0 s, got {args.duration}")
    rig = load_rig(cfg.rig) if cfg.rig is not None else None
    if args.live_server is not None:
        from cdpr.daq.live_server import parse_address

        parse_address(args.live_server)  # bad input before anything opens
    point = {
        "airspeed_mps": args.airspeed,
        "static_pressure_Pa": args.pressure,
        "temperature_K": args.temperature,
    }
    point = {k: v for k, v in point.items() if v is not None}
    if point:
        # tunnel conditions entered on the command line for this test point (no data link)
        manual = [sc for sc in cfg.sources if sc.kind == "manual_tunnel"]
        if not manual:
            from cdpr.analysis.errors import ConfigError

            raise ConfigError(
                str(cfg.path),
                "sources",
                "--airspeed/--pressure/--temperature need a manual_tunnel source",
            )
        for sc in manual:
            sc.settings.update(point)
            if args.label:
                sc.settings["label"] = args.label
    sources = build_sources(cfg)
    if rig is not None:
        _check_cables(str(cfg.path), sources, rig)
    label = args.label or cfg.label
    out = Path(args.out) if args.out else (cfg.out or Path("runs"))
    attachments = [Attachment.from_file(cfg.path, "config/" + cfg.path.name)]
    if cfg.rig is not None:
        attachments.append(Attachment.from_file(cfg.rig, "rig/" + cfg.rig.name))
    attachments += [Attachment.from_file(c, "calibration/" + c.name) for c in cfg.calibrations]
    for sc in cfg.sources:  # a camera's model and marker layout travel with its poses
        if sc.kind == "camera":
            for key in ("camera", "layout"):
                if isinstance(sc.settings.get(key), str):
                    f = Path(sc.settings[key])
                    name = f"calibration/{f.name}"
                    if all(a.name != name for a in attachments):
                        attachments.append(Attachment.from_file(f, name))
    config_snapshot = {
        "file": str(cfg.path),
        "sha256": file_sha256(cfg.path),
        "toml": cfg.raw,
        "sources": {s.name: {"kind": s.kind, **s.settings()} for s in sources},
    }
    notes = " ".join(x for x in (cfg.notes, args.notes or "") if x)
    path = new_run_path(out, label)
    from time import time_ns

    md = run_metadata(
        label=label,
        start_ns=time_ns(),
        software_version=__version__,
        rig=rig.name if rig else "",
        rig_sha256=file_sha256(cfg.rig) if cfg.rig else "",
        calibration_ids=cfg.calibration_ids(),
        config=config_snapshot,
        operator=cfg.operator,
        notes=notes,
        extra={"command": "record"},
    )
    # the live server binds its port before the run file exists (a port in use: exit 2)
    live = start_live(
        args.live_server,
        rig,
        matrix_file=args.test_matrix,
        terminal=not args.quiet and sys.stdout.isatty(),
    )
    options = RecorderOptions(
        queue_readings=cfg.queue_readings,
        chunk_size=cfg.chunk_size,
        flush_interval_s=cfg.flush_interval_s,
        compression=cfg.compression,
        startup_timeout_s=cfg.startup_timeout_s,
        stall_timeout_s=cfg.stall_timeout_s,
        allow_degraded=args.allow_degraded,
    )
    try:
        st = record_run(
            sources,
            path,
            metadata=md,
            attachments=attachments,
            options=options,
            duration_s=args.duration,
            quiet=args.quiet,
            t_min_N=list(rig.t_min_N) if rig else None,
            t_max_N=list(rig.t_max_N) if rig else None,
            nice=cfg.nice,
            rig=rig,
            test_points=test_points,
            live=live,
        )
    finally:
        if live is not None:
            live.stop()
    return 3 if st.failure or st.faults else 0


def _check_cables(origin: str, sources: Any, rig: Any) -> None:
    """Every load-cell source names cables of the rig, and together they cover all of them.

    A tension column the rig does not know, or a cable nobody measures, would only surface when the
    run is analysed; it is bad input now.
    """
    from cdpr.analysis.errors import ConfigError

    rig_cables = list(rig.cable_names)
    seen: list[str] = []
    for s in sources:
        cables = s.settings().get("cables")
        if cables is None:
            continue
        unknown = [c for c in cables if c not in rig_cables]
        if unknown:
            raise ConfigError(
                origin,
                f"sources.{s.name}.cables",
                f"{unknown[0]!r} is not a cable of rig {rig.name!r} (cables: {rig_cables})",
            )
        seen += list(cables)
    if not seen:
        return  # no load-cell source (a tunnel-only recording)
    missing = [c for c in rig_cables if c not in seen]
    if missing:
        raise ConfigError(
            origin,
            "sources",
            f"no load-cell source measures cable {missing[0]!r} of rig {rig.name!r} "
            f"({len(set(seen))} of {len(rig_cables)} cables listed)",
        )
