"""``cdpr import``: a run recorded by other tools (a CAN log plus a pose CSV, the tunnel's log and
the test-point list) as a normal MCAP run; the arguments here, the work in
:mod:`cdpr.pipelines.importer`."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "import",
        help="turn a CAN log (candump/ASC/BLF/TRC/CSV) plus a pose CSV into a normal MCAP run",
    )
    p.add_argument(
        "--can-log", required=True, help="CAN log (.log candump, .asc, .blf, .trc, .csv, ...)"
    )
    p.add_argument("--dbc", required=True, help="DBC of the load-cell amplifier")
    p.add_argument(
        "--poses",
        help="pose CSV (t_ns or t_s, x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad, optionally the "
        "covariance cov_00 .. cov_55)",
    )
    p.add_argument(
        "--pose-sd",
        nargs=6,
        type=float,
        metavar=("X_M", "Y_M", "Z_M", "ROLL_RAD", "PITCH_RAD", "YAW_RAD"),
        help="the camera's stated per-frame standard deviation of each pose coordinate, for a pose "
        "CSV without covariance columns (recorded in the run's metadata)",
    )
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
    from ..importer import ImportRequest, import_run

    report = import_run(
        ImportRequest(
            can_log=args.can_log, dbc=args.dbc, rig=args.rig, out=args.out, poses=args.poses,
            pose_sd=args.pose_sd, calibration=args.calibration, tunnel=args.tunnel,
            events=args.events, raw_only=args.raw_only, rate_hz=args.rate, label=args.label,
            cable_lengths=args.cable_lengths, length_sd_m=args.length_sd_m,
        )
    )  # fmt: skip
    print(f"wrote {report.out}: " + ", ".join(f"{k} {v}" for k, v in report.counts.items() if v))
    for note in report.notes:
        print(f"note: {note}")
    return 0
