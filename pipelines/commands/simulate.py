"""``cdpr simulate``: the virtual rig and the recorder end to end, through a real transport.

- ``--transport virtual``: the rig sends CAN frames on a python-can virtual bus in this process;
- ``--transport slcan`` / ``serial``: the rig runs in a second process
  (``python -m cdpr.daq.virtual_rig``) and emulates an slcan adapter (or the serial load-cell line
  protocol) on a pseudo-terminal; this process records it with python-can's ``slcan`` interface
  (or pyserial).  The tunnel conditions always go out as ``$TUN`` lines on a second pty.

The run is ``<out>/<date>_<time>_<label>.mcap``; the truth (poses, wrench, tensions) is written
beside it as ``<run>.truth.npz``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "simulate",
        help="run the virtual rig through a real transport and record it (MCAP run + truth)",
    )
    p.add_argument("--rig", help="rig file (TOML); with --campaign, the campaign's rig")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--schedule", help="virtual-rig schedule (TOML)")
    what.add_argument(
        "--campaign",
        help="test matrix (TOML, docs/campaign.md): rehearse the campaign; the run carries "
        "the test-point events on /events",
    )
    p.add_argument("--out", required=True, help="output folder for the run")
    p.add_argument(
        "--transport",
        choices=("virtual", "slcan", "serial"),
        default="virtual",
        help="virtual: in-process python-can bus; slcan/serial: emulator in a second process on a pty",
    )
    p.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KIND:START_S:DURATION_S[:CABLE]",
        help="add a fault to the schedule (kinds: docs/daq_drivers.md), repeatable",
    )
    p.add_argument(
        "--loadcell-calibration",
        help="load-cell calibration file (cdpr calibrate loadcells): the virtual amplifiers' "
        "offsets and gains (default: the campaign's, else random offsets from the seed); the "
        "rig's calibration is always written beside the run as <run>.loadcells.toml",
    )
    p.add_argument("--label", help="test-point label (default: the schedule's name)")
    p.add_argument("--duration", type=float, help="stop recording after this many seconds")
    p.add_argument("--speed", type=float, default=1.0, help="time scale of the schedule")
    p.add_argument("--seed", type=int, help="random seed (default: the schedule's)")
    p.add_argument("--quiet", action="store_true", help="no live view")
    p.add_argument(
        "--camera",
        help="camera model (JSON, e.g. data_samples/camera_virtual.json): adds a virtual camera "
        "rendering the markers at the true pose; the run then carries /pose (and /image)",
    )
    p.add_argument("--markers", help="marker layout on the model (TOML), with --camera")
    p.add_argument(
        "--tunnel",
        help="test section ([tunnel] and [model] tables, e.g. data_samples/tunnel_section_octagon"
        ".toml): the cables in the flow add their drag to the physics (--transport virtual)",
    )
    p.add_argument(
        "--camera-rate-hz", type=float, default=5.0, help="camera frame rate (default 5)"
    )
    from .record import add_live_argument

    add_live_argument(p)
    p.add_argument(
        "--image-rate-hz",
        type=float,
        default=0.5,
        help="camera frames stored in the run (default 0.5)",
    )
    p.set_defaults(func=run)


def _parse_fault(text: str) -> dict[str, Any]:
    from cdpr.analysis.errors import ConfigError

    parts = text.split(":")
    if len(parts) not in (3, 4):
        raise ConfigError("--fault", text, "expected KIND:START_S:DURATION_S[:CABLE]")
    try:
        f: dict[str, Any] = {
            "kind": parts[0],
            "start_s": float(parts[1]),
            "duration_s": float(parts[2]),
        }
        if len(parts) == 4:
            f["cable"] = int(parts[3])
    except ValueError:
        raise ConfigError(
            "--fault", text, "start, duration must be numbers, cable an integer"
        ) from None
    return f


def run(args: argparse.Namespace) -> int:
    import tomli_w

    import cdpr.daq.drivers  # noqa: F401
    from cdpr.analysis.errors import InputError
    from cdpr.daq.recorder import Attachment, RecorderOptions
    from cdpr.daq.runs import new_run_path, run_metadata
    from cdpr.daq.source import create_source
    from cdpr.daq.virtual_rig import RigRun, VirtualRig, schedule_from_mapping

    from .. import __version__
    from ..config import file_sha256, load_rig, load_toml
    from .record import record_run, start_live

    if args.duration is not None and not args.duration > 0:
        raise InputError(f"--duration must be > 0 s, got {args.duration}")
    if not args.speed > 0:
        raise InputError(f"--speed must be > 0, got {args.speed}")
    if (args.camera is None) != (args.markers is None):
        raise InputError("--camera and --markers go together")
    matrix = None
    if args.campaign is not None:
        from ..campaign import load_test_matrix, schedule_mapping

        matrix = load_test_matrix(args.campaign)
        if args.rig is not None:
            raise InputError("--rig: the campaign file names its rig (campaign.rig)")
        args.rig = str(matrix.rig_path)
        if args.camera is None and matrix.camera is not None:
            args.camera, args.markers = str(matrix.camera), str(matrix.markers)
        sched_data = schedule_mapping(matrix)
        args.schedule = args.campaign
    elif args.rig is None:
        raise InputError("--rig is required with --schedule")
    else:
        sched_data = load_toml(args.schedule)
    rig = load_rig(args.rig)
    section = None
    if args.tunnel is not None:
        if args.transport != "virtual":
            raise InputError(
                "--tunnel: the cable drag runs in this process: use --transport virtual"
            )
        from ..tunnel_section import tunnel_section_from_mapping

        section = tunnel_section_from_mapping(load_toml(args.tunnel), str(args.tunnel)).geometry
    elif matrix is not None and matrix.tunnel is not None:
        if args.transport != "virtual":
            raise InputError(
                f"{args.campaign}: [tunnel] puts the cable drag in this process: use --transport "
                "virtual"
            )
        section = matrix.tunnel.geometry
    cal_file = args.loadcell_calibration
    if cal_file is None and matrix is not None and matrix.loadcell_calibration is not None:
        cal_file = str(matrix.loadcell_calibration)
    if cal_file is not None:
        from cdpr.daq.loadcell import read_calibration_file

        lc = read_calibration_file(cal_file).for_cables(rig.cable_names)
        sensor = sched_data.setdefault("sensor", {})
        if "offset_counts" in sensor or "gain_N_per_count" in sensor:
            from cdpr.analysis.errors import ConfigError

            raise ConfigError(
                str(args.schedule), "sensor.offset_counts", f"given both here and by {cal_file}"
            )
        sensor["offset_counts"] = lc.offset_counts.tolist()
        sensor["gain_N_per_count"] = lc.gain_N_per_count.tolist()
        if matrix is not None:  # the matrix's schedule is rebuilt from the matrix
            import dataclasses

            vr_tab = dict(matrix.virtual_rig)
            vr_tab["sensor"] = {**dict(vr_tab.get("sensor", {})), **sensor}
            matrix = dataclasses.replace(matrix, virtual_rig=vr_tab)
    faults = [_parse_fault(f) for f in args.fault]
    if faults:
        sched_data.setdefault("faults", [])
        if not isinstance(sched_data["faults"], list):
            from cdpr.analysis.errors import ConfigError

            raise ConfigError(args.schedule, "faults", "expected an array of tables")
        sched_data["faults"] = list(sched_data["faults"]) + faults
    if args.seed is not None:
        sched_data.setdefault("schedule", {})["seed"] = args.seed
    try:
        if matrix is not None:
            from ..campaign import schedule_from_matrix
            from ..motion_plan import check_matrix_motion

            schedule = schedule_from_matrix(matrix, rig, faults)
            # an oscillation the plan refuses (slack, winch limits, a mode) is not run
            check_matrix_motion(matrix, rig, schedule.method)
        else:
            schedule = schedule_from_mapping(sched_data, str(args.schedule), rig)
        vr = VirtualRig(rig, schedule, section=section)
    except (
        InputError
    ) as exc:  # the schedule is checked (ConfigError): this is the rig's cable count
        from cdpr.analysis.errors import ConfigError

        raise ConfigError(args.rig, "cables", f"{rig.n_cables} cables: {exc}") from None
    if schedule.pose_camera is not None and args.camera:
        from cdpr.analysis.errors import ConfigError

        raise ConfigError(
            str(args.schedule), "pose_camera", "one camera: --camera (rendered frames) or a pose "
            "camera ([pose_camera] / [virtual_rig.pose_camera]), not both",
        )  # fmt: skip
    camera_model = layout = None
    if args.camera:  # checked before anything is created
        from ..vision_config import load_camera, load_marker_layout

        camera_model, layout = load_camera(args.camera), load_marker_layout(args.markers)
    label = args.label or schedule.name
    path = new_run_path(args.out, label)
    truth_path = path.with_name(path.stem + ".truth.npz")
    cal_out = path.with_name(path.stem + ".loadcells.toml")
    try:  # before any source opens: a bad --out must not leave a bus or a child process behind
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        from cdpr.analysis.errors import ConfigError

        raise ConfigError(str(path.parent), "", f"cannot create: {exc.strerror or exc}") from None

    # the live server binds its port before anything runs (a port in use: exit 2, no run file)
    live = start_live(
        args.live_server,
        rig,
        matrix_file=args.campaign,
        terminal=not args.quiet and sys.stdout.isatty(),
        name="cdpr simulate",
    )
    work = Path(tempfile.mkdtemp(prefix="cdpr-sim-"))
    child: subprocess.Popen[str] | None = None
    rig_run: Any = None
    try:
        sched_file = work / "schedule.toml"
        sched_file.write_bytes(tomli_w.dumps(sched_data).encode())
        link = work / "loadcell"
        tunnel_link = work / "tunnel"
        channel = f"cdpr-sim-{os.getpid()}-{time.monotonic_ns()}"
        if args.transport == "virtual":
            settings = vr.source_settings("virtual", channel=channel, tunnel_link=str(tunnel_link))
        else:
            cmd = [
                sys.executable, "-m", "cdpr.daq.virtual_rig",
                "--rig", str(args.rig), "--schedule", str(sched_file),
                "--transport", args.transport, "--pty-link", str(link),
                "--tunnel-link", str(tunnel_link), "--truth", str(truth_path),
                "--wait-reader", "15", "--speed", str(args.speed),
                "--linger", "600",  # ports stay open until the recording stopped (terminate)
            ]  # fmt: skip
            child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            assert child.stdout is not None
            line = child.stdout.readline()
            if not line.startswith("READY"):
                err = child.stderr.read() if child.stderr else ""
                raise InputError(f"virtual rig process failed to start: {(line + err).strip()}")

            def follow_start(proc: subprocess.Popen[str]) -> None:
                # "STARTED <t0_ns>": the child's schedule start, so the camera here renders the
                # same true pose the child's load cells see
                assert proc.stdout is not None
                for text in proc.stdout:
                    if text.startswith("STARTED "):
                        vr.speed = args.speed
                        vr.t0_ns = int(text.split()[1])

            threading.Thread(target=follow_start, args=(child,), daemon=True).start()
            settings = vr.source_settings(
                args.transport, link=str(link), tunnel_link=str(tunnel_link)
            )
        sources = [create_source(kind, name, s, origin=str(args.schedule))
                   for name, (kind, s) in settings.items()]  # fmt: skip
        if args.camera:
            from cdpr.analysis.rotations import rotation_from_euler
            from cdpr.daq.camera_source import VirtualCameraSource

            assert camera_model is not None and layout is not None
            sources.append(
                VirtualCameraSource(
                    "camera",
                    camera_model,
                    layout,
                    pose_at=vr.camera_pose_at,  # its clock's offset (schedule) included
                    rate_hz=args.camera_rate_hz,
                    image_rate_hz=args.image_rate_hz,
                    realtime=True,
                    reference=(
                        rig.reference_position_O_m,
                        rotation_from_euler(rig.reference_euler_rad),
                    ),
                    seed=schedule.seed,
                )
            )
            settings["camera"] = ("virtual_camera", sources[-1].settings())
        elif schedule.pose_camera is not None:
            from cdpr.daq.pose_camera import PoseCameraSource

            pc = schedule.pose_camera
            sources.append(
                PoseCameraSource(
                    "camera",
                    pose_at=vr.camera_pose_at,  # the camera's clock offset included
                    rate_hz=pc.rate_hz,
                    position_sd_m=pc.position_sd_m,
                    rotation_sd_rad=pc.rotation_sd_rad,
                    seed=schedule.seed,
                )
            )
            settings["camera"] = ("pose_camera", sources[-1].settings())
        events = vr.test_point_events()
        if events:
            from cdpr.daq.vrig_events import SCHEDULE_EVENT_NAME, TestPointEventSource

            if schedule.test_points_on_link:
                # one source of test_point events: the tunnel link's $TPT lines; the schedule's
                # own are kept apart (/events_schedule, name test_point_schedule) for comparison
                sources.append(
                    TestPointEventSource(
                        "events_schedule", events, clock=lambda: (vr.t0_ns, vr.speed),
                        stream="events_schedule", event_name=SCHEDULE_EVENT_NAME,
                    )
                )  # fmt: skip
                print(
                    "test points: from the tunnel link ($TPT lines, /events); the schedule's own "
                    f"are kept on /events_schedule as '{SCHEDULE_EVENT_NAME}'",
                    flush=True,
                )
                settings["events_schedule"] = ("test_point_events", sources[-1].settings())
            else:
                sources.append(
                    TestPointEventSource("events", events, clock=lambda: (vr.t0_ns, vr.speed))
                )
                settings["events"] = ("test_point_events", sources[-1].settings())
        if args.transport == "virtual":
            # the transports exist once the RigRun is built; it sends only after start()
            rig_run = RigRun(vr, "virtual", channel, None, tunnel_link, 0.0, args.speed)
        # readers exist before the rig starts sending (a virtual bus only delivers to open buses,
        # a pty drops what nobody reads)
        for s in sources:
            s.open()
        if rig_run is not None:
            rig_run.start()

        def watch(rec: Any) -> None:
            def waiter() -> None:
                if rig_run is not None:
                    rig_run.done.wait()
                elif child is not None:
                    # the schedule's end by the child's clock (its STARTED line), not the child's
                    # exit: closing its ports under a running recorder would be a fault
                    while child.poll() is None and vr.t0_ns is None:
                        time.sleep(0.05)
                    if vr.t0_ns is not None:
                        # after the schedule's end, wait until the load cells fall silent for 1 s
                        # (a child starved on a busy machine sends behind its clock)
                        end_ns = vr.t0_ns + int(schedule.duration_s / args.speed * 1e9)
                        last_n, quiet_since = -1, time.monotonic()
                        while child.poll() is None:
                            n = rec.status().counts.get("tensions", 0)
                            if n != last_n:
                                last_n, quiet_since = n, time.monotonic()
                            elif time.time_ns() > end_ns and time.monotonic() - quiet_since > 1.0:
                                break
                            time.sleep(0.05)
                time.sleep(0.3)  # the last frames in flight
                rec.request_stop("schedule done")

            threading.Thread(target=waiter, name="sim-watch", daemon=True).start()

        md = run_metadata(
            label=label,
            start_ns=time.time_ns(),
            software_version=__version__,
            rig=rig.name,
            rig_sha256=file_sha256(args.rig),
            calibration_ids={
                "loadcell": (
                    f"{Path(cal_file).name}@{file_sha256(cal_file)[:12]}"
                    if cal_file
                    else f"virtual-rig:{schedule.name}:seed{schedule.seed}"
                )
            },
            config={
                "command": "simulate",
                "transport": args.transport,
                "schedule_file": str(args.schedule),
                "campaign_file": str(args.campaign) if args.campaign else None,
                "schedule": sched_data,
                "faults_added": faults,
                "speed": args.speed,
                "tunnel_file": args.tunnel,
                "cable_drag": section is not None,
                "sources": {n: {"kind": k, **s} for n, (k, s) in settings.items()},
            },
            notes=f"virtual rig, schedule {schedule.name}, transport {args.transport}, cable drag "
            + ("on" if section is not None else "off"),
            extra={"command": "simulate", "truth_file": truth_path.name},
        )
        attachments = [
            Attachment.from_file(args.rig, "rig/" + Path(args.rig).name),
            Attachment(
                "schedule/" + Path(args.schedule).name, sched_file.read_bytes(), "application/toml"
            ),
        ]
        if args.tunnel is not None:
            attachments.append(
                Attachment.from_file(args.tunnel, "tunnel/" + Path(args.tunnel).name)
            )
        if cal_file:
            attachments.append(Attachment.from_file(cal_file, "calibration/" + Path(cal_file).name))
        if args.campaign:
            attachments.append(
                Attachment.from_file(args.campaign, "campaign/" + Path(args.campaign).name)
            )
        dbc = getattr(sources[0], "dbc_path", None)
        if dbc:
            attachments.append(Attachment.from_file(dbc, "calibration/" + Path(dbc).name))
        if args.camera:
            attachments.append(
                Attachment.from_file(args.camera, "calibration/" + Path(args.camera).name)
            )
            attachments.append(
                Attachment.from_file(args.markers, "calibration/" + Path(args.markers).name)
            )
        if args.transport == "virtual":
            rig_run.started.wait(5.0)
        record_run(
            sources,
            path,
            metadata=md,
            attachments=attachments,
            options=RecorderOptions(),
            duration_s=args.duration,
            quiet=args.quiet,
            t_min_N=list(rig.t_min_N),
            t_max_N=list(rig.t_max_N),
            on_started=watch,
            live=live,
        )
    finally:
        if live is not None:
            live.stop()
        if rig_run is not None:
            rig_run.stop()
            if path.exists():
                vr.write_truth(truth_path)
        if path.exists():
            vr.write_calibration(cal_out)
        if child is not None:
            if child.poll() is None:
                child.terminate()
            try:
                child.wait(10)
            except subprocess.TimeoutExpired:
                child.kill()
        shutil.rmtree(work, ignore_errors=True)
    print(f"truth written to {truth_path}; load-cell calibration to {cal_out}")
    return 0
